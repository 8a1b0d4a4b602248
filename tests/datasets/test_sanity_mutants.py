"""The sanity checks' tolerances, pinned from both sides (issue 26: a unit-slip tolerance 10× looser survived the
other tests). Each case is a mistake just outside a tolerance that must be found, beside its neighbour inside it
that must not be called the same thing. Simulated UR10 data, ``check_measurements`` as the import calls it."""

from __future__ import annotations

import numpy as np
import pytest

import scenarios as sc
from labcal.datasets.sanity import check_measurements
from labcal.robots import load

UR10 = load("ur10")


@pytest.fixture(scope="module")
def good():
    return sc.good("ur10", 40, seed=3)


def findings(q, points, targets) -> dict[str, str]:
    report = check_measurements(q, points, targets, robot=UR10)
    return {f.check: f.message for f in report.failures}


def test_good_data_have_no_finding(good):
    assert findings(good.q, good.points, good.targets) == {}


def test_a_scale_within_5_percent_of_a_unit_ratio_is_a_unit_slip_and_20_percent_off_is_not(good):
    near = findings(good.q, good.points * 1000 * 1.04, good.targets)["target-distances"]
    assert near.startswith("length unit slip") and "mm imported as m" in near
    far = findings(good.q, good.points * 1000 * 1.2, good.targets)["target-distances"]
    assert "unit slip" not in far and "does not match the data" in far
    inch = findings(good.q, good.points * 25.4 * 1.3, good.targets)["target-distances"]
    assert "unit slip" not in inch


def test_a_target_10_mm_off_in_the_targets_file_is_found(good):
    targets = good.targets.copy()
    targets[0, 0] += 0.010  # t1 10 mm off: its distances change by ~9 mm, above 2 % of 224-335 mm
    msg = findings(good.q, good.points, targets)["target-distances"]
    assert "does not match the data" in msg and "t1–t2 335.4 mm measured vs 344.4 mm in the file" in msg


def test_points_60_mm_off_the_nominal_robot_are_found(good):
    # Every target moved by the same 60 mm in the tool frame: the distances agree, the robot does not.
    f = findings(good.q, good.points, good.targets + np.array([0.0, 0.0, 0.06]))
    assert set(f) == {"nominal"} and "60.1 mm (mean over 40 rows)" in f["nominal"]


def test_one_row_with_a_target_8_mm_off_is_an_outlier(good):
    points = good.points.copy()
    points[7, 1] += [0.008, 0.0, 0.0]
    f = findings(good.q, points, good.targets)
    assert set(f) == {"target-outliers"} and "row 8" in f["target-outliers"]


def test_radians_read_as_degrees_are_found_on_an_arm_with_limits_under_360_degrees():
    # A FANUC-class arm: joint limits 135° to 360° wide, so the check must not wait for ±360° joints.
    fanuc = load("fanuc-m1000ia")
    g = sc.good("fanuc-m1000ia", 40, seed=3)
    report = check_measurements(np.radians(g.q), g.points, g.targets, robot=fanuc, angle_unit="deg")
    f = {f.check: f.message for f in report.failures}
    assert "joint-span" in f and "the values look like radians imported as degrees" in f["joint-span"]
