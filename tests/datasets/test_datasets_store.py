"""Session store: seal → load round trip, immutability, versions, verify, references, fits, listing."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from datasets_testutil import ROBOT_HASH, TARGETS, fake_measurement, flip_byte, new_journal

from labcal.datasets import (
    DatasetCorrupted,
    DatasetError,
    InvalidId,
    SessionHeader,
    SessionStore,
    UnknownSession,
    UnknownVersion,
    default_root,
    load_version,
    new_fit_id,
    new_session_id,
    parse_ref,
    validate_id,
)


def _record(store, n=5, seed=0, **kw):
    rng = np.random.default_rng(seed)
    j = new_journal(store, **kw)
    written = []
    for i in range(n):
        m = fake_measurement(rng)
        written.append(
            j.append_measurement(
                pose_index=i, **m, split=["train", "val", "test", "", None][i % 5], extra={"temperature": 20 + i}
            )
        )
    return j, written


def test_seal_then_load_equals_what_was_written_bit_for_bit(tmp_path):
    store = SessionStore(tmp_path)
    j, written = _record(store, n=6)
    j.append_measurement(
        pose_index=9, q_commanded=None, q_actual=None, points=None, status="rejected", reason="lost line of sight"
    )
    j.stop("success")
    j.close()
    res = store.seal(j.session_id)
    assert res.created and res.rows_added == 6 and res.ref == f"{j.session_id}@v001"
    ds = load_version(store, res.ref)
    q = np.array([d.q_actual for d in written])
    pts = np.array([d.points for d in written])
    assert ds.q.tobytes() == q.tobytes()
    assert ds.points.tobytes() == pts.tobytes()
    assert ds.table["timestamp"].to_numpy().tobytes() == np.array([d.time for d in written]).tobytes()
    assert ds.spread.tobytes() == np.array([d.spread for d in written]).tobytes()
    assert ds.split.tolist() == ["train", "val", "test", "", "", "train"]
    assert ds.pose.tolist() == [0, 1, 2, 3, 4, 5]
    assert ds.table["x_temperature"].tolist() == [20, 21, 22, 23, 24, 25]
    assert np.array_equal(ds.targets, TARGETS) and ds.frame == "base"
    m = ds.manifest
    assert m["row_count"] == 6 and m["source"] == "journal" and m["parent"] is None
    assert m["session"]["robot"] == {"name": "ur10", "hash": ROBOT_HASH, "n_joints": 6}
    assert m["units"]["q1"] == "rad" and m["units"]["t3_z"] == "m" and m["units"]["x_temperature"] == "degC"
    assert m["session"]["plan"]["length"] == 10 and m["session"]["tracker"]["driver"] == "sim"


def test_versions_are_read_only_and_never_rewritten(tmp_path):
    store = SessionStore(tmp_path)
    j, _ = _record(store, n=3)
    sid = j.session_id
    ref1 = store.seal(sid).ref
    v1 = store.version_dir(ref1)
    for p in (v1 / "measurements.parquet", v1 / "manifest.json"):
        assert stat.S_IMODE(p.stat().st_mode) == 0o444
    before = {p.name: p.read_bytes() for p in v1.iterdir()}
    again = store.seal(sid)
    assert not again.created and again.ref == ref1 and "nothing new" in again.message
    assert store.versions(sid) == [1]
    rng = np.random.default_rng(9)
    j.append_measurement(pose_index=3, **fake_measurement(rng))
    j.append_measurement(pose_index=4, q_commanded=None, q_actual=None, points=None, status="rejected", reason="x")
    j.close()
    res = store.seal(sid)
    assert res.ref == f"{sid}@v002" and res.rows_added == 1
    assert {p.name: p.read_bytes() for p in v1.iterdir()} == before
    d1, d2 = store.load(ref1), store.load(sid)
    assert d2.manifest["parent"] == "v001" and len(d2) == len(d1) + 1
    pd.testing.assert_frame_equal(d2.table.iloc[: len(d1)], d1.table)
    assert not store.seal(sid).created  # only a rejected one is newer: nothing to add


def test_nothing_to_seal_in_an_empty_journal(tmp_path):
    store = SessionStore(tmp_path)
    with new_journal(store) as j:
        res = store.seal(j.session_id)
    assert res.ref is None and not res.created and store.versions(j.session_id) == []
    with pytest.raises(UnknownVersion, match="no versions yet"):
        store.load(j.session_id)


@pytest.fixture
def sealed(tmp_path):
    store = SessionStore(tmp_path)
    j, _ = _record(store, n=4)
    j.close()
    ref = store.seal(j.session_id).ref
    return store, ref, store.version_dir(ref)


def test_verify_passes_on_intact_version(sealed):
    store, ref, _ = sealed
    report = store.verify(ref)
    assert report.ok and "measurements.parquet" in report.checked and "manifest.json" in report.checked


@pytest.mark.parametrize("offset", [100, -50])
def test_verify_catches_a_flipped_byte_in_parquet(sealed, offset):
    store, ref, vdir = sealed
    p = vdir / "measurements.parquet"
    expected = json.loads((vdir / "manifest.json").read_text())["files"]["measurements.parquet"]["sha256"]
    flip_byte(p, offset % p.stat().st_size)
    report = store.verify(ref)
    assert not report.ok
    assert len(report.problems) == 1 and report.problems[0].startswith("measurements.parquet: sha256 mismatch")
    assert expected in report.problems[0]
    with pytest.raises(DatasetCorrupted, match=r"measurements\.parquet"):
        store.load(ref)


@pytest.mark.parametrize("where", ["value", "key", "whitespace", "hash"])
def test_verify_catches_a_flipped_byte_in_manifest(sealed, where):
    store, ref, vdir = sealed
    p = vdir / "manifest.json"
    text = p.read_bytes()
    offset = {
        "value": text.index(b'"row_count": 4') + len(b'"row_count": '),
        "key": text.index(b'"row_count"') + 2,
        "whitespace": text.index(b"\n  "),
        "hash": text.index(b'"manifest_sha256": "') + 25,
    }[where]
    flip_byte(p, offset)
    report = store.verify(ref)
    assert report.problems and all(pr.startswith("manifest.json") for pr in report.problems)
    with pytest.raises(DatasetCorrupted, match=r"manifest\.json"):
        load_version(store, ref)


def test_verify_reports_missing_and_extra_files(sealed):
    store, ref, vdir = sealed
    os.chmod(vdir, 0o755)
    (vdir / "measurements.parquet").unlink()
    (vdir / "notes.txt").write_text("hi")
    problems = store.verify(ref).problems
    assert any(p.startswith("measurements.parquet: missing") for p in problems)
    assert any(p.startswith("notes.txt: extra file") for p in problems)
    with pytest.raises(DatasetCorrupted):
        store.load(ref)


def test_verify_catches_an_edited_journal_prefix(sealed):
    store, ref, vdir = sealed
    jpath = vdir.parent / "journal.jsonl"
    data = bytearray(jpath.read_bytes())
    i = data.index(b'"samples":5')
    data[i + 10] = ord("6")
    jpath.write_bytes(bytes(data))
    sid = ref.split("@")[0]
    assert any(p.startswith("journal.jsonl: the first") for p in store.check_session(sid).problems)
    # the version stands on its own manifest: the edited journal does not make it unusable
    assert store.verify(ref).ok and len(store.load(ref)) > 0


def test_references_and_ids(sealed):
    store, ref, _ = sealed
    sid = ref.split("@")[0]
    assert parse_ref(f"{sid}@v1") == parse_ref(f"{sid}@v001") == parse_ref(ref)
    assert parse_ref(sid).version is None and str(store.resolve(sid)) == f"{sid}@v001"
    with pytest.raises(UnknownVersion, match=r"v007.*available: v001"):
        store.resolve(f"{sid}@v7")
    with pytest.raises(UnknownSession, match="no session 'nope'.*" + sid):
        store.load("nope@v1")
    for bad in ["../x", "a/b", "", ".hidden", "a@b@c", "a@x1", "a@v0", "x y"]:
        with pytest.raises(InvalidId):
            parse_ref(bad)
    a = new_session_id("UR10e (lab 2)")
    assert validate_id(a) == a and "-ur10e-lab-2-" in a
    ids = [new_fit_id() for _ in range(20)]
    assert len(set(ids)) == 20 and ids == sorted(ids)


def test_fits_are_stored_under_their_version_with_input_hashes(sealed):
    store, ref, vdir = sealed
    before = {p.name: p.read_bytes() for p in vdir.iterdir() if p.is_file()}
    weights = bytes(range(256))
    fit = store.save_fit(
        ref,
        {"model.npz": weights, "metrics.json": '{"mean_mm": 0.4}'},
        {"method": "local-poe", "seed": 7, "metrics": {"mean": 4e-4}},
    )
    assert fit.path.parent == vdir / "fits"
    assert fit.inputs[0]["ref"] == ref
    assert fit.inputs[0]["manifest_sha256"] == store.manifest(ref)["manifest_sha256"]
    assert (
        fit.inputs[0]["files"]["measurements.parquet"] == store.manifest(ref)["files"]["measurements.parquet"]["sha256"]
    )
    assert store.verify(ref).ok  # the fits folder is outside the version's hashes
    assert {p.name: p.read_bytes() for p in vdir.iterdir() if p.is_file()} == before
    loaded = store.load_fit(ref, fit.fit_id)
    assert loaded.read("model.npz") == weights and json.loads(loaded.read("metrics.json")) == {"mean_mm": 0.4}
    assert loaded.metadata["seed"] == 7 and store.find_fit(fit.fit_id).path == fit.path
    fit2 = store.save_fit(ref, {"a.bin": b"1"}, {"method": "ann"})
    assert [f.fit_id for f in store.list_fits(ref)] == sorted([fit.fit_id, fit2.fit_id])
    flip_byte(fit.path / "model.npz", 3)
    with pytest.raises(DatasetCorrupted, match=r"model\.npz"):
        store.load_fit(ref, fit.fit_id)
    with pytest.raises(UnknownVersion, match="no fit"):
        store.load_fit(ref, "20990101-000000-000000-abcdef")


def test_pooled_fit_records_every_input(tmp_path):
    store = SessionStore(tmp_path)
    j1, _ = _record(store, n=2, seed=1, session_id="a")
    j2, _ = _record(store, n=3, seed=2, session_id="b")
    j1.close()
    j2.close()
    r1, r2 = store.seal("a").ref, store.seal("b").ref
    fit = store.save_fit([r1, r2], {}, {"method": "hybrid"})
    assert fit.ref == r1 and [i["ref"] for i in fit.inputs] == [r1, r2]
    assert [i["row_count"] for i in fit.inputs] == [2, 3]
    assert store.list_fits(r2) == []


def test_fit_refuses_a_corrupted_input(sealed):
    store, ref, vdir = sealed
    flip_byte(vdir / "measurements.parquet", 200)
    with pytest.raises(DatasetCorrupted):
        store.save_fit(ref, {"m": b""}, {})
    assert not (vdir / "fits").exists() or not any((vdir / "fits").iterdir())


def test_list_and_show(tmp_path):
    store = SessionStore(tmp_path)
    j, _ = _record(store, n=2, session_id="s1")
    j.stop("aborted", "operator")
    j.close()
    store.seal("s1")
    with new_journal(store, session_id="s2") as j2:
        j2.pause("protective stop")
    (tmp_path / "README.md").write_text("not a session")
    (tmp_path / ".tmp-session-x-1234").mkdir()
    infos = {i.session_id: i for i in store.list_sessions()}
    assert set(infos) == {"s1", "s2"}
    assert infos["s1"].status == "aborted" and infos["s1"].rows == 2 and infos["s1"].measurements == 2
    assert [v.name for v in infos["s1"].versions] == ["v001"] and infos["s1"].robot["name"] == "ur10"
    assert infos["s2"].status == "paused" and infos["s2"].versions == []


def test_default_root_follows_env(tmp_path, monkeypatch):
    monkeypatch.setenv("LABCAL_STORE", str(tmp_path / "elsewhere"))
    assert SessionStore().root == tmp_path / "elsewhere"
    monkeypatch.delenv("LABCAL_STORE")
    monkeypatch.chdir(tmp_path)
    assert default_root() == Path.cwd() / "sessions"


def test_a_failed_version_write_leaves_nothing(tmp_path, monkeypatch):
    store = SessionStore(tmp_path)
    j, _ = _record(store, n=2)
    j.close()
    import labcal.datasets.store as store_mod

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(store_mod, "publish_dir", boom)
    # One line naming the store and the operation (the CLI prints it without a traceback), the OS error chained.
    with pytest.raises(DatasetError, match=r"cannot seal the journal into a version in the session store .*disk full"):
        store.seal(j.session_id)
    assert sorted(p.name for p in store.session_dir(j.session_id).iterdir()) == ["journal.jsonl"]


def test_a_refused_session_leaves_no_folder(tmp_path):
    store = SessionStore(tmp_path)
    with pytest.raises(Exception, match="coincide"):
        store.create_session(
            SessionHeader.of("r", ROBOT_HASH, 6, targets=np.zeros((3, 3)), frame="base", session_id="bad")
        )
    assert store.session_ids() == [] and not (tmp_path / "bad").exists()


def test_verify_catches_a_version_copied_under_another_name(sealed):
    import shutil

    store, ref, vdir = sealed
    shutil.copytree(vdir, vdir.parent / "v002")
    problems = store.verify(ref.split("@")[0] + "@v2").problems
    assert any("belongs to" in p for p in problems)
