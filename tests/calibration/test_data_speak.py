"""Issue 27: weak directions stay at the nominal, the validity region, the large-correction gate's cause."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

import scenarios
from data_speak import narrow
from labcal.calibration import Observations
from labcal.calibration.fit import _large_correction
from labcal.calibration.local_poe import fit_local_poe
from labcal.compensator import CalibratedRobot
from labcal.compensator import save as save_compensator
from labcal.compensator.io import from_payload, to_payload
from labcal.compensator.validity import ValidityRegion
from labcal.robots import load


@pytest.fixture(scope="module")
def narrow_data():
    return narrow(60, held_out=30)


def test_narrow_data_hold_weak_directions_at_the_nominal_and_name_them(narrow_data):
    obs, (qh, truth), model, _ = narrow_data
    held, info = fit_local_poe(obs, model)
    free, free_info = fit_local_poe(obs, model, error_bound=math.inf)
    assert free_info["weak"] == 0 and info["weak"] >= 1
    assert info["identified"] == info["rank"] - info["weak"] and len(info["weak_directions"]) == info["weak"]
    assert "tool frame" in " ".join(info["weak_directions"])  # the tool traded against the base translation
    # the free fit drifts far along them and corrects by a tenth of a radian in the data's joint box; the held one
    # corrects by a few hundredths at most. (Parameters are not compared: the tool split re-expresses the chain.)
    box = np.random.default_rng(3).uniform(obs.q.min(0), obs.q.max(0), (50, 6))
    free_dq = np.abs(free.correct(box, extrapolate=True) - box).max()
    assert free_dq > 0.05 > 0.02 > np.abs(held.correct(box, extrapolate=True) - box).max()
    from data_speak import point_error

    assert point_error(held, qh, truth) <= 1.01 * point_error(free, qh, truth)


def test_wide_data_have_no_weak_direction_and_the_rule_changes_nothing():
    scn = scenarios.good("ur10", 60, seed=1)
    obs = Observations(**scn.arrays())
    model = load("ur10").model
    a, info = fit_local_poe(obs, model)
    b, _ = fit_local_poe(obs, model, error_bound=math.inf)
    assert info["weak"] == 0 and info["identified"] == info["expected_rank"]
    assert np.array_equal(a.model.frames, b.model.frames)


def test_validity_region_refuses_configurations_away_from_the_data_unless_extrapolating():
    model = load("ur10").model
    q = np.random.default_rng(0).uniform(-0.3, 0.3, (40, 6)) + np.array([0, -1.2, 1.0, -1.4, -1.5, 0.2])
    region = ValidityRegion.from_configurations(q)
    robot = CalibratedRobot(nominal=model, model=model.perturbed(np.full((7, 6), 1e-4)), validity=region)
    robot.correct(q[3])  # a measured configuration: accepted
    far = q[3] + np.array([0.0, 0.0, 0.0, 1.5, 0.0, 0.0])  # inside the joint limits, far from every pose
    with pytest.raises(ValueError, match="validity radius"):
        robot.correct(far)
    with pytest.raises(ValueError, match="validity radius"):
        robot.check_range(far[None])
    robot.correct(far, extrapolate=True)
    assert region.inside(region.sample(100, np.random.default_rng(1))).all()


def test_the_validity_region_is_stored_bounded_checked_and_old_files_still_load(tmp_path):
    model = load("ur10").model
    q = np.random.default_rng(0).uniform(-1, 1, (700, 6))
    region = ValidityRegion.from_configurations(q)
    assert len(region.centres) <= 512 and region.inside(q).all()  # subsampled, every fitted pose still inside
    robot = CalibratedRobot(nominal=model, model=model.perturbed(np.full((7, 6), 1e-4)), validity=region)
    payload = json.loads(json.dumps(to_payload(robot)))
    loaded, _ = from_payload(payload)
    assert np.array_equal(loaded.validity.centres, region.centres) and loaded.validity.radius == region.radius
    edited = json.loads(json.dumps(payload))
    edited["validity"]["radius"] = 10.0
    with pytest.raises(ValueError, match="validity"):
        from_payload(edited)
    old = json.loads(json.dumps(to_payload(CalibratedRobot(nominal=model, model=robot.model))))
    assert "validity" not in old and from_payload(old)[0].validity is None
    from labcal.compensator.io import load as load_compensator

    for name in ("c.json", "c.npz"):
        stored = load_compensator(save_compensator(robot, tmp_path / name)).robot.validity
        assert np.array_equal(stored.centres, region.centres) and np.array_equal(stored.weights, region.weights)


def test_the_large_correction_gate_names_a_tool_mismatch_with_the_identified_tool():
    model = load("ur10").model
    dz = np.zeros((7, 6))
    dz[-1, :3] = [0.0, 0.0, 0.08]  # the measurement fixture 80 mm beyond the robot file's tool
    robot = CalibratedRobot(nominal=model, model=model.perturbed(dz))
    q = np.random.default_rng(0).uniform(-1, 1, (40, 6)) + np.array([0, -1.2, 1.0, -1.4, -1.5, 0.2])
    message = _large_correction(robot, q, 0)
    assert message and "tool mismatch" in message and "80 mm" in message


def test_the_large_correction_gate_names_a_unit_slip_when_the_data_themselves_need_it():
    model = load("ur10").model
    dz = np.zeros((7, 6))
    dz[1, 5] = 0.2  # joint 2's zero turned by 0.2 rad (a slipped offset: 11° read as … )
    robot = CalibratedRobot(nominal=model, model=model.perturbed(dz))
    q = np.random.default_rng(0).uniform(-1, 1, (40, 6)) + np.array([0, -1.2, 1.0, -1.4, -1.5, 0.2])
    message = _large_correction(robot, q, 0)
    assert message and "unit slip" in message and "tool mismatch" not in message


def test_single_reflector_corrections_in_the_validity_region_stay_below_a_tenth_of_a_radian():
    from labcal.calibration import fit

    scn = scenarios.with_targets(scenarios.good("ur10", 60, seed=0), [0])
    result = fit(Observations(**scn.arrays()), load("ur10").model, "local-poe")
    assert not result.warnings  # exports without --force
    robot = result.robot
    q = robot.validity.sample(300, np.random.default_rng(5))
    dq = np.abs(robot.correct(q) - q).max(axis=1)
    unbounded = np.abs(dataclasses.replace(robot, validity=None).correct(q, extrapolate=True) - q).max(axis=1)
    assert unbounded.max() > 0.1 >= dq.max() - 1e-12  # the ill-conditioned tail is there, and bounded
    assert np.median(dq) == pytest.approx(np.median(unbounded), rel=1e-6)  # the typical correction is unchanged


def test_the_large_correction_gate_names_a_weak_direction_when_the_rule_is_off():
    from labcal.calibration import fit
    from labcal.calibration.fit import _correction_cause

    obs, _, model, _ = narrow(60, spin=0.5)  # the tool axis fixed: its length trades against the base translation
    # Since the compensator corrects the flange, not the fixture, the free fit's corrections here stay under the
    # gate's bound (0.056 rad); the cause the gate would name for them is asked directly.
    free, free_info = fit_local_poe(obs, model, error_bound=math.inf)
    message = _correction_cause(free, 0.0, free_info)
    assert "weakly determined direction" in message and "unit slip" not in message
    held = fit(obs, model, "local-poe")
    assert not held.warnings  # exports without --force: joint 5's sliver is all the validity region claims
    assert any(note.startswith("weak: ") and "tool frame" in note for note in held.notes)
