"""The session runner on the sim rig: happy path, retries and rejections, protective stop → resume, Ctrl-C, kill -9."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from labcal.datasets import SessionStore, read_journal
from labcal.datasets.targets import pair_distances
from labcal.drivers.base import ConnectionFailed, Measurement
from labcal.drivers.sim import SimFaults, SimRig
from labcal.robots import load, loads
from labcal.sessions import (
    Plan,
    Progress,
    RetryPolicy,
    SessionError,
    Validation,
    check_measurement,
    make_plan,
    random_configurations,
    resume,
    run,
)
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03]])


@pytest.fixture(scope="module")
def spec():
    return load("ur10")


@pytest.fixture(scope="module")
def actual(spec):
    return simulate(spec, ErrorSpec.default(), seed=3)


@pytest.fixture
def store(tmp_path):
    return SessionStore(tmp_path / "store")


def plan_of(spec, n: int, seed: int = 1) -> Plan:
    return make_plan(random_configurations(spec.model, n, seed=seed), samples=3, settle=0.0)


def journal_docs(store: SessionStore, session_id: str) -> list[dict]:
    return read_journal(store.session_dir(session_id) / "journal.jsonl").documents


def measurements(store, session_id) -> list[dict]:
    return [d for d in journal_docs(store, session_id) if d["type"] == "measurement"]


class JournalCheckingRobot:
    """Wraps a robot; before every move, checks on disk that each earlier pose's document is already written."""

    def __init__(self, robot, store):
        self._robot, self._store = robot, store
        self.n_joints, self.limits = robot.n_joints, robot.limits
        self.moves = 0
        self.seen_on_disk: list[int] = []

    def move_joints(self, q, speed, acceleration):
        sessions = self._store.session_ids()
        on_disk = len(measurements(self._store, sessions[0])) if sessions else 0
        self.seen_on_disk.append(on_disk)
        self.moves += 1
        return self._robot.move_joints(q, speed, acceleration)

    def __getattr__(self, name):
        return getattr(self._robot, name)


# ------------------------------------------------------------------------------------------------------------


def test_happy_path_records_every_pose_durably_and_seals_a_version(spec, actual, store):
    plan = plan_of(spec, 8)
    rig = SimRig(actual, TARGETS, seed=1)
    events: list[Progress] = []
    with rig.robot() as sim_robot, rig.tracker() as tracker:
        robot = JournalCheckingRobot(sim_robot, store)
        summary = run(store, spec, TARGETS, plan, robot, tracker, progress=events.append)
    assert (summary.exit_status, summary.valid, summary.rejected, summary.remaining) == ("success", 8, 0, 0)
    # Every document was on disk before the robot moved on (read back from the file, not from memory).
    assert robot.seen_on_disk == list(range(8))

    docs = measurements(store, summary.session_id)
    assert [d["pose_index"] for d in docs] == list(range(8))
    assert [d["seq"] for d in docs] == list(range(1, 9))
    assert all(d["status"] == "valid" and d["samples"] == 3 for d in docs)
    np.testing.assert_allclose([d["q_commanded"] for d in docs], plan.configurations)

    ds = store.load(summary.ref)
    assert summary.ref.endswith("@v001") and len(ds) == 8
    np.testing.assert_array_equal(ds.pose, [d["pose_index"] for d in docs])
    np.testing.assert_array_equal(ds.q, [d["q_actual"] for d in docs])
    np.testing.assert_array_equal(ds.points, [d["points"] for d in docs])
    np.testing.assert_array_equal(ds.spread, [d["spread"] for d in docs])

    stop = journal_docs(store, summary.session_id)[-1]
    assert stop["type"] == "stop" and stop["exit_status"] == "success"
    assert [e.status for e in events if e.pose is not None and e.status in ("valid", "rejected")] == ["valid"] * 8
    assert [e.done for e in events if e.status == "valid"] == list(range(1, 9))
    assert events[-1].status == "success" and events[-1].done == 8 == events[-1].total


