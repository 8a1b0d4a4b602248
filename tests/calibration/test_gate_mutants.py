"""The fit's gates, each pinned just outside and inside its threshold (issue 26: demoting rows-dropped to a note and
transposing the tracker rotation of the point residuals survived the other tests; the mutation benchmark,
benchmarks/mutation.py, found the rest). Small simulated UR10 sets fit by local POE in a fraction of a second."""

from __future__ import annotations

import dataclasses
import importlib
from types import SimpleNamespace

import numpy as np
import pytest

from labcal.calibration import Observations, fit
from labcal.calibration.metrics import point_errors, point_residuals
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

UR10 = load("ur10")
# labcal.calibration re-exports the function fit under the module's name
fit_module = importlib.import_module("labcal.calibration.fit")
TARGETS = np.array([[0.12, 0.0, 0.05], [-0.06, 0.15, 0.05], [-0.07, -0.11, 0.04]])


def random_poses(k, seed=2):
    rng = np.random.default_rng(seed)
    return rng.uniform(UR10.model.limits[:, 0], UR10.model.limits[:, 1], size=(k, 6))


def measure(q, errors=None, seed=3):
    actual = simulate(UR10, errors or ErrorSpec.paper(), seed=seed)
    return actual.measure(q, TARGETS, np.random.default_rng(seed + 100))


def codes(result) -> set[str]:
    return {w["code"] for w in result.warnings}


# -- rows-dropped -------------------------------------------------------------------------------------------------


def _dropped(count: int, rows: int, kept_network: bool):
    net = {"dropped_causes": [{"cause": "joint 5 near a singular value", "rows": count}],
           "observations": {"dropped": count}} if kept_network else None  # fmt: skip
    warnings, notes = [], []
    table = SimpleNamespace(cv=None)  # no cross-validation record: only the kept network speaks
    fit_module._dropped(table, SimpleNamespace(k=rows), net, warnings, notes)
    return [w["code"] for w in warnings], notes


def test_a_kept_network_missing_more_than_a_tenth_of_the_rows_is_a_warning():
    assert _dropped(3, 20, kept_network=True)[0] == ["rows-dropped"]


def test_a_tenth_or_less_dropped_is_a_note():
    warnings, notes = _dropped(2, 20, kept_network=True)
    assert warnings == [] and len(notes) == 1 and notes[0].startswith("rows-dropped: 2 of 20 rows dropped")


# -- point residuals in the tracker frame -------------------------------------------------------------------------


def test_point_residuals_rotate_predictions_into_the_tracker_frame():
    q = random_poses(6)
    # A rotation that is not its own transpose (about a skew axis), and a shift: points exactly where it puts them.
    T = se3.pose([0.4, -1.2, 2.0], [0.7, -0.2, 1.1])
    robot = CalibratedRobot(UR10.model, UR10.model, T_tracker_base=T)
    pred = robot.predict_points(q, TARGETS)
    points = np.einsum("ab,kmb->kma", T[:3, :3], pred) + T[:3, 3]
    obs = Observations(q, points, TARGETS, frame="tracker")
    np.testing.assert_allclose(point_residuals(robot, obs), 0.0, atol=1e-12)
    assert point_errors(robot, obs).max() < 1e-12


# -- the fit's blocking warnings -----------------------------------------------------------------------------------


def test_points_10_mm_off_at_random_are_a_poor_fit():
    q = random_poses(40)
    noisy = measure(q) + np.random.default_rng(1).normal(0.0, 0.010, (40, 3, 3))
    r = fit(Observations(q, noisy, TARGETS), UR10.model, "local-poe")
    assert "poor-fit" in codes(r)
    assert "above 5 mm" in next(w["message"] for w in r.warnings if w["code"] == "poor-fit")


def test_a_calibration_a_fraction_of_a_mm_worse_than_the_nominal_is_worse_than_nominal():
    # A perfect robot seen by a noisy tracker: no parameter helps, the fit can only add noise.
    q = random_poses(30)
    perfect = ErrorSpec.paper(length_std=0, angle_std=0, joint_offset_std=0, axis_std=0, tracker_noise=0.3e-3)
    r = fit(Observations(q, measure(q, perfect), TARGETS), UR10.model, "local-poe")
    assert r.cv["mean"]["local-poe"] - r.cv["mean"]["nominal"] < 1e-4  # less than 0.1 mm worse …
    assert "worse-than-nominal" in codes(r)  # … and still refused


