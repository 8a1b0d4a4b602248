"""Planner properties: limits, conditioning and the cell respected; optimised sets beat random ones."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.kinematics.se3 import skew
from labcal.robots import load
from labcal.sessions.planning import (
    DEFAULT_MAX_CONDITION,
    PlanningError,
    greedy_d_optimal,
    identifiable_basis,
    identification_jacobian,
    joint_ranges,
    length_scaled_condition,
    optimal_configurations,
    random_configurations,
)
from planning import observability, prediction_variance  # benchmarks/planning.py: the planner's indices

TARGETS = np.array([[0.15, 0.0, 0.05], [-0.075, 0.13, 0.05], [-0.075, -0.13, 0.05]])


@pytest.fixture(scope="module")
def ur10():
    return load("ur10").model


@pytest.fixture(scope="module")
def fanuc():
    return load("fanuc-m1000ia").model


def test_configurations_stay_inside_the_shrunk_joint_ranges(ur10):
    q = random_configurations(ur10, 200, seed=4, range_fraction=0.3)
    lo, hi = ur10.limits[:, 0], ur10.limits[:, 1]
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * 0.3
    assert q.shape == (200, 6)
    assert np.all(q >= mid - half) and np.all(q <= mid + half)
    # The whole shrunk range is used, not a corner of it.
    assert np.all(q.max(axis=0) - q.min(axis=0) > 1.5 * half)


def test_every_configuration_meets_the_conditioning_threshold(ur10):
    for bound in (DEFAULT_MAX_CONDITION, 20.0):
        q = random_configurations(ur10, 100, seed=2, max_condition=bound)
        assert np.all(length_scaled_condition(ur10, q) <= bound)
    # ... and the check really removes something: unfiltered draws exceed the tighter bound.
    raw = random_configurations(ur10, 100, seed=2, max_condition=None)
    assert np.any(length_scaled_condition(ur10, raw) > 20.0)


def test_condition_metric_divides_the_linear_rows_by_the_reach(ur10):
    q = random_configurations(ur10, 3, seed=9, max_condition=None)
    J = ur10.equivalent_jacobian(q)
    L = ur10.reach()
    expected = [np.linalg.cond(np.vstack([Ji[:3] / L, Ji[3:]])) for Ji in J]
    np.testing.assert_allclose(length_scaled_condition(ur10, q), expected, rtol=1e-9)


def test_a_wrist_singularity_is_flagged_ill_conditioned(ur10):
    q = np.zeros((1, 6))
    q[0, 1], q[0, 2] = -1.0, 1.2  # q5 = 0: wrist axes 4 and 6 align
    assert length_scaled_condition(ur10, q)[0] > 1e6


@pytest.mark.parametrize("count", [0, -1, 2.5])
def test_bad_count_is_refused(ur10, count):
    with pytest.raises(PlanningError, match="count"):
        random_configurations(ur10, count, seed=0)


def test_same_seed_same_configurations_other_seed_others(ur10):
    a = random_configurations(ur10, 20, seed=11, max_condition=50)
    b = random_configurations(ur10, 20, seed=11, max_condition=50)
    c = random_configurations(ur10, 20, seed=12, max_condition=50)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_lower_mobility_robot_is_planned_too():
    scara = load("scara4").model
    q = random_configurations(scara, 20, seed=0)
    assert q.shape == (20, 4) and np.all(length_scaled_condition(scara, q) <= DEFAULT_MAX_CONDITION)


def test_joint_ranges_rejects_a_bad_fraction(ur10):
    with pytest.raises(PlanningError, match="range_fraction"):
        joint_ranges(ur10.limits, range_fraction=0.0)


# ------------------------------------------------------------------------------------------------------------
# Observability


def test_identification_jacobian_predicts_target_motion_of_a_perturbed_model(ur10):
    q = random_configurations(ur10, 4, seed=1)
    rng = np.random.default_rng(0)
    dz = rng.normal(size=(7, 6)) * 1e-6
    moved = ur10.perturbed(dz).target_points(q, TARGETS) - ur10.target_points(q, TARGETS)
    L = ur10.reach()
    scaled = dz.copy()
    scaled[:, 3:] *= L  # the Jacobian's parameters are (δv, L·δω)
    G = identification_jacobian(ur10, q, TARGETS)
    np.testing.assert_allclose(G @ scaled.ravel(), moved.reshape(4, 9), atol=1e-10)


@pytest.mark.parametrize(("name", "rank"), [("fanuc-m1000ia", 4 * 6 + 6), ("scara4", 4 * 3 + 2 * 1 + 6)])
def test_identifiable_subspace_has_the_textbook_dimension(name, rank):
    # 4 per revolute and 2 per prismatic joint plus 6 for the tool (a complete, minimal POE-type model).
    model = load(name).model
    assert identifiable_basis(model, TARGETS).shape == (6 * (model.n + 1), rank)


def test_indices_follow_their_definitions(fanuc):
    q = random_configurations(fanuc, 12, seed=2)
    basis = identifiable_basis(fanuc, TARGETS)
    R = (identification_jacobian(fanuc, q, TARGETS) @ basis).reshape(-1, basis.shape[1])
    s = np.linalg.svd(R, compute_uv=False)
    obs = observability(fanuc, q, TARGETS, basis=basis)
    assert obs.rows == 12 * 9 and obs.parameters == 30 and obs.rank == 30
    assert obs.o1 == pytest.approx(np.prod(s ** (1 / 30)) / np.sqrt(12 * 9), rel=1e-9)
    assert obs.log_det == pytest.approx(np.linalg.slogdet(R.T @ R)[1], rel=1e-9)


def test_too_few_configurations_are_rank_deficient(fanuc):
    obs = observability(fanuc, random_configurations(fanuc, 3, seed=0), TARGETS)
    assert obs.rank < obs.parameters and obs.o1 == 0.0 and obs.log_det == -np.inf


def test_optimised_subset_beats_random_subsets_of_the_same_size(fanuc):
    pool = random_configurations(fanuc, 300, seed=7, targets=TARGETS)
    basis = identifiable_basis(fanuc, TARGETS)
    best = optimal_configurations(fanuc, 12, seed=7, targets=TARGETS, pool=pool, criterion="d")
    opt = observability(fanuc, best, TARGETS, basis=basis)
    rng = np.random.default_rng(0)
    for _ in range(20):
        subset = pool[rng.choice(len(pool), 12, replace=False)]
        rand = observability(fanuc, subset, TARGETS, basis=basis)
        assert opt.log_det > rand.log_det
        assert opt.o1 > rand.o1
    # The chosen configurations come from the pool.
    assert all(any(np.array_equal(c, p) for p in pool) for c in best)


def test_i_optimal_subset_predicts_better_than_random_and_d_optimal_ones(fanuc):
    pool = random_configurations(fanuc, 300, seed=8, targets=TARGETS)
    basis = identifiable_basis(fanuc, TARGETS)
    workspace = random_configurations(fanuc, 400, seed=99)  # fresh configurations of the same workspace

    def variance(q):
        return prediction_variance(fanuc, q, TARGETS, workspace, basis=basis)

    i_opt = variance(optimal_configurations(fanuc, 12, seed=8, targets=TARGETS, pool=pool, criterion="i"))
    d_opt = variance(optimal_configurations(fanuc, 12, seed=8, targets=TARGETS, pool=pool, criterion="d"))
    assert i_opt < d_opt
    rng = np.random.default_rng(1)
    assert all(i_opt < variance(pool[rng.choice(len(pool), 12, replace=False)]) for _ in range(20))


def test_prediction_variance_halves_when_the_same_configurations_are_measured_twice(fanuc):
    q = random_configurations(fanuc, 10, seed=4)
    workspace = random_configurations(fanuc, 50, seed=5)
    once = prediction_variance(fanuc, q, TARGETS, workspace)
    assert prediction_variance(fanuc, np.vstack([q, q]), TARGETS, workspace) == pytest.approx(once / 2, rel=1e-6)
    assert prediction_variance(fanuc, q[:3], TARGETS, workspace) == np.inf


def test_unknown_criterion_is_refused(fanuc):
    with pytest.raises(PlanningError, match="criterion"):
        optimal_configurations(fanuc, 5, seed=0, targets=TARGETS, candidates=20, criterion="a")


def test_exchange_passes_never_lose_to_plain_greedy(fanuc):
    pool = random_configurations(fanuc, 150, seed=3, targets=TARGETS)
    basis = identifiable_basis(fanuc, TARGETS)
    G = identification_jacobian(fanuc, pool, TARGETS) @ basis

    def logdet(idx):
        R = G[idx].reshape(-1, G.shape[2])
        return np.linalg.slogdet(R.T @ R)[1]

    greedy = greedy_d_optimal(G, 8, exchange_passes=0)
    exchanged = greedy_d_optimal(G, 8, exchange_passes=3)
    assert len(set(exchanged.tolist())) == 8
    assert logdet(exchanged) >= logdet(greedy) - 1e-9


def test_optimal_configurations_is_deterministic_and_respects_the_sampling_checks(fanuc):
    cell = Workspace(keep_out=(Box((-3.0, -3.0, -3.0), (3.0, -0.2, 3.0), "half the cell"),))  # y > -0.2 m only
    a = optimal_configurations(fanuc, 8, seed=1, targets=TARGETS, candidates=200, workspace=cell, max_condition=50)
    b = optimal_configurations(fanuc, 8, seed=1, targets=TARGETS, candidates=200, workspace=cell, max_condition=50)
    np.testing.assert_array_equal(a, b)
    assert cell.admits(checked_points(fanuc, a, TARGETS)).all()
    assert np.all(length_scaled_condition(fanuc, a) <= 50)


def test_sampling_options_with_an_explicit_pool_are_refused(fanuc):
    pool = random_configurations(fanuc, 20, seed=0)
    with pytest.raises(PlanningError, match="no effect"):
        optimal_configurations(fanuc, 5, seed=0, targets=TARGETS, pool=pool, max_condition=50)


def test_skew_convention_matches_the_cross_product():
    # δp = δv + δω × p = δv − skew(p) δω: the sign the identification Jacobian relies on.
    p, w = np.array([0.3, -0.2, 0.7]), np.array([0.1, 0.5, -0.4])
    np.testing.assert_allclose(-skew(p) @ w, np.cross(w, p))


# --------------------------------------------------------------------------------------------------------------
# The cell: the robot's own limits, the workspace, the targets facing the tracker; the order of the poses


from labcal.drivers.base import MotionRejected, SafetyLimits  # noqa: E402
from labcal.drivers.workspace import Box, Workspace  # noqa: E402
from labcal.robots.joint_map import JointMap  # noqa: E402
from labcal.sessions.planning import (  # noqa: E402
    TargetFacing,
    checked_points,
    move_time_matrix,
    order_for_motion,
)
from labcal.sessions.plans import make_plan, motion_time  # noqa: E402

NARROW_DEG = [[-90, 90], [-150, -30], [-150, 150], [-180, 0], [-180, 180], [-180, 180]]


def _narrowed_profile(folder, workspace: str = "") -> str:
    """drivers/ur10-lab.toml with the joint limits narrowed to NARROW_DEG (and a [workspace] table)."""
    from pathlib import Path

    text = (Path(__file__).parents[2] / "drivers" / "ur10-lab.toml").read_text()
    lower = [lo for lo, _ in NARROW_DEG]
    upper = [hi for _, hi in NARROW_DEG]
    text = text.replace("lower = [-360.0, -360.0, -360.0, -360.0, -360.0, -360.0]", f"lower = {lower}")
    text = text.replace("upper = [360.0, 360.0, 360.0, 360.0, 360.0, 360.0]", f"upper = {upper}")
    assert f"lower = {lower}" in text and f"upper = {upper}" in text
    path = folder / "ur10-narrow.toml"
    path.write_text(text + workspace)
    return str(path)


def test_a_narrowed_profile_gets_a_plan_its_own_limit_check_accepts(ur10, tmp_path):
    from labcal.drivers.ur import load_ur_profile

    limits = load_ur_profile(_narrowed_profile(tmp_path)).limits
    for q in (
        random_configurations(ur10, 60, seed=5, targets=TARGETS, safety=limits),
        optimal_configurations(ur10, 20, seed=5, targets=TARGETS, candidates=300, safety=limits),
    ):
        assert np.all((q >= np.radians(NARROW_DEG)[:, 0]) & (q <= np.radians(NARROW_DEG)[:, 1]))
        for row in q:  # the driver's own check, which raises MotionRejected for a pose it refuses
            limits.check_motion(row, limits.max_speed, limits.max_acceleration)
    # Without the robot's limits the planner draws over the model's ±360°, and the driver refuses those poses.
    unaware = random_configurations(ur10, 60, seed=5, targets=TARGETS)
    with pytest.raises(MotionRejected, match="outside its limits"):
        for row in unaware:
            limits.check_motion(row, limits.max_speed, limits.max_acceleration)


def test_controller_joint_limits_through_a_joint_map_are_checked_on_the_commanded_joints(ur10):
    # A controller whose J3 is measured from the horizontal (model elbow = J2 + J3), limits on controller joints.
    M = np.eye(6)
    M[2, 1] = 1.0
    joints = JointMap(M, np.zeros(6))
    box = np.radians([[-180, 180], [-120, -60], [-60, 60], [-180, 180], [-180, 180], [-180, 180]])
    safety = SafetyLimits(box, max_speed=0.5, max_acceleration=0.8)
    q = random_configurations(ur10, 40, seed=2, targets=TARGETS, safety=safety, joint_map=joints)
    for row in joints.to_controller(q):
        safety.check_motion(row, 0.5, 0.8)


def test_keep_out_boxes_and_the_allowed_box_hold_for_targets_tool_and_links(ur10):
    table = Box((-2.0, -2.0, -1.0), (2.0, 2.0, -0.01), "table")  # the robot stands on it
    stand = Box((0.6, -0.5, -1.0), (2.0, 0.5, 1.0), "tracker stand")
    workspace = Workspace(allowed=Box((-1.3, -1.3, -0.5), (1.3, 1.3, 1.6), "allowed"), keep_out=(table, stand))
    q = random_configurations(ur10, 60, seed=3, targets=TARGETS, workspace=workspace)
    points = checked_points(ur10, q, TARGETS)
    assert points.shape == (60, 3 + 1 + 7, 3)
    assert not table.contains(points).any() and not stand.contains(points).any()
    assert workspace.allowed.contains(points).all()
    # The same draw without the workspace puts links or targets into the table or the stand.
    free = checked_points(ur10, random_configurations(ur10, 60, seed=3, targets=TARGETS), TARGETS)
    assert table.contains(free).any(axis=1).sum() > 10 and stand.contains(free).any(axis=1).sum() > 0


def test_a_workspace_that_excludes_everything_says_what_was_hit(ur10):
    small = Workspace(allowed=Box((-0.3, -0.3, -0.1), (0.3, 0.3, 0.3), "allowed"))
    with pytest.raises(PlanningError, match=r"workspace: 2000 \(e.g. outside the allowed box\)"):
        random_configurations(ur10, 5, seed=1, workspace=small, max_tries=2000)
    table = Box((-2.0, -2.0, -1.0), (2.0, 2.0, 0.0), "table")
    with pytest.raises(PlanningError, match=r"refuses the robot's base .* table; a keep-out box must leave the base"):
        random_configurations(ur10, 5, seed=1, workspace=Workspace(keep_out=(table,)))


def test_targets_facing_away_from_the_tracker_are_dropped(ur10):
    normals = np.array([[0.0, 0.0, 1.0]] * 3)  # reflectors looking along the tool's z axis
    facing = TargetFacing((2.5, 0.0, 0.6), normals, np.radians(45.0))
    q = random_configurations(ur10, 80, seed=6, targets=TARGETS, facing=facing)
    assert facing.visible(ur10, q, TARGETS).all()
    # Check the geometry independently: the angle between each rotated normal and the ray to the tracker.
    T = ur10.fk(q)
    for Ti in T:
        for p, n in zip(TARGETS, normals, strict=True):
            point, normal = Ti[:3, :3] @ p + Ti[:3, 3], Ti[:3, :3] @ n
            ray = np.array([2.5, 0.0, 0.6]) - point
            assert np.degrees(np.arccos(normal @ ray / np.linalg.norm(ray))) <= 45.0 + 1e-9
    unaware = random_configurations(ur10, 80, seed=6, targets=TARGETS)
    assert facing.visible(ur10, unaware, TARGETS).all(axis=1).mean() < 0.5


def test_ordering_lowers_motion_time_and_is_deterministic(ur10):
    q = random_configurations(ur10, 60, seed=8, targets=TARGETS)
    order = order_for_motion(q, 0.5, 0.8)
    assert sorted(order.tolist()) == list(range(60))  # every pose once
    assert np.array_equal(order, order_for_motion(q.copy(), 0.5, 0.8))
    before = motion_time(make_plan(q, speed=0.5, acceleration=0.8))
    after = motion_time(make_plan(q[order], speed=0.5, acceleration=0.8))
    assert after < 0.6 * before
    # 2-opt's promise: no reversal of a stretch of the path shortens it.
    D = move_time_matrix(q[order], q[order], 0.5, 0.8)
    path = D[np.arange(59), np.arange(1, 60)].sum()
    for i in range(59):
        for j in range(i + 1, 60):
            flipped = np.r_[np.arange(i), np.arange(j, i - 1, -1), np.arange(j + 1, 60)]
            assert D[flipped[:-1], flipped[1:]].sum() >= path - 1e-9


# --------------------------------------------------------------------------------------------------------------
# `session new` on hardware profiles: the plan is drawn inside the robot's own limits, ordered, at its caps

WORKSPACE_TOML = """
[workspace]
allowed_min_mm = [-1400.0, -1400.0, -300.0]
allowed_max_mm = [1400.0, 1400.0, 1600.0]
tracker_mm = [2500.0, 0.0, 600.0]

