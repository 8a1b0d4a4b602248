"""The compensator runtime: fast kernels agree with the kinematics reference, correct() solves the calibrated
forward model, exports round-trip and refuse damaged files, and the import stays numpy-only."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from labcal.compensator import (
    CalibratedRobot,
    Compensator,
    CompensatorFileError,
    Network,
    field_checksums,
    input_features,
    solve,
)
from labcal.compensator import save as save_compensator
from labcal.kinematics import se3
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel, poe_joint_twists, poe_link_frames
from labcal.robots import load


def make_network(model, features, hidden=8, seed=0, out=0.5e-3) -> Network:
    rng = np.random.default_rng(seed)
    f = input_features(np.zeros((1, model.n)), features, model).shape[1]
    return Network(
        features=tuple(features),
        weights=(rng.normal(size=(hidden, f)) / np.sqrt(f), rng.normal(size=(6, hidden)) / np.sqrt(hidden)),
        biases=(rng.normal(size=hidden) * 0.1, rng.normal(size=6) * 0.1),
        in_mean=rng.normal(size=f) * 0.1,
        in_scale=rng.uniform(0.5, 2.0, size=f),
        out_mean=rng.normal(size=6) * 1e-4,
        out_scale=np.full(6, out),
    )


def make_series(model, features, seed=0, out=0.5e-3) -> Network:
    """A network without hidden layer (the joint series' and the hybrid's learned term); the first feature's first
    column unused (zero weights), as the series' penalties leave some."""
    rng = np.random.default_rng(seed)
    f = input_features(np.zeros((1, model.n)), features, model).shape[1]
    W = rng.normal(size=(6, f)) / np.sqrt(f)
    W[:, 0] = 0.0
    return Network(
        features=tuple(features),
        weights=(W,),
        biases=(rng.normal(size=6) * 0.1,),
        in_mean=rng.normal(size=f) * 0.1,
        in_scale=rng.uniform(0.5, 2.0, size=f),
        out_mean=rng.normal(size=6) * 1e-4,
        out_scale=np.full(6, out),
    )


def hybrid(robot="ur10", features=("q", "sincos", "sincos2", "gravity"), seed=0, odd_twists=False, pitch=False):
    nominal = load(robot).model
    rng = np.random.default_rng(seed)
    model = nominal.perturbed(rng.normal(size=(nominal.n + 1, 6)) * 0.5e-3)
    if odd_twists:  # axes off z, a shifted axis line and a screw pitch: exercises the general joint path
        tw = model.twists.copy()
        for j, t in enumerate(model.joint_types):
            if t == "revolute":
                w = tw[j, 3:] + rng.normal(size=3) * 2e-3
                w /= np.linalg.norm(w)
                v = rng.normal(size=3) * 2e-3
                tw[j] = np.concatenate([v if pitch else v - (v @ w) * w, w])
            else:
                d = tw[j, :3] + rng.normal(size=3) * 2e-3
                tw[j, :3] = d / np.linalg.norm(d)
        model = model.replace(twists=tw)
    return CalibratedRobot(nominal, model, make_network(model, features, seed=seed), method="hybrid")


def sample(robot: CalibratedRobot, k: int, seed: int, max_cond: float = 100.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    lo, hi = np.maximum(lo, -np.pi), np.minimum(hi, np.pi)
    q = lo + (hi - lo) * rng.uniform(size=(20 * k, robot.n))
    J = robot.model.equivalent_jacobian(q, length_scale=robot.length_scale)
    D = np.array([1 / robot.length_scale] * 3 + [1.0] * 3)
    return q[np.linalg.cond(D[None, :, None] * J) < max_cond][:k]


def reference_predict(robot: CalibratedRobot, q):
    """T_real = exp((J_ρ δρ)^) T_model from the plain kinematics functions (no fast kernels)."""
    T = robot.model.fk(q)
    J = robot.model.equivalent_jacobian(q, length_scale=robot.length_scale)
    rho = robot.network(q, robot.model)
    return se3.exp_se3(np.einsum("kab,kb->ka", J, rho)) @ T


@pytest.mark.parametrize("name,odd", [("ur10", False), ("ur10", True), ("scara4", False), ("scara4", True)])
def test_fast_kernels_match_the_kinematics_reference(name, odd):
    robot = hybrid(name, odd_twists=odd, pitch=odd)
    q = sample(robot, 50, seed=1, max_cond=1e9)
    np.testing.assert_allclose(robot.predict_pose(q), reference_predict(robot, q), atol=1e-13)
    np.testing.assert_allclose(robot.joint_motion_errors(q), robot.network(q, robot.model), atol=1e-15)
    initial, J, _ = robot._evaluate(q)
    np.testing.assert_allclose(J, poe_joint_twists(robot.model.frames, robot.model.twists, q), atol=1e-13)
    np.testing.assert_allclose(initial, poe_link_frames(robot.model.frames, robot.model.twists, q), atol=1e-13)


@pytest.mark.parametrize("name", ["ur10", "fanuc-m1000ia"])
def test_correct_reaches_the_nominal_pose_and_matches_the_converged_solution(name):
    robot = hybrid(name)
    q = sample(robot, 200, seed=2)
    q_cmd = robot.correct(q)
    residual = se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.predict_pose(q_cmd)))
    assert np.max(np.abs(residual)) < 1e-10
    converged = robot.correct(q, iterations=60, tol=1e-16)
    assert np.max(np.abs(q_cmd - converged)) <= 1e-9
    # single-configuration path: same answer
    for i in range(0, 200, 20):
        np.testing.assert_allclose(robot.correct(q[i]), converged[i], atol=1e-9)
    # the correction is real: milliradians, not zero
    assert 1e-4 < np.max(np.abs(q_cmd - q)) < 0.1


def test_correct_lower_mobility_robot_is_least_squares_on_actuated_joints():
    robot = hybrid("scara4")
    q = sample(robot, 40, seed=3, max_cond=1e4)
    # batched, and one at a time (where a step's Jacobian must not be reused: a least-squares zero moves with J)
    for q_cmd in (robot.correct(q), np.array([robot.correct(qi) for qi in q])):
        # At the least-squares solution the scaled residual is orthogonal to the actuated joint twists.
        scale = np.array([1 / robot.length_scale] * 3 + [1.0] * 3)
        r = se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.predict_pose(q_cmd))) * scale
        J = robot.model.joint_twists(q_cmd) * scale[:, None]
        assert np.max(np.abs(np.einsum("kai,ka->ki", J, r))) < 1e-9
        assert np.max(np.abs(q_cmd - q)) > 1e-5