def test_rows_scattered_by_3_mm_without_a_step_are_not_a_frame_jump():
    # Each row's targets shifted together (a wobbling stand, not a moved one): the block means differ by more than
    # FRAME_JUMP somewhere, but by less than the scatter within the blocks, which is no step in time.
    q = random_poses(80)
    noisy = measure(q) + np.random.default_rng(4).normal(0.0, 3e-3, (80, 1, 3))
    r = fit(Observations(q, noisy, TARGETS), UR10.model, "local-poe")
    assert "frame-jump" not in codes(r), r.warnings


def test_a_step_of_4_mm_is_a_frame_jump():
    q = random_poses(80)
    points = measure(q)
    points[50:] += np.array([0.004, -0.002, 0.001])
    r = fit(Observations(q, points, TARGETS), UR10.model, "local-poe")
    assert "frame-jump" in codes(r)


@pytest.fixture(scope="module")
def narrow_fit():
    q = random_poses(60)
    q[:, 5] = 0.3 + np.random.default_rng(0).uniform(-0.015, 0.015, len(q))  # joint 6 moved over 1.7°
    return q, fit(Observations(q, measure(q), TARGETS), UR10.model, "local-poe")


def test_a_joint_moved_over_2_degrees_is_narrow(narrow_fit):
    q, r = narrow_fit
    # The fitted compensator's validity region keeps joint 6 on its sliver (it refuses the rest), so it claims no
    # wider range and is not warned about; the same calibration claiming the joint's whole range is.
    assert "narrow-joint" not in codes(r)
    with pytest.raises(ValueError):
        r.robot.check_range(np.concatenate([q[0, :5], [1.0]]))
    message = fit_module._narrow_joints(dataclasses.replace(r.robot, validity=None), q)
    assert message is not None and "joint 6 moved over 1.71°" in message


def test_a_narrow_joint_whose_claimed_range_is_its_data_is_not_extrapolated(narrow_fit):
    q, r = narrow_fit
    data_ranges = np.stack([q.min(axis=0), q.max(axis=0)], axis=1)
    claims_only_its_data = dataclasses.replace(r.robot, joint_ranges=data_ranges)
    assert fit_module._narrow_joints(claims_only_its_data, q) is None


def test_a_single_direction_left_unidentified_is_rank_deficient():
    # Four poses seeing three targets and one seeing two (the rotation about their line unseen): 4·6 + 5 = 29 of the
    # 30 identifiable parameters.
    q = random_poses(5)
    points = measure(q)
    points[-1, 2] = np.nan
    r = fit(Observations(q, points, TARGETS), UR10.model, "local-poe")
    assert "rank-deficient" in codes(r)
    assert "rank 29 of 30" in next(w["message"] for w in r.warnings if w["code"] == "rank-deficient")


def test_held_out_rows_worse_after_calibration_are_a_warning_when_nothing_cross_validates():
    # Two sessions (groups) are too few to cross-validate: the held-out test rows are the only check left.
    q = random_poses(40)
    perfect = ErrorSpec.paper(length_std=0, angle_std=0, joint_offset_std=0, axis_std=0, tracker_noise=0.3e-3)
    split = np.array(["train"] * 30 + ["test"] * 10)
    group = np.array(["a"] * 20 + ["b"] * 20)
    r = fit(Observations(q, measure(q, perfect), TARGETS, split=split, group=group), UR10.model, "local-poe")
    assert r.cv is None
    (w,) = [w for w in r.warnings if w["code"] == "worse-than-nominal"]
    assert w["message"].startswith("on the held-out 'test' rows the mean position error")


def test_large_corrections_at_a_third_of_the_configurations_are_a_warning():
    # The rule, apart from any fit: a compensator that moves joint 2 by 0.2 rad wherever joint 1 is above 0.35 rad
    # (about a third of the data's range [-1, 1]) corrects far too much there. A unit slip or a wrong model exceeds
    # nearly everywhere; a tenth of the checked configurations is already too many.
    q = np.random.default_rng(0).uniform(-1.0, 1.0, size=(40, 6))

    def correct(q, extrapolate=True, damped_iterations=None):
        return q + np.where(q[:, :1] > 0.35, [[0.0, 0.2, 0, 0, 0, 0]], 0.0)

    model = SimpleNamespace(joint_types=UR10.model.joint_types, frames=UR10.model.frames)
    robot = SimpleNamespace(network=None, validity=None, nominal=UR10.model, correct=correct, model=model)
    message = fit_module._large_correction(robot, q, seed=0)
    assert message is not None and "move joint 2 by 0.2 rad" in message
    assert "32% of 296 checked configurations" in message