[[workspace.keep_out]]
name = "table"
min_mm = [-2000.0, -2000.0, -1000.0]
max_mm = [2000.0, 2000.0, -10.0]
"""


@pytest.fixture
def hardware(monkeypatch, tmp_path):
    """`session new --robot-driver ur --tracker-driver serial` with the sim rig behind the UR driver's limits:
    the rig's robot checks its moves against the SafetyLimits of the profile file, as URRobot does."""
    from labcal.cli.ops import sessions as session_ops
    from labcal.drivers.ur import load_ur_profile

    opened = []

    def drivers(profile, tracker_profile, targets, robot_host=None, tracker_port=None):
        rig = session_ops._sim_rig(load("ur10"), targets, {"errors": "none", "seed": 1, "noise_seed": 1})
        rig.safety = load_ur_profile(profile).limits
        robot = rig.robot()
        opened.append(robot)
        return robot, rig.tracker()

    monkeypatch.setattr(session_ops, "_real_drivers", drivers)
    import functools

    import labcal.sessions

    # the sim rig settles at once: no half-second sleep per pose
    monkeypatch.setattr(
        labcal.sessions, "RunOptions", functools.partial(labcal.sessions.RunOptions, sleep=lambda s: None)
    )
    return opened


TARGETS_TEXT = 'unit = "m"\npoints = [[0.15, 0.0, 0.05], [-0.075, 0.13, 0.05], [-0.075, -0.13, 0.05]]\n'


