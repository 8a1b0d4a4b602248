"""What the journal and the store refuse to write (batch 2 of benchmarks/mutation.py: each rule could be dropped
with every other test green): an unknown measurement status on reading, a second stop, a negative sample count, an
unsafe session id, a fit id that exists, a caller's file named fit.json."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from datasets_testutil import fake_measurement, new_journal

from labcal.datasets import DatasetError, InvalidId, Journal, JournalError, SessionHeader, SessionStore, read_journal


def test_a_measurement_line_with_an_unknown_status_is_corrupt(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(0)
    with new_journal(store) as j:
        j.append_measurement(pose_index=0, **fake_measurement(rng))
        path = Path(j.path)
    line = json.loads(path.read_bytes().split(b"\n")[1])
    line.update(seq=2, pose_index=1, status="maybe", uid="x")
    with open(path, "ab") as f:
        f.write(json.dumps(line).encode() + b"\n")
    with open(path, "ab") as f:  # a later good line: the bad one is in the middle, not a torn end
        f.write(json.dumps({"type": "pause", "uid": "y", "time": 0.0, "reason": "r"}).encode() + b"\n")
    c = read_journal(path)
    assert c.corrupt_lines == [3] and c.corrupt_reasons[3] == "measurement with unknown status 'maybe'"
    assert [d.seq for d in c.measurements] == [1]


def test_a_stopped_run_cannot_be_stopped_again(tmp_path):
    with new_journal(SessionStore(tmp_path)) as j:
        j.stop("success")
        size = Path(j.path).stat().st_size
        with pytest.raises(JournalError, match="already stopped"):
            j.stop("aborted")
        assert Path(j.path).stat().st_size == size


def test_a_negative_sample_count_is_refused(tmp_path):
    with new_journal(SessionStore(tmp_path)) as j:
        m = fake_measurement(np.random.default_rng(1))
        m["samples"] = -1
        with pytest.raises(JournalError, match="samples must be an integer >= 0"):
            j.append_measurement(pose_index=0, **m)
        assert j.next_seq == 1


def test_a_journal_is_not_created_for_an_unsafe_session_id(tmp_path):
    header = SessionHeader.of("ur10", "5" * 64, 6, targets=[[0, 0, 0]], frame="base")
    with pytest.raises(InvalidId):
        Journal.create(tmp_path / "journal.jsonl", header, session_id="../elsewhere")
    assert not (tmp_path / "journal.jsonl").exists()


@pytest.fixture
def sealed(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(2)
    with new_journal(store) as j:
        for i in range(3):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
        sid = j.session_id
    return store, store.seal(sid).ref


def test_a_fit_id_that_exists_is_refused_and_the_fit_kept(sealed):
    store, ref = sealed
    first = store.save_fit(ref, {"w.bin": b"first"}, {}, fit_id="fit-1")
    with pytest.raises(DatasetError, match="fit 'fit-1' already exists"):
        store.save_fit(ref, {"w.bin": b"second"}, {}, fit_id="fit-1")
    assert store.load_fit(ref, "fit-1").read("w.bin") == b"first" and first.fit_id == "fit-1"


def test_a_callers_file_named_fit_json_is_refused(sealed):
    store, ref = sealed
    with pytest.raises(DatasetError, match=r"fit\.json is reserved"):
        store.save_fit(ref, {"fit.json": b"{}"}, {})
    assert store.list_fits(ref) == []
