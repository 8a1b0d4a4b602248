"""Typed run documents: the header a caller fills in, and the JSON they write and read back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from datasets_testutil import ROBOT_HASH, TARGETS, fake_measurement, new_journal

from labcal.datasets import JournalError, MeasurementDoc, SessionHeader, SessionStore, StartDoc, StopDoc, read_journal
from labcal.robots import load


def test_the_header_becomes_the_start_document(tmp_path):
    spec = load("ur10")
    header = SessionHeader(robot=spec.record(), targets=TARGETS, frame="tracker", plan=[{"q": [0.0] * 6}],
                           tracker={"driver": "ndi"}, metadata={"operator": "A"}, session_id="s1")  # fmt: skip
    with SessionStore(tmp_path).create_session(header) as j:
        start = j.start
    assert isinstance(start, StartDoc) and start.session_id == "s1" and start.n_joints == 6
    assert start.robot == spec.record() and start.robot_hash == spec.hash and start.n_targets == 3
    np.testing.assert_array_equal(start.targets_array(), TARGETS)
    line = json.loads((tmp_path / "s1" / "journal.jsonl").read_text().splitlines()[0])
    assert line == start.to_json() and StartDoc.from_json(line) == start
    assert line["targets_unit"] == "m" and line["tracker"] == {"driver": "ndi"}


def test_a_header_is_checked_before_anything_is_written(tmp_path):
    store = SessionStore(tmp_path)
    cases = {
        "frame must be one of": {"frame": "world"},
        "n_joints must be a positive integer": {"robot": {"name": "r", "hash": ROBOT_HASH, "n_joints": 0}},
        "extra field name": {"extra_units": {"bad key": "m"}},
        "coincide": {"targets": np.zeros((2, 3))},
    }
    for message, change in cases.items():
        fields = {"robot": {"name": "r", "hash": ROBOT_HASH, "n_joints": 6}, "targets": TARGETS, "frame": "base",
                  "session_id": "x", **change}  # fmt: skip
        with pytest.raises(Exception, match=message):
            store.create_session(SessionHeader(**fields))
        assert not (tmp_path / "x").exists()
    with pytest.raises(JournalError, match="disagrees"):
        SessionHeader.of("r", ROBOT_HASH, 6, {"name": "r", "hash": "0" * 64}, targets=TARGETS, frame="base")


def test_measurement_and_stop_documents_round_trip_and_stay_the_old_json(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(7)
    with new_journal(store) as j:
        m = j.append_measurement(pose_index=2, **fake_measurement(rng), split="val", extra={"t": 20.5})
        r = j.append_measurement(pose_index=3, q_commanded=[0.0] * 6, q_actual=None, points=None, status="rejected",
                                 reason="lost")  # fmt: skip
        s = j.stop("success", "done")
    lines = [json.loads(x) for x in (store.session_dir(j.session_id) / "journal.jsonl").read_text().splitlines()]
    # The keys of every document are exactly those written before the documents had types.
    assert set(lines[1]) == {"type", "uid", "time", "seq", "pose_index", "q_commanded", "q_actual", "points",
                             "spread", "samples", "status", "reason", "split", "extra", "units"}  # fmt: skip
    assert set(lines[3]) == {"type", "uid", "time", "exit_status", "reason", "num_measurements"}
    assert [MeasurementDoc.from_json(x) for x in lines[1:3]] == [m, r] and StopDoc.from_json(lines[3]) == s
    c = read_journal(store.session_dir(j.session_id) / "journal.jsonl")
    assert c.measurements == [m, r] and c.stop == s and c.status == "success"
    assert m.valid and not r.valid and r.points is None and r.points_array() is None
    assert m.q == m.q_actual and r.q == [0.0] * 6  # no read-back: the commanded joints
    with pytest.raises(JournalError, match="has 3 target"):
        m.points_array(2)