def _new(tmp_path, profile, targets_text=TARGETS_TEXT, poses=16, tracker_profile="drivers/ndi-polaris.toml"):
    from labcal.cli.ops.sessions import new_session
    from labcal.datasets import SessionStore

    targets = tmp_path / "targets.toml"
    targets.write_text(targets_text)
    store = SessionStore(tmp_path / "store")
    summary = new_session(
        store, robot="ur10", targets_file=targets, poses=poses, robot_driver="ur", tracker_driver="serial",
        profile=profile, tracker_profile=tracker_profile,
    )  # fmt: skip
    return store, summary


def _recorded_plan(store, summary):
    from labcal.sessions.plans import Plan

    return Plan.from_pose_documents(store.read_journal(summary.session_id).start.plan)


def test_session_new_with_a_narrowed_profile_records_every_pose(hardware, tmp_path):
    from labcal.drivers.ur import load_ur_profile

    profile = _narrowed_profile(tmp_path, WORKSPACE_TOML)
    store, summary = _new(tmp_path, profile)
    assert (summary.exit_status, summary.valid, summary.rejected) == ("success", 16, 0)
    plan = _recorded_plan(store, summary)
    prof = load_ur_profile(profile)
    limits = prof.limits
    # The plan, listed: Move at the profile's caps, Settle, Measure; every Move inside the profile's limits.
    assert [type(c).__name__ for c in plan[:3]] == ["Move", "Settle", "Measure"]
    moves = [c for c in plan if type(c).__name__ == "Move"]
    assert {(m.speed, m.acceleration) for m in moves} == {(limits.max_speed, limits.max_acceleration)}
    assert limits.within(plan.configurations).all()
    assert prof.workspace.admits(checked_points(load("ur10").model, plan.configurations, TARGETS)).all()
    # The same poses the planner drew for this cell, ordered for less motion.
    drawn = random_configurations(
        load("ur10").model, 16, seed=0, targets=TARGETS, safety=limits, joint_map=load("ur10").joints,
        workspace=prof.workspace,
    )  # fmt: skip
    assert sorted(map(tuple, drawn)) == sorted(map(tuple, plan.configurations))
    assert motion_time(plan) < motion_time(make_plan(drawn, speed=limits.max_speed, acceleration=0.8))


