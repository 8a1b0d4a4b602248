"""Session and store faults (issue 12 item 5): a corrupt journal stops resume before any motion and its valid prefix
can be sealed; a silent tracker or a run without one valid pose is a failure; fits are verified; plan size is
bounded; a missing or unwritable store is one clear error before any work."""

from __future__ import annotations

import hashlib
import json
import os

import pytest
from sessions_testutil import TARGETS, CountingRobot, record_interrupted

from labcal.cli.common import UserError, open_store
from labcal.cli.ops.sessions import MAX_POSES, plan_configurations, resume_session
from labcal.datasets import JournalCorrupted, SessionStore, read_journal
from labcal.drivers.base import MotionRejected
from labcal.drivers.sim import SimFaults, SimRig
from labcal.robots import load
from labcal.sessions import RetryPolicy, SessionError, make_plan, random_configurations, resume, run
from labcal.simulation import ErrorSpec, simulate


@pytest.fixture(scope="module")
def spec():
    return load("ur10")


@pytest.fixture
def store(tmp_path):
    return SessionStore(tmp_path / "store")


def corrupt_line(path, line_no: int) -> None:
    """Overwrite one journal line in place with bytes that are not JSON (same length: the rest stays put)."""
    lines = path.read_bytes().split(b"\n")
    lines[line_no - 1] = b"#" * len(lines[line_no - 1])
    path.write_bytes(b"\n".join(lines))


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ------------------------------------------------------------------------------------------------------------ journal


def test_resume_on_a_corrupt_journal_refuses_before_any_motion_naming_the_line(spec, store):
    first = record_interrupted(store, spec, n_poses=10, interrupt_at=7)  # poses 0..5 measured
    journal = store.session_dir(first.session_id) / "journal.jsonl"
    corrupt_line(journal, 4)  # measurement of pose 2 (line 1 is the start document)
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0)
    robot = CountingRobot(rig.robot())
    with robot, rig.tracker() as tracker, pytest.raises(SessionError, match=r"corrupt at line 4 .*--valid-prefix"):
        resume(store, first.session_id, robot, tracker, spec=spec)
    assert robot.moves == 0 and rig.measurements == 0
    # Through the CLI's workflow too (it builds the sim rig itself).
    with pytest.raises(SessionError, match="line 4"):
        resume_session(store, first.session_id)


def test_seal_valid_prefix_records_what_it_skipped_and_deletes_nothing(spec, store):
    first = record_interrupted(store, spec, n_poses=12, interrupt_at=9)  # 8 measured, v001 sealed with them
    sid = first.session_id
    journal = store.session_dir(sid) / "journal.jsonl"
    # A later run measures poses 8..11 (not sealed yet), then a line in it is corrupted: pose 10's.
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0)
    with rig.robot() as robot, rig.tracker() as tracker:
        second = resume(store, sid, robot, tracker, spec=spec, seal=False)
    assert second.valid == 12
    docs = read_journal(journal)
    lines = dict(zip([d.get("pose_index") for d in docs.documents], docs.document_lines, strict=True))
    corrupt_line(journal, lines[10])
    before = sha(journal)

    with pytest.raises(JournalCorrupted, match="--valid-prefix"):
        store.seal(sid)
    result = store.seal(sid, valid_prefix=True)
    assert result.created and result.ref.endswith("@v002")
    ds = store.load(result.ref)
    assert sorted(ds.pose.tolist()) == list(range(10))  # pose 10 corrupt, pose 11 after it: both left out
    skipped = store.manifest(result.ref)["provenance"]["journal"]["valid_prefix"]["skipped"]
    assert skipped[0]["line"] == lines[10] and "unreadable" in skipped[0]["reason"]
    assert any(s.get("pose_index") == 11 and s["line"] == lines[11] and "after the corrupt line" in s["reason"]
               for s in skipped)  # fmt: skip
    assert "left out" in result.message
    assert sha(journal) == before  # nothing recorded is deleted or rewritten
    assert store.verify(result.ref).ok


