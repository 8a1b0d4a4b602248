"""Any number of targets (issue 15): one reflector, two, three, and targets lost in some rows, end to end.

The data come from the simulator's true robot; targets are dropped from its three-target measurements here (as a
lab that moves one reflector, or loses one, would record them). What the points cannot show (the tool's
orientation with one target, the rotation about the line through two) must be reported, not invented.
"""

from __future__ import annotations

import numpy as np
import pytest

from labcal.calibration import Observations, fit
from labcal.calibration.cv import row_errors
from labcal.calibration.equivalent import joint_error_observations
from labcal.calibration.local_poe import expected_rank, fit_local_poe, register
from labcal.calibration.metrics import observability, point_errors, split_table
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.12, 0.0, 0.05], [-0.06, 0.15, 0.05], [-0.07, -0.11, 0.04]])  # m, tool frame
T_TRACKER = se3.exp_se3(np.array([0.4, -0.3, 1.1, 0.2, -0.1, 0.3]))


def sample(model, k, rng):
    return rng.uniform(model.limits[:, 0], model.limits[:, 1], size=(k, model.n))


def simulated(robot="ur10", k=60, seed=1, errors=None):
    spec = load(robot)
    actual = simulate(spec, errors if errors is not None else ErrorSpec.paper(tracker_noise=0.0), seed=seed)
    rng = np.random.default_rng(seed + 100)
    q = sample(spec.model, k, rng)
    return spec.model, actual, q, actual.measure(q, TARGETS, rng)


def true_points(actual, q, targets=TARGETS):
    T = actual.true_pose(q)
    return np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]


def held_out(robot, actual, k=200, seed=7):
    """(k, 3) distances of the robot's predicted target points from the true ones, base frame."""
    q = sample(actual.nominal, k, np.random.default_rng(seed))
    return np.linalg.norm(robot.predict_points(q, TARGETS) - true_points(actual, q), axis=-1)


def drop(points, rate, seed):
    """Points with a share of the cells blanked (NaN), every row keeping at least one target."""
    rng = np.random.default_rng(seed)
    lost = rng.random(points.shape[:2]) < rate
    lost[lost.all(axis=1), 0] = False
    out = points.copy()
    out[lost] = np.nan
    return out


@pytest.mark.parametrize("robot", ["ur10", "fanuc-m1000ia"])
def test_one_target_fits_its_point_exactly_and_reports_the_tool_orientation_unobservable(robot):
    nominal, actual, q, pts = simulated(robot)
    robot_1, info = fit_local_poe(Observations(q, pts[:, :1], TARGETS[:1]), nominal)
    # Three rotations of the tool about the one target are structural: counted out, named, not a rank failure.
    assert info["target_geometry"] == "point"
    assert info["expected_rank"] == expected_rank(nominal) - 3 and info["rank"] == info["expected_rank"]
    assert not info["rank_deficient"] and "orientation of the tool" in info["unobservable"][0]
    e = held_out(robot_1, actual)
    # Noise-free geometric errors: the measured target is predicted exactly, also on configurations not fitted,
    # so the tool position (where t1 sits on the flange) was estimated along with the arm.
    assert np.max(e[:, 0]) < 1e-6
    # The other targets need the tool's orientation, which one point never saw.
    assert np.mean(e[:, 1:]) > 100 * np.max(e[:, 0])


def test_two_targets_leave_only_the_rotation_about_their_line():
    nominal, actual, q, pts = simulated()
    robot_2, info = fit_local_poe(Observations(q, pts[:, :2], TARGETS[:2]), nominal)
    assert info["target_geometry"] == "line" and info["rank"] == expected_rank(nominal) - 1 == info["expected_rank"]
    assert "line through t1, t2" in info["unobservable"][0]
    e = held_out(robot_2, actual)
    assert np.max(e[:, :2]) < 1e-6


def test_three_targets_with_missing_cells_identify_everything():
    nominal, actual, q, pts = simulated(k=80)
    obs = Observations(q, drop(pts, 0.3, seed=2), TARGETS)
    assert not obs.complete and obs.seen.sum(axis=1).min() >= 1
    robot, info = fit_local_poe(obs, nominal)
    assert info["rank"] == expected_rank(nominal) and info["unobservable"] == []
    assert np.max(held_out(robot, actual)) < 1e-6


def test_tracker_frame_registration_from_one_point_per_pose():
    exact = ErrorSpec.paper(tracker_noise=0.0, length_std=0.0, angle_std=0.0, joint_offset_std=0.0, axis_std=0.0)
    nominal, actual, q, _ = simulated(errors=exact)
    tool_point = TARGETS[:1]
    pts = np.einsum("ab,kmb->kma", T_TRACKER[:3, :3], true_points(actual, q, tool_point)) + T_TRACKER[:3, 3]
    reg, _info = register(Observations(q, pts, tool_point, frame="tracker"), nominal)
    assert np.allclose(reg.T_tracker_base, T_TRACKER, atol=1e-9)


