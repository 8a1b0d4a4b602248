"""Planner properties: limits, conditioning, region and line of sight respected; optimised sets beat random ones."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.kinematics.se3 import skew
from labcal.robots import load
from labcal.sessions.planning import (
    DEFAULT_MAX_CONDITION,
    LineOfSight,
    PlanningError,
    greedy_d_optimal,
    identifiable_basis,
    identification_jacobian,
    joint_ranges,
    length_scaled_condition,
    observability,
    optimal_configurations,
    prediction_variance,
    random_configurations,
)

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


def test_explicit_limits_are_respected_and_must_lie_inside_the_model(ur10):
    limits = np.array(ur10.limits)
    limits[1] = [-1.0, -0.5]
    q = random_configurations(ur10, 50, seed=1, limits=limits, max_condition=None)
    assert np.all((q[:, 1] >= -1.0) & (q[:, 1] <= -0.5))
    limits[2] = [-10.0, 0.0]
    with pytest.raises(PlanningError, match=r"row 2 \(joint 3\)"):
        random_configurations(ur10, 5, seed=1, limits=limits)


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


def test_tool_origin_stays_inside_the_region(ur10):
    box = np.array([[0.3, -0.5, 0.0], [1.0, 0.5, 0.8]])
    q = random_configurations(ur10, 40, seed=3, region=box)
    p = ur10.fk(q)[:, :3, 3]
    assert np.all(p >= box[0]) and np.all(p <= box[1])


def test_unreachable_region_gives_a_clear_error(ur10):
    with pytest.raises(PlanningError, match="region"):
        random_configurations(ur10, 5, seed=0, region=[[10, 10, 10], [11, 11, 11]], max_tries=2000)


def test_targets_stay_in_the_tracker_cone_and_apart_across_lines_of_sight(ur10):
    tracker = LineOfSight(position=(3.0, 0.0, 0.5), axis=(-1.0, 0.0, 0.0), half_angle=np.radians(20))
    q = random_configurations(ur10, 30, seed=5, targets=TARGETS, tracker=tracker, min_target_distance=0.05)
    p = ur10.target_points(q, TARGETS)  # (k, 3, 3) base frame
    d = p - np.array(tracker.position)
    angle = np.arccos(np.clip(-d[..., 0] / np.linalg.norm(d, axis=-1), -1, 1))
    assert np.all(angle <= np.radians(20) + 1e-12)
    for i in range(3):
        u = d[:, i] / np.linalg.norm(d[:, i], axis=-1, keepdims=True)
        for j in range(3):
            if i != j:
                dist = np.linalg.norm(np.cross(d[:, j], u), axis=-1)  # distance of t_j from t_i's ray
                assert np.all(dist >= 0.05 - 1e-12)


def test_min_target_distance_needs_a_tracker(ur10):
    with pytest.raises(PlanningError, match="needs a tracker"):
        random_configurations(ur10, 5, seed=0, targets=TARGETS, min_target_distance=0.01)


@pytest.mark.parametrize("count", [0, -1, 2.5])
def test_bad_count_is_refused(ur10, count):
    with pytest.raises(PlanningError, match="count"):
        random_configurations(ur10, count, seed=0)


def test_same_seed_same_configurations_other_seed_others(ur10):
    a = random_configurations(ur10, 20, seed=11, region=[[-1, -1, -0.2], [1, 1, 1]])
    b = random_configurations(ur10, 20, seed=11, region=[[-1, -1, -0.2], [1, 1, 1]])
    c = random_configurations(ur10, 20, seed=12, region=[[-1, -1, -0.2], [1, 1, 1]])
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_lower_mobility_robot_is_planned_too():
    scara = load("scara4").model
    q = random_configurations(scara, 20, seed=0)
    assert q.shape == (20, 4) and np.all(length_scaled_condition(scara, q) <= DEFAULT_MAX_CONDITION)


def test_joint_ranges_rejects_a_bad_fraction(ur10):
    with pytest.raises(PlanningError, match="range_fraction"):
        joint_ranges(ur10, range_fraction=0.0)


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
    box = [[0.5, -2.0, 0.0], [3.0, 2.0, 2.5]]
    a = optimal_configurations(fanuc, 8, seed=1, targets=TARGETS, candidates=200, region=box, max_condition=50)
    b = optimal_configurations(fanuc, 8, seed=1, targets=TARGETS, candidates=200, region=box, max_condition=50)
    np.testing.assert_array_equal(a, b)
    p = fanuc.fk(a)[:, :3, 3]
    assert np.all(p >= box[0]) and np.all(p <= box[1])
    assert np.all(length_scaled_condition(fanuc, a) <= 50)


def test_sampling_options_with_an_explicit_pool_are_refused(fanuc):
    pool = random_configurations(fanuc, 20, seed=0)
    with pytest.raises(PlanningError, match="no effect"):
        optimal_configurations(fanuc, 5, seed=0, targets=TARGETS, pool=pool, region=[[0, 0, 0], [1, 1, 1]])


def test_skew_convention_matches_the_cross_product():
    # δp = δv + δω × p = δv − skew(p) δω: the sign the identification Jacobian relies on.
    p, w = np.array([0.3, -0.2, 0.7]), np.array([0.1, 0.5, -0.4])
    np.testing.assert_allclose(-skew(p) @ w, np.cross(w, p))
