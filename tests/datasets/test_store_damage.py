"""Data never lost (issue 26): damage to one part of a session never makes another part unusable, every recording
command checks the whole session before the robot moves, verify reports what is gone, foreign entries are skipped.

Each test is one finding of the hostile-input review; each fails on main 5770eeb."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from datasets_testutil import fake_measurement, flip_byte, new_journal
from typer.testing import CliRunner

from labcal.cli.app import app
from labcal.datasets import DatasetCorrupted, JournalCorrupted, SessionStore
from labcal.datasets.journal import Journal

runner = CliRunner()


def cli(*args):
    return runner.invoke(app, [str(a) for a in args])


def _append(store: SessionStore, sid: str, poses: range, seed: int) -> None:
    """More measurements in an existing journal (a resumed run), not sealed."""
    rng = np.random.default_rng(seed)
    with store.open_journal(sid) as j:
        j.resume("test")
        for i in poses:
            j.append_measurement(pose_index=i, **fake_measurement(rng))


@pytest.fixture
def two_runs(tmp_path):
    """A journal of 10 plan poses: poses 0-4 sealed into v001, then poses 5-7 recorded after it (not sealed)."""
    store = SessionStore(tmp_path / "store")
    rng = np.random.default_rng(0)
    with new_journal(store) as j:
        for i in range(5):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
        j.stop("paused")
        sid = j.session_id
    assert store.seal(sid).ref == f"{sid}@v001"
    _append(store, sid, range(5, 8), seed=1)
    return store, sid, store.session_dir(sid) / "journal.jsonl"


def _damage_line(path, line_no: int) -> None:
    """Overwrite one journal line with non-JSON bytes of the same length (the rest of the file stays put)."""
    lines = path.read_bytes().split(b"\n")
    lines[line_no - 1] = b"#" * len(lines[line_no - 1])
    path.write_bytes(b"\n".join(lines))


# ------------------------------------------------------------------ a damaged sealed journal never locks a version


def test_a_damaged_line_in_the_sealed_part_leaves_v001_usable_and_seal_valid_prefix_seals_the_rest(two_runs):
    store, sid, journal = two_runs
    _damage_line(journal, 3)  # the measurement of pose 1, inside the part sealed into v001
    before = journal.read_bytes()
    assert store.verify(f"{sid}@v001").ok
    assert store.load(f"{sid}@v001").pose.tolist() == [0, 1, 2, 3, 4]  # fit reads it
    problems = store.check_session(sid).problems
    assert any("line 3" in p and "--valid-prefix" in p for p in problems), problems
    with pytest.raises(JournalCorrupted, match="--valid-prefix"):
        store.seal(sid)
    result = store.seal(sid, valid_prefix=True)
    assert result.created and result.ref == f"{sid}@v002"
    assert store.load(result.ref).pose.tolist() == list(range(8))  # v001's rows, then poses 5-7 recorded after it
    prov = store.manifest(result.ref)["provenance"]["journal"]["valid_prefix"]
    assert prov["skipped"][0]["line"] == 3 and "sealed_part_damage" in prov
    assert journal.read_bytes() == before  # the journal is never rewritten
    # verify still reports the damaged journal, now as handled: no advice to run the same seal again
    after = store.check_session(sid).problems
    assert after and all("--valid-prefix`" not in p and "recorded by v002" in p for p in after), after


def test_a_flipped_byte_in_the_start_document_leaves_v001_usable_and_is_named(two_runs):
    store, sid, journal = two_runs
    data = bytearray(journal.read_bytes())
    i = data.index(b'"targets":[[') + len(b'"targets":[[')
    data[i] = ord("7") if data[i] != ord("7") else ord("8")  # still valid JSON: another target position
    journal.write_bytes(bytes(data))
    assert store.verify(f"{sid}@v001").ok and len(store.load(f"{sid}@v001")) == 5
    problems = store.check_session(sid).problems
    assert any("line 1: the start document differs" in p for p in problems), problems
    result = store.seal(sid, valid_prefix=True)
    assert result.created
    # the new version takes the session's targets from v001's verified copy, not from the damaged start document
    assert store.manifest(result.ref)["session"]["targets"] == store.manifest(f"{sid}@v001")["session"]["targets"]


def test_a_journal_cut_shorter_than_when_sealed_leaves_v001_usable_and_seal_valid_prefix_answers(two_runs):
    store, sid, journal = two_runs
    sealed = store.manifest(f"{sid}@v001")["provenance"]["journal"]["bytes"]
    with open(journal, "r+b") as f:
        f.truncate(sealed - 100)
    assert store.verify(f"{sid}@v001").ok and len(store.load(f"{sid}@v001")) == 5
    assert any("shorter" in p for p in store.check_session(sid).problems)
    result = store.seal(sid, valid_prefix=True)  # was: "journal.jsonl: shorter (…) than when sealed (…)"
    assert not result.created and result.ref == f"{sid}@v001" and "shorter" in result.message


# ----------------------------------------------------------------------------------- verify before the first motion


def _interrupted_sim_session(store: SessionStore, n_poses: int, stop_at: int) -> str:
    """A sim session recorded by the runner (resumable by resume_session), Ctrl-C at move ``stop_at``; v001 sealed."""
    from labcal.cli.ops.sessions import sim_actual
    from labcal.drivers.sim import SimRig
    from labcal.robots import load
    from labcal.sessions import make_plan, random_configurations, run

    spec = load("ur10")
    targets = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.08, 0.02]])
    rig = SimRig(sim_actual(spec, "default", 0), targets, seed=0)
    plan = make_plan(random_configurations(spec.model, n_poses, seed=0, targets=targets), samples=1, settle=0.0)

    class Interrupting:
        def __init__(self, robot):
            self._robot, self.moves = robot, 0

        def move_joints(self, q, speed, acceleration):
            self.moves += 1
            if self.moves == stop_at:
                raise KeyboardInterrupt
            return self._robot.move_joints(q, speed, acceleration)

        def __getattr__(self, name):
            return getattr(self._robot, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._robot.close()

    with Interrupting(rig.robot()) as robot, rig.tracker() as tracker:
        summary = run(store, spec, targets, plan, robot, tracker, frame="base",
                      metadata={"sim": {"errors": "default", "seed": 0}})  # fmt: skip
    assert summary.exit_status == "aborted" and summary.ref.endswith("@v001")
    return summary.session_id


def test_resume_refuses_a_damaged_version_before_any_motion(tmp_path):
    from labcal.cli.ops.sessions import resume_session
    from labcal.sessions import SessionError

    store = SessionStore(tmp_path / "store")
    sid = _interrupted_sim_session(store, n_poses=12, stop_at=4)
    flip_byte(store.session_dir(sid) / "v001" / "measurements.parquet", 200)
    journal = store.session_dir(sid) / "journal.jsonl"
    before = journal.read_bytes()
    with pytest.raises(SessionError, match=r"nothing was moved: .*v001: measurements\.parquet: sha256 mismatch"):
        resume_session(store, sid)
    assert journal.read_bytes() == before  # no resume document, no measurement: the robot never moved


def test_a_start_document_that_does_not_read_back_as_written_is_refused_before_recording(tmp_path, monkeypatch):
    from labcal.datasets import journal as journal_module

    real = journal_module.write_all

    def flipping(fd, data):  # a disk that stores one bit wrong
        real(fd, data[:40] + bytes([data[40] ^ 0x04]) + data[41:])

    monkeypatch.setattr(journal_module, "write_all", flipping)
    with pytest.raises(JournalCorrupted, match="read back differs"):
        new_journal(SessionStore(tmp_path / "store"))


# --------------------------------------------------------------------------------- verify reports what is gone


def test_verify_reports_a_deleted_latest_version(two_runs):
    from labcal.datasets._util import remove_tree

    store, sid, _ = two_runs
    assert store.seal(sid).ref.endswith("@v002")
    remove_tree(store.session_dir(sid) / "v002")
    r = cli("session", "verify", sid, "--store", store.root)
    assert r.exit_code == 1, r.stdout
    assert f"{sid}: v002: missing" in r.stdout


def test_verify_reports_a_deleted_first_version(two_runs):
    from labcal.datasets._util import remove_tree

    store, sid, _ = two_runs
    assert store.seal(sid).ref.endswith("@v002")
    remove_tree(store.session_dir(sid) / "v001")
    r = cli("session", "verify", sid, "--store", store.root, "--json")
    assert r.exit_code == 1
    doc = json.loads(r.stdout)
    assert any(p.startswith("v001: missing") for p in doc["session_checks"]["problems"])
    # a session written before the versions log: the gap in the numbering still names it
    (store.session_dir(sid) / "versions.jsonl").unlink()
    assert any(p.startswith("v001: missing (v002 exists") for p in store.check_session(sid).problems)


def test_verify_reports_a_deleted_journal(two_runs):
    store, sid, journal = two_runs
    journal.unlink()
    r = cli("session", "verify", sid, "--store", store.root)
    assert r.exit_code == 1, r.stdout
    assert f"{sid}: journal.jsonl: missing" in r.stdout
    assert store.verify(f"{sid}@v001").ok  # the version itself is intact and usable


def test_a_damaged_journal_is_reported_once_for_the_session_not_against_every_version(two_runs):
    store, sid, journal = two_runs
    _damage_line(journal, 2)
    r = cli("session", "verify", sid, "--store", store.root)
    assert r.exit_code == 1
    assert f"{sid}@v001: ok" in r.stdout and f"{sid}: journal.jsonl: line 2" in r.stdout
    assert "line 2: unreadable (JSONDecodeError): it lies in the part already sealed" in r.stdout  # v001 has it


# ------------------------------------------------------------------------------------------------ foreign entries


def test_a_copied_session_folder_and_os_files_are_listed_as_foreign_not_fatal(two_runs):
    import shutil

    store, sid, _ = two_runs
    shutil.copytree(store.session_dir(sid), store.root / f"{sid} (copy)")
    (store.root / ".DS_Store").write_bytes(b"\0\0\0\1Bud1")
    (store.root / "Thumbs.db").write_bytes(b"x")
    r = cli("session", "list", "--store", store.root)
    assert r.exit_code == 0, r.stdout + r.stderr
    assert sid in r.stdout and f"foreign: '{sid} (copy)' skipped" in r.stdout and "'Thumbs.db'" in r.stdout
    doc = json.loads(cli("session", "list", "--store", store.root, "--json").stdout)
    assert [s["session"] for s in doc["sessions"]] == [sid]
    assert {f["name"] for f in doc["foreign"]} == {f"{sid} (copy)", ".DS_Store", "Thumbs.db"}


def test_os_and_editor_files_inside_a_version_are_noted_not_fatal(two_runs):
    store, sid, _ = two_runs
    vdir = store.session_dir(sid) / "v001"
    (vdir / ".DS_Store").write_bytes(b"\0")
    (vdir / "manifest.json~").write_bytes(b"{}")
    report = store.verify(f"{sid}@v001")
    assert report.ok and len(report.notes) == 2
    assert len(store.load(f"{sid}@v001")) == 5
    (vdir / "extra").mkdir()  # anything else is still a problem
    assert any(p.startswith("extra: extra directory") for p in store.verify(f"{sid}@v001").problems)


def test_verify_of_a_session_with_only_a_journal_checks_the_journal(tmp_path):
    store = SessionStore(tmp_path / "store")
    rng = np.random.default_rng(0)
    with new_journal(store) as j:
        for i in range(2):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
        sid = j.session_id
    _damage_line(store.session_dir(sid) / "journal.jsonl", 2)  # not the last line: not a torn write
    r = cli("session", "verify", sid, "--store", store.root)
    assert r.exit_code == 1 and "journal.jsonl: line 2" in r.stdout, r.stdout + r.stderr


def test_a_full_disk_names_the_file_that_could_not_be_written(two_runs, monkeypatch):
    import errno

    from labcal.datasets import _util
    from labcal.datasets.store import StoreWriteError

    store, sid, _ = two_runs
    real = os.write

    def full(fd, data):
        if len(data) > 1000:  # the parquet file; small writes (the versions log) would pass
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data)

    monkeypatch.setattr(_util.os, "write", full)
    with pytest.raises(StoreWriteError, match=r"No space left on device \(.*measurements\.parquet\).*free space"):
        store.seal(sid)
    monkeypatch.undo()
    assert store.versions(sid) == [1] and not list(store.session_dir(sid).glob(".tmp-*"))


def test_a_damaged_version_stops_seal_with_the_version_named(two_runs):
    store, sid, _ = two_runs
    flip_byte(store.session_dir(sid) / "v001" / "measurements.parquet", 100)
    with pytest.raises(DatasetCorrupted, match="v001"):
        store.seal(sid)
    # and Journal stays appendable: the damage is in the version, not in the journal
    Journal.open(store.session_dir(sid) / "journal.jsonl").close()


def test_a_full_disk_while_recording_names_the_journal_and_how_to_continue(tmp_path, monkeypatch):
    import errno

    from labcal.datasets import JournalError
    from labcal.datasets import journal as journal_module

    store = SessionStore(tmp_path / "store")
    rng = np.random.default_rng(0)
    with new_journal(store) as j:
        j.append_measurement(pose_index=0, **fake_measurement(rng))

        def full(fd, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(journal_module.os, "write", full)
        with pytest.raises(JournalError) as e:
            j.append_measurement(pose_index=1, **fake_measurement(rng))
        monkeypatch.undo()
    message = str(e.value)
    assert "\n" not in message and str(j.path) in message and "No space left on device" in message
    assert "free space on its disk" in message and f"labcal session resume {j.session_id}" in message
    assert len(store.read_journal(j.session_id).measurements) == 1  # what was written before is there


def test_os_files_among_the_fits_are_noted_not_fatal(two_runs):
    store, sid, _ = two_runs
    ref = f"{sid}@v001"
    store.save_fit(ref, {"model.json": b"{}"}, {"method": "test"})
    fits = store.session_dir(sid) / "v001" / "fits"
    (fits / "Thumbs.db").write_bytes(b"\0")
    report = store.verify_fits(ref)
    assert report.ok and report.notes and len(store.list_fits(ref)) == 1
    r = cli("session", "verify", ref, "--store", store.root)
    assert r.exit_code == 0 and "note: fits/Thumbs.db: foreign file" in r.stdout, r.stdout


def test_an_unreadable_start_document_leaves_v001_usable_and_seal_valid_prefix_seals_the_rest(two_runs, tmp_path):
    store, sid, journal = two_runs
    _damage_line(journal, 1)
    assert store.verify(f"{sid}@v001").ok and len(store.load(f"{sid}@v001")) == 5
    problems = store.check_session(sid).problems
    assert any(p.startswith("journal.jsonl: line 1: the start document is damaged") and "--valid-prefix" in p
               for p in problems), problems  # fmt: skip
    result = store.seal(sid, valid_prefix=True)
    assert result.created and store.load(result.ref).pose.tolist() == list(range(8))
    # without a version, nothing holds a copy of the start document: no --valid-prefix advice, a clear refusal
    other = SessionStore(tmp_path / "other")
    rng = np.random.default_rng(0)
    with new_journal(other) as j:
        for i in range(3):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
    _damage_line(j.path, 1)
    problems = other.check_session(j.session_id).problems
    assert len(problems) == 1 and "restore the journal from a backup" in problems[0], problems
    with pytest.raises(JournalCorrupted, match="no version holds a copy"):
        other.seal(j.session_id, valid_prefix=True)


def test_a_session_recorded_on_after_its_seal_checks_clean(two_runs):
    """The journal grows after v001 was sealed: only the sealed prefix is compared, so growth is no damage."""
    store, sid, _journal = two_runs
    assert store.check_session(sid).problems == []
    store.check_before_recording(sid)  # raises DatasetCorrupted when the session is damaged
    assert store.seal(sid).ref == f"{sid}@v002"


def test_valid_prefix_stops_at_a_corrupt_line_in_the_unsealed_part(two_runs):
    """After an unexplained corrupt line the order of later documents cannot be trusted: they are skipped, named."""
    store, sid, journal = two_runs
    lines = journal.read_bytes().split(b"\n")
    pose6 = next(i for i, raw in enumerate(lines, 1) if b'"pose_index":6' in raw.replace(b" ", b""))
    _damage_line(journal, pose6)
    result = store.seal(sid, valid_prefix=True)
    assert store.load(result.ref).pose.tolist() == [0, 1, 2, 3, 4, 5]  # pose 7 came after the damage
    skipped = store.manifest(result.ref)["provenance"]["journal"]["valid_prefix"]["skipped"]
    assert [s["line"] for s in skipped] == [pose6, pose6 + 1]
    assert skipped[1]["pose_index"] == 7 and f"after the corrupt line {pose6}" in skipped[1]["reason"]


def test_a_versions_log_line_torn_by_a_crash_does_not_swallow_the_next_version(two_runs):
    # A crash in the middle of appending to versions.jsonl leaves an unfinished last line (a note, not damage). The
    # next seal must start its entry on a fresh line: glued onto the torn one, both become one unreadable line in
    # the middle, which check_before_recording refuses forever, and v002's entry is lost.
    store, sid, _ = two_runs
    log = store.session_dir(sid) / "versions.jsonl"
    log.write_bytes(log.read_bytes()[:-20])  # v001's entry cut short, no newline
    assert store.seal(sid).ref == f"{sid}@v002"
    report = store.check_session(sid)
    assert report.problems == []
    listed = [n for n in report.notes if "not listed in versions.jsonl" in n]
    assert len(listed) == 1 and listed[0].startswith("v001: ")  # its entry was torn; v002's is whole
    store.check_before_recording(sid)  # a resume is not refused


def test_a_whole_versions_log_entry_without_its_newline_is_kept(two_runs):
    store, sid, _ = two_runs
    log = store.session_dir(sid) / "versions.jsonl"
    log.write_bytes(log.read_bytes().rstrip(b"\n"))  # v001's entry whole, only its newline lost
    assert store.seal(sid).ref == f"{sid}@v002"
    report = store.check_session(sid)
    assert report.problems == [] and not [n for n in report.notes if "not listed" in n]
    assert [json.loads(line)["version"] for line in log.read_text().splitlines()] == ["v001", "v002"]