def test_single_target_with_an_unknown_tool_offset_estimates_the_tool_position():
    nominal, actual, q, _ = simulated()
    # The reflector sits 20 mm from where the targets file says: the last frame's error parameters absorb it.
    truth, claimed = np.array([[0.05, 0.02, 0.1]]), np.array([[0.05, 0.0, 0.1]])
    obs = Observations(q, true_points(actual, q, truth), claimed)
    robot, info = fit_local_poe(obs, nominal)
    q_new = sample(nominal, 100, np.random.default_rng(3))
    err = np.linalg.norm(robot.predict_points(q_new, claimed) - true_points(actual, q_new, truth), axis=-1)
    assert np.max(err) < 1e-6 and info["rank"] == info["expected_rank"]


def test_equivalent_observation_uses_only_the_rows_of_the_targets_a_pose_saw():
    nominal, _actual, q, pts = simulated(k=12, errors=ErrorSpec.paper())
    base = CalibratedRobot(nominal=nominal, model=nominal)
    partial = pts.copy()
    partial[::2, 2] = np.nan  # even rows: t1 and t2 only
    jeo = joint_error_observations(Observations(q, partial, TARGETS), base, max_condition=None)
    two = joint_error_observations(Observations(q, pts[:, :2], TARGETS[:2]), base, max_condition=None)
    full = joint_error_observations(Observations(q, pts, TARGETS), base, max_condition=None)
    assert jeo.rank.tolist() == [5, 6] * 6 and two.rank.tolist() == [5] * 12
    assert np.allclose(jeo.PJ[::2, 6:], 0.0) and np.allclose(jeo.delta_p[::2, 6:], 0.0)
    assert np.allclose(jeo.delta_rho[::2], two.delta_rho[::2], rtol=1e-9, atol=1e-12)
    assert np.allclose(jeo.delta_rho[1::2], full.delta_rho[1::2], rtol=1e-6, atol=1e-12)
    # A least-squares solution (residual orthogonal to what P J_ρ can produce) of minimum norm (no component
    # along the rotation about the line, which moves neither point).
    residual = two.delta_p - np.einsum("kab,kb->ka", two.PJ, two.delta_rho)
    assert np.allclose(np.einsum("kab,ka->kb", two.PJ, residual), 0.0, atol=1e-12)
    null = np.linalg.svd(two.PJ)[2][:, -1]  # (k, 6): the direction the two points cannot see
    assert np.allclose(np.einsum("ka,ka->k", null, two.delta_rho), 0.0, atol=1e-12)
    one = joint_error_observations(Observations(q, pts[:, :1], TARGETS[:1]), base, max_condition=None)
    assert one.rank.tolist() == [3] * 12 and np.all(np.isfinite(one.condition))
    assert one.summary()["rank_below_6"] == 12 and "rank_below_6" not in full.summary()


@pytest.mark.parametrize("method", ["nominal", "local-poe", "ann", "hybrid", "auto"])
def test_every_method_fits_one_target_and_says_what_orientation_it_can_claim(method):
    nominal, _actual, q, pts = simulated(k=50, errors=ErrorSpec.paper())
    obs = Observations(q, pts[:, :1], TARGETS[:1])
    result = fit(obs, nominal, method, seed=0, **({"restarts": 1} if method in ("ann", "hybrid", "auto") else {}))
    assert result.observability["orientation"] == "none" and result.observability["rows_with_pose"] == 0
    assert any(n.startswith("unobservable: the orientation of the tool") for n in result.notes)
    assert not any(w["code"] == "rank-deficient" for w in result.warnings)
    entry = result.metrics["all"]
    assert entry["primary"] == "points" and entry["after"]["count"] == 0 and np.isnan(entry["after"]["pos_mean"])
    assert np.isfinite(entry["points"]["after"]["mean"])
    if method != "nominal":
        assert entry["points"]["after"]["mean"] < entry["points"]["before"]["mean"]
    if method == "ann":
        assert result.info["loss"] == "task" and result.info["loss_note"]
        assert any("point loss of eq. (20)" in n for n in result.notes)


def test_fit_with_missing_cells_matches_the_complete_fit_closely():
    nominal, actual, q, pts = simulated(k=60, errors=ErrorSpec.paper())
    full = fit(Observations(q, pts, TARGETS), nominal, "local-poe")
    lossy = fit(Observations(q, drop(pts, 0.3, seed=4), TARGETS), nominal, "local-poe")
    e_full, e_lossy = np.mean(held_out(full.robot, actual)), np.mean(held_out(lossy.robot, actual))
    assert e_lossy < 1.5 * e_full
    assert lossy.observability["orientation"] == "partial" and lossy.metrics["all"]["primary"] == "points"
    assert full.observability["orientation"] == "measured" and full.metrics["all"]["primary"] == "pose"
    assert not lossy.warnings


