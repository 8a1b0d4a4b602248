"""--format ur-kinematics: ur_description's calibration YAML. Forward kinematics is computed here from the YAML with
URDF joint semantics (origin xyz/rpy, then a rotation about the joint's z) — not with labcal's FK — and compared
on the manifold with the calibrated model's predict_pose."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from export_fixtures import hybrid, sample

from labcal.compensator import CalibratedRobot
from labcal.export import export
from labcal.export.ros import UR_SEGMENTS, ur_kinematics_text
from labcal.kinematics import se3
from labcal.robots import load
from labcal.robots.joint_map import JointMap

KEYS = ("x", "y", "z", "roll", "pitch", "yaw")


def parse_yaml(text: str) -> tuple[dict, str, np.ndarray]:
    """The kinematics entries, the hash and the tcp_in_tool0 comment of the file (its strict two-level layout)."""
    entries, current, digest, tcp = {}, None, None, None
    for line in text.splitlines():
        if line.startswith("# tcp_in_tool0: "):
            tcp = np.array([float(v) for v in line.split(": ", 1)[1].split()])
        if not line or line.startswith("#"):
            continue
        if line == "kinematics:":
            continue
        if line.startswith("  hash: "):
            digest = json.loads(line.split(": ", 1)[1])  # a double-quoted YAML scalar (JSON string syntax)
        elif line.startswith("    "):
            key, value = line.strip().split(": ")
            entries[current][key] = float(value)
        elif line.startswith("  ") and line.endswith(":"):
            current = line.strip()[:-1]
            entries[current] = {}
        else:
            raise AssertionError(f"unexpected line {line!r}")
    return entries, digest, tcp


def rot(axis: int, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(4)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def urdf_origin(e: dict) -> np.ndarray:
    """URDF <origin xyz rpy>: translation, then R = Rz(yaw) Ry(pitch) Rx(roll) (fixed axes x, y, z)."""
    T = rot(2, e["yaw"]) @ rot(1, e["pitch"]) @ rot(0, e["roll"])
    T[:3, 3] = (e["x"], e["y"], e["z"])
    return T


def rotation_vector_pose(v: np.ndarray) -> np.ndarray:
    """x, y, z, rx, ry, rz (a UR TCP) → 4×4 by Rodrigues' formula."""
    T = np.eye(4)
    T[:3, 3] = v[:3]
    w = v[3:]
    th = np.linalg.norm(w)
    if th > 0:
        k = w / th
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        T[:3, :3] = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
    return T


def yaml_fk(entries: dict, q: np.ndarray) -> np.ndarray:
    """base_link_inertia → tool0 of the URDF ur_description builds from these entries (tool0 = wrist_3_link)."""
    T = np.eye(4)
    for name, qj in zip(UR_SEGMENTS, q, strict=True):
        T = T @ urdf_origin(entries[name]) @ rot(2, qj)
    return T


# ur_description's config/ur10/default_kinematics.yaml (the UR10's nominal calibration file).
UR10_DEFAULT = {
    "shoulder": (0, 0, 0.1273, 0, 0, 0),
    "upper_arm": (0, 0, 0, 1.570796327, 0, 0),
    "forearm": (-0.612, 0, 0, 0, 0, 0),
    "wrist_1": (-0.5723, 0, 0.163941, 0, 0, 0),
    "wrist_2": (0, -0.1157, -2.373046667922381e-11, 1.570796327, 0, 0),
    "wrist_3": (0, 0.0922, -1.891053610911353e-11, 1.570796326589793, 3.141592653589793, 3.141592653589793),
}


def test_nominal_ur10_reproduces_ur_descriptions_default_file():
    nominal = load("ur10").model
    entries, digest, tcp = parse_yaml(ur_kinematics_text(CalibratedRobot(nominal, nominal)))
    assert list(entries) == list(UR_SEGMENTS) and digest.startswith("labcal_")
    np.testing.assert_allclose(tcp, 0.0, atol=1e-15)
    for name, values in UR10_DEFAULT.items():
        ours, theirs = urdf_origin(entries[name]), urdf_origin(dict(zip(KEYS, values, strict=True)))
        np.testing.assert_allclose(ours, theirs, atol=1e-9, err_msg=name)