def test_start_document_records_provenance(spec, actual, store):
    plan = plan_of(spec, 2)
    rig = SimRig(actual, TARGETS, seed=1)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, validation=Validation(absolute_tolerance=1e-3))
    start = journal_docs(store, summary.session_id)[0]
    # The robot file itself is stored (self-contained sessions): the record reads back to the same model.
    assert start["robot"] == spec.record() and start["robot"]["text"]
    assert loads(start["robot"]["text"], start["robot"]["format"]).hash == spec.hash
    np.testing.assert_array_equal(start["targets"], TARGETS)
    assert Plan.from_pose_documents(start["plan"]) == plan
    assert start["tracker"]["driver"] == "sim" and start["robot_driver"]["driver"] == "sim"
    assert start["robot_driver"]["class"].endswith("SimRobot")
    assert start["metadata"]["runner"]["validation"]["absolute_tolerance"] == 1e-3
    assert {"labcal", "numpy", "python"} <= set(start["software"])


def test_dropouts_and_timeouts_are_retried_then_rejected_with_reasons(spec, actual, store):
    # Tracker calls: pose 0 → 1; pose 1 → 2 (dropout) + 3; pose 2 → 4, 5, 6 (timeouts): rejected; pose 3 → 7.
    faults = SimFaults(dropout_at={2}, timeout_at={4, 5, 6})
    rig = SimRig(actual, TARGETS, seed=1, faults=faults)
    events: list[Progress] = []
    every_target = Validation(min_targets=3)  # a pose with a lost target is measured again
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 4), robot, tracker, progress=events.append,
                      validation=every_target)  # fmt: skip
    docs = measurements(store, summary.session_id)
    assert [(d["pose_index"], d["status"], d["extra"]["attempts"]) for d in docs] == [
        (0, "valid", 1),
        (1, "valid", 2),
        (2, "rejected", 3),
        (3, "valid", 1),
    ]
    reason = docs[2]["reason"]
    assert reason.count("DriverTimeout") == 3 and "attempt 3" in reason
    assert docs[2]["points"] is None
    assert rig.measurements == 7 and rig.moves == 4  # retries re-measure without moving by default
    assert (summary.exit_status, summary.valid, summary.rejected) == ("success", 3, 1)
    assert len(store.load(summary.ref)) == 3
    assert [e.pose for e in events if e.status == "retry"] == [1, 2, 2]


def test_missing_target_every_time_is_rejected_and_remove_moves_again(spec, actual, store):
    faults = SimFaults(dropout_at={1, 2}, garbled_at={3})
    rig = SimRig(actual, TARGETS, seed=1, faults=faults)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 2), robot, tracker, retry=RetryPolicy(3, remove=True),
                      validation=Validation(min_targets=3))  # fmt: skip
    docs = measurements(store, summary.session_id)
    assert docs[0]["status"] == "rejected"
    assert docs[0]["reason"].count("missing target") == 2 and "ProtocolError" in docs[0]["reason"]
    assert docs[0]["q_actual"] is not None
    assert docs[1]["status"] == "valid"
    assert rig.moves == 3 + 1


def test_rejected_dropouts_in_reject_mode_name_the_target(spec, actual, store):
    rig = SimRig(actual, TARGETS, seed=1, faults=SimFaults(dropout_at={1}, dropout_mode="reject", dropout_target=0))
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 1), robot, tracker, retry=RetryPolicy(1))
    (doc,) = measurements(store, summary.session_id)
    assert doc["status"] == "rejected" and "t1 not visible" in doc["reason"]
    assert summary.ref is None  # nothing valid: no version


def test_triangle_check_uses_the_tolerance_plus_the_spread():
    nominal = TARGETS
    stretched = TARGETS * np.array([1.01, 1.0, 1.0])  # t1–t2 side grows by ~0.9 mm
    error = np.max(np.abs(pair_distances(stretched) - pair_distances(nominal)))
    quiet = Measurement(stretched, 0.0, spread=np.zeros(3))
    noisy = Measurement(stretched, 0.0, spread=np.full(3, error / 5))
    why, residual = check_measurement(quiet, nominal, Validation(absolute_tolerance=0.5e-3))
    assert "triangle" in why and residual == pytest.approx(error)
    assert check_measurement(noisy, nominal, Validation(absolute_tolerance=0.5e-3, spread_factor=5.0))[0] == ""
    lost = Measurement(np.where(np.arange(3)[:, None] == 2, np.nan, TARGETS), 0.0)
    assert check_measurement(lost, nominal, Validation(min_targets=3))[0] == "missing target(s) t3 (2 seen, 3 needed)"
    # By default a pose with a target lost is valid: the distance t1–t2 is checked, the two involving t3 are not.
    assert check_measurement(lost, nominal, Validation()) == ("", pytest.approx(0.0, abs=1e-15))


