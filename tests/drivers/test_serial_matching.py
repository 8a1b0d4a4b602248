"""Labelling unordered markers as t1, t2, t3 by the target triangle's side lengths."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from serial_fixtures import TARGETS

from labcal.drivers.base import MeasurementRejected
from labcal.drivers.serial.matching import check_targets, match_targets

TOL = 0.5e-3


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    extra=st.integers(0, 3),
    noise=st.floats(0.0, 0.1e-3),
)
def test_any_pose_any_order_with_extra_markers_recovers_the_labels(seed, extra, noise):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    seen = TARGETS @ R.T + rng.uniform(-1.0, 1.0, 3)
    seen = seen + rng.normal(0.0, noise / 3, seen.shape).clip(-noise / 2, noise / 2)
    # Spurious reflections well away from the tool (> 0.3 m): they cannot fake a target triangle.
    far = seen.mean(axis=0) + rng.choice([-1, 1], (extra, 3)) * rng.uniform(0.3, 0.6, (extra, 3))
    strays = np.vstack([seen, far])
    order = rng.permutation(len(strays))
    m = match_targets(strays[order], TARGETS, TOL)
    np.testing.assert_array_equal(order[list(m.indices)], [0, 1, 2])
    np.testing.assert_allclose(m.points, seen)
    assert m.mismatch <= TOL


def test_reports_the_worst_side_error():
    seen = TARGETS.copy()
    seen[1, 0] += 0.3e-3  # t1-t2 grows by 0.3 mm, t2-t3 changes a little less
    m = match_targets(seen[::-1], TARGETS, TOL)
    assert m.indices == (2, 1, 0)
    assert m.mismatch == pytest.approx(0.3e-3, rel=1e-6)


def test_too_few_markers():
    with pytest.raises(MeasurementRejected, match="only 2 marker"):
        match_targets(TARGETS[:2], TARGETS, TOL)


def test_inconsistent_triangle_is_rejected_with_the_mismatch_in_mm():
    bent = TARGETS + np.array([[0, 0, 0], [0, 0, 0], [0, 0.002, 0]])  # t1-t3 is 2 mm too long
    with pytest.raises(MeasurementRejected, match=r"mismatch 2\.000 mm > tolerance 0\.500 mm"):
        match_targets(bent, TARGETS, TOL)


def test_two_copies_of_the_triangle_are_ambiguous():
    strays = np.vstack([TARGETS, TARGETS + np.array([0.5, 0.0, 0.0])])
    with pytest.raises(MeasurementRejected, match="ambiguous"):
        match_targets(strays, TARGETS, TOL)


def test_check_targets_accepts_scalene_and_refuses_isosceles_and_degenerate_triangles():
    np.testing.assert_array_equal(check_targets(TARGETS, TOL), TARGETS)
    iso = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.05, 0.08, 0.0]])
    with pytest.raises(ValueError, match=r"t1-t3.*t2-t3.*not scalene enough"):
        check_targets(iso, TOL)
    with pytest.raises(ValueError, match="coincident"):
        check_targets(np.zeros((3, 3)), TOL)
    with pytest.raises(ValueError, match=r"\(m, 3\)"):
        check_targets(np.zeros((3, 2)), TOL)
