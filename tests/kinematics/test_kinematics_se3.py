"""SE(3)/SO(3) tools: round trips at every angle regime, an independent matrix-exponential oracle, adjoints."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from labcal.kinematics import se3

# Angles where closed forms and series meet or degenerate: zero, the series threshold (1e-2) from both sides,
# and π where the logarithm must switch to the symmetric part of R.
SPECIAL_ANGLES = [0.0, 1e-300, 1e-12, 1e-8, 1e-5, 1e-3, 0.0099, 0.01, 0.0101, 0.02, 0.1, 1.0, 2.0, 3.0]
NEAR_PI = [0.75 * np.pi - 1e-9, 0.75 * np.pi, np.pi - 1e-3, np.pi - 1e-6, np.pi - 1e-9, np.pi]
TOL = 2e-14  # round trips; the unfixed code lost ~1.5e-12 just above the series threshold

unit_vectors = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda x: np.linalg.norm(x) > 0.1)
angles = st.one_of(st.sampled_from(SPECIAL_ANGLES), st.floats(0.0, np.pi - 1e-3))
translations = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)


def _unit(x) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x / np.linalg.norm(x)


def _rodrigues_oracle(w: np.ndarray) -> np.ndarray:
    return scipy.linalg.expm(np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]))


# --------------------------------------------------------------------------------------------------------------
# hat / vee / skew / unskew


@given(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3), st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3))
def test_skew_is_the_cross_product_and_unskew_inverts_it(w, x):
    w, x = np.array(w), np.array(x)
    np.testing.assert_allclose(se3.skew(w) @ x, np.cross(w, x), rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(se3.unskew(se3.skew(w)), w)
    np.testing.assert_array_equal(se3.skew(w), -se3.skew(w).T)


@given(st.lists(st.floats(-1e3, 1e3), min_size=6, max_size=6))
def test_hat_vee_are_inverse_and_order_twists_v_then_omega(xi):
    xi = np.array(xi)
    X = se3.hat(xi)
    np.testing.assert_array_equal(se3.vee(X), xi)
    np.testing.assert_array_equal(X[:3, 3], xi[:3])  # (v, ω): linear part first (paper eq. 4)
    np.testing.assert_array_equal(X[:3, :3], se3.skew(xi[3:]))
    np.testing.assert_array_equal(X[3], 0.0)


def test_unskew_takes_the_antisymmetric_part():
    rng = np.random.default_rng(0)
    w = rng.normal(size=3)
    S = rng.normal(size=(3, 3))
    np.testing.assert_allclose(se3.unskew(se3.skew(w) + S + S.T), w, atol=1e-15)


# --------------------------------------------------------------------------------------------------------------
# SO(3)


@settings(max_examples=150, deadline=None)
@given(unit_vectors, angles)
def test_so3_exp_log_round_trip(axis, theta):
    w = _unit(axis) * theta
    R = se3.exp_so3(w)
    assert np.all(np.isfinite(R))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(se3.log_so3(R), w, rtol=0, atol=TOL)


@settings(max_examples=120, deadline=None)
@given(unit_vectors, st.sampled_from(NEAR_PI))
def test_so3_log_near_pi(axis, theta):
    w = _unit(axis) * theta
    R = se3.exp_so3(w)
    w_back = se3.log_so3(R)
    assert np.all(np.isfinite(w_back))
    assert np.linalg.norm(w_back) == pytest.approx(theta, abs=1e-14)
    np.testing.assert_allclose(se3.exp_so3(w_back), R, atol=1e-14)
    if theta < np.pi:
        # Below π the logarithm is unique, so the axis sign must come out right even 1e-9 rad from π.
        np.testing.assert_allclose(w_back, w, atol=1e-12)


def test_so3_log_at_exactly_pi_of_a_symmetric_matrix():
    # Rotation by π about x: R = diag(1, -1, -1), antisymmetric part exactly zero.
    w = se3.log_so3(np.diag([1.0, -1.0, -1.0]))
    assert np.abs(w[0]) == pytest.approx(np.pi, abs=1e-15)
    np.testing.assert_allclose(w[1:], 0.0, atol=1e-15)
    axis = _unit([1.0, 2.0, -2.0])
    R = 2 * np.outer(axis, axis) - np.eye(3)  # rotation by π about axis, built without exp_so3
    w = se3.log_so3(R)
    np.testing.assert_allclose(np.abs(w), np.pi * np.abs(axis), atol=1e-14)


@settings(max_examples=100, deadline=None)
@given(unit_vectors, st.floats(0.0, 3.0))
def test_so3_exp_matches_matrix_exponential_oracle(axis, theta):
    w = _unit(axis) * theta
    np.testing.assert_allclose(se3.exp_so3(w), _rodrigues_oracle(w), atol=1e-14)


# --------------------------------------------------------------------------------------------------------------
# SE(3)


@settings(max_examples=150, deadline=None)
@given(unit_vectors, angles, translations)
def test_se3_exp_log_round_trip(axis, theta, v):
    xi = np.concatenate([v, _unit(axis) * theta])
    T = se3.exp_se3(xi)
    assert np.all(np.isfinite(T))
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(se3.log_se3(T), xi, rtol=0, atol=TOL * (1 + np.linalg.norm(xi)))


@settings(max_examples=120, deadline=None)
@given(unit_vectors, st.sampled_from(NEAR_PI), translations)
def test_se3_log_near_pi(axis, theta, v):
    xi = np.concatenate([v, _unit(axis) * theta])
    T = se3.exp_se3(xi)
    xi_back = se3.log_se3(T)
    assert np.all(np.isfinite(xi_back))
    np.testing.assert_allclose(se3.exp_se3(xi_back), T, atol=1e-13)
    if theta < np.pi:
        np.testing.assert_allclose(xi_back, xi, atol=1e-11)


def test_pure_translation_and_identity():
    np.testing.assert_array_equal(se3.log_se3(np.eye(4)), np.zeros(6))
    np.testing.assert_array_equal(se3.log_so3(np.eye(3)), np.zeros(3))
    np.testing.assert_array_equal(se3.exp_se3(np.zeros(6)), np.eye(4))
    T = se3.exp_se3(np.array([1.0, -2.0, 3.0, 0, 0, 0]))
    np.testing.assert_array_equal(T[:3, 3], [1.0, -2.0, 3.0])
    np.testing.assert_array_equal(T[:3, :3], np.eye(3))


def test_exp_of_a_unit_rotation_twist_rotates_about_its_axis_line():
    # ξ = (−ω × r, ω) is a rotation about the line through r: r must stay fixed, and r + ω too.
    rng = np.random.default_rng(3)
    for _ in range(20):
        w, r, theta = _unit(rng.normal(size=3)), rng.normal(size=3), rng.uniform(-3, 3)
        T = se3.exp_se3(np.concatenate([-np.cross(w, r), w]) * theta)
        for point in (r, r + w):
            np.testing.assert_allclose(T[:3, :3] @ point + T[:3, 3], point, atol=1e-14)


def test_se3_matches_scipy_expm_and_logm_for_random_twists():
    rng = np.random.default_rng(11)
    for i in range(40):
        xi = np.concatenate([rng.normal(size=3), _unit(rng.normal(size=3)) * rng.uniform(0.0, 3.0)])
        T_oracle = scipy.linalg.expm(se3.hat(xi))
        np.testing.assert_allclose(se3.exp_se3(xi), T_oracle, atol=1e-13)
        if i < 8:  # logm is slow
            logm = np.real(scipy.linalg.logm(T_oracle))
            np.testing.assert_allclose(se3.log_se3(T_oracle), se3.vee(logm), atol=1e-10)


@settings(max_examples=120, deadline=None)
@given(
    st.lists(st.floats(-2, 2), min_size=6, max_size=6),
    unit_vectors,
    st.one_of(st.sampled_from(SPECIAL_ANGLES), st.floats(0.0, np.pi)),
    st.lists(st.floats(-2, 2), min_size=3, max_size=3),
)
def test_adjoint_identity(pose_twist, axis, theta, v):
    T = se3.exp_se3(np.array(pose_twist))
    xi = np.concatenate([v, _unit(axis) * theta])
    lhs = T @ se3.exp_se3(xi) @ se3.inv(T)
    rhs = se3.exp_se3(se3.adjoint(T) @ xi)
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_adjoint_is_a_group_homomorphism():
    rng = np.random.default_rng(5)
    A, B = se3.exp_se3(rng.normal(size=(2, 6)))
    np.testing.assert_allclose(se3.adjoint(A @ B), se3.adjoint(A) @ se3.adjoint(B), atol=1e-13)
    np.testing.assert_allclose(se3.adjoint(se3.inv(A)), np.linalg.inv(se3.adjoint(A)), atol=1e-12)


def test_inverse():
    rng = np.random.default_rng(2)
    T = se3.exp_se3(rng.normal(size=(10, 6)) * 2)
    np.testing.assert_allclose(T @ se3.inv(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-14)
    np.testing.assert_allclose(se3.inv(T), np.linalg.inv(T), atol=1e-13)


# --------------------------------------------------------------------------------------------------------------
# batching and tiny angles


def test_batched_calls_equal_single_calls():
    rng = np.random.default_rng(7)
    xi = rng.normal(size=(3, 4, 6))
    xi[0, 0, 3:] = 0.0  # exactly zero angle inside a batch
    xi[0, 1, 3:] *= 1e-9
    xi[1, 0, 3:] = [np.pi, 0, 0]  # exactly π inside a batch
    xi[1, 1, 3:] = _unit([1, 2, 3]) * (np.pi - 1e-9)
    single = {
        "exp_se3": np.array([[se3.exp_se3(x) for x in row] for row in xi]),
        "exp_so3": np.array([[se3.exp_so3(x[3:]) for x in row] for row in xi]),
    }
    T = se3.exp_se3(xi)
    assert T.shape == (3, 4, 4, 4)
    np.testing.assert_array_equal(T, single["exp_se3"])
    np.testing.assert_array_equal(se3.exp_so3(xi[..., 3:]), single["exp_so3"])
    checks = {
        se3.log_se3: T,
        se3.log_so3: T[..., :3, :3],
        se3.adjoint: T,
        se3.inv: T,
        se3.hat: xi,
        se3.skew: xi[..., 3:],
        se3.matrix_to_rpy: T[..., :3, :3],
    }
    for fn, arg in checks.items():
        batched = fn(arg)
        looped = np.array([[fn(a) for a in row] for row in arg])
        np.testing.assert_array_equal(batched, looped, err_msg=fn.__name__)


@pytest.mark.parametrize("theta", [0.0, 1e-300, 1e-200, 1e-16, 1e-12, 1e-8, 1e-5])
def test_no_nan_at_tiny_angles(theta):
    rng = np.random.default_rng(1)
    w = _unit(rng.normal(size=3)) * theta
    xi = np.concatenate([rng.normal(size=3), w])
    T = se3.exp_se3(xi)
    outputs = [se3.exp_so3(w), T, se3.log_se3(T), se3.log_so3(T[:3, :3]), se3.adjoint(T), *se3.pose_distance(T, T)]
    for out in outputs:
        assert np.all(np.isfinite(out))
    np.testing.assert_allclose(se3.log_se3(T), xi, atol=1e-15)


# --------------------------------------------------------------------------------------------------------------
# URDF roll-pitch-yaw, poses, distances


def _rx(a):
    return _rodrigues_oracle(np.array([a, 0, 0]))


def _ry(a):
    return _rodrigues_oracle(np.array([0, a, 0]))


def _rz(a):
    return _rodrigues_oracle(np.array([0, 0, a]))


def test_rpy_convention_is_fixed_axes_xyz():
    r, p, y = 0.3, -0.7, 2.1
    np.testing.assert_allclose(se3.rpy_to_matrix([r, p, y]), _rz(y) @ _ry(p) @ _rx(r), atol=1e-15)


@settings(max_examples=150, deadline=None)
@given(
    st.floats(-np.pi, np.pi),
    st.one_of(
        st.floats(-np.pi / 2, np.pi / 2),
        st.sampled_from([np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-6, np.pi / 2 - 1e-8, -np.pi / 2 + 1e-7]),
    ),
    st.floats(-np.pi, np.pi),
)
def test_rpy_round_trip_including_gimbal_lock(r, p, y):
    R = se3.rpy_to_matrix([r, p, y])
    rpy = se3.matrix_to_rpy(R)
    # Near the lock, roll and yaw are individually ill-defined; the rotation must still come back exactly.
    np.testing.assert_allclose(se3.rpy_to_matrix(rpy), R, atol=1e-14)
    assert -np.pi / 2 <= rpy[1] <= np.pi / 2


def test_rpy_at_exact_lock_sets_roll_to_zero():
    rpy = se3.matrix_to_rpy(_ry(np.pi / 2) @ _rx(0.4))
    assert rpy[0] == 0.0
    assert rpy[1] == pytest.approx(np.pi / 2, abs=1e-15)


def test_pose_and_pose_distance():
    rng = np.random.default_rng(4)
    xyz, rpy = rng.normal(size=3), rng.normal(size=3)
    T = se3.pose(xyz, rpy)
    np.testing.assert_array_equal(T[:3, 3], xyz)
    np.testing.assert_array_equal(T[:3, :3], se3.rpy_to_matrix(rpy))
    np.testing.assert_array_equal(se3.pose(xyz)[:3, :3], np.eye(3))
    for angle in (1e-9, 0.3, 3.0, np.pi):
        axis = _unit(rng.normal(size=3))
        shift = np.eye(4)
        shift[:3, :3] = _rodrigues_oracle(axis * angle)
        shift[:3, 3] = [0.003, 0.0, -0.004]
        dp, dr = se3.pose_distance(shift @ T, T)
        assert dr == pytest.approx(angle, rel=1e-9)
        assert dp == pytest.approx(np.linalg.norm(shift[:3, :3] @ xyz + shift[:3, 3] - xyz), rel=1e-12)
