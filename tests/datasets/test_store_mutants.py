"""What the store refuses, one rule per test: ids and version names, rows that do not belong to a session, a manifest
whose bytes or inputs changed, half-seen targets and non-finite spreads, rows and targets files that break the
table's rules. Each was a surviving mutation of benchmarks/mutation.py (the rule dropped, every other test green)."""

from __future__ import annotations

import json
import os

import numpy as np
import pandas as pd
import pytest
from datasets_testutil import ROBOT_HASH, TARGETS, fake_measurement, new_journal

from labcal.datasets import (
    DatasetCorrupted,
    DatasetError,
    InvalidId,
    JournalError,
    SessionStore,
    TargetsError,
    import_targets_csv,
    validate_id,
    validate_targets,
)
from labcal.datasets.ids import version_name
from labcal.datasets.schema import normalize_table, validate_split

N = 6


def _sealed(tmp_path, n=4, seed=0):
    store = SessionStore(tmp_path / "store")
    rng = np.random.default_rng(seed)
    with new_journal(store) as j:
        for i in range(n):
            j.append_measurement(pose_index=i, **fake_measurement(rng))
        sid = j.session_id
    return store, store.seal(sid).ref


# -- ids ------------------------------------------------------------------------------------------------------------


def test_ids_refuse_dot_dot_anywhere_and_more_than_100_characters():
    assert validate_id("a.b-c_d") == "a.b-c_d" and validate_id("a" * 100) == "a" * 100
    for bad in ("a..b", "x..", "a" * 101):
        with pytest.raises(InvalidId):
            validate_id(bad)


def test_version_numbers_start_at_1():
    assert version_name(1) == "v001" and version_name(1000) == "v1000"
    for bad in (0, -1):
        with pytest.raises(InvalidId, match="start at 1"):
            version_name(bad)


# -- rows that do not belong to the session -------------------------------------------------------------------------


def _frame(k: int, targets: np.ndarray, seed: int) -> pd.DataFrame:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    df = pd.DataFrame(rng.uniform(-3, 3, (k, N)), columns=[f"q{j}" for j in range(1, N + 1)])
    R = Rotation.random(k, random_state=rng).as_matrix()
    pts = (np.einsum("kab,mb->kma", R, targets) + rng.normal(0, 0.7, (k, 1, 3))).reshape(k, 9)
    for c, col in enumerate(f"t{i}_{a}" for i in (1, 2, 3) for a in "xyz"):
        df[col] = pts[:, c]
    return df


@pytest.fixture
def session(tmp_path):
    store = SessionStore(tmp_path / "s")
    path = tmp_path / "a.csv"
    _frame(12, TARGETS, 1).to_csv(path, index=False, float_format="%.17g")
    import_targets_csv(store, path, "ur10", ROBOT_HASH, N, TARGETS, session_id="lab", frame="base")
    return store, tmp_path


def test_rows_measured_with_targets_1_cm_elsewhere_are_not_merged(session):
    store, tmp = session
    moved = TARGETS + np.array([0.01, 0.0, 0.0])  # the same triangle (distances agree), mounted 1 cm away
    path = tmp / "b.csv"
    _frame(3, moved, 2).to_csv(path, index=False, float_format="%.17g")
    with pytest.raises(DatasetError, match="has targets"):
        import_targets_csv(store, path, "ur10", ROBOT_HASH, N, moved, session_id="lab", frame="base")
    assert store.versions("lab") == [1]


def test_rows_in_another_frame_are_not_merged(session):
    store, tmp = session
    path = tmp / "b.csv"
    _frame(3, TARGETS, 2).to_csv(path, index=False, float_format="%.17g")
    with pytest.raises(DatasetError, match="points in the base frame, new data in tracker"):
        import_targets_csv(store, path, "ur10", ROBOT_HASH, N, TARGETS, session_id="lab", frame="tracker")
    assert store.versions("lab") == [1]


# -- manifests ------------------------------------------------------------------------------------------------------