def test_session_new_plans_targets_facing_the_tracker_of_the_profile(hardware, tmp_path):
    profile = _narrowed_profile(tmp_path, WORKSPACE_TOML)
    normals = "normals = [[0, 0, 1], [0, 0, 1], [0, 0, 1]]\nacceptance_deg = 50\n"
    store, summary = _new(tmp_path, profile, TARGETS_TEXT + normals)
    assert summary.exit_status == "success"
    q = _recorded_plan(store, summary).configurations
    facing = TargetFacing((2.5, 0.0, 0.6), [[0, 0, 1.0]] * 3, np.radians(50.0))
    assert facing.visible(load("ur10").model, q, TARGETS).all()


def test_two_tracker_positions_that_disagree_are_refused_before_planning(hardware, tmp_path):
    from labcal.cli.common import UserError

    tracker = tmp_path / "ndi.toml"
    tracker.write_text(open("drivers/ndi-polaris.toml").read() + "\n[placement]\nposition_mm = [2400.0, 0.0, 600.0]\n")
    profile = _narrowed_profile(tmp_path, WORKSPACE_TOML)
    with pytest.raises(UserError, match=r"tracker's position differs between .*tracker_mm and .*position_mm"):
        _new(tmp_path, profile, tracker_profile=str(tracker))


