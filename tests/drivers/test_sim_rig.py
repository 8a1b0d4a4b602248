"""The simulated rig: ports, true target positions, noise and averaging, seeding, limits, and every injected fault."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.drivers.base import (
    DriverError,
    DriverTimeout,
    MeasurementRejected,
    MotionRejected,
    ProtectiveStop,
    ProtocolError,
    Robot,
    Tracker,
)
from labcal.drivers.sim import SimFaults, SimRig
from labcal.kinematics.se3 import pose
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.1, 0.0, 0.03], [-0.05, 0.08, 0.03], [-0.05, -0.08, 0.03]])
Q = np.array([0.3, -1.2, 1.4, -0.5, 1.1, 0.2])


@pytest.fixture(scope="module")
def spec():
    return load("ur10")


def rig_for(spec, errors=None, **kwargs) -> SimRig:
    return SimRig(simulate(spec, errors or ErrorSpec.default(), seed=5), TARGETS, seed=kwargs.pop("seed", 1), **kwargs)


def test_robot_and_tracker_implement_the_ports(spec):
    rig = rig_for(spec)
    with rig.robot() as robot, rig.tracker() as tracker:
        assert isinstance(robot, Robot) and isinstance(tracker, Tracker)
        assert robot.n_joints == 6
        np.testing.assert_array_equal(robot.limits.joint_limits, spec.model.limits)


def test_perfect_robot_reports_the_nominal_target_positions(spec):
    rig = rig_for(spec, ErrorSpec.none())
    with rig.robot() as robot, rig.tracker() as tracker:
        robot.move_joints(Q, speed=0.5, acceleration=1.0)
        np.testing.assert_array_equal(robot.joint_positions(), Q)
        m = tracker.measure(samples=4)
    np.testing.assert_allclose(m.points, spec.model.target_points(Q, TARGETS)[0], atol=1e-12)
    assert m.samples == 4 and np.all(m.spread == 0)


def test_tracker_sees_the_actual_robot_in_its_own_frame(spec):
    T_tb = pose([1.0, -0.5, 0.2], [0.1, -0.2, 0.3])
    actual = simulate(spec, ErrorSpec.default(tracker_noise=0.0, T_tracker_base=T_tb), seed=2)
    rig = SimRig(actual, TARGETS, seed=0)
    with rig.robot() as robot, rig.tracker() as tracker:
        robot.move_joints(Q, speed=0.5, acceleration=1.0)
        m = tracker.measure()
    true_base = actual.true_points(Q, TARGETS)[0]
    np.testing.assert_allclose(m.points, true_base @ T_tb[:3, :3].T + T_tb[:3, 3], atol=1e-12)
    # The actual robot is not the nominal one: errors of a fraction of a millimetre or more.
    assert np.max(np.linalg.norm(true_base - spec.model.target_points(Q, TARGETS)[0], axis=1)) > 1e-4


def test_averaging_reduces_noise_and_reports_the_spread(spec):
    noise = 0.05e-3
    rig = rig_for(spec, ErrorSpec.default(tracker_noise=noise))
    with rig.robot() as robot, rig.tracker() as tracker:
        robot.move_joints(Q, 0.5, 1.0)
        truth = rig.true_points()
        singles = np.array([tracker.measure(1).points for _ in range(200)])
        averaged = np.array([tracker.measure(25).points for _ in range(200)])
        spread = tracker.measure(400).spread
    err1 = np.std(singles - truth)
    err25 = np.std(averaged - truth)
    assert err1 == pytest.approx(noise, rel=0.15)
    assert err25 == pytest.approx(noise / 5, rel=0.2)
    # RMS 3-D distance of a sample from the mean: √3 σ per target.
    np.testing.assert_allclose(spread, np.sqrt(3) * noise, rtol=0.15)


def test_same_seed_same_measurements_other_seed_other_noise(spec):
    def readings(seed):
        rig = rig_for(spec, seed=seed)
        with rig.robot() as robot, rig.tracker() as tracker:
            out = []
            for q in (Q, Q * 0.5):
                robot.move_joints(q, 0.5, 1.0)
                out.append(tracker.measure(3).points)
        return np.array(out)

    np.testing.assert_array_equal(readings(1), readings(1))
    assert not np.allclose(readings(1), readings(2), atol=1e-9, rtol=0)


def test_repeatability_is_drawn_per_motion_not_per_frame(spec):
    rig = rig_for(spec, ErrorSpec.default(tracker_noise=0.0, repeatability=2e-5))
    with rig.robot() as robot, rig.tracker() as tracker:
        robot.move_joints(Q, 0.5, 1.0)
        a, b = tracker.measure().points, tracker.measure().points
        robot.move_joints(Q * 0, 0.5, 1.0)
        robot.move_joints(Q, 0.5, 1.0)
        c = tracker.measure().points
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c, atol=1e-9, rtol=0)


def test_limits_and_caps_are_checked_before_moving(spec):
    rig = rig_for(spec)
    with rig.robot() as robot:
        bad = Q.copy()
        bad[0] = 7.0
        with pytest.raises(MotionRejected, match="joint 1"):
            robot.move_joints(bad, 0.5, 1.0)
        with pytest.raises(MotionRejected, match="speed"):
            robot.move_joints(Q, 5.0, 1.0)
        with pytest.raises(MotionRejected, match="acceleration"):
            robot.move_joints(Q, 0.5, 50.0)
        assert rig.moves == 0 and np.all(robot.joint_positions() == 0)


def test_realistic_motion_time_follows_a_trapezoidal_profile(spec):
    rig = rig_for(spec, motion_time="realistic")
    far, near = np.zeros(6), np.zeros(6)
    far[2], near[2] = 1.0, 0.04
    # 1 rad at 0.5 rad/s, 1 rad/s²: 0.5 s accelerating, 0.5 s braking, 1.5 s cruising.
    assert rig._move_duration(far, 0.5, 1.0) == pytest.approx(2.5)
    # 0.04 rad never reaches full speed: 2·√(d/a).
    assert rig._move_duration(near, 0.5, 1.0) == pytest.approx(0.4)
    assert rig_for(spec, motion_time=0.3)._move_duration(far, 0.5, 1.0) == 0.3
    with pytest.raises(ValueError, match="motion_time"):
        rig_for(spec, motion_time="slow")


def test_closed_drivers_refuse_work_but_stop_is_always_safe(spec):
    rig = rig_for(spec)
    robot, tracker = rig.robot(), rig.tracker()
    robot.close()
    robot.close()
    tracker.close()
    robot.stop()
    with pytest.raises(DriverError):
        robot.move_joints(Q, 0.5, 1.0)
    with pytest.raises(DriverError):
        tracker.measure()


# ------------------------------------------------------------------------------------------------------------
# Faults


def measure_outcomes(rig, calls: int) -> list[str]:
    out = []
    with rig.tracker() as tracker:
        for _ in range(calls):
            try:
                m = tracker.measure(2)
            except (DriverTimeout, ProtocolError, MeasurementRejected) as e:
                out.append(type(e).__name__)
            else:
                out.append("nan" if not np.all(np.isfinite(m.points)) else "ok")
    return out


def test_dropout_at_a_call_returns_nan_for_one_target(spec):
    rig = rig_for(spec, faults=SimFaults(dropout_at={2}, dropout_target=1))
    with rig.tracker() as tracker:
        assert np.all(np.isfinite(tracker.measure().points))
        m = tracker.measure(3)
    assert np.all(np.isnan(m.points[1])) and np.all(np.isfinite(m.points[[0, 2]]))
    assert m.quality == ("missing:t2",)
    assert measure_outcomes(rig_for(spec, faults=SimFaults(dropout_at={2, 4})), 5) == ["ok", "nan", "ok", "nan", "ok"]


def test_dropout_in_reject_mode_raises_measurement_rejected(spec):
    rig = rig_for(spec, faults=SimFaults(dropout_at={1}, dropout_mode="reject", dropout_target=2))
    with rig.tracker() as tracker, pytest.raises(MeasurementRejected, match="t3"):
        tracker.measure()


def test_timeout_and_garbled_reply_at_given_calls(spec):
    faults = SimFaults(timeout_at={2}, garbled_at={3})
    assert measure_outcomes(rig_for(spec, faults=faults), 4) == ["ok", "DriverTimeout", "ProtocolError", "ok"]


@pytest.mark.parametrize("kind", ["dropout", "timeout", "garbled"])
def test_fault_probabilities(spec, kind):
    expected = {"dropout": "nan", "timeout": "DriverTimeout", "garbled": "ProtocolError"}[kind]
    always = measure_outcomes(rig_for(spec, faults=SimFaults(**{f"{kind}_probability": 1.0})), 20)
    never = measure_outcomes(rig_for(spec, faults=SimFaults(**{f"{kind}_probability": 0.0})), 20)
    some = measure_outcomes(rig_for(spec, faults=SimFaults(**{f"{kind}_probability": 0.3})), 300)
    assert set(always) == {expected} and set(never) == {"ok"}
    assert 0.2 < some.count(expected) / 300 < 0.4
    assert set(some) == {"ok", expected}
    # Seeded: the same rig makes the same faults.
    assert some == measure_outcomes(rig_for(spec, faults=SimFaults(**{f"{kind}_probability": 0.3})), 300)


def test_faults_do_not_change_the_noise_of_other_frames(spec):
    plain = rig_for(spec)
    faulty = rig_for(spec, faults=SimFaults(timeout_at={2}))
    with plain.tracker() as a, faulty.tracker() as b:
        a.measure(), b.measure()
        with pytest.raises(DriverTimeout):
            b.measure()
        np.testing.assert_array_equal(a.measure(3).points, b.measure(3).points)


def test_protective_stop_at_move_k_until_cleared(spec):
    rig = rig_for(spec, faults=SimFaults(protective_stop_at={2}))
    with rig.robot() as robot:
        robot.move_joints(Q, 0.5, 1.0)
        assert not robot.state().protective_stop
        with pytest.raises(ProtectiveStop, match="move 2"):
            robot.move_joints(np.zeros(6), 0.5, 1.0)
        assert robot.state().protective_stop
        # Stopped on the way: neither at the start nor at the goal.
        q = robot.joint_positions()
        assert not np.allclose(q, Q) and not np.allclose(q, 0)
        with pytest.raises(ProtectiveStop, match="clear"):
            robot.move_joints(np.zeros(6), 0.5, 1.0)
        robot.clear_protective_stop()
        assert not robot.state().protective_stop
        robot.move_joints(np.zeros(6), 0.5, 1.0)
        np.testing.assert_array_equal(robot.joint_positions(), np.zeros(6))


@pytest.mark.parametrize(
    ("faults", "message"),
    [
        (dict(dropout_at={0}), "counts calls from 1"),
        (dict(timeout_probability=1.5), "timeout_probability"),
        (dict(dropout_mode="vanish"), "dropout_mode"),
        (dict(dropout_target=-1), "dropout_target"),
    ],
)
def test_bad_fault_settings_are_named(faults, message):
    with pytest.raises(ValueError, match=message):
        SimFaults(**faults)


def test_a_dropout_target_the_rig_does_not_have_is_named(spec):
    with pytest.raises(ValueError, match="dropout_target 3 is not one of the 3 targets"):
        rig_for(spec, faults=SimFaults(dropout_target=3))


# -- any number of targets, per-target drop-out ---------------------------------------------------------------


def test_any_number_of_targets_are_measured_where_the_actual_robot_puts_them(spec):
    for targets in (TARGETS[:1], TARGETS[:2], np.vstack([TARGETS, [[0.0, 0.0, 0.12]]])):
        rig = SimRig(simulate(spec, ErrorSpec.none()), targets, seed=0)
        with rig.robot() as robot, rig.tracker() as tracker:
            robot.move_joints(Q, speed=0.5, acceleration=1.0)
            m = tracker.measure(samples=2)
        assert m.points.shape == (len(targets), 3) and m.spread.shape == (len(targets),)
        np.testing.assert_allclose(m.points, spec.model.target_points(Q, targets)[0], atol=1e-12)


def test_three_targets_without_dropout_measure_exactly_as_before_the_dropout_stream(spec):
    # The drop-out stream is separate: a rig with dropout 0 draws the same noise as one that never heard of it, and
    # switching drop-out on changes only which rows are NaN, not the noise of the rows that are seen.
    plain, lossy = rig_for(spec), rig_for(spec, dropout=0.4)
    with plain.tracker() as a, lossy.tracker() as b:
        for _ in range(12):
            ma, mb = a.measure(2), b.measure(2)
            np.testing.assert_array_equal(mb.points[mb.seen], ma.points[mb.seen])


def test_per_target_dropout_is_seeded_and_follows_each_probability(spec):
    def seen_matrix(seed):
        rig = rig_for(spec, seed=seed, dropout=[0.0, 0.5, 1.0])
        rows = []
        with rig.tracker() as tracker:
            for _ in range(200):
                m = tracker.measure()
                rows.append(m.seen)
                assert m.quality == tuple(f"missing:t{i + 1}" for i in np.flatnonzero(~m.seen))
                assert np.all(np.isnan(m.spread[~m.seen])) and np.all(np.isfinite(m.points[m.seen]))
        return np.array(rows)

    seen = seen_matrix(7)
    assert seen[:, 0].all() and not seen[:, 2].any()
    assert 0.35 < seen[:, 1].mean() < 0.65  # 200 fair coins: outside this band once in ~20,000 runs
    np.testing.assert_array_equal(seen_matrix(7), seen)
    assert not np.array_equal(seen_matrix(8), seen)


def test_a_measurement_that_sees_no_target_is_rejected(spec):
    rig = SimRig(simulate(spec, ErrorSpec.none()), TARGETS[:1], seed=0, dropout=1.0)
    with rig.tracker() as tracker, pytest.raises(MeasurementRejected, match="none of the 1 target"):
        tracker.measure()


@pytest.mark.parametrize(
    "dropout, message",
    [(1.5, "probability in"), ([0.1, 0.2], "3 of them"), (-0.1, "probability in")],
)
def test_bad_dropout_is_named(spec, dropout, message):
    with pytest.raises(ValueError, match=message):
        rig_for(spec, dropout=dropout)


@pytest.mark.parametrize("targets", [np.zeros((0, 3)), np.zeros((2, 2)), [[0.0, np.nan, 0.0]]])
def test_bad_targets_are_named(spec, targets):
    with pytest.raises(ValueError, match=r"finite \(m, 3\)"):
        SimRig(simulate(spec, ErrorSpec.none()), targets, seed=0)