def test_seal_valid_prefix_of_a_never_sealed_session(spec, store):
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0)
    plan = make_plan(random_configurations(spec.model, 6, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base", seal=False)
    journal = store.session_dir(summary.session_id) / "journal.jsonl"
    corrupt_line(journal, 5)  # pose 3
    result = store.seal(summary.session_id, valid_prefix=True)
    assert store.load(result.ref).pose.tolist() == [0, 1, 2]


# ------------------------------------------------------------------------------------------------- failure statuses


def test_a_tracker_that_never_answers_fails_the_run_after_a_few_poses(spec, store):
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0,
                 faults=SimFaults(timeout_probability=1.0))  # fmt: skip
    plan = make_plan(random_configurations(spec.model, 12, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base")
    assert summary.exit_status == "failed" and "did not answer on 3 consecutive poses" in summary.reason
    assert summary.valid == 0 and summary.ref is None
    assert rig.moves == 3  # it stopped instead of walking the robot through the other 9 poses
    stop = read_journal(store.session_dir(summary.session_id) / "journal.jsonl").stop
    assert stop.exit_status == "failed"


def test_a_tracker_sending_only_garbage_stops_the_run_after_max_failed_poses(spec, store):
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0,
                 faults=SimFaults(garbled_probability=1.0))  # fmt: skip
    plan = make_plan(random_configurations(spec.model, 60, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base", retry=RetryPolicy(max_failed_poses=4))
    assert summary.exit_status == "failed" and "4 consecutive poses rejected" in summary.reason
    assert rig.moves == 4 and summary.rejected == 4  # not 60 poses walked for nothing
    assert read_journal(store.session_dir(summary.session_id) / "journal.jsonl").stop.exit_status == "failed"


def test_a_valid_pose_resets_the_count_of_failed_poses(spec, store):
    # one move and three measure attempts per rejected pose: poses 0, 1 use calls 1-6, pose 2 is valid at call 7
    garbled = set(range(1, 40)) - {7}
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0,
                 faults=SimFaults(garbled_at=garbled))  # fmt: skip
    plan = make_plan(random_configurations(spec.model, 12, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base", retry=RetryPolicy(max_failed_poses=3))
    assert summary.exit_status == "failed" and "3 consecutive poses rejected (last at pose 5" in summary.reason
    assert (summary.valid, summary.rejected) == (1, 5)


class RefusingRobot:
    """Wraps a robot: its driver refuses (MotionRejected) the moves numbered in ``refuse`` (1-based)."""

    def __init__(self, inner, refuse):
        self.inner, self.refuse, self.moves = inner, set(refuse), 0

    def move_joints(self, q, speed, acceleration):
        self.moves += 1
        if self.moves in self.refuse:
            raise MotionRejected("outside the profile's joint limits")
        return self.inner.move_joints(q, speed, acceleration)

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.inner.close()


def test_poses_the_robot_refuses_neither_count_nor_reset_failed_poses(spec, store):
    # every frame garbled; the moves to poses 1 and 2 are refused: rejected 0, (1, 2 refused), 3, 4 -> stop at 4
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0,
                 faults=SimFaults(garbled_probability=1.0))  # fmt: skip
    plan = make_plan(random_configurations(spec.model, 12, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with RefusingRobot(rig.robot(), refuse={2, 3}) as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base", retry=RetryPolicy(max_failed_poses=3))
    assert "3 consecutive poses rejected (last at pose 4" in summary.reason
    assert RetryPolicy().max_failed_poses == 5  # the documented default (README, --max-failed-poses)
    with pytest.raises(ValueError, match="max_failed_poses must be an integer >= 0"):
        RetryPolicy(max_failed_poses=-1)


def test_a_run_where_every_pose_is_rejected_is_a_failure_that_says_why(spec, store):
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0)
    plan = make_plan(random_configurations(spec.model, 4, seed=0, targets=TARGETS), samples=1, settle=0.0)
    wrong = TARGETS * 1.5  # the targets file does not match the tool: every triangle check fails
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, wrong, plan, robot, tracker, frame="base")
    assert summary.exit_status == "failed" and summary.valid == 0 and summary.rejected == 4
    assert "no valid measurement" in summary.reason and "target triangle differs" in summary.reason


def test_a_run_with_some_valid_poses_still_succeeds(spec, store):
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0,
                 faults=SimFaults(timeout_at={1, 2, 3}))  # fmt: skip
    plan = make_plan(random_configurations(spec.model, 3, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base")
    assert (summary.exit_status, summary.valid, summary.rejected) == ("success", 2, 1)


# ------------------------------------------------------------------------------------------------------------ fits


def test_verify_fits_reports_changed_missing_and_extra_fit_files(spec, store):
    first = record_interrupted(store, spec, n_poses=6, interrupt_at=6)
    record = store.save_fit(first.ref, {"model.json": b'{"a": 1}', "notes.txt": "x"}, {"method": "test"})
    assert store.verify_fits(first.ref).ok
    weights = record.path / "model.json"
    weights.chmod(0o644)
    weights.write_bytes(b'{"a": 2}')
    (record.path / "notes.txt").unlink()
    (record.path / "stray.bin").write_bytes(b"?")
    problems = store.verify_fits(first.ref).problems
    assert any(f"fits/{record.fit_id}/model.json: sha256 mismatch" in p for p in problems)
    assert any(f"fits/{record.fit_id}/notes.txt: missing" in p for p in problems)
    assert any(f"fits/{record.fit_id}/stray.bin: extra file" in p for p in problems)
    assert store.verify(first.ref).ok  # the version's own data are intact


def test_verify_fits_catches_an_edited_fit_json(spec, store):
    first = record_interrupted(store, spec, n_poses=6, interrupt_at=6)
    record = store.save_fit(first.ref, {"model.json": b"{}"}, {"method": "test"})
    fj = record.path / "fit.json"
    fj.chmod(0o644)
    meta = json.loads(fj.read_text())
    meta["metadata"]["method"] = "edited"
    fj.write_text(json.dumps(meta, indent=2))
    assert any("fit.json: content sha256 mismatch" in p for p in store.verify_fits(first.ref).problems)


# ------------------------------------------------------------------------------------------------ plan size, store


def test_plan_size_is_bounded_before_anything_is_allocated(spec, monkeypatch):
    import labcal.sessions as sessions

    def never(*a, **k):  # the planner must not even be called
        raise AssertionError("planned despite the bound")

    monkeypatch.setattr(sessions, "random_configurations", never)
    with pytest.raises(UserError, match=r"--poses 100,000,000 is more than .* \(100,000\).*memory"):
        plan_configurations(spec, 100_000_000, "random", 0, TARGETS)
    with pytest.raises(UserError, match="more than labcal plans"):
        plan_configurations(spec, MAX_POSES + 1, "random", 0, TARGETS)
    with pytest.raises(UserError, match="--samples"):
        plan_configurations(spec, 10, "optimal", 0, TARGETS, samples=10**9)


def test_open_store_read_write_create(tmp_path):
    with pytest.raises(UserError, match=r"no session store at .*missing \(.*--store or LABCAL_STORE"):
        open_store(tmp_path / "missing", create=False)
    assert not (tmp_path / "missing").exists()
    assert open_store(tmp_path / "new", create=True).root.is_dir()
    a_file = tmp_path / "file"
    a_file.write_text("not a store")
    with pytest.raises(UserError, match="is not a folder"):
        open_store(a_file, create=True)
    with pytest.raises(UserError, match="cannot create the session store"):
        open_store(a_file / "sub", create=True)
    # Old callers that do not say what they do keep working on a missing store (no folder is created).
    assert not open_store(tmp_path / "lazy").root.exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_open_store_refuses_a_read_only_store_for_writing(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(UserError, match="is not writable"):
            open_store(ro, create=True)
        assert open_store(ro).root == ro  # reading it is fine
    finally:
        ro.chmod(0o755)


def test_a_missing_store_is_named_by_any_command_that_reads_a_session(tmp_path):
    store = SessionStore(tmp_path / "nowhere")
    with pytest.raises(LookupError, match=r"no session store at .*nowhere"):
        store.load("20261122-031500-ur10-3f9a")
    assert not store.root.exists()


# ------------------------------------------------------------------------------------------------ record-time sanity


def _wrong_model_run(store, spec, allow=()):
    """The session says ur10 but the arm is a ur5e: every pose is valid by itself (the target triangle is right),
    only the nominal-model check can tell."""
    rig = SimRig(simulate(load("ur5e"), ErrorSpec.none(), seed=0), TARGETS, seed=0)
    plan = make_plan(random_configurations(spec.model, 20, seed=0, targets=TARGETS), samples=1, settle=0.0)
    robot = CountingRobot(rig.robot())
    with robot, rig.tracker() as tracker:
        return run(store, spec, TARGETS, plan, robot, tracker, frame="base", allow=allow), robot


def test_a_wrong_robot_model_stops_the_run_at_the_record_time_sanity_check(spec, store):
    summary, robot = _wrong_model_run(store, spec)
    assert summary.exit_status == "failed" and "[nominal]" in summary.reason and "--allow nominal" in summary.reason
    assert robot.moves == 12 and summary.valid == 12  # checked at 2n = 12 valid poses, nothing moved after
    assert summary.ref is not None and len(store.load(summary.ref)) == 12  # what was recorded is kept

    rig = SimRig(simulate(load("ur5e"), ErrorSpec.none(), seed=0), TARGETS, seed=0)
    again = CountingRobot(rig.robot())
    with again, rig.tracker() as tracker, pytest.raises(SessionError, match=r"\[nominal\]"):
        resume(store, summary.session_id, again, tracker, spec=spec)
    assert again.moves == 0  # refused before any motion
    with rig.robot() as robot2, rig.tracker() as tracker:
        done = resume(store, summary.session_id, robot2, tracker, spec=spec, allow=["nominal"])
    assert done.exit_status == "success" and done.valid == 20


def test_an_allowed_check_lets_the_run_finish_and_is_recorded(spec, store):
    summary, robot = _wrong_model_run(store, spec, allow=["nominal"])
    assert summary.exit_status == "success" and robot.moves == 20
    start = read_journal(store.session_dir(summary.session_id) / "journal.jsonl").start
    assert start.metadata["runner"]["sanity_allow"] == ["nominal"]


def test_a_store_that_cannot_be_written_is_one_error_line_not_a_traceback(spec, store, monkeypatch):
    import errno

    import labcal.datasets.store as store_module
    from labcal.datasets import DatasetError

    first = record_interrupted(store, spec, n_poses=4, interrupt_at=4)

    def read_only(path, data):
        raise OSError(errno.EROFS, "Read-only file system", str(path))

    monkeypatch.setattr(store_module, "write_file_durable", read_only)
    with pytest.raises(DatasetError, match=r"cannot store the fit in the session store .*Read-only file system"):
        store.save_fit(first.ref, {"a.json": b"{}"}, {})
    assert store.list_fits(first.ref) == []  # nothing half-written is visible


def test_finding_a_fit_in_a_missing_store_names_the_store(tmp_path):
    with pytest.raises(LookupError, match=r"no session store at .*nowhere \(does not exist"):
        SessionStore(tmp_path / "nowhere").find_fit("20261123-203029-193273-f0a349")
