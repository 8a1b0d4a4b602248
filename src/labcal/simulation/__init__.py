"""Simulated actual robots (true error models) shared by the calibration benchmarks and the sim drivers.

Adversarial data sets built on them (few-pose sweeps, singular wrists, unit slips, …) are benchmarks/scenarios.py
(for tests and benchmarks, not part of the package).
"""

from labcal.simulation.actual import GRAVITY, ActualRobot, ErrorSpec, drop_unseen, seen_mask, simulate

__all__ = ["GRAVITY", "ActualRobot", "ErrorSpec", "drop_unseen", "seen_mask", "simulate"]
