"""`labcal filter` through its typer command: pose and joint programs in their units, the outputs, and the errors
(row named, seed required, existing output)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))

from export_fixtures import hybrid, sample

from labcal.cli.filter import filter_program
from labcal.compensator import save
from labcal.export.program import filter_joints, filter_poses
from labcal.kinematics import se3
from labcal.testing import urscript_subset

app = typer.Typer()
app.command("filter")(filter_program)
app.command("unused")(lambda: None)  # two commands: typer keeps "filter" as a subcommand name
runner = CliRunner()


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("filter")
    robot = hybrid("ur10", features=None, seed=7)
    save(robot, root / "ur10.json")
    q = sample(robot, 1, seed=2)[0] + np.linspace(0, 0.2, 4)[:, None] * np.array([1, -1, 1, 1, -1, 1])
    T = robot.nominal.fk(q)
    poses = np.concatenate([T[:, :3, 3] * 1000, se3.log_so3(T[:, :3, :3])], axis=1)
    (root / "poses.csv").write_text(
        "x,y,z,rx,ry,rz\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in poses) + "\n"
    )
    (root / "joints.csv").write_text(
        "q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(repr(float(v)) for v in np.degrees(row)) for row in q) + "\n"
    )
    return {"root": root, "robot": robot, "q": q, "poses": poses}


def run(*args):
    return runner.invoke(app, ["filter", *map(str, args)])


def read_q(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()[1:]
    return np.array([[float(v) for v in line.split(",")[1:7]] for line in lines])


def test_pose_program_in_mm_is_corrected_with_a_movej_script(setup):
    root, robot, q = setup["root"], setup["robot"], setup["q"]
    seed = ",".join(repr(float(v)) for v in q[0] + 0.02)
    out, script = root / "poses-out.csv", root / "poses-out.script"
    r = run(root / "poses.csv", "--calibration", root / "ur10.json", "--length-unit", "mm", "--seed-joints", seed,
            "--out", out, "--script", script)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    assert r.stdout.strip().splitlines()[-1] == str(out)
    assert "joint correction" in r.stderr
    poses_m = setup["poses"] * np.array([1e-3] * 3 + [1.0] * 3)
    expected = filter_poses(robot, poses_m, q[0] + 0.02)
    np.testing.assert_array_equal(read_q(out), expected.q_command)
    urscript_subset.check(script.read_text())


def test_joint_program_in_degrees(setup):
    root, robot, q = setup["root"], setup["robot"], setup["q"]
    out = root / "joints-out.csv"
    r = run(root / "joints.csv", "--kind", "joints", "--angle-unit", "deg", "--calibration", root / "ur10.json",
            "--out", out)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    np.testing.assert_allclose(read_q(out), filter_joints(robot, q).q_command, atol=1e-12)


def test_errors_name_the_row_and_the_fix(setup):
    root, q = setup["root"], setup["q"]
    r = run(root / "poses.csv", "--calibration", root / "ur10.json", "--out", root / "x.csv")
    assert r.exit_code != 0 and "--seed-joints" in r.stderr
    # metres read as millimetres: the program is 1000x too far away
    seed = ",".join(repr(float(v)) for v in q[0])
    r = run(root / "poses.csv", "--calibration", root / "ur10.json", "--seed-joints", seed, "--out", root / "y.csv")
    assert r.exit_code != 0 and "row 1: " in r.stderr
    (root / "z.csv").write_text("old")
    r = run(root / "joints.csv", "--kind", "joints", "--calibration", root / "ur10.json", "--out", root / "z.csv")
    assert r.exit_code != 0 and "already exists" in r.stderr
    assert (root / "z.csv").read_text() == "old"
