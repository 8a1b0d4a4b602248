"""Every Jacobian against central finite differences of the forward kinematics, on every built-in robot."""

from __future__ import annotations

import numpy as np
import pytest
from kin_testutil import general_model, random_q

from labcal.kinematics import se3
from labcal.kinematics.poe import LocalPOEModel
from labcal.robots import BUILTINS, load

H = 1e-6  # central differences: truncation ~h² ≈ 1e-12, rounding ~1e-16/h ≈ 1e-10
FD_TOL = 1e-8


def _models() -> list[tuple[str, LocalPOEModel]]:
    return [(name, load(name).model) for name in BUILTINS] + [("general", general_model())]


def _spatial_difference(T_plus: np.ndarray, T_minus: np.ndarray, T: np.ndarray, h: float) -> np.ndarray:
    """(log(T₊T⁻¹) − log(T₋T⁻¹)) / 2h: the spatial twist (in K0) of d pose / d parameter."""
    T_inv = se3.inv(T)
    return (se3.log_se3(T_plus @ T_inv) - se3.log_se3(T_minus @ T_inv)) / (2 * h)


@pytest.mark.parametrize(("name", "model"), _models(), ids=[n for n, _ in _models()])
def test_joint_twists_are_the_derivative_of_the_pose(name, model):
    q = random_q(model, 16, seed=20)
    T, J = model.fk_and_twists(q)
    for j in range(model.n):
        dq = np.zeros(model.n)
        dq[j] = H
        fd = _spatial_difference(model.fk(q + dq), model.fk(q - dq), T, H)
        np.testing.assert_allclose(J[:, :, j], fd, rtol=0, atol=FD_TOL, err_msg=f"{name} joint {j + 1}")


@pytest.mark.parametrize(("name", "model"), _models(), ids=[n for n, _ in _models()])
def test_frame_jacobian_is_the_derivative_with_respect_to_frame_perturbations(name, model):
    q = random_q(model, 6, seed=21)
    T = model.fk(q)
    J = model.frame_jacobian(q)
    assert J.shape == (len(q), 6, 6 * (model.n + 1))
    for p in range(6 * (model.n + 1)):
        dz = np.zeros(6 * (model.n + 1))
        dz[p] = H
        fd = _spatial_difference(model.perturbed(dz).fk(q), model.perturbed(-dz).fk(q), T, H)
        np.testing.assert_allclose(J[:, :, p], fd, rtol=0, atol=FD_TOL, err_msg=f"{name} parameter {p}")


def _scaled(model: LocalPOEModel, J: np.ndarray) -> np.ndarray:
    D = np.array([1 / model.reach()] * 3 + [1.0] * 3)
    return D[:, None] * J


@pytest.mark.parametrize("robot", BUILTINS)
def test_equivalent_jacobian_is_full_rank_and_starts_with_the_joint_twists(robot):
    model = load(robot).model
    q = random_q(model, 50, seed=22)
    J_rho = model.equivalent_jacobian(q)
    assert J_rho.shape == (50, 6, max(6, model.n))  # n > 6: the joint twists alone, no virtual joints
    np.testing.assert_array_equal(J_rho[:, :, : model.n], model.joint_twists(q))
    scaled = _scaled(model, J_rho)
    assert np.all(np.linalg.matrix_rank(scaled) == 6)
    cond = np.linalg.cond(scaled)
    assert np.all(np.isfinite(cond)) and np.all(cond < 1e6), f"worst condition number {cond.max():.3g}"


def test_equivalent_jacobian_detects_a_wrist_singularity():
    # UR wrist singularity at q5 = 0 (axes 4 and 6 parallel): a rank test that cannot see it would be worthless.
    model = load("ur10").model
    J = model.equivalent_jacobian(np.array([0.3, -1.2, 1.1, -0.5, 0.0, 0.7]))
    assert np.linalg.matrix_rank(_scaled(model, J)[0], tol=1e-9) == 5


