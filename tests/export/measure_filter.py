"""Measure `labcal filter` on the simulated UR10 (not a test: prints one line per calibration method).

    .venv/bin/python tests/export/measure_filter.py

A 200-pose fit of a simulated robot with known errors (local POE on geometric errors; hybrid on geometric plus
compliance and gear errors), then a 50-row TCP-pose program filtered and sent to the simulated TRUE robot: its
tool error with the program's nominal joints and with the filtered joints.

Then rows approaching the elbow (q3 → 0) and wrist (q5 → 0) singularities, on a local-POE calibration whose frames
are off by ~0.5 mm / mrad: the length-scaled condition, how far ``correct()`` leaves the calibrated robot from the
row's nominal pose (what main 5770eeb wrote without looking), and what the filter says now.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
# The scenario generators live with the benchmarks (pytest puts benchmarks/ on the path; a script must).
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from export_fixtures import hybrid
from test_program import program_poses

from labcal.calibration import Observations
from labcal.calibration.fit import fit
from labcal.export.program import MAX_CONDITION, ProgramError, filter_joints, filter_poses, pose_matrix
from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec
from scenarios import good


def main() -> None:
    for errors, method in [(ErrorSpec.paper(tracker_noise=1e-5), "local-poe"), (ErrorSpec.default(), "hybrid")]:
        scn = good("ur10", 200, errors=errors, seed=4)
        robot = fit(Observations(**scn.arrays()), load("ur10").model, method, seed=0).robot
        poses, q = program_poses(robot, 50, seed=1)
        result = filter_poses(robot, poses, seed=q[0] + 0.05)
        asked = pose_matrix(poses)
        filtered, _ = se3.pose_distance(scn.actual.true_pose(result.q_command), asked)
        plain, _ = se3.pose_distance(scn.actual.true_pose(result.q_nominal), asked)
        print(
            f"{method}: true-robot tool error, program joints {1e3 * plain.mean():.3f} / {1e3 * plain.max():.3f} mm, "
            f"filtered {1e3 * filtered.mean():.4f} / {1e3 * filtered.max():.4f} mm (mean / max); {result.summary()}"
        )

    singular_sweep()


def singular_sweep() -> None:
    robot = hybrid("ur10", features=None, seed=7)
    print(f"rows near a singularity (MAX_CONDITION {MAX_CONDITION:g}): joint, condition, correct() miss, filter")
    for j in (2, 4):
        for value in (1e-5, -1e-5, 1e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1):
            q = np.array([[0.3, -1.2, 1.4, -1.6, -1.5, 0.4]])
            q[0, j] = value
            J = robot.nominal.equivalent_jacobian(q, length_scale=robot.length_scale)
            cond = scaled_condition(J, robot.length_scale)[0]
            missed, _ = se3.pose_distance(robot.predict_pose(robot.correct(q)), robot.nominal.fk(q))
            try:
                filter_joints(robot, q)
                verdict = "accepted"
            except ProgramError as e:
                verdict = "refused: " + str(e).split(" (")[0]
            print(f"  q{j + 1} = {value:8.1e}  condition {cond:9.3g}  miss {1e3 * missed[0]:8.4f} mm  {verdict}")


if __name__ == "__main__":
    main()
