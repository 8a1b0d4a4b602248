"""The exports of a 7-joint calibration through the real app (issue 28): a sim session of a Franka Panda, fitted with
local POE, exported without --force as JSON, NPZ and URDF and used by `labcal filter`; URScript and the UR YAML
refuse a non-UR robot in one line. The checks use semantics written here: the Panda's modified-DH product (the
maker's published parameters, not the robot file) for the nominal pose, and a URDF walk of origin · rot(axis, q)
per joint."""

from __future__ import annotations

import math
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "cli"))
sys.path.insert(0, str(Path(__file__).parents[1] / "kinematics"))

from cli_testutil import TARGETS, invoke, last_line
from kin_testutil import dh_product

from labcal.compensator import Compensator
from labcal.kinematics import se3

PI2 = math.pi / 2
ROWS = [  # the Panda's modified DH (a_{j-1}, alpha_{j-1}, d_j, theta_j), Franka's published values
    {"a": a, "alpha": alpha, "d": d, "theta": 0.0}
    for a, alpha, d in zip(
        [0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088],
        [0.0, -PI2, PI2, PI2, -PI2, PI2, PI2],
        [0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0],
        strict=True,
    )
]
FLANGE_D = 0.107  # m: the flange along joint 7's axis


def nominal_fk(q: np.ndarray) -> np.ndarray:
    """(4, 4) the nominal flange pose at one configuration, from the DH product."""
    flange = np.eye(4)
    flange[2, 3] = FLANGE_D
    return dh_product(ROWS, q, modified=True) @ flange


@pytest.fixture(scope="module")
def fit(tmp_path_factory):
    """A 60-pose sim session of the built-in franka-panda with three targets, a local-POE fit, and its JSON export."""
    root = tmp_path_factory.mktemp("seven")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"
    r = invoke(
        "session", "new", "--robot", "franka-panda", "--robot-driver", "sim", "--tracker-driver", "sim",
        "--targets", root / "targets.toml", "--poses", 60, "--seed", 3, store=store,
    )  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = last_line(r)
    f = invoke("fit", ref, "--method", "local-poe", "--seed", 1, store=store)
    assert f.exit_code == 0, f.stdout + f.stderr
    out = {"root": root, "store": store, "ref": ref, "fit": last_line(f)}
    r, path = export(out, "json", "calib.json")
    assert r.exit_code == 0, r.stdout + r.stderr  # no --force: the fit's warnings do not block it
    out["comp"] = Compensator.load(path)
    assert out["comp"].robot.n == 7
    return out


def export(fit, fmt, name, *extra):
    out = fit["root"] / name
    r = invoke("export", fit["ref"], "--fit", fit["fit"], "--format", fmt, "--out", out, *extra, store=fit["store"])
    return r, out


def inside(comp: Compensator, k: int) -> np.ndarray:
    """(k, 7) configurations the calibration measured, moved by a few mrad (inside its validity region)."""
    region = comp.robot.validity
    q = region.centres[:k] / region.weights
    return q + 0.003 * np.sin(np.arange(7) + 1.0)


def test_json_and_npz_correct_a_7_joint_robot_onto_the_nominal_pose(fit):
    comp = fit["comp"]
    r, path = export(fit, "npz", "calib.npz")
    assert r.exit_code == 0, r.stdout + r.stderr
    assert last_line(r) == str(path)
    npz = Compensator.load(path)
    q = inside(comp, 10)
    q_cmd = comp.correct(q)
    np.testing.assert_array_equal(npz.correct(q), q_cmd)
    assert np.abs(q_cmd - q).max() > 1e-3  # the sim robot's errors need millirad corrections
    for i in range(len(q)):
        gap = se3.log_se3(se3.inv(comp.predict_pose(q_cmd[i])) @ nominal_fk(q[i]))
        assert np.abs(gap).max() < 1e-10
        # one configuration (the compiled kernel) as in the batch (the numpy definition), to rounding
        np.testing.assert_allclose(comp.correct(q[i]), q_cmd[i], rtol=0, atol=1e-12)


def urdf_fk(text: str, q: np.ndarray, tip: str = "tool0") -> np.ndarray:
    """Walk the URDF from its root link to ``tip``: origin (xyz, rpy = Rz Ry Rx) then a turn about the axis."""
    root = ET.fromstring(text)
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    chain, link = [], tip
    while link in by_child:
        chain.append(by_child[link])
        link = by_child[link].find("parent").get("link")
    T, i = np.eye(4), 0
    for joint in reversed(chain):
        origin = joint.find("origin")
        x, y, z = (float(v) for v in origin.get("xyz").split())
        roll, pitch, yaw = (float(v) for v in origin.get("rpy").split())
        step = np.eye(4)
        step[:3, :3] = se3.exp_so3(np.array([0, 0, yaw])) @ se3.exp_so3(np.array([0, pitch, 0]))
        step[:3, :3] = step[:3, :3] @ se3.exp_so3(np.array([roll, 0, 0]))
        step[:3, 3] = (x, y, z)
        T = T @ step
        if joint.get("type") == "revolute":
            axis = np.array([float(v) for v in joint.find("axis").get("xyz").split()])
            turn = np.eye(4)
            turn[:3, :3] = se3.exp_so3(axis * q[i])
            T, i = T @ turn, i + 1
    assert i == len(q)
    return T