def test_a_plan_pose_outside_the_limits_is_rejected_without_retries(spec, actual, store):
    q = random_configurations(spec.model, 2, seed=1)
    q[0, 0] = 9.0  # beyond the ±2π limit
    rig = SimRig(actual, TARGETS, seed=1)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, make_plan(q, samples=1, settle=0.0), robot, tracker)
    docs = measurements(store, summary.session_id)
    assert docs[0]["status"] == "rejected" and docs[0]["reason"].startswith("attempt 1: motion rejected: joint 1")
    assert docs[0]["extra"]["attempts"] == 1 and rig.measurements == 1
    assert summary.valid == 1


def test_protective_stop_pauses_then_resume_completes_without_duplicates(spec, actual, store):
    plan = plan_of(spec, 6)
    rig = SimRig(actual, TARGETS, seed=1, faults=SimFaults(protective_stop_at={4}))
    with rig.robot() as robot, rig.tracker() as tracker:
        first = run(store, spec, TARGETS, plan, robot, tracker)
        assert (first.exit_status, first.valid, first.remaining, first.ref) == ("paused", 3, 3, None)
        assert rig.stop_calls == 1
        tail = [d["type"] for d in journal_docs(store, first.session_id)[-2:]]
        assert tail == ["pause", "stop"] and journal_docs(store, first.session_id)[-1]["exit_status"] == "paused"

        with pytest.raises(SessionError, match="still in a protective stop"):
            resume(store, first.session_id, robot, tracker)
        robot.clear_protective_stop()
        second = resume(store, first.session_id, robot, tracker, spec=spec)
    assert (second.exit_status, second.valid, second.remaining, second.measured) == ("success", 6, 0, 3)
    docs = measurements(store, first.session_id)
    assert sorted(d["pose_index"] for d in docs) == list(range(6))
    ds = store.load(second.ref)
    assert len(ds) == 6 and sorted(ds.pose.tolist()) == list(range(6))
    types = [d["type"] for d in journal_docs(store, first.session_id)]
    assert types.count("resume") == 1 and types[-1] == "stop"


class InterruptingTracker:
    """A tracker whose k-th measure raises KeyboardInterrupt (the operator pressing Ctrl-C)."""

    def __init__(self, tracker, at: int):
        self._tracker, self._at, self.calls = tracker, at, 0

    def measure(self, samples=1):
        self.calls += 1
        if self.calls == self._at:
            raise KeyboardInterrupt
        return self._tracker.measure(samples)

    def close(self):
        self._tracker.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def test_ctrl_c_stops_the_robot_and_closes_the_session_as_aborted(spec, actual, store):
    plan = plan_of(spec, 5)
    rig = SimRig(actual, TARGETS, seed=1)
    with rig.robot() as robot, rig.tracker() as sim_tracker:
        summary = run(store, spec, TARGETS, plan, robot, InterruptingTracker(sim_tracker, at=3))
        assert summary.exit_status == "aborted" and "Ctrl-C" in summary.reason
        assert summary.reason.endswith("with 2 of 5 poses recorded valid")  # what is recorded, not a plan index
        assert rig.stop_calls == 1
        stop = journal_docs(store, summary.session_id)[-1]
        assert stop["type"] == "stop" and stop["exit_status"] == "aborted"
        assert [d["pose_index"] for d in measurements(store, summary.session_id)] == [0, 1]
        assert summary.ref.endswith("@v001") and len(store.load(summary.ref)) == 2

        again = resume(store, summary.session_id, robot, sim_tracker)
    assert again.exit_status == "success" and again.measured == 3
    assert [d["pose_index"] for d in measurements(store, summary.session_id)] == [0, 1, 2, 3, 4]
    ds = store.load(again.ref)
    assert again.ref.endswith("@v002") and ds.manifest["parent"] == "v001" and len(ds) == 5


def test_a_lost_connection_fails_the_run_resumably(spec, actual, store):
    rig = SimRig(actual, TARGETS, seed=1)

    class Unplugged:
        def __init__(self, robot):
            self._robot, self.n_joints, self.limits = robot, robot.n_joints, robot.limits

        def move_joints(self, q, speed, acceleration):
            if rig.moves == 2:
                raise ConnectionFailed("cable pulled")
            self._robot.move_joints(q, speed, acceleration)

        def __getattr__(self, name):
            return getattr(self._robot, name)

    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 4), Unplugged(robot), tracker)
        assert summary.exit_status == "failed" and "cable pulled" in summary.reason
        assert journal_docs(store, summary.session_id)[-1]["exit_status"] == "failed"
        assert rig.stop_calls == 1
        done = resume(store, summary.session_id, robot, tracker)
    assert done.exit_status == "success" and done.valid == 4


