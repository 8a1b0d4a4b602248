"""CalibratedRobot.correct on a redundant arm (7 joints): the least joint change that reaches the pose, so the
self-motion the user commanded (the elbow) is left alone; the bound, range and validity checks of a 6-joint arm;
one configuration and a batch agree.

The arm is the Franka Emika Panda, built here from its published modified-DH parameters (Franka Control Interface
documentation, "Robot and interface specifications"), so these tests do not depend on a robot file. Jacobians are
taken by central differences of ``predict_pose`` (not labcal's twists), so the least-norm property is checked
against the calibrated robot's own poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labcal.compensator import CalibratedRobot, solve
from labcal.compensator.validity import ValidityRegion
from labcal.kinematics import se3
from labcal.kinematics.conversions import from_mdh

PI2 = math.pi / 2
A = [0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088]
D = [0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0]
ALPHA = [0.0, -PI2, PI2, PI2, -PI2, PI2, PI2]
LIMITS = [
    (-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698), (-2.8973, 2.8973),
    (-0.0175, 3.7525), (-2.8973, 2.8973),
]  # fmt: skip
FLANGE = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.107], [0, 0, 0, 1]])
HOME = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8])  # elbow bent, wrist away from its singularities


def panda(theta=(0.0,) * 7):
    """The nominal Panda to its flange; ``theta``: joint zero offsets (MDH θ), i.e. T(q) = T_nominal(q + theta)."""
    rows = [{"a": A[j], "alpha": ALPHA[j], "d": D[j], "theta": theta[j], "limits": list(LIMITS[j])} for j in range(7)]
    return from_mdh(rows, FLANGE, name="panda-mdh")


def configurations(k: int, seed: int, spread: float = 0.4) -> np.ndarray:
    """(k, 7) configurations around HOME, inside the joint limits."""
    q = HOME + np.random.default_rng(seed).uniform(-spread, spread, size=(k, 7))
    lo, hi = np.array(LIMITS).T
    return np.clip(q, lo + 0.05, hi - 0.05)


def calibrated(model, q_data=None) -> CalibratedRobot:
    nominal = panda()
    validity = None if q_data is None else ValidityRegion.from_configurations(q_data)
    return CalibratedRobot(nominal, model, method="local-poe", validity=validity)


@pytest.fixture(scope="module")
def robot():
    """Frames perturbed by ~1 mm / mrad: corrections of about 10 mrad, where iterated minimum-norm steps from q
    would leave a self-motion of ~1e-4 rad in q_cmd − q."""
    nominal = panda()
    model = nominal.perturbed(np.random.default_rng(3).normal(size=(8, 6)) * 1e-3)
    return calibrated(model, configurations(200, seed=1))


def jacobian(robot: CalibratedRobot, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(6, 7) d/dq of the calibrated pose, as twists in the base frame, by central differences."""
    cols = []
    for j in range(7):
        e = np.zeros(7)
        e[j] = h
        cols.append(se3.log_se3(robot.predict_pose(q + e) @ se3.inv(robot.predict_pose(q - e))) / (2 * h))
    return np.stack(cols, axis=1)


