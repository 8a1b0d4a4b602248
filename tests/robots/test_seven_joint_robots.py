"""The 7-joint built-ins (Franka Emika Panda, KUKA LBR iiwa 14 R820) against their makers' published numbers.

The reference kinematics here are written from the published documents, not read from the robot files: the Panda
as Franka's modified-DH product plus the flange row, the iiwa as a space-frame product of exponentials from the
joint axes of its zero pose and the KUKA link lengths (a different construction from the file's DH rows).
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from labcal.robots import BUILTINS, builtin_path, load

HALF_PI = np.pi / 2
SEVEN = ("franka-panda", "kuka-iiwa14-r820")


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _shift(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


# FCI "Robot and interface specifications": a_{j-1}, d_j, alpha_{j-1} (Craig), then the flange row d = 0.107.
PANDA_A = [0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088]
PANDA_D = [0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0]
PANDA_ALPHA = [0.0, -HALF_PI, HALF_PI, HALF_PI, -HALF_PI, HALF_PI, HALF_PI]
PANDA_Q_MIN = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
PANDA_Q_MAX = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
PANDA_DQ_MAX = [2.1750, 2.1750, 2.1750, 2.1750, 2.6100, 2.6100, 2.6100]


def panda_flange(q: np.ndarray) -> np.ndarray:
    """Franka's flange F in the base frame: Π Rx(α_{j-1}) Tx(a_{j-1}) Rz(q_j) Tz(d_j), then Tz(0.107)."""
    T = np.eye(4)
    for a, d, alpha, qj in zip(PANDA_A, PANDA_D, PANDA_ALPHA, q, strict=True):
        T = T @ _rot_x(alpha) @ _shift(x=a) @ _rot_z(qj) @ _shift(z=d)
    return T @ _shift(z=0.107)


# KUKA spec: 360 mm base to A2, 420 mm A2 to A4, 400 mm A4 to A6, 126 mm A6 to the flange; at q = 0 the arm stands
# straight up, A1/A3/A5/A7 along base z, A2 and A6 along +y, A4 along −y.
IIWA_AXES = [(0, 0, 1), (0, 1, 0), (0, 0, 1), (0, -1, 0), (0, 0, 1), (0, 1, 0), (0, 0, 1)]
IIWA_HEIGHTS = [0.0, 0.360, 0.0, 0.780, 0.0, 1.180, 0.0]  # a point on each axis: (0, 0, h)
IIWA_FLANGE_Z = 0.360 + 0.420 + 0.400 + 0.126
IIWA_LIMITS_DEG = [170, 120, 170, 120, 170, 120, 175]
IIWA_SPEEDS_DEG = [85, 85, 100, 75, 130, 135, 135]


def _screw_exp(w, p, theta: float) -> np.ndarray:
    """The rigid motion of a turn by theta about the line through p with unit direction w (Rodrigues)."""
    w, p = np.asarray(w, float), np.asarray(p, float)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    R = np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p - R @ p
    return T


def iiwa_flange(q: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    for w, h, qj in zip(IIWA_AXES, IIWA_HEIGHTS, q, strict=True):
        T = T @ _screw_exp(w, (0.0, 0.0, h), qj)
    return T @ _shift(z=IIWA_FLANGE_Z)


def _random_q(limits: np.ndarray, k: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(limits[:, 0], limits[:, 1], size=(k, len(limits)))


def test_both_are_builtins_with_seven_revolute_joints():
    for name in SEVEN:
        assert name in BUILTINS
        spec = load(name)
        assert spec.name == name and spec.model.n == 7
        assert spec.model.joint_types == ("revolute",) * 7


def test_panda_zero_pose_is_franka_flange():
    # q = 0: the flange sits 0.088 m forward at 0.333 + 0.316 + 0.384 − 0.107 m, its z axis pointing down.
    T = load("franka-panda").model.fk(np.zeros(7))
    np.testing.assert_allclose(T[:3, 3], [0.088, 0.0, 0.926], atol=1e-15)
    np.testing.assert_allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-15)


def test_panda_matches_the_fci_modified_dh_product_everywhere():
    model = load("franka-panda").model
    q = _random_q(model.limits, 50, seed=3)
    for qi, Ti in zip(q, model.fk(q), strict=True):
        np.testing.assert_allclose(Ti, panda_flange(qi), atol=1e-14)


def test_panda_ready_pose():
    # Franka's "ready" pose, where libfranka reports the hand's nominal end effector (0.1034 m beyond the flange)
    # at about (0.307, 0, 0.487) m with the flange pointing straight down.
    q = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])
    T = load("franka-panda").model.fk(q)
    np.testing.assert_allclose(T, panda_flange(q), atol=1e-14)
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)  # pointing straight down
    np.testing.assert_allclose(T[:3, 3] + 0.1034 * T[:3, 2], [0.307, 0.0, 0.487], atol=1e-3)


def test_iiwa_zero_pose_and_joint_axes():
    model = load("kuka-iiwa14-r820").model
    T = model.fk(np.zeros(7))
    np.testing.assert_allclose(T, _shift(z=1.306), atol=1e-15)
    twists = model.joint_twists(np.zeros((1, 7)))[0]  # (6, n) space twists (v, ω)
    np.testing.assert_allclose(twists[3:].T, IIWA_AXES, atol=1e-15)
    for j, h in enumerate(IIWA_HEIGHTS):  # v = −ω × p for a point p = (0, 0, h) on the axis
        np.testing.assert_allclose(twists[:3, j], -np.cross(IIWA_AXES[j], (0.0, 0.0, h)), atol=1e-15)


def test_iiwa_matches_a_product_of_exponentials_from_kuka_dimensions():
    model = load("kuka-iiwa14-r820").model
    q = _random_q(model.limits, 50, seed=4)
    for qi, Ti in zip(q, model.fk(q), strict=True):
        np.testing.assert_allclose(Ti, iiwa_flange(qi), atol=1e-14)


def test_limits_speeds_and_torques_are_the_published_ones():
    panda = load("franka-panda")
    np.testing.assert_array_equal(panda.model.limits, np.column_stack([PANDA_Q_MIN, PANDA_Q_MAX]))
    iiwa = load("kuka-iiwa14-r820")
    lim = np.radians(IIWA_LIMITS_DEG)
    np.testing.assert_allclose(iiwa.model.limits, np.column_stack([-lim, lim]), rtol=1e-15)
    rows = {name: tomllib.loads(builtin_path(name).read_text())["joints"] for name in SEVEN}
    assert [r["velocity"] for r in rows["franka-panda"]] == PANDA_DQ_MAX
    assert [r["effort"] for r in rows["franka-panda"]] == [87.0] * 4 + [12.0] * 3
    np.testing.assert_allclose([r["velocity"] for r in rows["kuka-iiwa14-r820"]], np.radians(IIWA_SPEEDS_DEG))
    assert [r["effort"] for r in rows["kuka-iiwa14-r820"]] == [320.0, 320.0, 176.0, 176.0, 110.0, 40.0, 40.0]


@pytest.mark.parametrize("name", SEVEN)
def test_masses_are_given_so_the_simulator_has_gravity_torques(name):
    spec = load(name)
    assert spec.masses.shape == (8,) and np.all(spec.masses[:7] > 0)
