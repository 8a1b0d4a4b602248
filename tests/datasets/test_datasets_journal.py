"""Journal: documents written and fsynced as they arrive, torn-line tolerance, resume helpers, crash safety."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from datasets_testutil import ROBOT_HASH, TARGETS, fake_measurement, new_journal
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labcal.datasets import Journal, JournalError, SessionHeader, SessionStore, read_journal


def test_documents_have_the_event_model_shape(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(0)
    with new_journal(store) as j:
        m = j.append_measurement(pose_index=3, **fake_measurement(rng), extra={"temperature": 21.5})
        j.append_measurement(
            pose_index=4,
            q_commanded=[0] * 6,
            q_actual=None,
            points=None,
            status="rejected",
            reason="target 2 not visible",
        )
        j.pause("protective stop")
        j.resume("operator cleared the stop")
        j.stop("success", "plan done")
    docs = read_journal(j.path).documents
    assert [d["type"] for d in docs] == ["start", "measurement", "measurement", "pause", "resume", "stop"]
    start = docs[0]
    assert start["robot"] == {"name": "ur10", "hash": ROBOT_HASH, "n_joints": 6}
    assert start["targets"] == TARGETS.tolist() and start["frame"] == "base"
    assert len(start["plan"]) == 10 and start["session_id"] == j.session_id
    assert {"labcal", "python", "numpy"} <= set(start["software"])
    assert [d["seq"] for d in docs if d["type"] == "measurement"] == [1, 2]
    assert m.units["q_actual"] == "rad" and m.units["points"] == "m"
    assert docs[2]["status"] == "rejected" and docs[2]["points"] is None
    assert docs[-1]["exit_status"] == "success"
    assert len({d["uid"] for d in docs}) == len(docs)


def test_each_document_is_on_disk_when_append_returns(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(1)
    with new_journal(store) as j:
        for i in range(3):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
            # Read through a separate file handle: the document must already be there, complete.
            lines = Path(j.path).read_bytes().split(b"\n")
            assert lines[-1] == b"" and json.loads(lines[-2])["seq"] == i + 1


def test_resume_helpers_and_lifecycle(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(2)
    with new_journal(store) as j:
        j.append_measurement(pose_index=0, **fake_measurement(rng))
        j.append_measurement(pose_index=5, **fake_measurement(rng))
        j.append_measurement(
            pose_index=7, q_commanded=None, q_actual=None, points=None, status="rejected", reason="tracker timeout"
        )
        j.stop("paused", "Ctrl-C")
        with pytest.raises(JournalError, match="resume"):
            j.append_measurement(pose_index=1, **fake_measurement(rng))
        sid = j.session_id
    with store.open_journal(sid) as j2:
        assert j2.valid_pose_indices() == {0, 5}
        assert j2.next_seq == 4 and j2.state == "stopped"
        j2.resume("continue")
        assert j2.append_measurement(pose_index=7, **fake_measurement(rng)).seq == 4
    c = store.read_journal(sid)
    assert c.valid_pose_indices() == {0, 5, 7} and c.status == "open"


def test_invalid_measurements_are_refused_before_writing(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(3)
    with new_journal(store) as j:
        size = Path(j.path).stat().st_size
        good = fake_measurement(rng)
        with pytest.raises(JournalError, match=r"shape \(6,\)"):
            j.append_measurement(pose_index=0, **{**good, "q_actual": np.zeros(5)})
        with pytest.raises(JournalError, match="non-finite"):
            j.append_measurement(pose_index=0, **{**good, "points": np.full((3, 3), np.nan)})
        with pytest.raises(JournalError, match="outside the plan"):
            j.append_measurement(pose_index=10, **good)
        with pytest.raises(JournalError, match="reason"):
            j.append_measurement(pose_index=0, **good, status="rejected")
        with pytest.raises(JournalError, match="exit_status"):
            j.stop("done")
        assert Path(j.path).stat().st_size == size
        assert j.next_seq == 1


def test_second_writer_is_refused(tmp_path):
    store = SessionStore(tmp_path)
    with new_journal(store) as j, pytest.raises(JournalError, match="another process"):
        Journal.open(j.path)


def test_torn_last_line_is_ignored_and_next_append_starts_a_fresh_line(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(4)
    with new_journal(store) as j:
        for i in range(3):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
        sid, path = j.session_id, Path(j.path)
    whole = path.read_bytes()
    # Simulate a kill in the middle of writing document seq 4: half a line, no newline.
    half = json.dumps({"type": "measurement", "seq": 4, "pose_index": 3, "q_actual": [0.1] * 6})[:40]
    with open(path, "ab") as f:
        f.write(half.encode())
    c = read_journal(path)
    assert [d.seq for d in c.measurements] == [1, 2, 3]
    assert c.needs_newline and c.torn_lines == [5] and not c.corrupt_lines
    assert any("torn" in w for w in c.warnings)
    with store.open_journal(sid) as j:
        assert j.next_seq == 4
        j.append_measurement(pose_index=3, **fake_measurement(rng))
    data = path.read_bytes()
    assert data.startswith(whole + half.encode() + b"\n")  # earlier bytes untouched, fresh line started
    c = read_journal(path)
    assert [d.seq for d in c.measurements] == [1, 2, 3, 4]
    assert not c.corrupt_lines and not c.needs_newline
    assert any("repaired" in w for w in c.warnings)
    assert store.seal(sid).rows_added == 4


def test_unexplained_corrupt_middle_line_blocks_sealing(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(5)
    with new_journal(store) as j:
        for i in range(3):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
        path, sid = Path(j.path), j.session_id
    lines = path.read_bytes().split(b"\n")
    lines[2] = lines[2][:10]  # damage seq 2 in the middle of the file
    path.write_bytes(b"\n".join(lines))
    c = read_journal(path)
    assert c.corrupt_lines == [3] and [d.seq for d in c.measurements] == [1, 3]
    from labcal.datasets import JournalCorrupted

    with pytest.raises(JournalCorrupted, match=r"\[3\]"):
        store.seal(sid)


_WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    from labcal.datasets import SessionHeader, SessionStore
    store = SessionStore(sys.argv[1])
    j = store.create_session(SessionHeader.of("ur10", "5" * 64, 6, targets=[[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]],
                                              frame="base", session_id="crash"))
    rng = np.random.default_rng(0)
    i = 0
    while True:
        q = rng.uniform(-3, 3, 6)
        # A big document makes a kill in the middle of a write likely.
        d = j.append_measurement(pose_index=i, q_commanded=q, q_actual=q, points=rng.normal(size=(3, 3)),
                                 extra={f"pad{k}": "x" * 200 for k in range(40)})
        print(d.seq, flush=True)
        i += 1
    """
)