def test_urdf_of_a_7_joint_fit_reproduces_the_compensator(fit):
    r, path = export(fit, "urdf", "panda.urdf")
    assert r.exit_code == 0, r.stdout + r.stderr
    text = path.read_text()
    comp = fit["comp"]
    assert len(ET.fromstring(text).findall("joint[@type='revolute']")) == 7
    for qi in inside(comp, 5):
        err = se3.log_se3(se3.inv(urdf_fk(text, qi)) @ comp.predict_pose(qi))
        assert np.abs(err).max() < 1e-9


@pytest.mark.parametrize(
    ("fmt", "says"),
    [
        ("urscript", "URScript export of a 7-joint robot is not supported"),
        ("urscript-program", "URScript export of a 7-joint robot is not supported"),
        ("ur-kinematics", "Universal Robots"),
    ],
)
def test_ur_formats_refuse_a_7_joint_robot_in_one_line(fit, fmt, says):
    r, path = export(fit, fmt, f"panda.{fmt}")
    assert r.exit_code == 2
    assert says in r.stderr and "7 joints" in r.stderr.replace("7-joint", "7 joints")
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not path.exists()


def test_filter_corrects_joint_and_pose_programs_of_a_7_joint_robot(fit):
    root, comp = fit["root"], fit["comp"]
    q = inside(comp, 1)[0] + np.linspace(0.0, 0.02, 4)[:, None] * np.array([1, -1, 1, 1, -1, 1, 1])
    (root / "joints.csv").write_text(
        ",".join(f"q{j}" for j in range(1, 8)) + "\n" + "\n".join(",".join(map(repr, row.tolist())) for row in q)
    )
    out = root / "joints-out.csv"
    r = invoke("filter", root / "joints.csv", "--kind", "joints", "--calibration", root / "calib.json", "--out", out)
    assert r.exit_code == 0, r.stdout + r.stderr
    assert "wrote q1..q7" in r.stderr
    rows = np.array([[float(v) for v in line.split(",")] for line in out.read_text().splitlines()[1:]])
    q_cmd, q_nominal = rows[:, 1:8], rows[:, 8:15]
    np.testing.assert_array_equal(q_nominal, q)
    for i in range(len(q)):
        gap = se3.log_se3(se3.inv(comp.predict_pose(q_cmd[i])) @ nominal_fk(q[i]))
        assert np.abs(gap).max() < 1e-10

    # the same program as TCP poses (mm, rotation vectors), solved from a seed near its first row
    T = np.stack([nominal_fk(row) for row in q])
    poses = np.concatenate([T[:, :3, 3] * 1e3, se3.log_so3(T[:, :3, :3])], axis=1)
    (root / "poses.csv").write_text("x,y,z,rx,ry,rz\n" + "\n".join(",".join(map(repr, row.tolist())) for row in poses))
    seed = ",".join(repr(v) for v in (q[0] + 0.01).tolist())
    out = root / "poses-out.csv"
    r = invoke("filter", root / "poses.csv", "--calibration", root / "calib.json", "--length-unit", "mm",
               "--seed-joints", seed, "--out", out)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    rows = np.array([[float(v) for v in line.split(",")] for line in out.read_text().splitlines()[1:]])
    q_cmd, q_nominal = rows[:, 1:8], rows[:, 8:15]
    for i in range(len(q)):
        assert np.abs(se3.log_se3(se3.inv(nominal_fk(q_nominal[i])) @ T[i])).max() < 1e-9
        gap = se3.log_se3(se3.inv(comp.predict_pose(q_cmd[i])) @ T[i])
        assert np.abs(gap).max() < 1e-9

    # a URScript movej program is for a UR controller's six joints
    script = root / "joints.script"
    r = invoke("filter", root / "joints.csv", "--kind", "joints", "--calibration", root / "calib.json",
               "--out", root / "again.csv", "--script", script)  # fmt: skip
    assert r.exit_code == 2
    assert "--script writes a URScript movej program for a UR controller (6 joints); this robot has 7" in r.stderr
    assert not script.exists() and not (root / "again.csv").exists()
