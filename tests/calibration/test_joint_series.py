"""Per-joint Fourier series of the equivalent robot's joint motion errors (labcal.calibration.joint_series)."""

from __future__ import annotations

import numpy as np
import pytest

from labcal import features
from labcal.calibration import ObservationError, Observations
from labcal.calibration.joint_series import fit_joint_series
from labcal.calibration.observations import rigid_fit
from labcal.compensator import CalibratedRobot, input_features
from labcal.compensator import save as save_compensator
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.0, 0.0, 0.05], [0.1, 0.0, 0.05], [0.0, 0.1, 0.05]])
# Injected transmission errors: (joint, order, sin amplitude rad, cos amplitude rad).
INJECTED = [(0, 1, 2e-4, 0.0), (1, 3, 0.0, 1.5e-4), (2, 7, 1e-4, 5e-5), (4, 5, -1e-4, 0.0), (5, 2, 8e-5, 8e-5)]


# ----------------------------------------------------------------------------------------------------------------
# Reference evaluation, written out from eq. (14) here so the tests do not check the compensator against itself.


def joint_motion_errors(robot: CalibratedRobot, q: np.ndarray) -> np.ndarray:
    """(k, 6) δρ(q) of a series robot through numpy features and the network's own forward pass (zeros without)."""
    q2 = np.atleast_2d(np.asarray(q, dtype=float))
    net = robot.network
    if net is None:
        return np.zeros((q2.shape[0], 6))
    x = input_features(q2, net.features, robot.model)
    return net.forward_features(x)


def predict_pose(robot: CalibratedRobot, q: np.ndarray) -> np.ndarray:
    """(k, 4, 4) base-frame pose the real robot reaches: exp((J_ρ δρ)^) · T_model (first order, eq. 14)."""
    q2 = np.atleast_2d(np.asarray(q, dtype=float))
    T = robot.model.fk(q2)
    if robot.network is None:
        return T
    J = robot.model.equivalent_jacobian(q2, length_scale=robot.length_scale)
    dy = np.einsum("kab,kb->ka", J, joint_motion_errors(robot, q2))
    return se3.exp_se3(dy) @ T


def position_errors(robot: CalibratedRobot, obs: Observations) -> np.ndarray:
    """(k,) tool-origin position error (m) of :func:`predict_pose` against the rigid fit of the measured points."""
    if obs.k == 0:
        return np.zeros(0)
    T_pred = robot.T_tracker_base @ predict_pose(robot, obs.q)
    if robot.measurement_tool is not None:  # the measured poses are the fixture's
        T_pred = T_pred @ robot.measurement_tool
    return np.linalg.norm(rigid_fit(obs.targets, obs.points)[:, :3, 3] - T_pred[:, :3, 3], axis=1)


def _injected(q: np.ndarray) -> np.ndarray:
    dq = np.zeros_like(q)
    for j, h, a, b in INJECTED:
        dq[:, j] += a * np.sin(h * q[:, j]) + b * np.cos(h * q[:, j])
    return dq


def _measure(actual, q, rng, noise):
    """Points of an error-free-geometry robot whose joints really move by q + δq(q), plus tracker noise."""
    T = actual.geometric.fk(q + _injected(q))
    p = np.einsum("kab,mb->kma", T[:, :3, :3], TARGETS) + T[:, None, :3, 3]
    return p + rng.normal(0.0, noise, size=p.shape)