# --------------------------------------------------------------------------------------------------------------
# Where the cell is described: the targets' normals, the robot profile's [workspace], the tracker's [placement]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("normals = [[0, 0, 1], [0, 0, 1]]\n", "normals lists 2 directions for 3 targets"),
        ("normals = [[0, 0, 1], [0, 0, 0], [0, 0, 1]]\n", "normals entry t2 is zero"),
        ("normals = [[0, 0, 1], [0, 0, 1], [0, 0, 1]]\n", "normals need acceptance_deg"),
        ("normals = [[0, 0, 1], [0, 0, 1], [0, 0, 1]]\nacceptance_deg = 120\n", "acceptance_deg must be one angle"),
        ("acceptance_deg = 30\n", "acceptance_deg needs normals"),
    ],
)
def test_bad_target_normals_name_the_key(tmp_path, extra, message):
    from labcal.datasets.errors import TargetsError
    from labcal.datasets.targets import load_target_normals

    path = tmp_path / "t.toml"
    path.write_text(TARGETS_TEXT + extra)
    with pytest.raises(TargetsError, match=message):
        load_target_normals(path)


def test_target_normals_are_unit_vectors_and_acceptance_radians(tmp_path):
    from labcal.datasets.targets import load_target_normals, load_targets

    path = tmp_path / "t.toml"
    path.write_text(TARGETS_TEXT + "normals = [[0, 0, 2], [0, 1, 1], [1, 0, 0]]\nacceptance_deg = [30, 45, 60]\n")
    normals, acceptance = load_target_normals(path)
    assert np.allclose(normals, [[0, 0, 1], [0, 2**-0.5, 2**-0.5], [1, 0, 0]])
    assert np.allclose(acceptance, np.radians([30, 45, 60]))
    assert load_targets(path).shape == (3, 3)  # the points read as before
    path.write_text(TARGETS_TEXT)
    assert load_target_normals(path) is None