def test_resume_refuses_another_robot_model(spec, actual, store):
    rig = SimRig(actual, TARGETS, seed=1, faults=SimFaults(protective_stop_at={1}))
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 2), robot, tracker)
        robot.clear_protective_stop()
        with pytest.raises(SessionError, match="recorded with robot model 'ur10'"):
            resume(store, summary.session_id, robot, tracker, spec=load("ur10e"))


def test_resume_of_a_finished_session_measures_nothing(spec, actual, store):
    rig = SimRig(actual, TARGETS, seed=1)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan_of(spec, 2), robot, tracker)
        again = resume(store, summary.session_id, robot, tracker)
    assert again.measured == 0 and again.ref == summary.ref and rig.moves == 2


KILLED_RUN = textwrap.dedent(
    """
    import sys
    import numpy as np
    from labcal.datasets import SessionStore
    from labcal.drivers.sim import SimRig
    from labcal.robots import load, loads
    from labcal.sessions import make_plan, random_configurations, run
    from labcal.simulation import ErrorSpec, simulate

    spec = load("ur10")
    targets = np.array(sys.argv[3:12], dtype=float).reshape(3, 3)
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=3), targets, seed=1, motion_time=0.05)
    plan = make_plan(random_configurations(spec.model, 40, seed=1), samples=3, settle=0.0)
    run(SessionStore(sys.argv[1]), spec, targets, plan, rig.robot(), rig.tracker(), session_id=sys.argv[2])
    """
)


def test_kill_9_loses_nothing_and_resume_measures_nothing_twice(spec, actual, store):
    session_id = "killed-session"
    journal = Path(store.root) / session_id / "journal.jsonl"
    args = [sys.executable, "-c", KILLED_RUN, str(store.root), session_id, *map(str, TARGETS.ravel())]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            if journal.exists() and len(read_journal(journal).measurements) >= 4:
                break
            time.sleep(0.01)
        assert proc.poll() is None, f"the run ended before it could be killed: {proc.stderr.read().decode()}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    before = read_journal(journal).measurements
    assert 4 <= len(before) < 40

    rig = SimRig(actual, TARGETS, seed=2)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = resume(store, session_id, robot, tracker, spec=spec)
    assert summary.exit_status == "success" and summary.measured == 40 - len(before)
    assert rig.moves == 40 - len(before)  # no pose recorded before the kill was visited again
    after = read_journal(journal)
    poses = [d.pose_index for d in after.measurements]
    assert sorted(poses) == list(range(40))  # exact count, no duplicates
    kept = {d.uid: d for d in after.measurements}
    assert all(kept[d.uid] == d for d in before)  # every fsynced document survived unchanged
    resumed = [d for d in after.documents if d["type"] == "resume"]
    assert len(resumed) == 1 and "without a stop document" in resumed[0]["reason"]
    ds = store.load(summary.ref)
    assert len(ds) == summary.valid == sum(d.status == "valid" for d in after.measurements)
    assert json.loads(json.dumps(ds.manifest))["row_count"] == len(ds)


def test_resume_with_a_lowered_speed_cap_refuses_before_moving_instead_of_rejecting_every_pose(spec, actual, store):
    # The plan's moves were made at the robot's caps when the session started. Resumed on a robot whose cap was
    # lowered since (the profile narrowed), every remaining move would be refused and journaled as a rejected pose:
    # the plan burnt for good, nothing measured. Refused up front instead, naming the cap; nothing is journaled.
    plan = make_plan(random_configurations(spec.model, 4, seed=1), samples=3, settle=0.0, speed=0.8)
    first = SimRig(actual, TARGETS, seed=1, max_speed=1.0, faults=SimFaults(protective_stop_at={2}))
    with first.robot() as robot, first.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker)
    assert summary.exit_status == "paused"
    before = journal_docs(store, summary.session_id)
    slower = SimRig(actual, TARGETS, seed=1, max_speed=0.5)
    with slower.robot() as robot, slower.tracker() as tracker:
        with pytest.raises(SessionError, match=r"pose 1 moves at 0.8 rad/s.*0.5 rad/s"):
            resume(store, summary.session_id, robot, tracker)
    assert slower.moves == 0
    assert journal_docs(store, summary.session_id) == before