def redundant_robot(seed=3) -> CalibratedRobot:
    """A 7-joint arm (random z-revolute chain) and its calibrated copy: local POE only, no network."""
    rng = np.random.default_rng(seed)
    nominal = LocalPOEModel.from_frames(se3.exp_se3(rng.normal(size=(8, 6)) * 0.3), (REVOLUTE,) * 7)
    return CalibratedRobot(nominal, nominal.perturbed(rng.normal(size=(8, 6)) * 0.5e-3), method="local-poe")


def test_redundant_arm_correct_takes_minimum_norm_gauss_newton_steps(monkeypatch):
    robot = redundant_robot()
    monkeypatch.setattr(solve, "damped_step", lambda *a: pytest.fail("fell back to the damped steps"))
    q = sample(robot, 20, seed=2)
    q_cmd = robot.correct(q)
    assert np.max(np.abs(se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.predict_pose(q_cmd))))) < 1e-12
    for i in range(0, 20, 5):
        np.testing.assert_allclose(robot.correct(q[i]), q_cmd[i], rtol=0, atol=1e-12)
    # Minimum norm: no motion along the self-motion (the null space of the joint twists at q), to first order.
    dq = q_cmd - q
    for J, d in zip(robot.model.joint_twists(q), dq, strict=True):
        null = np.linalg.svd(J)[2][-1]
        assert abs(null @ d) < 1e-2 * np.linalg.norm(d)
    assert np.max(np.abs(dq)) > 1e-4


def test_a_redundant_arms_network_moves_each_of_its_joints_by_its_output():
    """n > 6: one network output per joint, δρ applied as exp(Σ δρ_j ξ_j) on the model (eq. 14); six outputs for a
    7-joint arm are refused naming both counts."""
    robot = redundant_robot()
    with pytest.raises(ValueError, match=r"network has 6 outputs; .* 7-joint robot has 7 joint motion errors"):
        CalibratedRobot(robot.nominal, robot.model, make_network(robot.model, ("q",)))
    rng = np.random.default_rng(1)
    net = Network(("q",), (rng.normal(size=(7, 7)) * 1e-3,), (rng.normal(size=7) * 1e-3,),
                  np.zeros(7), np.ones(7), np.zeros(7), np.ones(7))  # fmt: skip
    learned = CalibratedRobot(robot.nominal, robot.model, net)
    q = sample(learned, 5, seed=4)
    rho = q @ net.weights[0].T + net.biases[0]
    np.testing.assert_allclose(learned.joint_motion_errors(q), rho, rtol=0, atol=1e-15)
    twist = np.einsum("kaj,kj->ka", robot.model.joint_twists(q), rho)
    np.testing.assert_allclose(learned.predict_pose(q), se3.exp_se3(twist) @ robot.model.fk(q), rtol=0, atol=1e-12)


def test_redundant_arm_golden_vectors_accept_any_solution_and_refuse_a_wrong_one(tmp_path):
    robot = redundant_robot()
    path = save_compensator(robot, tmp_path / "r7.json")
    q = np.asarray(json.loads(path.read_text())["golden"]["q"])
    comp = Compensator.load(path)
    np.testing.assert_array_equal(comp.correct(q), robot.correct(q))
    # Another point of the same self-motion (another solver might land there) is as good as the stored one.
    other = robot.correct(q) + 1e-2 * np.linalg.svd(robot.model.joint_twists(q))[2][:, -1]
    for _ in range(8):
        r = se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.model.fk(other)))
        other += np.einsum("kia,ka->ki", np.linalg.pinv(robot.model.joint_twists(other)), r)
    assert np.max(np.abs(other - robot.correct(q))) > 1e-3
    _tamper_json(path, lambda d: d["golden"].update(q_cmd=other.tolist()), reseal=True)
    Compensator.load(path)
    edit = lambda d: d["golden"]["q_cmd"][0].__setitem__(3, d["golden"]["q_cmd"][0][3] + 1e-8)  # noqa: E731
    _tamper_json(path, edit, reseal=True)
    with pytest.raises(CompensatorFileError, match="pose error at the stored q_cmd"):
        Compensator.load(path)


def test_singular_configuration_is_no_worse_than_uncorrected():
    robot = hybrid("ur10")
    q = np.array([[0.3, -1.2, 1.1, -1.3, 0.0, 0.4], [0.1, -1.0, 0.0, -1.0, 1.0, 0.2]])  # wrist / elbow singular
    q_cmd = robot.correct(q)
    assert np.all(np.isfinite(q_cmd))
    scale = np.array([1 / robot.length_scale] * 3 + [1.0] * 3)

    def err(x):
        return np.linalg.norm(se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.predict_pose(x))) * scale, axis=1)

    assert np.all(err(q_cmd) <= err(q) + 1e-15)


# -- single configurations (a control loop's call) ----------------------------------------------------------------

SINGLE_CASES = [
    ("ur10", ("gravity", "harmonics:4", "q"), "series"),  # linear learned term: Newton steps (_linear_series)
    ("ur10", ("harmonics:3", "gravity"), "series"),
    ("ur10", ("sincos", "gravity"), False),
    ("ur5e", ("q", "sincos", "gravity"), False),
    ("fanuc-m1000ia", ("gravity", "q"), False),
    ("ur10", ("q", "sincos", "sincos2", "gravity"), False),
    ("ur10", ("gravity", "harmonics:2"), False),  # the joint series' features
    ("ur10", ("sincos", "gravity"), True),  # off-z joint axes
]


def _single_robot(name, features, odd):
    robot = hybrid(name, features=features, odd_twists=odd is True)
    if odd == "series":
        robot = dataclasses.replace(robot, network=make_series(robot.model, features))
    variants = {
        "hybrid": robot,
        "ann": CalibratedRobot(robot.nominal, robot.nominal, robot.network, method="ann"),
        "local-poe": CalibratedRobot(robot.nominal, robot.model, method="local-poe"),
    }
    return variants


