"""Measure `labcal filter` on the simulated UR10 (not a test: prints one line per calibration method).

    .venv/bin/python tests/export/measure_filter.py

A 200-pose fit of a simulated robot with known errors (local POE on geometric errors; hybrid on geometric plus
compliance and gear errors), then a 50-row TCP-pose program filtered and sent to the simulated TRUE robot: its
tool error with the program's nominal joints and with the filtered joints.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from test_program import program_poses

from labcal.calibration import Observations
from labcal.calibration.fit import fit
from labcal.export.program import filter_poses, pose_matrix
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec
from labcal.simulation.scenarios import good


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


if __name__ == "__main__":
    main()
