"""The simulated actual robot: determinism, error-free limit, gravity torques, compliance scaling, the tracker."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labcal.kinematics import se3
from labcal.robots import BUILTINS, load
from labcal.simulation import GRAVITY, ErrorSpec, simulate

TARGETS = np.array([[0.1, 0.0, 0.05], [0.0, 0.1, 0.05], [-0.1, -0.1, 0.02]])


def _random_q(model, k: int, seed: int) -> np.ndarray:
    lo, hi = np.maximum(model.limits[:, 0], -np.pi), np.minimum(model.limits[:, 1], np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, size=(k, model.n))


def _fields(actual) -> dict:
    return {f.name: getattr(actual, f.name) for f in dataclasses.fields(actual)}


def test_same_seed_same_robot_and_different_seed_different_robot():
    spec = load("ur10")
    a, b, c = simulate(spec, seed=7), simulate(spec, seed=7), simulate(spec, seed=8)
    for name, value in _fields(a).items():
        other = _fields(b)[name]
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, other, err_msg=name)
    np.testing.assert_array_equal(a.geometric.frames, b.geometric.frames)
    np.testing.assert_array_equal(a.geometric.twists, b.geometric.twists)
    q = _random_q(spec.model, 20, seed=1)
    np.testing.assert_array_equal(a.true_pose(q), b.true_pose(q))
    np.testing.assert_array_equal(
        a.measure(q, TARGETS, np.random.default_rng(3)), b.measure(q, TARGETS, np.random.default_rng(3))
    )
    assert not np.array_equal(a.delta_zeta, c.delta_zeta)
    assert not np.array_equal(a.true_pose(q), c.true_pose(q))


@pytest.mark.parametrize("robot", BUILTINS)
def test_no_errors_means_the_nominal_robot_and_a_perfect_tracker(robot):
    spec = load(robot)
    actual = simulate(spec, ErrorSpec.none(), seed=1)
    q = _random_q(spec.model, 30, seed=2)
    np.testing.assert_array_equal(actual.joint_errors(q), 0.0)
    np.testing.assert_allclose(actual.true_pose(q), spec.model.fk(q), rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        actual.measure(q, TARGETS, np.random.default_rng(0)), spec.model.target_points(q, TARGETS), atol=1e-15
    )


def test_geometric_errors_are_the_recorded_frame_errors_and_valid_twists():
    spec = load("ur10")
    actual = simulate(spec, ErrorSpec.paper(), seed=4)
    for j in range(spec.model.n + 1):
        np.testing.assert_allclose(
            actual.geometric.frames[j], spec.model.frames[j] @ se3.exp_se3(actual.delta_zeta[j]), atol=1e-15
        )
    # about 0.5 mm / 0.5 mrad: the sample standard deviation over the 21 + 21 draws is within a factor of 2
    for part in (actual.delta_zeta[:, :3], actual.delta_zeta[:, 3:]):
        assert 0.25e-3 < part.std() < 1e-3
    w, v = actual.geometric.twists[:, 3:], actual.geometric.twists[:, :3]
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.sum(v * w, axis=1), 0.0, atol=1e-15)  # pure rotations: no pitch
    assert 0 < np.max(np.abs(w - spec.model.twists[:, 3:])) < 5e-3  # misaligned, slightly
    # the paper's setting has no configuration-dependent joint errors: only constant offsets
    q = _random_q(spec.model, 5, seed=5)
    errs = actual.joint_errors(q)
    np.testing.assert_allclose(errs, np.broadcast_to(actual.joint_offsets, errs.shape), atol=0)
    assert np.all(actual.joint_offsets != 0)


def test_prismatic_axis_errors_keep_a_unit_direction():
    actual = simulate(load("scara4"), ErrorSpec.default(axis_std=1e-2), seed=3)
    t = actual.geometric.twists[2]
    np.testing.assert_allclose(np.linalg.norm(t[:3]), 1.0, atol=1e-15)
    np.testing.assert_array_equal(t[3:], 0.0)


def _link_com_positions(spec, q: np.ndarray) -> np.ndarray:
    """(n+1, 3) centres of mass at q from a separate chain walk: link i rides on the frame after joint i moves."""
    model = spec.model

    def link_poses(qq):
        T, poses = model.frames[0], []
        for j in range(model.n):
            T = T @ se3.exp_se3(model.twists[j] * qq[j])  # exp_se3 is checked against scipy's expm elsewhere
            poses.append(T)
            T = T @ model.frames[j + 1]
        return [*poses, poses[-1]]  # the payload rides on the last link

    now, zero = link_poses(q), link_poses(np.zeros(model.n))
    return np.array([(P @ se3.inv(P0) @ np.append(c, 1.0))[:3] for P, P0, c in zip(now, zero, spec.coms, strict=True)])


@pytest.mark.parametrize("robot", ["ur10", "fanuc-m1000ia", "scara4"])
def test_gravity_torque_is_minus_the_gradient_of_potential_energy(robot):
    spec = load(robot)
    n = spec.model.n
    rng = np.random.default_rng(6)
    # a payload and off-axis centres of mass, so every joint and term is exercised
    spec = dataclasses.replace(
        spec, masses=np.r_[spec.masses[:n], 3.0], coms=spec.coms + rng.normal(size=spec.coms.shape) * 0.05
    )
    actual = simulate(spec, ErrorSpec.none(), seed=0)

    def potential(q):
        return -np.sum(spec.masses * (_link_com_positions(spec, q) @ GRAVITY))

    h = 1e-6
    for q in _random_q(spec.model, 4, seed=7):
        grad = np.array([(potential(q + h * e) - potential(q - h * e)) / (2 * h) for e in np.eye(n)])
        tau = actual.gravity_torque(q)[0]
        scale = np.max(np.abs(grad)) + 1.0
        np.testing.assert_allclose(tau, -grad, rtol=0, atol=1e-6 * scale)
    assert np.max(np.abs(tau)) > 1.0  # the test is not comparing zeros


@pytest.mark.parametrize("robot", BUILTINS)
def test_compliance_is_scaled_to_the_requested_maximum_deflection(robot):
    spec = load(robot)
    deflection = 3e-4
    actual = simulate(spec, ErrorSpec.default(compliance_deflection=deflection), seed=2)
    q = np.random.default_rng(99).uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(3000, spec.model.n))
    tau = actual.gravity_torque(q)
    worst = np.max(np.abs(actual.compliance * tau), axis=0)
    loaded = np.max(np.abs(tau), axis=0) > 1e-6
    assert loaded.sum() >= 1
    np.testing.assert_allclose(worst[loaded], deflection, rtol=0.2)
    # joints gravity cannot load (e.g. a vertical first axis) get no compliance rather than a huge one
    np.testing.assert_array_equal(actual.compliance[~loaded], 0.0)
    # and the compliance really enters the joint errors: switching gears/offsets off leaves c·τ
    only = simulate(spec, dataclasses.replace(ErrorSpec.none(), compliance_deflection=deflection), seed=2)
    np.testing.assert_allclose(only.joint_errors(q[:50]), only.compliance * only.gravity_torque(q[:50]), atol=1e-18)
    assert np.max(np.abs(only.joint_errors(q[:50]))) > 0.3 * deflection


def test_gear_errors_are_periodic_in_the_joint_angle():
    spec = load("ur10")
    actual = simulate(spec, dataclasses.replace(ErrorSpec.none(), gear_std=1e-4), seed=3)
    q = _random_q(spec.model, 10, seed=8)
    e = actual.joint_errors(q)
    np.testing.assert_allclose(actual.joint_errors(q + 2 * np.pi), e, atol=1e-15)
    assert 1e-6 < np.max(np.abs(e)) < 1e-3
    assert not np.allclose(actual.joint_errors(q + np.pi), e)  # the first harmonic is there


def test_tracker_to_base_transform_is_applied():
    spec = load("ur5e")
    T_tb = se3.exp_se3(np.array([1.5, -0.3, 0.8, 0.2, -0.1, 2.5]))
    errors = dataclasses.replace(ErrorSpec.paper(tracker_noise=0.0), T_tracker_base=T_tb)
    actual = simulate(spec, errors, seed=5)
    np.testing.assert_array_equal(actual.T_tracker_base, T_tb)
    q = _random_q(spec.model, 10, seed=9)
    in_base = actual.true_points(q, TARGETS)
    in_tracker = actual.measure(q, TARGETS, np.random.default_rng(0))
    expected = np.einsum("ab,kmb->kma", T_tb[:3, :3], in_base) + T_tb[:3, 3]
    np.testing.assert_allclose(in_tracker, expected, atol=1e-14)
    assert not np.allclose(in_tracker, in_base)
    np.testing.assert_allclose(
        in_base,
        np.einsum("kab,mb->kma", actual.true_pose(q)[:, :3, :3], TARGETS) + actual.true_pose(q)[:, None, :3, 3],
        atol=1e-15,
    )


def test_measurement_noise_has_the_requested_standard_deviation():
    spec = load("ur10")
    sigma = 5e-5
    actual = simulate(spec, dataclasses.replace(ErrorSpec.none(), tracker_noise=sigma), seed=0)
    q = _random_q(spec.model, 3000, seed=10)
    noise = actual.measure(q, TARGETS, np.random.default_rng(1)) - actual.true_points(q, TARGETS)
    assert noise.std() == pytest.approx(sigma, rel=0.03)  # 27,000 draws: the sample std is within ~1 %
    assert abs(noise.mean()) < 3 * sigma / np.sqrt(noise.size)
    for axis in range(3):
        assert noise[..., axis].std() == pytest.approx(sigma, rel=0.05)


def test_repeatability_scatters_the_pose_only_with_an_rng():
    spec = load("ur10")
    actual = simulate(spec, dataclasses.replace(ErrorSpec.none(), repeatability=2e-5), seed=0)
    q = np.tile(_random_q(spec.model, 1, seed=11), (2000, 1))
    np.testing.assert_array_equal(actual.true_pose(q[:3]), spec.model.fk(q[:3]))  # no rng: no scatter
    T = actual.true_pose(q, np.random.default_rng(2))
    spread = T[:, :3, 3] - spec.model.fk(q[:1])[0, :3, 3]
    assert 1e-5 < spread.std() < 1e-4
