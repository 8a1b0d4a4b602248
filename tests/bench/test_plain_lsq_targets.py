"""The plain least-squares measuring stick with any number of targets and targets not seen (NaN rows)."""

from __future__ import annotations

import numpy as np
import pytest

import scenarios as S
from labcal.robots import load
from labcal.simulation import ErrorSpec
from plain_lsq import fit_plain, seen_points


@pytest.fixture(scope="module")
def exact():
    """Geometric errors only and 0.1 µm of noise: a complete model fitted on enough points predicts them to the
    noise. (Some noise keeps the least-squares stopping rule meaningful: on exact data the cost heads to zero and
    the relative tolerance is never met.)"""
    return S.good("ur10", 60, errors=ErrorSpec.paper(tracker_noise=1e-7), seed=6)


def _held_out_error(fit, scn, rows) -> float:
    """Largest distance (m) between predicted and true points of all three targets in the rows given."""
    true = scn.actual.true_points(scn.q[rows], scn.targets)
    return float(np.linalg.norm(fit.predict_points(scn.q[rows], scn.targets) - true, axis=-1).max())


@pytest.mark.parametrize("tracker", [False, True])
@pytest.mark.parametrize("variant", ["t1", "t1+t2", "dropout"])
def test_fewer_points_still_reach_the_truth_at_the_measured_points(exact, variant, tracker):
    scn = exact if not tracker else S.in_tracker_frame(exact)
    if variant == "t1":
        data = S.with_targets(scn, [0])
    elif variant == "t1+t2":
        data = S.with_targets(scn, [0, 1])
    else:
        data = S.with_dropout(scn, 0.3, seed=2)
    fit = fit_plain(load("ur10").model, data.q[:45], data.points[:45], data.targets, data.frame)
    pred = fit.predict_points(exact.q[45:], data.targets)
    if tracker:
        back = np.linalg.inv(scn.T_tracker_base)  # to the base frame, where the truth is
        pred = np.einsum("ab,kmb->kma", back[:3, :3], pred) + back[:3, 3]
    true = exact.actual.true_points(exact.q[45:], data.targets)
    assert np.linalg.norm(pred - true, axis=-1).max() < 2e-6
    if variant == "dropout" and not tracker:
        # Three targets, some lost: the orientation is still fixed, so every target of every pose is predicted.
        assert _held_out_error(fit, exact, slice(45, None)) < 2e-6


def test_nan_cells_are_left_out_not_fitted(exact):
    # With the lost cells NaN the fit reaches the truth; the same cells read 1 mm off would pull it away, so the
    # NaN cells really are left out rather than read.
    data = S.with_dropout(exact, 0.3, seed=4)
    model = load("ur10").model
    fit = fit_plain(model, data.q[:45], data.points[:45], data.targets)
    assert _held_out_error(fit, exact, slice(45, None)) < 2e-6
    off = np.where(np.isnan(data.points), exact.points + 1e-3, data.points)
    bad = fit_plain(model, data.q[:45], off[:45], data.targets)
    assert _held_out_error(bad, exact, slice(45, None)) > 1e-5


def test_same_data_give_a_bit_identical_fit_whose_cost_counts_every_point(exact):
    noisy = S.good("ur10", 40, seed=7)
    model = load("ur10").model
    a = fit_plain(model, noisy.q, noisy.points, noisy.targets)
    b = fit_plain(model, noisy.q, noisy.points.copy(), noisy.targets.copy())
    assert np.array_equal(a.x, b.x) and a.nfev == b.nfev
    r = np.linalg.norm(a.predict_points(noisy.q, noisy.targets) - noisy.points, axis=-1)
    assert abs(np.sum(r**2) / 2 - a.cost) < 1e-3 * a.cost + 1e-15  # the cost is the sum over every point (+ ridge)


def test_bad_shapes_and_partly_nan_points_are_named():
    targets = np.zeros((2, 3))
    pts = np.zeros((4, 2, 3))
    pts[2, 1, 0] = np.nan
    with pytest.raises(ValueError, match="point of target t2 in row 2 is partly NaN"):
        seen_points(pts, targets)
    with pytest.raises(ValueError, match=r"points must have shape \(k, 2, 3\)"):
        seen_points(np.zeros((4, 3, 3)), targets)
    with pytest.raises(ValueError, match=r"targets must have shape \(m, 3\) with m ≥ 1"):
        seen_points(np.zeros((4, 0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="no target was seen"):
        fit_plain(load("ur10").model, np.zeros((2, 6)), np.full((2, 1, 3), np.nan), np.zeros((1, 3)))