def _pose_error(robot, q, q_cmd):
    """(k,) length-scaled distance between the nominal pose of q and the real pose at q_cmd, from the definition
    (plain kinematics functions: reference_predict)."""
    scale = np.array([1 / robot.length_scale] * 3 + [1.0] * 3)
    T_real = reference_predict(robot, np.atleast_2d(q_cmd)) if robot.network else robot.model.fk(np.atleast_2d(q_cmd))
    return np.linalg.norm(se3.log_se3(robot.nominal.fk(np.atleast_2d(q)) @ se3.inv(T_real)) * scale, axis=1)


@pytest.mark.parametrize("name,features,odd", SINGLE_CASES)
def test_single_configuration_calls_reach_the_nominal_pose(name, features, odd):
    for kind, robot in _single_robot(name, features, odd).items():
        q = sample(robot, 30, seed=11)
        single = np.array([robot.correct(qi) for qi in q])
        assert np.max(_pose_error(robot, q, single)) < 1e-10, kind  # tol = 1e-11 rad on the joints
        assert np.max(np.abs(single - robot.correct(q, iterations=60, tol=1e-16))) <= 1e-9, kind
        assert np.max(np.abs(single - q)) > 1e-5, kind  # a real correction
        np.testing.assert_array_equal(robot.correct(q[3]), robot.correct(q[3].copy()))  # deterministic


def test_single_singular_configuration_falls_back_and_is_no_worse_than_uncorrected():
    import warnings

    robot = hybrid("ur10", features=("sincos", "gravity"))
    for q in ([0.3, -1.2, 1.1, -1.3, 0.0, 0.4], [0.1, -1.0, 0.0, -1.0, 1.0, 0.2]):  # wrist / elbow singular
        q = np.array(q)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no "invalid value" warning from a singular solve leaks out
            q_cmd = robot.correct(q)
        assert np.all(np.isfinite(q_cmd)) and _pose_error(robot, q, q_cmd) <= _pose_error(robot, q, q) + 1e-15


@pytest.mark.parametrize("name,features,odd", SINGLE_CASES[::2])
def test_near_singular_configurations_take_damped_steps_that_never_make_the_pose_worse(
    name, features, odd, monkeypatch
):
    rng = np.random.default_rng(5)
    damped = solve.damped_step
    calls = []
    monkeypatch.setattr(solve, "damped_step", lambda *a: calls.append(1) or damped(*a))
    for robot in _single_robot(name, features, odd).values():
        q = sample(robot, 12, seed=4, max_cond=1e9)
        q[:, 4] = rng.normal(size=len(q)) * 0.05  # near the wrist singularity (q5 = 0 on these arms)
        for row in q:
            # the compiled single call and the numpy definition (a batch of one, whose damped steps are counted)
            for q_cmd in (robot.correct(row, extrapolate=True), robot.correct(row[None], extrapolate=True)[0]):
                assert np.all(np.isfinite(q_cmd)) and _pose_error(robot, row, q_cmd) <= _pose_error(robot, row, row)
    assert len(calls) >= 5  # the damped steps really ran


@pytest.mark.parametrize("features", [("harmonics:4", "q"), ("harmonics:3",), ("gravity", "harmonics:2")])
def test_a_linear_learned_term_gives_the_network_and_its_slope_and_newton_jacobian(features):
    robot = hybrid("ur10", features=features)
    robot = dataclasses.replace(robot, network=make_series(robot.model, features, seed=2, out=2e-3))
    h = 1e-6
    steps = np.eye(6) * h
    for q in sample(robot, 4, seed=8):
        rho_b, slope_b = robot._linear_series(q[None], robot.model.link_frames(q[None]))
        rho, slope = rho_b[0], slope_b[0]
        np.testing.assert_allclose(rho, robot.network(q[None], robot.model)[0], rtol=0, atol=1e-14)
        if "gravity" in features:
            continue  # the slope leaves gravity's part out (see _linear_series)
        numeric = (robot.network(q + steps, robot.model) - robot.network(q - steps, robot.model)).T / (2 * h)
        np.testing.assert_allclose(slope, numeric, rtol=0, atol=1e-8)
        # the residual's Jacobian is −(the returned J) up to O(|r|, |e|²): compare at a point off the solution
        target = robot.nominal.fk(q[None])

        def residual(qc, target=target):
            return robot.residual(qc[None], target)

        q1 = robot.correct(q) + 1e-5
        _, J1 = residual(q1)
        numeric = np.stack([residual(q1 + s)[0][0] - residual(q1 - s)[0][0] for s in steps])
        np.testing.assert_allclose(-J1[0], numeric.T / (2 * h), rtol=0, atol=2e-5)
        J = robot.model.joint_twists(q1[None])[0]
        assert np.abs(-J - numeric.T / (2 * h)).max() > 2e-4  # the twists alone are not the Jacobian


def test_one_configuration_and_a_batch_take_the_same_steps_near_a_singularity():
    # the batch used the twists as J and the single call the Newton Jacobian: near a wrist singularity their step
    # sequences parted, one converged where the other fell back, and the commands differed by up to 0.3 rad
    nominal = load("ur10").model
    model = nominal.perturbed(np.random.default_rng(0).normal(size=(7, 6)) * 0.5e-3)
    robot = CalibratedRobot(nominal, model, make_series(model, ("harmonics:3",)), method="hybrid")
    rng = np.random.default_rng(4)
    q = rng.uniform(-np.pi, np.pi, (60, 6))
    q[:, 4] = rng.choice([-1, 1], 60) * 10 ** rng.uniform(-6, -1, 60)
    q[0] = [-0.156643, 1.982775, -0.577401, 1.249577, 0.002262, -0.843747]  # found by a review
    single = np.array([robot.correct(row) for row in q])
    np.testing.assert_allclose(robot.correct(q), single, rtol=0, atol=1e-6)