def test_the_robot_profile_workspace_is_read_in_millimetres_and_checked(tmp_path):
    from labcal.drivers.ur import URProfileError, load_ur_profile

    workspace = load_ur_profile(_narrowed_profile(tmp_path, WORKSPACE_TOML)).workspace
    assert workspace.allowed.lo == (-1.4, -1.4, -0.3) and workspace.tracker == (2.5, 0.0, 0.6)
    assert [b.name for b in workspace.keep_out] == ["table"] and workspace.keep_out[0].hi[2] == pytest.approx(-0.01)
    bad = WORKSPACE_TOML.replace("max_mm = [2000.0, 2000.0, -10.0]", "max_mm = [2000.0, 2000.0, -2000.0]")
    with pytest.raises(URProfileError, match=r"workspace.keep_out\[0\] min_mm must be below max_mm"):
        load_ur_profile(_narrowed_profile(tmp_path, bad))
    half = WORKSPACE_TOML.replace("allowed_max_mm = [1400.0, 1400.0, 1600.0]\n", "")
    with pytest.raises(URProfileError, match="needs both allowed_min_mm and allowed_max_mm"):
        load_ur_profile(_narrowed_profile(tmp_path, half))
    typo = WORKSPACE_TOML.replace("tracker_mm", "traker_mm")
    with pytest.raises(URProfileError, match="did you mean 'tracker_mm'"):
        load_ur_profile(_narrowed_profile(tmp_path, typo))