def test_scara_virtual_joints_are_the_two_horizontal_rotations_and_constant():
    model = load("scara4").model
    q = random_q(model, 30, seed=23)
    J_rho = model.equivalent_jacobian(q)
    scaled = _scaled(model, J_rho)
    virtual = scaled[:, :, 4:]
    # orthonormal among themselves, orthogonal to every actuated twist, in the length-scaled metric
    np.testing.assert_allclose(
        np.einsum("kai,kaj->kij", virtual, virtual), np.broadcast_to(np.eye(2), (30, 2, 2)), atol=1e-12
    )
    np.testing.assert_allclose(np.einsum("kai,kaj->kij", scaled[:, :, :4], virtual), 0.0, atol=1e-12)
    # a SCARA cannot tilt its tool: the missing motions are rotations about base x and y, the same at every q
    np.testing.assert_allclose(
        np.abs(J_rho[:, :, 4:]), np.broadcast_to(np.abs(J_rho[0, :, 4:]), (30, 6, 2)), atol=1e-12
    )
    np.testing.assert_allclose(np.abs(J_rho[0, :, 4:]).T, [[0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0]], atol=1e-12)


def test_equivalent_jacobian_uses_the_given_length_scale():
    model = load("scara4").model
    q = random_q(model, 3, seed=24)
    a, b = model.equivalent_jacobian(q, length_scale=0.5), model.equivalent_jacobian(q)
    np.testing.assert_array_equal(a[:, :, :4], b[:, :, :4])
    assert np.all(np.isfinite(a))


def test_equivalent_jacobian_of_a_planar_arm_has_three_virtual_joints():
    # n = 3 < 6 with a non-constant complement: still full rank, batch equals single
    model = LocalPOEModel.from_frames(
        np.array([np.eye(4), se3.pose([0.5, 0, 0]), se3.pose([0.4, 0, 0]), se3.pose([0.1, 0, 0])]), ("revolute",) * 3
    )
    q = random_q(model, 10, seed=25)
    J = model.equivalent_jacobian(q)
    assert np.all(np.linalg.matrix_rank(_scaled(model, J)) == 6)
    np.testing.assert_array_equal(J[4], model.equivalent_jacobian(q[4])[0])


@pytest.mark.parametrize("n", [3, 5])
def test_virtual_joints_complete_an_orthonormal_basis_in_the_scaled_metric(n):
    # Random axes, so the complement mixes linear and angular parts and the length scaling matters.
    model = general_model(seed=26, n=n)
    q = random_q(model, 8, seed=27)
    J_rho = model.equivalent_jacobian(q)
    scaled = _scaled(model, J_rho)
    virtual = scaled[:, :, n:]
    np.testing.assert_allclose(
        np.einsum("kai,kaj->kij", virtual, virtual), np.broadcast_to(np.eye(6 - n), (8, 6 - n, 6 - n)), atol=1e-12
    )
    np.testing.assert_allclose(np.einsum("kai,kaj->kij", scaled[:, :, :n], virtual), 0.0, atol=1e-12)
    assert np.all(np.linalg.matrix_rank(scaled) == 6)


def test_virtual_joints_stay_independent_when_the_largest_projections_are_dependent():
    # Actuated span at q = 0 (length scale 1 m): a slide along (x + y)/√2, a rotation about y through (1, 0, 0)
    # (scaled twist (e_vz + e_ωy)/√2) and a rotation about z through the origin. The complement's largest coordinate
    # projections are e_ωx (1) and then a four-way tie at 1/√2 whose first two, e_vx and e_vy, project onto
    # ±(e_vx − e_vy)/√2: the same line. Taking both would leave a rounding-noise "virtual joint".
    u = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    model = LocalPOEModel.from_frames(
        np.array([np.eye(4)] * 4),
        ("prismatic", "revolute", "revolute"),
        np.array([[*u, 0, 0, 0], [0, 0, 1, 0, 1, 0], [0, 0, 0, 0, 0, 1]]),
    )
    J_rho = model.equivalent_jacobian(np.zeros(3), length_scale=1.0)[0]
    np.testing.assert_allclose(J_rho[:, 3:].T @ J_rho[:, 3:], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(J_rho[:, :3].T @ J_rho[:, 3:], 0.0, atol=1e-15)
    assert np.linalg.cond(J_rho) < 10