def _ur10_obs(k: int, seed: int, noise: float = 1e-6) -> tuple[Observations, CalibratedRobot]:
    spec = load("ur10")
    actual = simulate(spec, ErrorSpec.none(), seed=seed)
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, size=(k, 6))
    split = np.where(np.arange(k) < k * 2 // 3, "train", "val").astype(object)
    obs = Observations(q, _measure(actual, q, rng, noise), TARGETS, "base", split)
    return obs, CalibratedRobot(nominal=spec.model, model=spec.model)


@pytest.fixture(scope="module")
def ur10_fit():
    obs, base = _ur10_obs(240, seed=3)
    robot, info = fit_joint_series(obs, base, harmonics=(4, 8), seed=0)
    return obs, base, robot, info


def test_recovers_injected_per_joint_harmonics_on_held_out_configurations(ur10_fit):
    _, base, robot, info = ur10_fit
    held = _ur10_obs(200, seed=11)[0]  # new configurations; the error-free geometry is the same for every seed
    before = position_errors(base, held)
    after = position_errors(robot, held)
    assert np.mean(before) > 1e-4  # the injected errors are visible (sub-millimetre)
    assert np.mean(after) < 0.05 * np.mean(before)
    assert info["harmonics"] == 8  # order 7 is injected: 4 harmonics cannot fit it
    # The identified joint errors match the injected ones (joint 3's order-7 term included).
    q = held.q
    err = joint_motion_errors(robot, q)[:, :6] - _injected(q)
    assert np.max(np.abs(err)) < 2e-5


def test_network_is_block_diagonal_without_hidden_layer(ur10_fit):
    _, _, robot, info = ur10_fit
    net = robot.network
    H = info["harmonics"]
    assert net.features == (f"harmonics:{H}",)
    assert net.hidden == ()
    (W,) = net.weights
    assert W.shape == (6, 2 * 6 * H)
    owner = np.array([c.joint for c in features.get(f"harmonics:{H}").columns(("revolute",) * 6)])
    for j in range(6):
        assert np.all(W[j, owner != j] == 0.0)
        assert np.any(W[j, owner == j] != 0.0)
    assert robot.method == "series"


def test_own_prediction_path_matches_the_first_order_equivalent_robot(ur10_fit):
    _, _, robot, _ = ur10_fit
    q = np.random.default_rng(5).uniform(-1, 1, size=(4, 6))
    rho = joint_motion_errors(robot, q)
    T = predict_pose(robot, q)
    # Moving the joints themselves by rho gives the same pose to first order (rho ~ 1e-4 rad).
    T_joint = robot.model.fk(q + rho)
    assert np.max(np.abs(T[:, :3, 3] - T_joint[:, :3, 3])) < 1e-6
    assert np.max(np.abs(T[:, :3, 3] - robot.model.fk(q)[:, :3, 3])) > 1e-5


def test_same_data_and_seed_give_identical_weights_and_other_seeds_still_work():
    obs, base = _ur10_obs(90, seed=4)
    a, ia = fit_joint_series(obs, base, harmonics=(2, 4), seed=7)
    b, ib = fit_joint_series(obs, base, harmonics=(2, 4), seed=7)
    assert np.array_equal(a.network.weights[0], b.network.weights[0])
    assert np.array_equal(a.network.biases[0], b.network.biases[0])
    assert ia["cv"] == ib["cv"]
    _, ic = fit_joint_series(obs, base, harmonics=(2, 4), seed=8)
    assert ic["cv"] != ia["cv"]  # the folds changed
    assert np.isfinite(ic["val_error"])


def test_reports_validation_error_and_does_not_fit_on_val_rows():
    obs, base = _ur10_obs(90, seed=6)
    robot, info = fit_joint_series(obs, base, harmonics=3, seed=0)
    val = obs.where("val")
    assert info["val_rows"] == val.k and info["train_rows"] == obs.k - val.k
    assert info["val_error"] == pytest.approx(float(np.mean(position_errors(robot, val))))
    # Corrupting the val rows' measurements must not change the fitted weights.
    pts = obs.points.copy()
    pts[obs.split == "val"] += 0.01
    moved = Observations(obs.q, pts, obs.targets, obs.frame, obs.split)
    robot2, _ = fit_joint_series(moved, base, harmonics=3, seed=0)
    assert np.array_equal(robot.network.weights[0], robot2.network.weights[0])


def test_lower_mobility_robot_leaves_virtual_joints_at_zero():
    spec = load("scara4")
    rng = np.random.default_rng(2)
    lim = spec.model.limits
    q = rng.uniform(lim[:, 0], lim[:, 1], size=(80, 4))
    dq = np.zeros_like(q)
    dq[:, 0] = 2e-4 * np.sin(3 * q[:, 0])
    T = spec.model.fk(q + dq)
    targets = np.array([[0.05, 0, 0], [0, 0.05, 0], [-0.04, -0.03, 0.01]])
    pts = np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]
    split = np.where(np.arange(80) < 60, "train", "val").astype(object)
    obs = Observations(q, pts, targets, "base", split)
    robot, info = fit_joint_series(obs, CalibratedRobot(nominal=spec.model, model=spec.model), harmonics=(2, 4))
    rho = joint_motion_errors(robot, q)
    assert np.all(rho[:, 4:] == 0.0)
    assert info["virtual_joints"].startswith("not modelled")
    assert info["val_error"] < 0.1 * np.mean(position_errors(CalibratedRobot(spec.model, spec.model), obs.where("val")))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"harmonics": 0}, "harmonics"),
        ({"harmonics": ()}, "harmonics"),
        ({"harmonics": (4, 2.5)}, "harmonics"),
        ({"lambdas": [0.0]}, "lambdas"),
        ({"lambdas": [float("nan")]}, "lambdas"),
        ({"penalty_power": -1}, "penalty_power"),
        ({"folds": 1}, "folds"),
    ],
)
def test_bad_options_are_refused_by_name(kwargs, match):
    obs, base = _ur10_obs(30, seed=1)
    with pytest.raises(ValueError, match=match):
        fit_joint_series(obs, base, **kwargs)