def pose_gap(robot: CalibratedRobot, q_cmd: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(k,) largest twist coordinate between the calibrated pose at q_cmd and the nominal pose at q."""
    return np.abs(se3.log_se3(se3.inv(robot.predict_pose(q_cmd)) @ robot.nominal.fk(q))).max(axis=-1)


def test_correction_reaches_the_nominal_pose(robot):
    q = configurations(30, seed=5)
    q_cmd = robot.correct(q)
    assert np.abs(q_cmd - q).max(axis=1).min() > 3e-3  # a real correction, not a no-op
    assert pose_gap(robot, q_cmd, q).max() < 1e-12
    assert pose_gap(robot, q, q).min() > 1e-3  # uncorrected, the calibrated robot misses by millimetres


def test_correction_is_the_least_joint_change(robot):
    """q_cmd − q lies in the row space of J at q_cmd: no part of it moves the arm along its self-motion (J's null
    space), the first-order condition of min |q_cmd − q| over the joints that reach the pose. It equals the analytic
    minimum-norm solution of the problem linearised at q_cmd, J⁺ J (q_cmd − q)."""
    q = configurations(8, seed=6)
    q_cmd = robot.correct(q)
    for i in range(len(q)):
        d = q_cmd[i] - q[i]
        J = jacobian(robot, q_cmd[i])
        least = np.linalg.pinv(J) @ (J @ d)  # the least change with the same first-order effect on the pose
        null = d - least
        assert np.linalg.norm(d) > 3e-3
        assert np.linalg.norm(null) < 1e-9, (i, np.linalg.norm(null), np.linalg.norm(d))
        # and, to first order, the minimum-norm solution of the problem linearised at q itself
        r = se3.log_se3(robot.nominal.fk(q[i]) @ se3.inv(robot.predict_pose(q[i])))
        first_order = np.linalg.pinv(jacobian(robot, q[i])) @ r
        assert np.linalg.norm(d - first_order) < 0.05 * np.linalg.norm(d)


def test_iterated_minimum_norm_steps_would_leave_self_motion(robot):
    """The reason for the total-change step: the same solver with minimum-norm steps from each iterate (change
    not passed) reaches the pose with a self-motion part orders of magnitude above the tolerance above."""
    q = configurations(8, seed=6)
    T_target = robot.nominal.fk(q)

    def residual(qc, rows, jacobian=True):
        return robot.residual(qc, T_target[rows], jacobian)

    class Iterated(solve._Rows):
        def step(self, r, J, weights):
            return solve.gauss_newton_step(r, J, weights)

    rows = Iterated(q, 1e-11)
    for _ in range(10):
        qc, active = rows.active()
        r, J = residual(qc, active)
        if not rows.advance(rows.step(r, J, None)):
            break
    d = rows.out - q
    worst = max(np.linalg.norm(d[i] - np.linalg.pinv(J := jacobian(robot, rows.out[i])) @ (J @ d[i])) for i in range(8))
    assert pose_gap(robot, rows.out, q).max() < 1e-12
    assert worst > 1e-6


def test_an_error_that_is_pure_self_motion_needs_no_correction():
    """A model whose joint zeros are off along the self-motion at q (T_model(q) = T_nominal(q + ε n), n the null
    vector of J at q) reaches the nominal pose at q already, to first order: the least correction is O(ε²), not the
    −ε n that undoing the joint offsets would command (and would turn the elbow by ε)."""
    q = HOME.copy()
    J = panda().joint_twists(q[None])[0]
    null = np.linalg.svd(J)[2][-1]  # unit null vector of the 6 × 7 Jacobian
    eps = 1e-3
    model = panda(theta=tuple(eps * null))
    robot = CalibratedRobot(panda(), model, method="local-poe")
    assert np.abs(model.fk(q[None])[0] - panda().fk((q + eps * null)[None])[0]).max() < 1e-15
    q_cmd = robot.correct(q)
    assert np.linalg.norm(q_cmd - q) < 1e-2 * eps, np.linalg.norm(q_cmd - q)
    assert pose_gap(robot, q_cmd[None], q[None]).max() < 1e-12
    # a model whose offsets are not self-motion is corrected by about their size (the test can tell the two apart)
    other = np.linalg.svd(J)[2][0]
    robot2 = CalibratedRobot(panda(), panda(theta=tuple(eps * other)), method="local-poe")
    assert np.linalg.norm(robot2.correct(q) - q) > 0.5 * eps


def test_one_configuration_and_a_batch_agree(robot):
    q = configurations(12, seed=7)
    batch = robot.correct(q)
    single = np.stack([robot.correct(row) for row in q])
    np.testing.assert_allclose(single, batch, rtol=0, atol=1e-13)
    tcp = se3.pose(np.array([0.0, 0.05, 0.15]), np.array([0.1, 0.0, 0.0]))
    np.testing.assert_allclose(
        np.stack([robot.correct(row, tcp=tcp) for row in q]), robot.correct(q, tcp=tcp), rtol=0, atol=1e-13
    )
    # an exact correction is the same at every TCP: the least change does not depend on where the pose is measured
    np.testing.assert_allclose(robot.correct(q, tcp=tcp), batch, rtol=0, atol=1e-10)


def test_a_correction_beyond_the_bound_stays_within_it_and_never_makes_the_pose_worse():
    """Joint zeros off by 0.3 rad: the exact correction needs more than MAX_CORRECTION, so the damped mode finds
    the best pose inside the 0.1 rad box, never worse than the uncorrected q."""
    offsets = np.array([0.3, -0.3, 0.3, 0.3, -0.3, 0.3, 0.0])
    q = configurations(6, seed=8, spread=0.2)
    robot = calibrated(panda(theta=tuple(offsets)), configurations(200, seed=1))
    q_cmd = robot.correct(q)
    assert np.abs(q_cmd - q).max() <= solve.MAX_CORRECTION + 1e-12
    w = robot._twist_weights
    before = np.linalg.norm(w * se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.predict_pose(q))), axis=1)
    after = np.linalg.norm(w * se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.predict_pose(q_cmd))), axis=1)
    assert (after < before).all()
    # The single path takes the same damped steps; the best pose in the box lies in a flat valley of the cost, so
    # the one-row and the batched arithmetic's rounding stop at points ~1e-7 rad apart along it (same pose error).
    single = np.stack([robot.correct(row) for row in q])
    np.testing.assert_allclose(single, q_cmd, rtol=0, atol=1e-6)
    assert np.abs(single - q).max() <= solve.MAX_CORRECTION + 1e-12


def test_range_and_validity_checks_name_the_joint_and_the_configuration(robot):
    q = configurations(3, seed=9)
    q[1, 6] = 3.0  # joint 7 beyond its 2.8973 rad limit
    with pytest.raises(ValueError, match=r"configuration 1: joint 7 = 3\.000000 is outside the calibrated range"):
        robot.correct(q)
    far = HOME + np.array([1.2, 0.9, -1.5, 0.8, 1.4, -1.0, 1.1])  # inside the limits, far from the data
    assert (far > np.array(LIMITS)[:, 0]).all() and (far < np.array(LIMITS)[:, 1]).all()
    with pytest.raises(ValueError, match=r"configuration 0 is .* beyond its validity radius"):
        robot.correct(far)
    assert robot.correct(far, extrapolate=True).shape == (7,)
