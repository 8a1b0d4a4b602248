"""Eq. (18, 21): observed joint motion errors of the equivalent robot, and the condition filter."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.calibration.equivalent import joint_error_observations, point_matrix
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.robots import load

TARGETS = np.array([[0.1, 0.0, 0.0], [0.0, 0.15, 0.0], [0.0, 0.0, 0.2]])


def brute_force_points(model, base, q, rho):
    """Points of a robot whose joints move by δρ_a and whose virtual joints move by exp of their K0 twists."""
    n = model.n
    T = model.fk(q + rho[:, :n])
    if n < 6:
        virtual = base.equivalent_jacobian(q)[:, :, n:]
        T = se3.exp_se3(np.einsum("kab,kb->ka", virtual, rho[:, n:])) @ T
    return np.einsum("kab,mb->kma", T[:, :3, :3], TARGETS) + T[:, None, :3, 3]


@pytest.mark.parametrize("robot", ["ur10", "scara4"])
def test_eq21_recovers_a_known_small_joint_motion_error(robot):
    model = load(robot).model
    base = CalibratedRobot(nominal=model, model=model)
    rng = np.random.default_rng(3)
    q = rng.uniform(model.limits[:, 0] * 0.5, model.limits[:, 1] * 0.5, size=(40, model.n))
    rho = rng.normal(0.0, 1e-6, size=(40, 6))
    obs = Observations(q, brute_force_points(model, base, q, rho), TARGETS)
    jeo = joint_error_observations(obs, base, max_condition=1e5, soft_condition=None)
    kept = jeo.kept
    assert kept.sum() >= 35
    # First-order model: the error left is second order in δρ (≈1e-12) amplified by the conditioning.
    np.testing.assert_allclose(jeo.delta_rho[kept], rho[kept], atol=1e-9)


def test_point_matrix_sign_moves_points_like_a_small_twist():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(5, 3, 3))
    dy = rng.normal(0.0, 1e-7, size=(5, 6))
    moved = np.einsum("kab,kmb->kma", se3.exp_se3(dy)[:, :3, :3], p) + se3.exp_se3(dy)[:, None, :3, 3]
    np.testing.assert_allclose(np.einsum("kab,kb->ka", point_matrix(p), dy), (moved - p).reshape(5, 9), atol=1e-12)


def test_tracker_frame_residuals_are_rotated_back_into_the_base_frame():
    model = load("ur10").model
    T_tb = se3.pose([1.0, -2.0, 0.5], [0.3, -0.2, 1.1])
    base = CalibratedRobot(nominal=model, model=model)
    base_t = CalibratedRobot(nominal=model, model=model, T_tracker_base=T_tb)
    rng = np.random.default_rng(1)
    q = rng.uniform(-1.5, 1.5, size=(10, 6))
    q[:, 4] = 1.0
    rho = rng.normal(0.0, 1e-6, size=(10, 6))
    pts = brute_force_points(model, base, q, rho)
    in_tracker = np.einsum("ab,kmb->kma", T_tb[:3, :3], pts) + T_tb[:3, 3]
    a = joint_error_observations(Observations(q, pts, TARGETS), base)
    b = joint_error_observations(Observations(q, in_tracker, TARGETS, frame="tracker"), base_t)
    np.testing.assert_allclose(b.delta_rho, a.delta_rho, atol=1e-10)
    np.testing.assert_allclose(b.delta_rho, rho, atol=1e-9)


def test_condition_filter_drops_a_wrist_singularity_and_says_why():
    model = load("ur10").model
    base = CalibratedRobot(nominal=model, model=model)
    q = np.array(
        [[0.3, -1.2, 1.4, -1.0, 1.2, 0.4], [0.3, -1.2, 1.4, -1.0, 0.0, 0.4], [0.3, -1.2, 1.4, -1.0, 1e-3, 0.4]]
    )
    obs = Observations(q, model.target_points(q, TARGETS), TARGETS)
    jeo = joint_error_observations(obs, base)
    assert jeo.kept.tolist() == [True, False, False]
    assert "singular" in jeo.reason[1]
    assert jeo.reason[2].startswith("condition >")
    s = jeo.summary()
    assert s["dropped"] == 2 and sum(s["dropped_reasons"].values()) == 2
    # With the filter off, only the exactly singular row is refused.
    assert joint_error_observations(obs, base, max_condition=None).kept.tolist() == [True, False, True]


def test_soft_band_downweights_by_the_squared_condition_ratio():
    model = load("ur10").model
    base = CalibratedRobot(nominal=model, model=model)
    q = np.array([[0.3, -1.2, 1.4, -1.0, q5, 0.4] for q5 in (1.2, 0.05, 0.02)])
    obs = Observations(q, model.target_points(q, TARGETS), TARGETS)
    plain = joint_error_observations(obs, base, max_condition=1e5, soft_condition=None)
    soft = 0.5 * plain.condition.min() + 0.5 * plain.condition.max()
    jeo = joint_error_observations(obs, base, max_condition=1e5, soft_condition=soft)
    expected = np.where(plain.condition > soft, (soft / plain.condition) ** 2, 1.0)
    np.testing.assert_allclose(jeo.weight, expected)
    assert jeo.weight[0] == 1.0 and jeo.weight[-1] < 1.0


def test_bad_input_is_refused_clearly():
    model = load("ur10").model
    base = CalibratedRobot(nominal=model, model=model)
    obs = Observations(np.zeros((2, 4)), np.zeros((2, 3, 3)), TARGETS)
    with pytest.raises(ValueError, match="joint values per row"):
        joint_error_observations(obs, base)
    ok = Observations(np.zeros((2, 6)), np.zeros((2, 3, 3)), TARGETS)
    with pytest.raises(ValueError, match="soft_condition"):
        joint_error_observations(ok, base, max_condition=10.0, soft_condition=100.0)
