"""Simulated actual robots (true error models) shared by the calibration benchmarks and the sim drivers."""

from labcal.simulation.actual import GRAVITY, ActualRobot, ErrorSpec, simulate

__all__ = ["GRAVITY", "ActualRobot", "ErrorSpec", "simulate"]