def test_too_few_rows_wrong_robot_and_base_with_network_are_refused(ur10_fit):
    obs, base = _ur10_obs(12, seed=1)
    with pytest.raises(ObservationError, match="at least 10 training configurations"):
        fit_joint_series(obs, base, folds=5)
    scara = load("scara4").model
    with pytest.raises(ObservationError, match="the robot has 4"):
        fit_joint_series(obs, CalibratedRobot(nominal=scara, model=scara))
    _, _, robot, _ = ur10_fit
    with pytest.raises(ValueError, match="network-free"):
        fit_joint_series(obs, robot)


def test_compensator_runtime_evaluates_the_series_like_this_module_and_exports_round_trip(ur10_fit, tmp_path):
    from labcal.compensator import Compensator

    _, _, robot, _ = ur10_fit
    q = np.random.default_rng(8).uniform(-2, 2, size=(5, 6))
    np.testing.assert_allclose(robot.joint_motion_errors(q), joint_motion_errors(robot, q), rtol=0, atol=1e-15)
    np.testing.assert_allclose(robot.predict_pose(q), predict_pose(robot, q), rtol=0, atol=1e-12)
    loaded = Compensator.load(save_compensator(robot, tmp_path / "series.json"))
    assert loaded.robot.network.features == robot.network.features
    np.testing.assert_allclose(loaded.predict_pose(q, extrapolate=True), robot.predict_pose(q), rtol=0, atol=1e-15)
    # Correcting the commands cancels the injected joint errors: the real robot lands on the nominal pose.
    q_in = np.random.default_rng(9).uniform(-1.5, 1.5, size=(5, 6))
    q_cmd = loaded.correct(q_in, extrapolate=True)
    reached = robot.model.fk(q_cmd + _injected(q_cmd))
    target = robot.nominal.fk(q_in)
    assert np.max(np.linalg.norm(reached[:, :3, 3] - target[:, :3, 3], axis=1)) < 2e-5
    assert np.max(np.linalg.norm(robot.nominal.fk(q_in + _injected(q_in))[:, :3, 3] - target[:, :3, 3], axis=1)) > 1e-4


def _compliance_obs(k: int, seed: int) -> tuple[Observations, CalibratedRobot, object]:
    """A UR10 whose only error is joint compliance under gravity (no geometric or gear errors)."""
    spec = load("ur10")
    errors = ErrorSpec(0.0, 0.0, 0.0, 0.0, compliance_deflection=5e-4, gear_std=0.0, tracker_noise=1e-6)
    actual = simulate(spec, errors, seed=seed)
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, size=(k, 6))
    split = np.array(["train"] * (k // 2) + ["val"] * (k - k // 2), dtype=object)
    obs = Observations(q, actual.measure(q, TARGETS, rng), TARGETS, "base", split)
    return obs, CalibratedRobot(nominal=spec.model, model=spec.model), actual


def test_gravity_terms_are_chosen_for_compliance_and_beat_harmonics_alone():
    obs, base, actual = _compliance_obs(120, seed=4)
    with_gravity, info = fit_joint_series(obs, base, harmonics=(2, 4), seed=0)
    without, _ = fit_joint_series(obs, base, harmonics=(2, 4), seed=0, gravity=False)
    assert info["gravity"] is True and with_gravity.network.features[0] == "gravity"
    hold = np.random.default_rng(99).uniform(-np.pi, np.pi, size=(300, 6))
    truth = actual.true_pose(hold)[:, :3, 3]
    err_g = np.linalg.norm(predict_pose(with_gravity, hold)[:, :3, 3] - truth, axis=1).mean()
    err_h = np.linalg.norm(predict_pose(without, hold)[:, :3, 3] - truth, axis=1).mean()
    before = np.linalg.norm(base.model.fk(hold)[:, :3, 3] - truth, axis=1).mean()
    assert err_g < 0.2 * before and err_g < 0.5 * err_h
    # the compensator runtime evaluates the exported gravity + harmonics network identically
    assert np.allclose(with_gravity.predict_pose(hold), predict_pose(with_gravity, hold), atol=1e-12)
