"""Local-POE identification (eq. 11, 18) closed-loop on the simulator: recovery, rank, noise, base, errors."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.calibration import IdentificationError, ObservationError, Observations
from labcal.calibration.local_poe import fit_local_poe, register
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.12, 0.0, 0.05], [-0.06, 0.15, 0.05], [-0.07, -0.11, 0.04]])  # m, tool frame, scalene


def sample(model, k, rng):
    return rng.uniform(model.limits[:, 0], model.limits[:, 1], size=(k, model.n))


def observe(robot="fanuc-m1000ia", errors=None, k=60, seed=1, frame="base", targets=TARGETS):
    spec = load(robot)
    actual = simulate(spec, errors if errors is not None else ErrorSpec.paper(tracker_noise=0.0), seed=seed)
    rng = np.random.default_rng(seed + 100)
    q = sample(spec.model, k, rng)
    return spec.model, actual, Observations(q, actual.measure(q, targets, rng), targets, frame=frame)


def held_out_errors(robot, actual, k=200, seed=7):
    q = sample(actual.nominal, k, np.random.default_rng(seed))
    return se3.pose_distance(robot.predict_pose(q, tcp=robot.measurement_tool), actual.true_pose(q))


def identifiable(model):
    """4 per revolute + 2 per prismatic joint + 6 (counted here from the joint types, independently)."""
    return sum(4 if t == "revolute" else 2 for t in model.joint_types) + 6


@pytest.mark.parametrize("robot", ["fanuc-m1000ia", "ur10", "scara4"])
def test_noise_free_geometric_errors_are_recovered_exactly_on_held_out_configurations(robot):
    # The simulator's frame errors, joint offsets and axis misalignments are all representable by local-POE
    # frames, so an iterated identification must reproduce the true robot to round-off.
    nominal, actual, obs = observe(robot)
    calibrated, info = fit_local_poe(obs, nominal)
    pos, ori = held_out_errors(calibrated, actual)
    assert info["converged"]
    assert pos.max() <= 1e-9
    assert ori.max() <= 1e-9
    before = held_out_errors(register(obs, nominal)[0], actual)[0]
    assert before.mean() > 1e-4  # the errors were real to start with


@pytest.mark.parametrize("robot", ["fanuc-m1000ia", "ur10", "scara4"])
def test_numerical_rank_equals_the_literature_count_of_identifiable_parameters(robot):
    nominal, _, obs = observe(robot)
    _, info = fit_local_poe(obs, nominal)
    assert info["rank"] == identifiable(nominal)
    assert info["n_params"] == 6 * (nominal.n + 1)
    assert info["unidentifiable"] == 6 * (nominal.n + 1) - identifiable(nominal)
    assert len(info["null_directions"]) == info["unidentifiable"]


def test_reported_null_directions_do_not_change_the_predicted_points():
    nominal, _, obs = observe()
    calibrated, info = fit_local_poe(obs, nominal)
    null = info["null_space"]  # (6(n+1), d), SI units
    assert null.shape == (6 * (nominal.n + 1), info["unidentifiable"])
    eps = 1e-6
    base_pts = calibrated.model.target_points(obs.q, TARGETS)
    for d in range(null.shape[1]):
        v = null[:, d] / np.linalg.norm(null[:, d])
        moved = calibrated.model.perturbed(eps * v).target_points(obs.q, TARGETS)
        assert np.abs(moved - base_pts).max() < 1e-3 * eps  # second order only
    # while an identifiable direction moves them at first order
    moved = calibrated.model.perturbed(np.full(6 * (nominal.n + 1), eps)).target_points(obs.q, TARGETS)
    assert np.abs(moved - base_pts).max() > 0.1 * eps


def test_one_linear_step_is_not_enough_the_iteration_is():
    nominal, actual, obs = observe()
    one_step, _ = fit_local_poe(obs, nominal, max_iter=1)
    full, info = fit_local_poe(obs, nominal)
    assert held_out_errors(one_step, actual)[0].max() > 1e-8
    assert held_out_errors(full, actual)[0].max() <= 1e-9
    assert info["iterations"] > 1
    # accepted steps never raise the cost beyond round-off: the final sub-tol step is accepted at the floor,
    # where 540 residuals of ~1e-14 m give ~1e-28 m²; allow 1e-24 m²
    assert all(
        b <= a * (1 + 1e-9) + 1e-24 for a, b in zip(info["cost_history"], info["cost_history"][1:], strict=False)
    )


def test_with_tracker_noise_the_held_out_error_is_at_the_noise_floor():
    sigma, k = 0.05e-3, 100
    nominal, actual, obs = observe(errors=ErrorSpec.paper(), k=k)
    calibrated, info = fit_local_poe(obs, nominal)
    pos, _ = held_out_errors(calibrated, actual, k=500)
    # Linear least squares with p = 30 identifiable parameters from N = 9k coordinates of noise σ leaves a fitted
    # error of mean square σ² p / N per coordinate, so about σ·sqrt(3p/N) per point (3 coordinates). Held-out
    # configurations from the same distribution see the same order; the tool origin lies within the target
    # spread, so it is no worse. Allow a factor 3 for extrapolation and the spread of the estimate.
    p, N = info["rank"], 9 * k
    floor = sigma * np.sqrt(3 * p / N)
    assert pos.mean() <= 3 * floor
    before = held_out_errors(register(obs, nominal)[0], actual, k=500)[0]
    assert pos.max() < 0.02 * before.max()  # ≥ 98 % reduction of the maximum (the goal)
    # the residual standard deviation estimates the tracker noise (relative sd ~ 1/sqrt(2(N − p)) ≈ 2.4 %)
    assert info["sigma"] == pytest.approx(sigma, rel=0.1)
    std = info["std"]
    assert std.shape == (nominal.n + 1, 6) and np.all(np.isfinite(std)) and np.all(std > 0)


def test_tracker_frame_data_recover_a_large_tracker_to_base_transform():
    T_tb = se3.pose(np.array([2.5, -1.2, 0.8]), np.array([0.3, -0.2, 0.6]))  # metres and up to 34°
    nominal, actual, obs = observe(errors=ErrorSpec.paper(tracker_noise=0.0, T_tracker_base=T_tb), frame="tracker")
    calibrated, info = fit_local_poe(obs, nominal)
    q = sample(nominal, 200, np.random.default_rng(3))
    pos, ori = se3.pose_distance(
        calibrated.T_tracker_base @ calibrated.predict_pose(q, tcp=calibrated.measurement_tool),
        T_tb @ actual.true_pose(q),
    )
    assert pos.max() <= 1e-9 and ori.max() <= 1e-9
    # The base frame's own error is folded into T_tracker_base (gauge), so it differs from the truth only by
    # the simulated base-frame error: 0.5 mm / 0.5 mrad standard deviation.
    dp, dr = se3.pose_distance(calibrated.T_tracker_base, T_tb)
    assert dp < 5e-3 and dr < 5e-3
    assert info["rank"] == identifiable(nominal)
    # the registered nominal finds it too, to the size of the geometric errors
    reg, reg_info = register(obs, nominal)
    dp, dr = se3.pose_distance(reg.T_tracker_base, T_tb)
    assert dp < 1e-2 and dr < 1e-2 and reg_info["estimated"] == ["T_tracker_base"]
    assert np.array_equal(reg.model.frames, nominal.frames)


def test_register_on_base_frame_data_is_the_nominal_and_can_estimate_the_tool():
    nominal, _actual, obs = observe(errors=ErrorSpec.paper(tracker_noise=0.0))
    reg, _ = register(obs, nominal)
    assert np.array_equal(reg.model.frames, nominal.frames) and np.array_equal(reg.T_tracker_base, np.eye(4))
    with_tool, info = register(obs, nominal, estimate_tool=True)
    assert np.array_equal(with_tool.model.frames[:-1], nominal.frames[:-1])
    # robot and tool apart: the robot stays at tool0, the estimated tool is the measurement tool
    assert np.array_equal(with_tool.model.frames[-1], nominal.frames[-1]) and with_tool.measurement_tool is not None
    assert info["estimated"] == ["tool"]
    e_reg = np.mean((reg.predict_points(obs.q, TARGETS) - obs.points) ** 2)
    e_tool = np.mean((with_tool.predict_points(obs.q, TARGETS) - obs.points) ** 2)
    assert e_tool < e_reg


def test_only_training_and_unassigned_rows_are_fitted_unless_validation_is_included():
    nominal, _, obs = observe(k=80)
    split = np.array(["train"] * 40 + ["val"] * 20 + ["test"] * 20, dtype=object)
    obs = Observations(obs.q, obs.points, obs.targets, split=split)
    _, info = fit_local_poe(obs, nominal)
    assert info["rows"] == 40
    _, info = fit_local_poe(obs, nominal, include_val=True)
    assert info["rows"] == 60
    # corrupting the test and validation rows does not change the default fit
    bad = obs.points.copy()
    bad[40:] += 0.01
    a, _ = fit_local_poe(obs, nominal)
    b, _ = fit_local_poe(Observations(obs.q, bad, obs.targets, split=split), nominal)
    assert np.array_equal(a.model.frames, b.model.frames)


def test_same_data_give_bit_identical_parameters():
    nominal, _, obs = observe(errors=ErrorSpec.paper())
    a, _ = fit_local_poe(obs, nominal)
    b, _ = fit_local_poe(obs, nominal)
    assert np.array_equal(a.model.frames, b.model.frames)
    assert np.array_equal(a.T_tracker_base, b.T_tracker_base)


def test_too_few_configurations_is_a_clear_error():
    nominal, _, obs = observe(k=3)  # 27 coordinates < 30 identifiable parameters
    with pytest.raises(IdentificationError, match="at least 4 configurations"):
        fit_local_poe(obs, nominal)


def test_too_few_configurations_that_pass_the_count_are_reported_as_rank_deficient():
    nominal, _, obs = observe(k=4)  # 36 coordinates: enough to count, not to excite every direction
    _, info = fit_local_poe(obs, nominal)
    assert info["rank"] <= 36
    if info["rank"] < identifiable(nominal):
        assert info["rank_deficient"] and "rank" in info["warning"]


def test_mismatched_joint_counts_are_a_clear_error():
    _nominal, _, obs = observe()
    scara = load("scara4").model
    with pytest.raises(ObservationError, match="6 joint values per row, the robot has 4"):
        fit_local_poe(obs, scara)
    with pytest.raises(ObservationError, match="6 joint values per row, the robot has 4"):
        register(obs, scara)


def test_a_partly_empty_measurement_is_refused_before_fitting():
    _nominal, _, obs = observe()
    pts = obs.points.copy()
    pts[5, 1, 2] = np.nan
    with pytest.raises(ObservationError, match="row\\) 5"):
        Observations(obs.q, pts, obs.targets)