def test_the_tracker_profile_placement_is_read_in_millimetres(tmp_path):
    from labcal.drivers.serial.profiles import load_placement

    path = tmp_path / "ndi.toml"
    path.write_text(open("drivers/ndi-polaris.toml").read() + "\n[placement]\nposition_mm = [2400.0, 0.0, 600.0]\n")
    assert load_placement(path) == pytest.approx((2.4, 0.0, 0.6))
    assert load_placement("drivers/ndi-polaris.toml") is None


def _uncomment(text: str, first: str) -> str:
    """The file with its commented example block (from the line ``# {first}`` to the next blank line) switched on."""
    lines = text.splitlines()
    start = lines.index(f"# {first}")
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("#")), len(lines))
    block = [line[2:] if line.startswith("# ") else "" for line in lines[start:end]]
    return "\n".join(lines[:start] + block + lines[end:]) + "\n"


@pytest.mark.parametrize("name", ["ur10-lab.toml", "ur5e-lab.toml"])
def test_the_example_profiles_workspace_block_loads_and_plans(tmp_path, name):
    from pathlib import Path

    from labcal.drivers.ur import load_ur_profile

    path = tmp_path / name
    path.write_text(_uncomment((Path("drivers") / name).read_text(), "[workspace]"))
    profile = load_ur_profile(path)
    assert [b.name for b in profile.workspace.keep_out] == ["table", "tracker stand"]
    assert profile.workspace.tracker is not None and load_ur_profile(Path("drivers") / name).workspace is None
    model = load(name.split("-")[0]).model
    q = random_configurations(model, 10, seed=0, targets=TARGETS, workspace=profile.workspace, safety=profile.limits)
    assert profile.workspace.admits(checked_points(model, q, TARGETS)).all()


def test_the_example_placement_and_normals_load(tmp_path):
    from pathlib import Path

    from labcal.datasets.targets import load_target_normals
    from labcal.drivers.serial.profiles import load_placement

    for name in ("ndi-polaris.toml", "ascii-example.toml"):
        path = tmp_path / name
        path.write_text(_uncomment((Path("drivers") / name).read_text(), "[placement]"))
        assert load_placement(path) == pytest.approx((2.6, 0.0, 0.6))
    path = tmp_path / "targets.toml"
    path.write_text(
        _uncomment(
            Path("drivers/targets-example.toml").read_text(),
            "normals = [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]",
        )
    )
    normals, acceptance = load_target_normals(path)
    assert normals.shape == (3, 3) and np.allclose(acceptance, np.radians(30))


def test_runner_accepts_exactly_what_the_drivers_check_motion_accepts():
    from labcal.sessions.planning import runner_accepts

    M = np.eye(6)
    M[2, 1] = 1.0
    joints = JointMap(M, np.zeros(6))
    for safety in (
        SafetyLimits(np.radians(NARROW_DEG), max_speed=0.5, max_acceleration=0.8),  # controller joints
        SafetyLimits(np.radians(NARROW_DEG), max_speed=0.5, max_acceleration=0.8, joint_map=joints),  # model joints
    ):
        q = np.random.default_rng(0).uniform(-3.5, 3.5, size=(300, 6))  # model joints
        verdict = runner_accepts(q, safety, joints)
        assert 0 < verdict.sum() < 300
        for row, ok in zip(joints.to_controller(q), verdict, strict=True):
            try:
                safety.check_motion(row, 0.5, 0.8)
                refused = False
            except MotionRejected:
                refused = True
            assert refused != ok