@pytest.mark.parametrize("name,odd", [("ur10", False), ("ur10", True), ("ur5e", True), ("ur10e", False)])
def test_yaml_fk_with_urdf_semantics_equals_predict_pose(name, odd):
    robot = hybrid(name, features=None, odd_twists=odd, seed=11)  # a local-POE calibration: frames (and axes) moved
    entries, _, tcp = parse_yaml(ur_kinematics_text(robot))
    q = sample(robot, 40, seed=3, max_cond=1e6)
    T_tcp = rotation_vector_pose(tcp)
    for qi, T_pred in zip(q, robot.predict_pose(q), strict=True):
        err = se3.log_se3(se3.inv(yaml_fk(entries, qi) @ T_tcp) @ T_pred)
        assert np.max(np.abs(err)) < 1e-12
    # the calibration moved the frames: the file is not the nominal one, and the TCP part is a real offset
    nominal_entries, _, _ = parse_yaml(ur_kinematics_text(CalibratedRobot(robot.nominal, robot.nominal)))
    moved = max(abs(entries[s][k] - nominal_entries[s][k]) for s in UR_SEGMENTS for k in KEYS)
    assert moved > 1e-4
    assert np.linalg.norm(tcp[:3]) > 1e-5


def test_base_link_is_the_controller_base_turned_by_pi():
    """ur_description's base_link → base_link_inertia is a turn by π about z: poses in base_link are Rz(π) · ours."""
    robot = hybrid("ur10", features=None, seed=2)
    entries, _, tcp = parse_yaml(ur_kinematics_text(robot))
    q = sample(robot, 1, seed=4)[0]
    in_base_link = rot(2, np.pi) @ yaml_fk(entries, q) @ rotation_vector_pose(tcp)
    T = robot.predict_pose(q)
    np.testing.assert_allclose(in_base_link[:2, 3], -T[:2, 3], atol=1e-12)
    np.testing.assert_allclose(in_base_link[2, 3], T[2, 3], atol=1e-12)


def test_refuses_robots_that_are_not_ur_arms():
    for name in ("fanuc-m1000ia", "scara4"):
        nominal = load(name).model
        with pytest.raises(ValueError, match="Universal Robots"):
            ur_kinematics_text(CalibratedRobot(nominal, nominal))
    nominal = load("ur10").model
    flipped = CalibratedRobot(nominal, nominal, joint_map=JointMap(np.diag([1.0, -1, 1, 1, 1, 1]), np.zeros(6)))
    with pytest.raises(ValueError, match="joint map"):
        ur_kinematics_text(flipped)


def test_learned_term_is_refused_with_its_size_or_noted_when_geometry_only():
    robot = hybrid("ur10", seed=5)
    with pytest.raises(ValueError, match=r"moves the tool by [0-9.]+ mm on average and up to [0-9.]+ mm"):
        ur_kinematics_text(robot)
    text = ur_kinematics_text(robot, geometry_only=True)
    assert "# NOT INCLUDED (geometry only): the learned joint-motion-error term moves the tool by" in text
    geometric = CalibratedRobot(robot.nominal, robot.model)
    body = [line for line in text.splitlines() if not line.startswith("#")]
    assert body == [line for line in ur_kinematics_text(geometric).splitlines() if not line.startswith("#")]


def test_export_dispatch_writes_the_yaml_deterministically(tmp_path):
    robot = hybrid("ur10", features=None, seed=1)
    a = export(robot, "ur-kinematics", tmp_path / "a.yaml", {"fit_id": "f"})
    b = export(robot, "ur-kinematics", tmp_path / "b.yaml", {"fit_id": "f"})
    assert a.read_bytes() == b.read_bytes()
    other = export(hybrid("ur10", features=None, seed=2), "ur-kinematics", tmp_path / "c.yaml")
    assert parse_yaml(other.read_text())[1] != parse_yaml(a.read_text())[1]
