"""The runner's checks around one pose and one run, each shown to matter (surviving mutations of
benchmarks/mutation.py): a single joint off its command, a protective stop during the measurement, what counts as a
silent tracker, a plan for another arm, the sanity check of a short session; and the planner's range_fraction."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labcal.datasets import SessionStore, read_journal
from labcal.drivers.sim import SimFaults, SimRig
from labcal.robots import load
from labcal.sessions import SessionError, make_plan, random_configurations, run
from labcal.sessions.planning import PlanningError, joint_ranges
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03]])


@pytest.fixture(scope="module")
def spec():
    return load("ur10")


@pytest.fixture
def store(tmp_path):
    return SessionStore(tmp_path / "store")


def rig_for(spec, **faults) -> SimRig:
    return SimRig(simulate(spec, ErrorSpec.default(), seed=3), TARGETS, seed=3, faults=SimFaults(**faults))


def plan_of(spec, n: int):
    return make_plan(random_configurations(spec.model, n, seed=1, targets=TARGETS), samples=1, settle=0.0)


class Wrapped:
    """A sim robot with one behaviour replaced (the rest passes through)."""

    def __init__(self, robot):
        self._robot = robot
        self.n_joints, self.limits = robot.n_joints, robot.limits

    def __getattr__(self, name):
        return getattr(self._robot, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._robot.close()


class OneJointOff(Wrapped):
    """Reads joint 3 back 10 mrad off the command, every other joint exactly (a joint that did not get there)."""

    def joint_positions(self):
        q = np.array(self._robot.joint_positions(), dtype=float)
        q[2] += 0.01
        return q


def test_one_joint_off_its_command_rejects_the_pose(spec, store):
    rig = rig_for(spec)
    with OneJointOff(rig.robot()) as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 2), robot, tracker, frame="base")
    assert summary.valid == 0 and summary.rejected == 2
    first = read_journal(store.session_dir(summary.session_id) / "journal.jsonl").measurements[0]
    assert "robot is 0.010000 rad from the commanded joints" in first.reason


class StopsWhileMeasuring(Wrapped):
    """Enters a protective stop while the tracker measures pose ``at`` (0-based)."""

    def __init__(self, robot, tracker, at: int):
        super().__init__(robot)
        self.stopped = False
        measure = tracker.measure
        calls = iter(range(1000))

        def measuring(samples):
            m = measure(samples)
            if next(calls) == at:
                self.stopped = True
            return m

        tracker.measure = measuring

    def state(self):
        s = self._robot.state()
        return dataclasses.replace(s, protective_stop=True) if self.stopped else s


def test_a_protective_stop_during_the_measurement_pauses_and_keeps_no_frame(spec, store):
    rig = rig_for(spec)
    with rig.robot() as inner, rig.tracker() as tracker:
        robot = StopsWhileMeasuring(inner, tracker, at=1)
        summary = run(store, spec, TARGETS, plan_of(spec, 3), robot, tracker, frame="base")
    assert summary.exit_status == "paused" and "while measuring" in summary.reason
    assert summary.valid == 1 and summary.rejected == 0  # the frame of pose 1 is not in the journal


def test_a_pose_with_one_timeout_among_other_failures_is_not_silent(spec, store):
    # Three attempts per pose: a timeout, then two garbled replies. The tracker answers, badly: not "silent", so the
    # run must not stop as if its cable were out.
    per_pose = [(1 + 3 * p, 2 + 3 * p, 3 + 3 * p) for p in range(3)]
    rig = rig_for(spec, timeout_at={t for t, _, _ in per_pose}, garbled_at={g for _, *gs in per_pose for g in gs})
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 4), robot, tracker, frame="base")
    assert summary.exit_status == "success", summary.reason
    assert (summary.valid, summary.rejected) == (1, 3)


def test_a_plan_for_another_joint_count_is_refused_before_anything(spec, store):
    rig = rig_for(spec)
    five = make_plan(np.zeros((2, 5)), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker, pytest.raises(SessionError, match="the plan 5"):
        run(store, spec, TARGETS, five, robot, tracker, frame="base")
    assert rig.moves == 0 and store.session_ids() == []


def test_a_short_session_of_the_wrong_robot_fails_its_sanity_check_at_the_end(spec, store):
    # Four poses (fewer than 2 n = 12, so the check never ran during the run) of a UR10 recorded as a UR5e.
    ur5e = load("ur5e")
    rig = rig_for(spec)
    plan = make_plan(random_configurations(ur5e.model, 4, seed=1, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, ur5e, TARGETS, plan, robot, tracker, frame="base")
    assert summary.exit_status == "failed" and summary.valid == 4
    assert "sanity check failed on the first 4 valid poses, the run is over" in summary.reason


def test_range_fraction_above_one_is_refused(spec):
    assert np.allclose(joint_ranges(spec.model.limits, range_fraction=1.0), spec.model.limits)
    with pytest.raises(PlanningError, match=r"range_fraction must be in \(0, 1\]"):
        joint_ranges(spec.model.limits, range_fraction=2.0)