def test_metrics_count_pose_errors_only_where_a_pose_is_measured():
    nominal, _actual, q, pts = simulated(k=10, errors=ErrorSpec.paper())
    partial = pts.copy()
    partial[:4, 1] = np.nan
    obs = Observations(q, partial, TARGETS)
    robot = CalibratedRobot(nominal=nominal, model=nominal)
    table = split_table(robot, robot, obs)["all"]
    assert table["after"]["count"] == 6 and table["points"]["after"]["count"] == 26
    assert table["points"]["after"]["per_target"][1]["count"] == 6
    d = point_errors(robot, obs)
    assert np.isnan(d[:4, 1]).all()
    assert np.allclose(row_errors(robot, obs)[:4], np.mean(d[:4][:, [0, 2]], axis=1))
    claim = observability(obs)
    assert claim["orientation"] == "partial" and claim["rows_with_pose"] == 6


def test_collinear_targets_report_the_line_and_claim_partial_orientation():
    line = np.array([[0.0, 0.0, 0.05], [0.1, 0.0, 0.05], [0.2, 0.0, 0.05]])
    nominal, actual, q, _ = simulated(k=40)
    obs = Observations(q, true_points(actual, q, line), line)
    claim = observability(obs)
    assert claim["geometry"] == "line" and claim["orientation"] == "partial"
    assert "line through t1, t2, t3" in claim["unobservable"][0]
    _, info = fit_local_poe(obs, nominal)
    assert info["rank"] == info["expected_rank"] == expected_rank(nominal) - 1


def test_a_single_point_on_the_last_joint_axis_holds_that_axis_instead_of_fitting_noise_into_it():
    nominal, actual, q, _ = simulated(k=80, errors=ErrorSpec.paper())
    A = nominal.frames[-1]  # tool frame in K_n: joint n turns about K_n's z axis
    on_axis = np.linalg.solve(A, [0.0003, 0.0, 0.09, 1.0])[:3]  # 0.3 mm beside the axis, like a probe origin
    pts = actual.measure(q, on_axis[None], np.random.default_rng(5))
    result = fit(Observations(q, pts, on_axis[None]), nominal, "local-poe")
    info = result.info
    assert info["rank"] == info["expected_rank"] == expected_rank(nominal) - 5
    assert any(f"tilt of joint {nominal.n}'s axis" in w for w in info["unobservable"])
    assert any(f"tilt of joint {nominal.n}'s axis" in w for w in result.observability["unobservable"])
    assert not [w for w in result.warnings if w["code"] in ("large-correction", "rank-deficient")]
    dq = result.robot.correct(q) - q
    # milliradians (more only near a singular wrist), not the tenths of a radian noise fitted into the axis gave
    assert np.median(np.abs(dq)) < 0.005 and np.mean(np.abs(dq) > 0.05) < 0.05
    e = np.linalg.norm(
        result.robot.predict_points(q, on_axis[None])[:, 0] - true_points(actual, q, on_axis[None])[:, 0], axis=1
    )
    assert np.mean(e) < np.mean(
        np.linalg.norm(
            nominal.target_points(q, on_axis[None])[:, 0] - true_points(actual, q, on_axis[None])[:, 0], axis=1
        )
    )


FOUR = np.vstack([TARGETS, [[0.02, 0.03, 0.15]]])


def test_four_targets_and_two_with_missing_cells_fit_with_every_learned_stage_and_repeat_bit_for_bit():
    import json

    from labcal.compensator import to_payload

    spec = load("ur10")
    actual = simulate(spec, ErrorSpec.default(), seed=4)
    rng = np.random.default_rng(6)
    q = sample(spec.model, 40, rng)
    pts = actual.measure(q, FOUR, rng)
    four = fit(Observations(q, pts, FOUR), spec.model, "hybrid", seed=0, stage2=("series",))
    assert four.observability["orientation"] == "measured" and four.metrics["all"]["primary"] == "pose"
    two = Observations(q, drop(pts[:, [1, 3]], 0.3, seed=8), FOUR[[1, 3]])
    runs = [fit(two, spec.model, "auto", seed=0, restarts=1) for _ in range(2)]
    assert runs[0].observability["geometry"] == "line" and not runs[0].warnings
    assert set(runs[0].cv["mean"]) >= {"local-poe", "hybrid+series", "ann"}
    payloads = [json.dumps(to_payload(r.robot), sort_keys=True) for r in runs]
    assert payloads[0] == payloads[1]  # same data, same seed: the same fit, bit for bit
    for r in (four, runs[0]):
        pts_after = r.metrics["all"]["points"]["after"]["mean"]
        assert pts_after < r.metrics["all"]["points"]["before"]["mean"]