def test_a_manifest_reformatted_with_the_same_content_is_reported(tmp_path):
    store, ref = _sealed(tmp_path)
    mpath = store.version_dir(ref) / "manifest.json"
    os.chmod(mpath, 0o644)
    mpath.write_text(json.dumps(json.loads(mpath.read_text()), indent=4))  # same content, other bytes
    assert store.verify(ref).problems == [
        "manifest.json: bytes differ from the canonical form written (formatting was changed)"
    ]


def test_verify_fits_reports_an_input_version_whose_manifest_was_rewritten_consistently(tmp_path):
    from labcal.datasets.store import _dump_sealed

    store, ref = _sealed(tmp_path)
    store.save_fit(ref, {"weights.bin": b"w"}, {"method": "local-poe"})
    assert store.verify_fits(ref).ok
    mpath = store.version_dir(ref) / "manifest.json"
    manifest = json.loads(mpath.read_text())
    manifest["source"] = "edited"  # re-sealed with a valid sha256: the version verifies, the fit read other data
    os.chmod(mpath, 0o644)
    mpath.write_bytes(_dump_sealed(manifest, "manifest_sha256"))
    assert store.verify(ref).ok
    (problem,) = store.verify_fits(ref).problems
    assert f"input {ref} is not the data the fit read" in problem


# -- measurements as documents and as a table ---------------------------------------------------------------------


def test_a_target_with_some_coordinates_nan_is_refused_not_stored_as_unseen(tmp_path):
    store = SessionStore(tmp_path)
    m = fake_measurement(np.random.default_rng(3))
    m["points"][1, 2] = np.nan
    with new_journal(store) as j, pytest.raises(JournalError, match="non-finite value in target t2"):
        j.append_measurement(pose_index=0, **m)


def test_an_infinite_spread_is_refused_even_for_a_target_not_seen(tmp_path):
    store = SessionStore(tmp_path)
    m = fake_measurement(np.random.default_rng(4))
    m["points"][1] = np.nan
    m["spread"][1] = np.inf
    with new_journal(store) as j, pytest.raises(JournalError, match="spread has a non-finite value"):
        j.append_measurement(pose_index=0, **m)
    m["spread"][1] = np.nan  # unknown for the unseen target: stored as null
    with new_journal(store) as j:
        assert j.append_measurement(pose_index=0, **m).spread[1] is None


def _table(k=3) -> pd.DataFrame:
    rng = np.random.default_rng(5)
    df = pd.DataFrame(rng.uniform(-1, 1, (k, N)), columns=[f"q{j}" for j in range(1, N + 1)])
    for i in (1, 2, 3):
        for a in "xyz":
            df[f"t{i}_{a}"] = rng.normal(size=k)
    df["split"] = ""
    df["pose"] = np.arange(k)
    return df


def test_a_negative_pose_index_is_refused():
    df = _table()
    assert normalize_table(df, N, 3)["pose"].tolist() == [0, 1, 2]
    df.loc[1, "pose"] = -1
    with pytest.raises(DatasetError, match="'pose' must hold integers >= 0"):
        normalize_table(df, N, 3)


def test_a_missing_split_is_the_empty_split():
    assert validate_split(None) == "" and validate_split(" test ") == "test"
    with pytest.raises(DatasetError, match="unknown split value 'None'"):
        validate_split("None")


def test_a_targets_file_without_points_is_refused():
    with pytest.raises(TargetsError, match="at least 1 target point"):
        validate_targets([])
    assert validate_targets([[0.0, 0.0, 0.1]]).shape == (1, 3)


def test_load_hashes_the_very_bytes_it_parses(tmp_path, monkeypatch):
    # Another process rewriting the table between load's verify() and its read: the read bytes are hashed again.
    store, ref = _sealed(tmp_path)
    table = store.version_dir(ref) / "measurements.parquet"
    verify = SessionStore.verify

    def verify_then_rewrite(self, r):
        report = verify(self, r)
        os.chmod(table, 0o644)
        data = bytearray(table.read_bytes())
        data[len(data) // 2] ^= 0x01
        table.write_bytes(bytes(data))
        return report

    monkeypatch.setattr(SessionStore, "verify", verify_then_rewrite)
    with pytest.raises(DatasetCorrupted, match="changed while loading"):
        store.load(ref)
