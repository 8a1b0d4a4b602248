"""What a geometry-only export (URDF, ur_description YAML) drops of a calibration: the learned term's size.

A hybrid or ann calibration corrects the robot with the identified frames *and* a learned joint-motion-error term
(the network). A URDF or a kinematics YAML can hold only the frames, so exporting one silently loses the learned
part. :func:`dropped_learned_term` says how large that part is over the calibration's data range: the
difference between the calibrated forward model with and without the learned term at the tool (position and
orientation), over a fixed, seeded sample of configurations inside ``robot.joint_ranges`` (the joint ranges the
calibration data covered): the error a user of the geometry-only file keeps that the compensator would remove.

Example::

    >>> from labcal.compensator import CalibratedRobot
    >>> from labcal.robots import load
    >>> nominal = load("ur10").model
    >>> dropped_learned_term(CalibratedRobot(nominal, nominal)) is None       # no learned term: nothing dropped
    True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3

SAMPLES = 500


@dataclass(frozen=True)
class DroppedTerm:
    """Size of the learned correction over the data range (SI: m and rad), from ``configurations`` samples."""

    configurations: int
    position_mean: float
    position_max: float
    rotation_mean: float
    rotation_max: float

    def describe(self) -> str:
        """One sentence for warnings, refusals and file comments (mm, mrad)."""
        return (
            f"the learned joint-motion-error term moves the tool by {1e3 * self.position_mean:.3f} mm on average and "
            f"up to {1e3 * self.position_max:.3f} mm ({1e3 * self.rotation_mean:.3f} / {1e3 * self.rotation_max:.3f} "
            f"mrad mean / max) over {self.configurations} configurations in the calibration's joint ranges"
        )


def dropped_learned_term(robot: CalibratedRobot, count: int = SAMPLES, seed: int = 0) -> DroppedTerm | None:
    """The size of what a geometry-only export drops (None when the calibration has no learned term)."""
    if robot.network is None:
        return None
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    q = lo + (hi - lo) * np.random.default_rng(seed).uniform(size=(count, robot.n))  # in the calibrated ranges
    dp, dr = se3.pose_distance(robot.predict_pose(q), robot.model.fk(q))
    return DroppedTerm(count, float(dp.mean()), float(dp.max()), float(dr.mean()), float(dr.max()))


def refuse_or_note(robot: CalibratedRobot, fmt: str, geometry_only: bool) -> str | None:
    """For a geometry-only format: raise ValueError when a learned term would be dropped without
    ``geometry_only``; otherwise the note to write into the file (None when nothing is dropped)."""
    dropped = dropped_learned_term(robot)
    if dropped is None:
        return None
    if not geometry_only:
        raise ValueError(
            f"a {fmt} holds only the identified frames of this {robot.method} calibration, and {dropped.describe()}. "
            "Use the json/npz compensator (or the URScript export) to keep it, or pass geometry_only "
            "(--geometry-only) to export the frames alone"
        )
    return f"NOT INCLUDED (geometry only): {dropped.describe()}"
