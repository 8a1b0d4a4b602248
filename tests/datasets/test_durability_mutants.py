"""Journal and store durability: the behaviours that carry "nothing recorded is lost", each pinned by a test that
fails when that one behaviour breaks (issue 26: these mutations survived the existing tests).

- a measurement line that repeats (or goes back from) the previous ``seq`` is not accepted as a new row;
- every append is fsynced before it returns (a spy on ``os.fsync`` records the journal's descriptor);
- a complete last line that lost only its newline is kept, and the next document starts on a fresh line;
- ``verify`` reports any folder inside a version other than ``fits/`` (and a ``fits`` that is a file).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from datasets_testutil import fake_measurement, new_journal

from labcal.datasets import SessionStore, read_journal


def _recorded(tmp_path: Path, n: int = 3, seed: int = 0):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(seed)
    j = new_journal(store)
    for i in range(n):
        j.append_measurement(pose_index=i, **fake_measurement(rng))
    return store, j, rng


# -- seq order ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seq", [3, 2])  # the same seq again (a replayed line), and one that goes back
def test_a_measurement_not_after_the_previous_seq_is_refused_as_corrupt(tmp_path, seq):
    _store, j, _ = _recorded(tmp_path)
    path = Path(j.path)
    j.close()
    lines = path.read_bytes().split(b"\n")
    replay = json.loads(lines[3])  # seq 3, the last measurement
    replay["seq"] = seq
    replay["uid"] = "replayed-" + replay["uid"]
    with open(path, "ab") as f:
        f.write(json.dumps(replay).encode() + b"\n")
    c = read_journal(path)
    assert [d.seq for d in c.measurements] == [1, 2, 3]
    assert c.corrupt_lines == [5]
    assert c.corrupt_reasons[5] == f"seq {seq} does not follow 3"


# -- fsync before return ------------------------------------------------------------------------------------------


def test_every_append_is_fsynced_before_it_returns(tmp_path, monkeypatch):
    _store, j, rng = _recorded(tmp_path, n=1)
    journal_inode = os.stat(j.path).st_ino
    events: list[tuple[str, int]] = []
    real_fsync, real_write = os.fsync, os.write

    def spy_fsync(fd):
        if os.fstat(fd).st_ino == journal_inode:
            events.append(("fsync", os.fstat(fd).st_size))
        return real_fsync(fd)

    def spy_write(fd, data):
        n = real_write(fd, data)
        if os.fstat(fd).st_ino == journal_inode:
            events.append(("write", os.fstat(fd).st_size))
        return n

    monkeypatch.setattr(os, "fsync", spy_fsync)
    monkeypatch.setattr(os, "write", spy_write)
    calls = [
        lambda: j.append_measurement(pose_index=1, **fake_measurement(rng)),
        lambda: j.pause("protective stop"),
        lambda: j.resume("cleared"),
        lambda: j.stop("success"),
    ]
    for call in calls:
        events.clear()
        call()
        size = os.stat(j.path).st_size
        # The last thing done to the journal before the append returned: an fsync of all its bytes.
        assert events and events[-1] == ("fsync", size), events
    j.close()


# -- a complete last line without its newline ---------------------------------------------------------------------


def test_a_complete_last_line_without_newline_is_kept_and_the_next_append_starts_a_fresh_line(tmp_path):
    store, j, rng = _recorded(tmp_path)
    path, sid = Path(j.path), j.session_id
    j.close()
    whole = path.read_bytes()
    path.write_bytes(whole[:-1])  # the crash hit between the document and its newline
    c = read_journal(path)
    assert c.needs_newline and not c.torn_lines and [d.seq for d in c.measurements] == [1, 2, 3]
    with store.open_journal(sid) as j2:
        j2.append_measurement(pose_index=3, **fake_measurement(rng))
    data = path.read_bytes()
    assert data.startswith(whole)  # the newline was added; no earlier byte changed
    c = read_journal(path)
    assert [d.seq for d in c.measurements] == [1, 2, 3, 4]
    assert not c.corrupt_lines and not c.torn_lines and not c.needs_newline
    assert [d["type"] for d in c.documents][-2:] == ["repair", "measurement"]
    assert store.seal(sid).rows_added == 4


# -- verify: folders inside a version -----------------------------------------------------------------------------


@pytest.fixture
def sealed(tmp_path):
    store, j, _ = _recorded(tmp_path)
    j.close()
    ref = store.seal(j.session_id).ref
    vdir = store.version_dir(ref)
    os.chmod(vdir, 0o755)
    return store, ref, vdir


def test_verify_reports_an_extra_folder_inside_a_version(sealed):
    store, ref, vdir = sealed
    assert store.verify(ref).ok
    (vdir / "old-data").mkdir()
    (vdir / "old-data" / "measurements.parquet").write_bytes(b"x")
    problems = store.verify(ref).problems
    assert problems == ["old-data: extra directory not listed in the manifest"]


def test_verify_accepts_the_fits_folder_but_not_a_fits_file(sealed):
    store, ref, vdir = sealed
    (vdir / "fits").mkdir()
    assert store.verify(ref).ok  # fits/ is the one folder a version may gain after sealing
    (vdir / "fits").rmdir()
    (vdir / "fits").write_text("not a folder")
    assert store.verify(ref).problems == ["fits: extra file not listed in the manifest"]