def test_a_damped_row_without_a_solution_reaches_the_least_squares_minimum_and_stops_before_its_budget():
    calls = []

    def residual(q, rows, jacobian=True):  # |r| ≥ 1 whatever q: no exact solution, the minimum of |r| is at q = 0
        calls.append(1)
        r = np.zeros((len(rows), 6))
        r[:, 0] = 1.0 + q[:, 0] ** 2
        J = np.broadcast_to(np.eye(6), (len(rows), 6, 6)).copy()
        J[:, 0, 0] = -2 * q[:, 0]  # the solver's convention: dr/dq = −J
        return r, J

    # Tenfold λ jumps alternated refused and kept steps and crawled towards q = 0 for the whole budget; the gain
    # ratio rule keeps λ where steps are kept, so the row gets to the minimum and stops there (steps below tol).
    for q0 in (np.full((1, 6), 0.005), np.full((2, 6), 0.005)):
        calls.clear()
        out = solve._damped(residual, q0, np.arange(len(q0)), np.ones(6), 50, 1e-11)
        assert len(calls) < 30
        assert np.all(np.abs(out[:, 0]) < 1e-9)
        np.testing.assert_array_equal(out[:, 1:], q0[:, 1:])  # the other joints have nothing to gain


def test_a_damped_row_that_stalls_stops_at_half_its_budget_and_one_still_converging_finishes():
    calls = []

    def crawl(q, rows, jacobian=True):  # cost (1 + 1e-4 q0)²: every clipped step is kept, none lowers it much
        calls.append(1)
        r = np.zeros((len(rows), 6))
        r[:, 0] = 1.0 + 1e-4 * q[:, 0]
        J = np.broadcast_to(np.eye(6), (len(rows), 6, 6)).copy()
        J[:, 0, 0] = -1e-4
        return r, J

    def travel(q, rows, jacobian=True):  # an exact solution 0.3 rad away: 15 clipped steps, the cost falling fast
        calls.append(1)
        return 0.3 - q, np.broadcast_to(np.eye(6), (len(rows), 6, 6)).copy()

    for q0 in (np.zeros((1, 6)), np.zeros((3, 6))):
        calls.clear()
        out = solve._damped(crawl, q0, np.arange(len(q0)), np.ones(6), 24, 1e-11)
        assert len(calls) == 1 + 12  # the start, then half the budget: 4 steps never halved the cost
        assert np.all(out[:, 0] < -0.2)  # it did crawl the whole way it was allowed
        calls.clear()
        out = solve._damped(travel, q0, np.arange(len(q0)), np.ones(6), 24, 1e-11)
        assert 12 < len(calls) < 1 + 24  # past half the budget, and done before the end of it
        np.testing.assert_allclose(out, 0.3, rtol=0, atol=1e-12)


def test_a_least_squares_solve_asks_for_the_jacobian_at_every_step():
    """With fewer joints than six the solution is where Jᵀ W² r = 0, a point that moves with J: a step that reused
    an older J would converge to another point, so a residual that skips J when allowed is never allowed to."""
    rng = np.random.default_rng(4)
    A, B = rng.normal(size=(6, 2)), rng.normal(size=(6, 2)) * 0.3
    target = rng.normal(size=6) * 0.05  # not reachable with two joints: a residual is left
    asked = []

    def residual(q, rows, jacobian=True):  # r = target − (A q + B sin q); the solver's J is −dr/dq
        asked.append(jacobian)
        r = target - q @ A.T - np.sin(q) @ B.T
        J = (A[None] + B[None] * np.cos(q)[:, None, :]) if jacobian else None
        return r, J

    w = np.array([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])
    for q0 in (np.zeros((1, 2)), np.zeros((3, 2))):
        asked.clear()
        q = solve.solve(residual, q0, weights=w)
        r, J = residual(q, np.arange(len(q)))
        gradient = np.einsum("kai,ka->ki", J * (w**2)[:, None], r)
        assert np.abs(gradient).max() < 1e-9
        assert all(asked)


def test_once_settled_the_steps_reuse_the_kept_jacobian_even_when_the_residual_returns_one():
    """After a step below REUSE_BELOW the solver asks for r alone and steps with the J it kept (for one row, with the
    inverse it kept): a J the residual returns anyway is not used. Here that J is ten times too large, so steps made
    with it would crawl (contraction 0.9) and stop far from the root within the iteration budget."""
    target = np.array([0.02, -0.01, 0.015, 0.0, 0.01, -0.02])
    asked = []

    def residual(q, rows, jacobian=True):  # r = target − (q + q³/3), J = −dr/dq = I + diag(q²)
        asked.append(jacobian)
        r = target - (q + q**3 / 3)
        J = np.eye(6)[None] * (1 + q**2)[:, None, :]
        return r, (J if jacobian else 10 * J)

    for q0 in (np.zeros((1, 6)), np.zeros((3, 6))):
        asked.clear()
        q = solve.solve(residual, q0)
        assert not all(asked)  # it did settle and ask for r alone
        np.testing.assert_allclose(q + q**3 / 3, np.broadcast_to(target, q.shape), rtol=0, atol=1e-14)


def test_one_damped_row_follows_the_batched_rule():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))

    def residual(q, rows):  # a smooth map with a fold: r = A (q + q³) − target, J = −dr/dq
        r = (q + q**3) @ A.T - 0.2
        J = -A[None] * (1 + 3 * q**2)[:, None, :]
        return r, J

    q0 = rng.normal(size=(3, 6)) * 0.5
    batch = solve._damped(residual, q0, np.arange(3), np.ones(6), 30, 1e-11)
    for i in range(3):
        one = solve._damped(residual, q0[i : i + 1], np.arange(1), np.ones(6), 30, 1e-11)
        # the same rule; the 2-D and stacked products round differently, and λ follows the gain ratio
        np.testing.assert_allclose(one, batch[i : i + 1], rtol=0, atol=1e-8)


def test_the_gauss_newton_verdicts():
    """(failed, converged) per row: a first step fails above GN_MAX_STEP and converges below tol; a later one fails
    unless it at most halves the last (and stays below GN_MAX_STEP), converges when its estimated distance to the
    solution |step| ρ / (1 − ρ) is below tol, and below the noise floor converges whatever it did."""
    size = np.array([0.31, 0.29, 1e-12, np.nan])
    bad, done = solve.verdict(size, None, 1e-11)
    assert bad.tolist() == [True, False, False, True] and done.tolist() == [False, False, True, False]
    size = np.array([0.31, 0.6, 0.25, 1e-5, 1e-11, 1e-11, 9e-13, 1e-15, np.nan])
    prev = np.array([1.0, 1.0, 1.0, 1e-3, 1e-9, 2e-11, 1e-14, 0.0, 1.0])
    bad, done = solve.verdict(size, prev, 1e-11)
    assert bad.tolist() == [True, True, False, False, False, False, False, False, True]
    assert done.tolist() == [False, False, False, False, True, False, True, True, False]
    # the rule of one row is the rule of a batch
    for i in range(len(size)):
        one = solve.verdict(size[i : i + 1], prev[i : i + 1], 1e-11)
        assert (bool(one[0][0]), bool(one[1][0])) == (bool(bad[i]), bool(done[i]))


