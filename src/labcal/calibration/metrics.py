"""Accuracy metrics: one definition used by fits, reports, benchmarks and the CLI.

Position error: distance between predicted and measured tool origins (m). Orientation error: the angle of
``R_measured R_predictedᵀ`` (rad), measured on the manifold. For three-point data the measured pose is the rigid
fit of the targets to the measured points (:func:`labcal.calibration.observations.rigid_fit`).

Example::

    >>> s = summarize(np.array([1e-3, 2e-3]), np.array([1e-4, 3e-4]))
    >>> round(s["pos_mean"] * 1e3, 6), round(s["ori_max"] * 1e3, 6)
    (1.5, 0.3)
"""

from __future__ import annotations

import numpy as np

from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3

STATS = ("mean", "rms", "p95", "max", "std")


def summarize(pos: np.ndarray, ori: np.ndarray) -> dict[str, float]:
    """Mean, RMS, 95th percentile, max and std of position (m) and orientation (rad) errors."""
    out: dict[str, float] = {"count": float(len(pos))}
    for name, e in (("pos", np.asarray(pos, float)), ("ori", np.asarray(ori, float))):
        if e.size == 0:
            out.update({f"{name}_{s}": float("nan") for s in STATS})
            continue
        out[f"{name}_mean"] = float(np.mean(e))
        out[f"{name}_rms"] = float(np.sqrt(np.mean(e * e)))
        out[f"{name}_p95"] = float(np.percentile(e, 95))
        out[f"{name}_max"] = float(np.max(e))
        out[f"{name}_std"] = float(np.std(e))
    return out


def prediction_errors(robot: CalibratedRobot, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """Per-configuration (position m, orientation rad) error of the robot's predicted pose vs the measured one.

    Tracker-frame data are compared in the tracker frame through the robot's T_tracker_base.
    """
    if obs.k == 0:
        return np.zeros(0), np.zeros(0)
    T_pred = robot.T_tracker_base @ robot.predict_pose(obs.q)
    return se3.pose_distance(obs.measured_poses(), T_pred)


def split_table(before: CalibratedRobot, after: CalibratedRobot, obs: Observations) -> dict[str, dict]:
    """{split: {"before": summary, "after": summary}} for each split present (and "all")."""
    table: dict[str, dict] = {}
    for split in ("train", "val", "test", "all"):
        part = obs if split == "all" else obs.where(split)
        if part.k == 0:
            continue
        table[split] = {
            "before": summarize(*prediction_errors(before, part)),
            "after": summarize(*prediction_errors(after, part)),
        }
    return table


def reduction(before: float, after: float) -> float:
    """Percentage reduction of an error statistic (the paper's figure of merit)."""
    return 100.0 * (1.0 - after / before) if before > 0 else float("nan")
