"""Per-target point errors (metrics.point_errors / summarize_points) and split_table's "points" entries."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from labcal.calibration import metrics
from labcal.calibration.fit import fit
from labcal.calibration.observations import Observations, rigid_fit
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.12, 0.0, 0.06], [-0.06, 0.10, 0.06], [-0.06, -0.10, 0.09]])


@pytest.fixture(scope="module")
def rig():
    spec = load("ur10")
    actual = simulate(spec, ErrorSpec.paper(), seed=1)
    rng = np.random.default_rng(0)
    q = rng.uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(40, 6))
    points = actual.measure(q, TARGETS, rng)
    return spec, q, points


def test_point_errors_are_distances_per_configuration_and_target(rig):
    spec, q, points = rig
    nominal = CalibratedRobot(spec.model, spec.model)
    obs = Observations(q, points, TARGETS)
    d = metrics.point_errors(nominal, obs)
    assert d.shape == (40, 3)
    expected = np.linalg.norm(points - nominal.predict_points(q, TARGETS), axis=-1)
    np.testing.assert_allclose(d, expected, rtol=0, atol=1e-15)
    # A robot whose prediction is shifted by 1 mm along x has every point 1 mm further from its own prediction.
    shifted = CalibratedRobot(spec.model, spec.model, T_tracker_base=se3.pose(np.array([1e-3, 0, 0])))
    perfect = Observations(q, nominal.predict_points(q, TARGETS) + np.array([1e-3, 0, 0]), TARGETS, frame="tracker")
    np.testing.assert_allclose(metrics.point_errors(shifted, perfect), 0.0, atol=1e-12)


def test_missing_target_is_nan_for_that_target_only_and_skipped_by_the_summary(rig):
    spec, q, points = rig
    nominal = CalibratedRobot(spec.model, spec.model)
    pts = points.copy()
    pts[5, 1] = np.nan  # target 2 not seen in configuration 5
    obs = SimpleNamespace(k=40, q=q, points=pts, targets=TARGETS)
    d = metrics.point_errors(nominal, obs)
    assert np.isnan(d[5, 1]) and np.isfinite(np.delete(d.ravel(), 5 * 3 + 1)).all()
    s = metrics.summarize_points(d)
    assert s["count"] == 119 and s["per_target"][1]["count"] == 39 and s["per_target"][0]["count"] == 40
    assert s["per_target"][1]["mean"] == pytest.approx(np.nanmean(d[:, 1]), rel=1e-12)
    assert s["max"] == pytest.approx(np.nanmax(d), rel=1e-12)
    assert s["p95"] == pytest.approx(np.percentile(d[np.isfinite(d)], 95), rel=1e-12)


def test_split_table_adds_points_and_keeps_pose_keys_without_test_rows(rig):
    spec, q, points = rig
    nominal = CalibratedRobot(spec.model, spec.model)
    obs = Observations(q, points, TARGETS).with_splits(0.25, seed=0)
    table = metrics.split_table(nominal, nominal, obs)
    assert set(table) == {"train", "val", "all"}  # no test rows: skipped, no error
    for split in table.values():
        assert {"before", "after", "points"} <= set(split)
        assert "pos_mean" in split["before"] and "ori_max" in split["after"]
        pts = split["points"]["after"]
        assert len(pts["per_target"]) == 3 and pts["max"] >= pts["p95"] >= 0
    assert table["all"]["points"]["before"]["count"] == 120


def test_swapped_targets_hide_behind_the_pose_error_but_not_behind_the_point_error(rig):
    """Issue 13: with t1 and t2 swapped a fit reports a sub-mm pose error while the points are tens of mm off."""
    spec, q, points = rig
    swapped = TARGETS[[1, 0, 2]]
    result = fit(Observations(q, points, swapped), spec.model, "local-poe", val_fraction=0.0)
    table = metrics.split_table(result.before, result.robot, result.obs)
    pose_mm = table["all"]["after"]["pos_mean"] * 1e3
    point_mm = table["all"]["points"]["after"]["mean"] * 1e3
    # No calibration can bring the points closer than the rigid fit of the (wrong) triangle to them.
    T = rigid_fit(swapped, points)
    rigid = np.linalg.norm(points - (np.einsum("kab,mb->kma", T[:, :3, :3], swapped) + T[:, None, :3, 3]), axis=-1)
    assert pose_mm < 0.1  # the pose error looks like a good calibration …
    assert point_mm > 1.0 and point_mm > 20 * pose_mm  # … the point error does not
    assert point_mm >= 0.99 * rigid.mean() * 1e3