def test_a_bounded_damped_budget_limits_the_residual_evaluations_and_stays_no_worse(monkeypatch):
    robot = hybrid("ur10", features=("sincos", "gravity"))
    q = np.array([0.3, -1.2, 1.1, -1.3, 0.0, 0.4])  # wrist singular: the damped steps run
    calls = []
    real = CalibratedRobot.residual
    monkeypatch.setattr(CalibratedRobot, "residual", lambda *a: calls.append(1) or real(*a))
    q_cmd = robot.correct(q[None], damped_iterations=2)[0]  # the numpy definition (the kernel: test_kernel.py)
    assert len(calls) <= 10 + 1 + 2  # Gauss-Newton budget, the damped start, two damped steps
    assert _pose_error(robot, q, q_cmd) <= _pose_error(robot, q, q)


def test_single_configuration_input_checks():
    nominal = load("ur10").model
    robot = CalibratedRobot(
        nominal, nominal, make_network(nominal, ("sincos", "gravity")), joint_ranges=np.tile([-2.0, 2.0], (6, 1))
    )
    q = np.array([0.1, -1.2, 1.0, -1.4, -1.5, 0.2])
    expected = robot.correct(q)
    # lists take the batched path: the same answer to rounding (the compiled kernel answers float arrays)
    np.testing.assert_allclose(robot.correct(list(q)), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(robot.correct(q[None])[0], expected, rtol=0, atol=1e-12)
    assert robot.correct(np.array([0, -1, 1, -1, -1, 0])).shape == (6,)  # integers are converted
    np.testing.assert_allclose(robot.correct(q.astype(">f8")), expected, rtol=0, atol=1e-12)  # other layouts
    with pytest.raises(ValueError, match=r"shape \(6,\) or \(k, 6\)"):
        robot.correct(q[:5])
    bad = q.copy()
    bad[3] = 2.5
    with pytest.raises(ValueError, match=r"configuration 0: joint 4 = 2\.500000 is outside"):
        robot.correct(bad)
    assert np.all(np.isfinite(robot.correct(bad, extrapolate=True)))
    for value in (np.nan, np.inf):
        bad[3] = value
        with pytest.raises(ValueError, match="non-finite"):
            robot.correct(bad)
        with pytest.raises(ValueError, match="non-finite"):
            robot.correct(bad, extrapolate=True)


def ann(robot="ur10", features=("q", "sincos", "sincos2", "gravity"), seed=0):
    """The paper's ANN method: nominal frames plus a network."""
    nominal = load(robot).model
    return CalibratedRobot(nominal, nominal, make_network(nominal, features, seed=seed), method="ann")


def test_paper_method_is_eq_24_and_batch_shapes():
    robot = ann("ur10")
    q = sample(robot, 5, seed=4)
    np.testing.assert_allclose(robot.correct(q, method="paper"), q - robot.network(q, robot.model)[:, :6])
    assert robot.correct(q[0]).shape == (6,)
    assert robot.correct(q).shape == (5, 6)
    assert robot.predict_pose(q[0]).shape == (4, 4)
    with pytest.raises(ValueError, match="method"):
        robot.correct(q, method="magic")
    with pytest.raises(ValueError, match="shape"):
        robot.correct(np.zeros(5))


def test_joint_range_refusal_names_configuration_and_joint():
    nominal = load("ur10").model
    ranges = np.tile([-1.0, 1.0], (6, 1))
    robot = CalibratedRobot(nominal, nominal, joint_ranges=ranges)
    q = np.zeros((3, 6))
    q[2, 4] = 1.5
    with pytest.raises(ValueError, match=r"configuration 2: joint 5 = 1\.500000 is outside"):
        robot.correct(q)
    np.testing.assert_allclose(robot.correct(q, extrapolate=True), q, atol=1e-15)  # uncalibrated: identity


def test_harmonics_features_are_evaluated_by_the_runtime():
    nominal = load("ur10").model
    robot = CalibratedRobot(nominal, nominal, make_network(nominal, ("harmonics:3",)), method="series")
    q = sample(robot, 20, seed=5)
    np.testing.assert_allclose(robot.joint_motion_errors(q), robot.network(q, nominal), atol=1e-15)
    assert input_features(q, ("harmonics:3",), nominal).shape == (20, 36)


# -- export files ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_save_load_round_trip(tmp_path, suffix):
    robot = hybrid("ur10")
    robot = CalibratedRobot(
        robot.nominal,
        robot.model,
        robot.network,
        T_tracker_base=se3.pose([1.0, 2.0, 0.5], [0.1, 0.2, 0.3]),
        joint_ranges=np.tile([-3.0, 3.0], (6, 1)),
        method="hybrid",
    )
    path = save_compensator(robot, tmp_path / f"c{suffix}", provenance={"session": "S@v001", "fit_id": "f1"})
    comp = Compensator.load(path)
    q = sample(robot, 30, seed=6)
    np.testing.assert_array_equal(comp.correct(q), robot.correct(q))
    np.testing.assert_array_equal(comp.predict_pose(q), robot.predict_pose(q))
    np.testing.assert_array_equal(comp.T_tracker_base, robot.T_tracker_base)
    np.testing.assert_array_equal(comp.joint_ranges, robot.joint_ranges)
    assert comp.provenance == {"session": "S@v001", "fit_id": "f1"}
    assert comp.method == "hybrid" and comp.robot_hash == load("ur10").hash
    with pytest.raises(ValueError, match="outside the calibrated range"):
        comp.correct(np.full(6, 3.1))
    assert comp.correct(np.full(6, 3.1), extrapolate=True).shape == (6,)


def test_local_poe_only_export_round_trip(tmp_path):
    nominal = load("fanuc-m1000ia").model
    model = nominal.perturbed(np.random.default_rng(0).normal(size=(7, 6)) * 1e-3)
    robot = CalibratedRobot(nominal, model, method="local-poe")
    comp = Compensator.load(save_compensator(robot, tmp_path / "x.json"))
    assert comp.robot.network is None
    q = sample(robot, 10, seed=7)
    np.testing.assert_array_equal(comp.correct(q), robot.correct(q))


def _tamper_json(path, edit, reseal=False):
    """Edit a JSON export; reseal=True also rewrites its checksums, as a file edited consistently (or written by a
    labcal whose numbers differ) would be, so the checks behind the checksums are reached."""
    data = json.loads(path.read_text())
    edit(data)
    if reseal:
        data["checksums"] = field_checksums(data)
    path.write_text(json.dumps(data))


def test_tampered_weight_is_refused(tmp_path):
    path = save_compensator(hybrid("ur10"), tmp_path / "c.json")

    def edit(d):
        d["network"]["weights"][0][3][2] *= 1.0 + 1e-6

    original = path.read_text()
    _tamper_json(path, edit)
    with pytest.raises(CompensatorFileError, match="network does not match its checksum"):
        Compensator.load(path)
    path.write_text(original)
    _tamper_json(path, edit, reseal=True)  # the golden vectors catch what the checksums were rewritten to hide
    with pytest.raises(CompensatorFileError, match="golden vectors disagree"):
        Compensator.load(path)


def test_tampered_npz_array_is_refused(tmp_path):
    path = save_compensator(hybrid("ur10"), tmp_path / "c.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["model.frames"] = arrays["model.frames"].copy()
    arrays["model.frames"][2, 0, 3] += 1e-7
    np.savez(path, **arrays)
    with pytest.raises(CompensatorFileError, match="model does not match its checksum"):
        Compensator.load(path)


def test_edited_robot_model_fails_its_hash(tmp_path):
    path = save_compensator(hybrid("ur10"), tmp_path / "c.json")
    _tamper_json(path, lambda d: d["robot"]["frames"][1][0].__setitem__(3, 0.5), reseal=True)
    with pytest.raises(CompensatorFileError, match="hash"):
        Compensator.load(path)


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda d: d.__setitem__("schema_version", 99), "schema_version 99"),
        (lambda d: d.__setitem__("format", "other"), "not a labcal compensator"),
        (lambda d: d.pop("golden"), "golden"),
        (lambda d: d["golden"].__setitem__("q", []), "no golden vectors"),
        (lambda d: d.pop("checksums"), "no checksums field"),
        (lambda d: d.__setitem__("joint_map", {"matrix": [[1.0]], "offsets": [0.0]}), "joint_map is not a valid"),
    ],
)
def test_bad_files_are_refused_with_a_clear_error(tmp_path, edit, match):
    path = save_compensator(hybrid("ur10"), tmp_path / "c.json")
    _tamper_json(path, edit, reseal=match != "no checksums field")
    with pytest.raises(CompensatorFileError, match=match):
        Compensator.load(path)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(CompensatorFileError, match="no such"):
        Compensator.load(tmp_path / "nope.json")
    (tmp_path / "x.txt").write_text("{}")
    with pytest.raises(CompensatorFileError, match=r"\.json or \.npz"):
        Compensator.load(tmp_path / "x.txt")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(CompensatorFileError, match="cannot read"):
        Compensator.load(tmp_path / "bad.json")
    with pytest.raises(ValueError, match=r"\.json or \.npz"):
        save_compensator(hybrid("ur10"), tmp_path / "c.bin")