@pytest.mark.integration
def test_kill_9_loses_nothing_fsynced_and_duplicates_nothing(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    acked = []
    try:
        while len(acked) < 40:
            line = proc.stdout.readline()  # the writer prints only after fsync returned
            if not line:
                pytest.fail(f"writer died: {proc.stderr.read()}")
            acked.append(int(line))
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        rest = proc.communicate(timeout=20)[0]
    acked += [int(s) for s in rest.split()]
    store = SessionStore(tmp_path)
    c = store.read_journal("crash")
    seqs = [d.seq for d in c.measurements]
    assert seqs == list(range(1, len(seqs) + 1))  # no gaps, no duplicates
    assert set(acked) <= set(seqs)
    assert not c.corrupt_lines
    with store.open_journal("crash") as j:
        assert j.next_seq == len(seqs) + 1
        j.append_measurement(pose_index=0, q_commanded=None, q_actual=[0] * 6, points=np.eye(3))
    c2 = store.read_journal("crash")
    assert [d.seq for d in c2.measurements] == [*seqs, len(seqs) + 1]
    assert not c2.corrupt_lines and not c2.torn_lines


_floats = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    rows=st.lists(
        st.tuples(
            st.lists(_floats, min_size=3, max_size=3),
            st.lists(st.lists(_floats, min_size=3, max_size=3), min_size=3, max_size=3),
            st.sampled_from(["valid", "rejected"]),
            st.sampled_from([None, "train", "val", "test", ""]),
            st.one_of(st.none(), _floats, st.text(max_size=8), st.booleans(), st.integers(-(2**53), 2**53)),
        ),
        max_size=8,
    )
)
def test_journal_round_trip_property(tmp_path_factory, rows):
    store = SessionStore(tmp_path_factory.mktemp("prop"))
    written = []
    with store.create_session(SessionHeader.of("r", ROBOT_HASH, 3, targets=TARGETS, frame="tracker")) as j:
        for i, (q, pts, status, split, extra) in enumerate(rows):
            written.append(
                j.append_measurement(
                    pose_index=i,
                    q_commanded=q,
                    q_actual=q,
                    points=pts,
                    status=status,
                    reason="" if status == "valid" else "r",
                    split=split,
                    extra={"v": extra},
                )
            )
    read = read_journal(j.path).measurements
    assert read == written  # JSON float round trip is exact (repr), incl. -0.0 and subnormals
    for d, (q, _pts, _s, _sp, _e) in zip(read, rows, strict=True):
        assert np.array_equal(np.array(d.q_actual).view(np.uint64), np.array(q, dtype=np.float64).view(np.uint64))
    # ... and so is sealing into parquet and loading again (valid rows only, in order).
    res = store.seal(j.session_id)
    valid = [r for r in rows if r[2] == "valid"]
    assert res.created == bool(valid)
    if valid:
        ds = store.load(res.ref)
        assert ds.q.view(np.uint64).tolist() == np.array([r[0] for r in valid]).view(np.uint64).tolist()
        assert ds.points.view(np.uint64).tolist() == np.array([r[1] for r in valid]).view(np.uint64).tolist()
        assert ds.split.tolist() == [r[3] or "" for r in valid]
