"""Any number of targets in the simulator: m ≥ 1 targets, a seeded drop-out per cell (NaN rows), one reflector
(t1 alone)."""

from __future__ import annotations

import numpy as np
import pytest

import scenarios as S
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, drop_unseen, seen_mask, simulate

NOISE = ErrorSpec.default().tracker_noise


@pytest.mark.parametrize("m", [1, 2, 5])
def test_any_number_of_targets_is_measured_where_the_true_tool_puts_them(m):
    spec = load("ur10")
    actual = simulate(spec, ErrorSpec.paper(), seed=2)
    targets = np.random.default_rng(m).normal(scale=0.1, size=(m, 3))
    q = np.random.default_rng(0).uniform(-1, 1, (7, 6))
    T = actual.true_pose(q)
    expected = T[:, None, :3, :3] @ targets[None, :, :, None]
    expected = expected[..., 0] + T[:, None, :3, 3]
    np.testing.assert_allclose(actual.true_points(q, targets), expected, atol=1e-12)
    measured = actual.measure(q, targets, np.random.default_rng(1))
    assert measured.shape == (7, m, 3) and np.abs(measured - expected).max() < 6 * NOISE


@pytest.mark.parametrize("k,m,p", [(200, 3, 0.3), (150, 2, 0.5), (90, 3, 0.0), (30, 3, 2 / 3)])
def test_exact_drop_out_loses_the_requested_share_of_cells_and_never_a_whole_row(k, m, p):
    seen = seen_mask(k, m, p, np.random.default_rng(4), exact=True)
    assert seen.shape == (k, m) and seen.any(axis=1).all()
    assert (~seen).sum() == round(p * k * m)
    assert seen.dtype == bool and np.array_equal(seen, seen_mask(k, m, p, np.random.default_rng(4), exact=True))


def test_exact_drop_out_refuses_more_than_it_can_lose():
    # A single target can never be lost: the row would not be a measurement.
    with pytest.raises(ValueError, match=r"dropout ≤ 0\.000 for 1 target"):
        seen_mask(40, 1, 0.1, np.random.default_rng(0), exact=True)
    assert seen_mask(40, 1, 0.9, np.random.default_rng(0)).all()
    with pytest.raises(ValueError, match=r"cannot lose 8 of 9 cells and keep one target per row"):
        seen_mask(3, 3, 0.9, np.random.default_rng(0), exact=True)
    with pytest.raises(ValueError, match="probability in"):
        seen_mask(3, 3, 1.5, np.random.default_rng(0))


def test_per_target_probabilities_are_drawn_per_cell_and_seeded():
    p = np.array([0.0, 0.2, 0.6])
    a = seen_mask(4000, 3, p, np.random.default_rng(9))
    np.testing.assert_array_equal(a, seen_mask(4000, 3, p, np.random.default_rng(9)))
    assert not np.array_equal(a, seen_mask(4000, 3, p, np.random.default_rng(10)))
    lost = 1 - a.mean(axis=0)
    assert lost[0] == 0.0 and abs(lost[1] - 0.2) < 0.03 and abs(lost[2] - 0.6) < 0.03
    assert a.any(axis=1).all()
    # All three lost only where t1 was seen anyway (p = 0): no row is empty, even at p = 1 for two targets.
    b = seen_mask(500, 3, [1.0, 1.0, 1.0], np.random.default_rng(0))
    assert np.array_equal(b.sum(axis=1), np.ones(500))


def test_drop_unseen_blanks_whole_target_rows_only():
    pts = np.arange(2 * 3 * 3, dtype=float).reshape(2, 3, 3)
    seen = np.array([[True, False, True], [False, True, True]])
    out = drop_unseen(pts, seen)
    assert np.isnan(out[0, 1]).all() and np.isnan(out[1, 0]).all()
    np.testing.assert_array_equal(out[seen], pts[seen])
    assert not np.isnan(pts).any()  # the input is not touched


@pytest.fixture(scope="module")
def base():
    return S.good("ur10", 40, seed=5)


def test_with_targets_keeps_the_chosen_targets_of_every_row(base):
    one = S.with_targets(base, [0])
    assert one.m == 1 and one.points.shape == (40, 1, 3)
    np.testing.assert_array_equal(one.points[:, 0], base.points[:, 0])
    np.testing.assert_array_equal(one.targets, base.targets[:1])
    two = S.with_targets(base, [2, 0])
    np.testing.assert_array_equal(two.points, base.points[:, [2, 0]])
    for bad in ([], [3], [0, 0]):
        with pytest.raises(ValueError, match="distinct targets among 0 … 2"):
            S.with_targets(base, bad)


def test_with_dropout_is_seeded_and_loses_whole_targets(base):
    d = S.with_dropout(base, 0.3, seed=1)
    assert d.seen.sum() == 120 - 36 and d.seen.any(axis=1).all() and d.k == base.k
    np.testing.assert_array_equal(d.points[d.seen], base.points[d.seen])
    assert np.isnan(d.points[~d.seen]).all()
    np.testing.assert_array_equal(d.seen, S.with_dropout(base, 0.3, seed=1).seen)
    assert not np.array_equal(d.seen, S.with_dropout(base, 0.3, seed=2).seen)
    # Dropping more from an already incomplete set never brings a target back.
    again = S.with_dropout(d, 0.2, seed=3, exact=False)
    assert not (again.seen & ~d.seen).any()


def test_corruptions_that_need_targets_say_so(base):
    with pytest.raises(ValueError, match="two distinct targets among the 1 measured"):
        S.swapped_targets(S.with_targets(base, [0]))
    # Noise in the box of the points that were seen: NaN cells do not poison the box.
    noisy = S.pure_noise(S.with_dropout(base, 0.3, seed=0))
    assert np.isfinite(noisy.points).all()
    lo, hi = np.nanmin(base.points.reshape(-1, 3), axis=0), np.nanmax(base.points.reshape(-1, 3), axis=0)
    assert np.all(noisy.points >= lo - 1e-12) and np.all(noisy.points <= hi + 1e-12)


def test_repeatability_scale_is_the_length_scaled_twist():
    # The per-motion pose scatter: `repeatability` metres of translation and repeatability / reach radians.
    spec = load("ur10")
    actual = simulate(spec, ErrorSpec(0, 0, 0, 0, 0, 0, 1e-3, 0), seed=0)
    q = np.zeros((4000, 6))
    T = actual.true_pose(q, np.random.default_rng(0))
    d = se3.log_se3(T @ se3.inv(spec.model.fk(q)))
    L = spec.model.reach()
    assert abs(np.std(d[:, 3:]) - 1e-3 / L) < 0.05 * 1e-3 / L