def test_importing_the_runtime_loads_no_torch_scipy_typer_or_drivers():
    code = (
        "import sys, labcal.compensator\n"
        "bad = [m for m in ('torch', 'scipy', 'typer', 'rich', 'pandas', 'serial', 'labcal.drivers', "
        "'labcal.calibration', 'labcal.datasets') if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


# -- integrity of every behaviour-changing field (issue 12.5) ----------------------------------------------------


def _widen(d):
    d["joint_ranges"] = [[-10.0, 10.0]] * 6  # would silently switch off the out-of-range guard


@pytest.mark.parametrize(
    "field,edit",
    [
        ("joint_ranges", _widen),
        ("T_tracker_base", lambda d: d["T_tracker_base"][0].__setitem__(3, d["T_tracker_base"][0][3] + 1e-3)),
        ("length_scale", lambda d: d.__setitem__("length_scale", d["length_scale"] * 2)),
        ("joint_map", lambda d: d.__setitem__("joint_map", {"matrix": np.eye(6).tolist(), "offsets": [0.1] * 6})),
        ("method", lambda d: d.__setitem__("method", "nominal")),
        ("provenance", lambda d: d["provenance"].__setitem__("forced", False)),
        ("network", lambda d: d["network"]["out_scale"].__setitem__(0, 1.0)),
        ("model", lambda d: d["model"]["limits"][0].__setitem__(0, -3.0)),
        ("robot", lambda d: d["robot"].__setitem__("name", "other")),
        ("golden", lambda d: d["golden"].__setitem__("correct_method", "paper")),
    ],
)
def test_editing_any_behaviour_changing_field_is_refused_naming_it(tmp_path, field, edit):
    path = save_compensator(hybrid("ur10"), tmp_path / "c.json", provenance={"session": "S@v001", "forced": True})
    Compensator.load(path)
    _tamper_json(path, edit)
    with pytest.raises(CompensatorFileError, match=rf"{field} does not match its checksum"):
        Compensator.load(path)


def test_widened_ranges_in_an_npz_file_are_refused(tmp_path):
    path = save_compensator(hybrid("ur10"), tmp_path / "c.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["joint_ranges"] = np.tile([-10.0, 10.0], (6, 1))
    np.savez(path, **arrays)
    with pytest.raises(CompensatorFileError, match="joint_ranges does not match its checksum"):
        Compensator.load(path)


def test_checksums_agree_between_json_and_npz(tmp_path):
    robot = hybrid("ur10")
    a = json.loads(save_compensator(robot, tmp_path / "c.json", provenance={"n": 3}).read_text())["checksums"]
    with np.load(save_compensator(robot, tmp_path / "c.npz", provenance={"n": 3})) as z:
        b = json.loads(str(z["__meta__"]))["checksums"]
    assert a == b and set(a) >= {"joint_ranges", "T_tracker_base", "length_scale", "joint_map"}


def test_a_version_1_file_is_refused_with_the_fix(tmp_path):
    path = save_compensator(hybrid("ur10"), tmp_path / "c.json")
    _tamper_json(path, lambda d: d.__setitem__("schema_version", 1))
    with pytest.raises(CompensatorFileError, match=r"schema_version 1 is not supported.*export the fit again"):
        Compensator.load(path)


# -- empty, malformed and non-finite input -----------------------------------------------------------------------


def test_empty_input_gives_an_empty_answer(tmp_path):
    robot = hybrid("ur10")
    comp = Compensator.load(save_compensator(robot, tmp_path / "c.json"))
    mapped = Compensator.load(
        save_compensator(dataclasses.replace(robot, joint_map=load("coupled-elbow-6r").joint_map), tmp_path / "m.json")
    )
    for target in (robot, comp, mapped):
        out = target.correct(np.zeros((0, 6)))
        assert out.shape == (0, 6)
        assert target.correct(np.zeros((0, 6)), extrapolate=True).shape == (0, 6)
        assert target.predict_pose(np.zeros((0, 6))).shape == (0, 4, 4)
    assert robot.joint_motion_errors(np.zeros((0, 6))).shape == (0, 6)
    assert robot.predict_points(np.zeros((0, 6)), np.eye(3)).shape == (0, 3, 3)
    assert ann().correct(np.zeros((0, 6)), method="paper").shape == (0, 6)


@pytest.mark.parametrize(
    "q,match",
    [
        (np.zeros(5), r"shape \(6,\) or \(k, 6\) for this 6-joint robot, got \(5,\)"),
        (np.zeros((3, 7)), r"got \(3, 7\)"),
        (np.zeros((2, 3, 6)), r"got \(2, 3, 6\)"),
        (np.zeros((0,)), r"got \(0,\)"),
        (["a"] * 6, "must be real numbers.*got text"),
        (["0.1"] * 6, "must be real numbers.*got text"),  # parsed silently before
        (np.full(6, 0.1 + 0.5j), "got complex numbers"),  # its imaginary part was dropped with a warning
        (np.ma.masked_array(np.zeros(6), mask=[0, 0, 1, 0, 0, 0]), "masked values"),  # the mask was ignored
        ([object()] * 6, "must be numbers"),
        ([[0.0] * 6, [0.0] * 5], "must be numbers"),  # ragged: numpy's own error, unnamed, before
        (np.array([[0.0] * 6, [0.0, 0.0, np.nan, 0.0, 0.0, 0.0]]), "configuration 1, joint 3 is nan"),
        (np.array([0.0, np.inf, 0.0, 0.0, 0.0, 0.0]), "configuration 0, joint 2 is inf"),
    ],
)
def test_bad_input_is_a_clear_error(tmp_path, q, match):
    robot = hybrid("ur10")
    comp = Compensator.load(save_compensator(robot, tmp_path / "c.json"))
    for call in (robot.correct, robot.predict_pose, comp.correct, comp.predict_pose):
        with pytest.raises(ValueError, match=match):
            call(q)


# -- method="paper" only where it is the whole correction -----------------------------------------------------


def test_paper_and_fixed_point_are_refused_where_they_would_be_a_no_op_or_partial(tmp_path):
    nominal = load("ur10").model
    model = nominal.perturbed(np.random.default_rng(0).normal(size=(7, 6)) * 1e-3)
    local = CalibratedRobot(nominal, model, method="local-poe")
    comp = Compensator.load(save_compensator(local, tmp_path / "c.json"))
    q = sample(local, 3, seed=1)
    for method in ("paper", "fixed-point"):
        for target in (local, comp):
            with pytest.raises(ValueError, match=rf"method='{method}'.*no network.*uncorrected.*'newton'"):
                target.correct(q, method=method)
        with pytest.raises(ValueError, match="ignore the identified frames of this hybrid"):
            hybrid("ur10").correct(q, method=method)
    assert np.max(np.abs(comp.correct(q) - q)) > 1e-4  # newton does correct it
    robot = ann()
    assert np.max(np.abs(robot.correct(q, method="paper") - q)) > 1e-5  # the paper's own method is allowed


# -- joint maps: the compensator speaks controller joints -------------------------------------------------------


def test_a_mapped_compensator_converts_controller_joints_both_ways(tmp_path):
    spec = load("coupled-elbow-6r")
    base = hybrid("fanuc-m1000ia")
    robot = dataclasses.replace(base, joint_map=spec.joint_map)
    comp = Compensator.load(save_compensator(robot, tmp_path / "c.npz"))
    assert comp.robot_hash == spec.hash != load("fanuc-m1000ia").hash
    np.testing.assert_array_equal(comp.joint_map.matrix, spec.joints.matrix)
    q_model = sample(base, 12, seed=3)
    q_ctrl = spec.joints.to_controller(q_model)
    got = comp.correct(q_ctrl)
    np.testing.assert_allclose(got, spec.joints.to_controller(base.correct(q_model)), atol=1e-13)
    np.testing.assert_allclose(comp.correct(q_ctrl[0]), got[0], atol=1e-13)  # single configurations too
    np.testing.assert_allclose(comp.predict_pose(q_ctrl), base.predict_pose(q_model), atol=1e-13)
    # the real robot, commanded the corrected controller joints, lands on the nominal pose of the requested ones
    np.testing.assert_allclose(comp.predict_pose(got), spec.model.fk(q_model), atol=1e-9)
    # the same numbers taken as model joints would be a different configuration
    assert np.max(np.abs(comp.predict_pose(q_model, extrapolate=True) - base.predict_pose(q_model))) > 1e-2


def test_a_mapped_compensator_checks_the_model_joint_ranges(tmp_path):
    spec = load("coupled-elbow-6r")
    base = hybrid("fanuc-m1000ia")
    comp = Compensator(dataclasses.replace(base, joint_map=spec.joint_map))
    q = np.zeros(6)
    q[1], q[2] = 1.0, 1.5  # model elbow J2 + J3 = 2.5 rad, beyond its range; each number alone is inside
    with pytest.raises(ValueError, match=r"joint 3 = 2\.500000 is outside.*model joints.*joint map"):
        comp.correct(q)
    with pytest.raises(ValueError, match="outside"):
        comp.predict_pose(q)
    assert comp.correct(q, extrapolate=True).shape == (6,)


def test_an_identity_map_is_stored_as_no_map(tmp_path):
    base = hybrid("ur10")
    robot = dataclasses.replace(base, joint_map=load("ur10").joints)
    assert robot.joint_map is None
    data = json.loads(save_compensator(robot, tmp_path / "c.json").read_text())
    assert data["joint_map"] is None and data["robot"]["hash"] == load("ur10").hash


def test_exports_that_cannot_hold_a_joint_map_refuse_it(tmp_path):
    from labcal.export import export

    spec = load("coupled-elbow-6r")
    robot = dataclasses.replace(hybrid("fanuc-m1000ia"), joint_map=spec.joint_map)
    with pytest.raises(ValueError, match="URScript export of a robot with a joint map"):
        export(robot, "urscript", tmp_path / "a.script")
    with pytest.raises(ValueError, match="URDF export of a robot with a joint map"):
        export(robot, "urdf", tmp_path / "a.urdf")
    assert not (tmp_path / "a.script").exists() and not (tmp_path / "a.urdf").exists()
    assert Compensator.load(export(robot, "json", tmp_path / "a.json")).robot_hash == spec.hash


def test_every_payload_field_is_checksummed():
    """A field added to the export later must be covered too (or this test says which one is not)."""
    from labcal.compensator import CHECKED_FIELDS, to_payload

    payload = to_payload(hybrid("ur10"))
    unchecked = set(payload) - set(CHECKED_FIELDS) - {"format", "schema_version", "checksums"}
    assert not unchecked, f"export fields without a checksum: {sorted(unchecked)}"


@pytest.mark.parametrize("mapped", [False, True])
def test_the_runtime_passes_the_solver_settings_through(tmp_path, mapped):
    # a controller-side process bounds its worst case through Compensator, not only through CalibratedRobot
    spec = load("coupled-elbow-6r")
    base = hybrid("fanuc-m1000ia")
    robot = dataclasses.replace(base, joint_map=spec.joint_map) if mapped else base
    comp = Compensator.load(save_compensator(robot, tmp_path / "c.json"))
    q_model = sample(base, 40, seed=5)
    q_model[:20, 4] = 0.0  # wrist singular: these take the damped fallback, whose budget is then visible
    q = spec.joints.to_controller(q_model) if mapped else q_model
    to_controller = spec.joints.to_controller if mapped else (lambda x: x)
    for options in ({"damped_iterations": 0}, {"tol": 1e-6}, {"damped_iterations": 3, "tol": 1e-9}):
        # compared away from the singularity, where the joint map's rounding is not amplified
        want = to_controller(base.correct(q_model[20:], **options))
        np.testing.assert_allclose(comp.correct(q[20:], **options), want, rtol=0, atol=1e-12)
        np.testing.assert_allclose(comp.correct(q[20], **options), want[0], rtol=0, atol=1e-12)
    default = comp.correct(q)
    assert np.max(np.abs(comp.correct(q, damped_iterations=0) - default)) > 1e-3  # the budget reaches the solver
    assert np.max(np.abs(comp.correct(q, tol=1e-3) - default)) > 0  # and so does the tolerance


def test_a_tolerance_below_rounding_converges_instead_of_restarting_damped():
    # steps at the rounding floor no longer halve; they must end the row as converged, not send it back to q
    nominal = load("ur10").model
    model = nominal.perturbed(np.random.default_rng(0).normal(size=(7, 6)) * 0.5e-3)
    robot = CalibratedRobot(nominal, model, make_network(model, ("q", "sincos", "sincos2", "gravity")), "hybrid")
    found = [-0.4068558256761041, 0.10899587185075932, -2.005165476675237, 1.254102195428393]  # by a review
    found += [0.022819643934576916, -2.1450457229083737]
    q = np.vstack([found, sample(robot, 150, seed=21, max_cond=1e3)])

    def pose_error(q_cmd):
        gap = se3.log_se3(se3.inv(nominal.fk(q)) @ robot.predict_pose(q_cmd))
        return np.abs(gap).max(axis=1)

    default = pose_error(robot.correct(q))
    for tight in (robot.correct(q, tol=1e-16, iterations=60), [robot.correct(row, tol=1e-16) for row in q]):
        # (a row the default leaves at a least-squares floor, near a singularity, may end there too, up to rounding)
        assert np.all(pose_error(np.asarray(tight)) <= np.maximum(default * (1 + 1e-9), 1e-13))


def test_one_exactly_singular_row_does_not_change_the_others():
    # numpy's stacked solve refuses a whole stack for one singular J; only that row may take the damped mode
    robot = ann(features=("sincos", "gravity"))
    good = sample(robot, 200, seed=1, max_cond=1e3)
    alone = robot.correct(good)
    mixed = robot.correct(np.vstack([good[:100], np.zeros(6), good[100:]]))  # q = 0: J exactly singular
    np.testing.assert_array_equal(np.delete(mixed, 100, axis=0), alone)
    assert np.isfinite(mixed[100]).all()


def test_a_length_scale_that_is_not_a_positive_number_is_refused():
    # NaN or inf made correct() return q uncorrected without a word, 0 a ZeroDivisionError
    nominal = load("ur10").model
    for bad in (np.nan, np.inf, 0.0, -1.0):
        with pytest.raises(ValueError, match="length_scale must be a positive number"):
            CalibratedRobot(nominal, nominal, length_scale=bad)


def test_fixed_point_takes_at_least_one_step_like_newton():
    robot, q = ann(), sample(ann(), 4, seed=2)
    np.testing.assert_array_equal(
        robot.correct(q, method="fixed-point", iterations=0), robot.correct(q, method="fixed-point", iterations=1)
    )
    assert np.abs(robot.correct(q, method="fixed-point", iterations=0) - q).max() > 1e-5


def test_to_model_never_returns_the_callers_array(tmp_path):
    comp = Compensator.load(save_compensator(hybrid("ur10"), tmp_path / "c.json"))
    q = sample(comp.robot, 3, seed=1)
    for given in (q, q[0]):
        out = comp.to_model(given)
        np.testing.assert_array_equal(out, given)
        assert not np.shares_memory(out, given)
