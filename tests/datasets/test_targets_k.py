"""1..k targets and empty cells (issue 15.1): import, stored versions, journals, and old sessions unchanged."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from datasets_testutil import ROBOT_HASH, fake_measurement, new_journal

from labcal.cli.ops.common import load_observations
from labcal.datasets import (
    DatasetError,
    ImportFormatError,
    ImportOptions,
    JournalError,
    MeasurementDoc,
    SessionStore,
    StartDoc,
    StopDoc,
    TargetsError,
    import_mapped,
    import_targets_csv,
    load_targets,
    read_journal,
    target_columns,
    target_layout,
)
from labcal.datasets.schema import normalize_table
from labcal.robots import load

OLD = Path(__file__).parent / "data" / "old-three-targets"  # recorded and sealed by 65c384c (before 1..k targets)
N = 6


def _points_csv(path: Path, q: np.ndarray, points: np.ndarray, *, split: bool = True) -> Path:
    """A targets CSV (m from points (k, m, 3)); NaN cells are written empty."""
    m = points.shape[1]
    df = pd.DataFrame(q, columns=[f"q{j + 1}" for j in range(q.shape[1])])
    for i, name in enumerate(target_columns(m)):
        df[name] = points[:, i // 3, i % 3]
    if split:
        df["split"] = ""
    df.to_csv(path, index=False, float_format="%.17g", na_rep="")
    return path


def _robot_points(spec, targets: np.ndarray, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """k joint rows inside the limits and the nominal model's base-frame points of ``targets`` (m, 3) there."""
    rng = np.random.default_rng(seed)
    lim = spec.model.limits
    q = rng.uniform(0.5 * lim[:, 0], 0.5 * lim[:, 1], size=(k, spec.model.n))
    return q, spec.model.target_points(q, targets)


# ----------------------------------------------------------------------------------------------- old sessions


def _old_store(tmp_path: Path) -> SessionStore:
    shutil.copytree(OLD, tmp_path / "store" / OLD.name)
    return SessionStore(tmp_path / "store")


def test_an_old_three_target_version_loads_bit_for_bit(tmp_path):
    store = _old_store(tmp_path)
    ds = store.load(f"{OLD.name}@v1")
    # The table is the parquet file as written by the old code, column for column, byte for byte.
    raw = pq.read_table(io.BytesIO((OLD / "v001" / "measurements.parquet").read_bytes())).to_pandas()
    pd.testing.assert_frame_equal(ds.table, raw, check_exact=True)
    cols = raw[[f"t{i}_{a}" for i in (1, 2, 3) for a in "xyz"]].to_numpy()
    assert ds.points.shape == (len(raw), 3, 3) and ds.points.tobytes() == cols.reshape(-1, 3, 3).tobytes()
    assert ds.n_targets == 3 and ds.seen.all() and ds.spread.shape == (len(raw), 3)
    obs, _ = load_observations(store, [ds.ref])
    assert obs.points.tobytes() == ds.points.tobytes() and obs.targets.tobytes() == ds.targets.tobytes()


def test_an_old_journal_reads_as_typed_documents_and_seals_to_the_same_bytes(tmp_path):
    docs = [json.loads(line) for line in (OLD / "journal.jsonl").read_text().splitlines()]
    contents = read_journal(OLD / "journal.jsonl")
    assert isinstance(contents.start, StartDoc) and contents.start.to_json() == docs[0]
    assert [m.to_json() for m in contents.measurements] == [d for d in docs if d["type"] == "measurement"]
    assert isinstance(contents.stop, StopDoc) and contents.stop.to_json() == docs[-1]
    assert contents.start.n_targets == 3 and contents.measurements[0].points_array().shape == (3, 3)
    # Sealing the old journal again with today's code writes the very same measurements file.
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    shutil.copy(OLD / "journal.jsonl", fresh / "journal.jsonl")
    ref = SessionStore(tmp_path).seal("fresh").ref
    new = (tmp_path / "fresh" / "v001" / "measurements.parquet").read_bytes()
    assert new == (OLD / "v001" / "measurements.parquet").read_bytes()
    assert (
        SessionStore(tmp_path).manifest(ref)["columns"]
        == json.loads((OLD / "v001" / "manifest.json").read_text())["columns"]
    )


# ----------------------------------------------------------------------------------------------------- import


def test_one_target_csv_imports_into_a_version_and_loads_as_observations(tmp_path):
    spec = load("ur10")
    targets = np.array([[0.0, 0.0, 0.045]])
    q, pts = _robot_points(spec, targets, 30, seed=1)
    path = _points_csv(tmp_path / "one.csv", q, pts)
    tfile = tmp_path / "one.toml"
    tfile.write_text('unit = "mm"\npoints = [[0, 0, 45]]\n')
    np.testing.assert_array_equal(load_targets(tfile), targets)
    store = SessionStore(tmp_path / "s")
    ref = import_targets_csv(store, path, spec.name, spec.hash, N, load_targets(tfile), ImportOptions(robot=spec))
    ds = store.load(ref)
    assert list(ds.table.columns[:10]) == ["pose", *[f"q{j}" for j in range(1, 7)], "t1_x", "t1_y", "t1_z"]
    assert "t2_x" not in ds.table.columns and ds.n_targets == 1 and ds.points.shape == (30, 1, 3)
    np.testing.assert_array_equal(ds.points, pts)
    assert ds.manifest["units"]["t1_x"] == "m"
    obs, _, got = load_observations(store, [ref], with_spec=True)
    assert got.hash == spec.hash and obs.points.shape == (30, 1, 3) and obs.targets.shape == (1, 3)
    np.testing.assert_array_equal(obs.points, pts)
    assert obs.seen.all()


def test_three_targets_with_30_percent_of_cells_empty(tmp_path):
    spec = load("ur10")
    targets = np.array([[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03]])
    q, pts = _robot_points(spec, targets, 40, seed=2)
    rng = np.random.default_rng(3)
    lost = rng.random((40, 3)) < 0.3
    lost[lost.all(axis=1), 0] = False  # every row keeps at least one target
    pts[lost] = np.nan
    path = _points_csv(tmp_path / "holes.csv", q, pts)
    assert ",,," in path.read_text()  # empty cells, not "nan"
    store = SessionStore(tmp_path / "s")
    ref = import_targets_csv(store, path, spec.name, spec.hash, N, targets, robot=spec)
    ds = store.load(ref)
    np.testing.assert_array_equal(ds.seen, ~lost)
    np.testing.assert_array_equal(ds.points, pts)  # NaN where lost, the numbers elsewhere, bit for bit
    assert 0.2 < lost.mean() < 0.4
    obs, _ = load_observations(store, [ref])
    np.testing.assert_array_equal(obs.seen, ~lost)
    # Appending the same file again makes v002 with all rows of v001 plus the new ones (NaN survives the round trip).
    ref2 = import_targets_csv(store, path, spec.name, spec.hash, N, targets, robot=spec, session_id=ref.split("@")[0],
                              allow=["duplicates"])  # fmt: skip
    np.testing.assert_array_equal(store.load(ref2).seen, np.concatenate([~lost, ~lost]))


def _bad_rows(tmp_path, edit) -> Path:
    targets = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.08, 0.02]])
    q = np.tile(np.linspace(-1, 1, 6), (5, 1)) + np.arange(5)[:, None] * 0.1
    pts = np.broadcast_to(targets, (5, 3, 3)).copy()
    edit(pts)
    return _points_csv(tmp_path / "bad.csv", q, pts)


def test_a_partly_empty_target_is_an_error_naming_row_line_and_column(tmp_path):
    path = _bad_rows(tmp_path, lambda p: p.__setitem__((2, 1, 1), np.nan))  # row 3: t2_y empty, t2_x/t2_z given
    with pytest.raises(ImportFormatError, match=r"target t2 is partly empty \(t2_x, t2_z given, t2_y empty\)") as e:
        import_targets_csv(tmp_path / "s", path, "r", ROBOT_HASH, N, np.eye(3) * 0.1)
    assert (e.value.row, e.value.line, e.value.column) == (3, 4, "t2_y")
    assert "leave all three empty if the target was not seen" in str(e.value)
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())


def test_a_row_with_no_target_seen_is_an_error_naming_the_row(tmp_path):
    path = _bad_rows(tmp_path, lambda p: p.__setitem__((slice(3, 5),), np.nan))  # rows 4 and 5 see nothing
    with pytest.raises(ImportFormatError, match="no target seen") as e:
        import_targets_csv(tmp_path / "s", path, "r", ROBOT_HASH, N, np.eye(3) * 0.1)
    assert (e.value.row, e.value.line) == (4, 5) and "1 more row(s) like it" in str(e.value)
    assert "data row 4 (line 5 of the file)" in str(e.value)


def test_nan_text_is_still_an_error_and_extra_target_columns_are_named(tmp_path):
    path = _bad_rows(tmp_path, lambda p: None)
    text = path.read_text().splitlines()
    head, row = text[0].split(","), text[1].split(",")
    row[head.index("t1_x")] = "nan"
    (tmp_path / "nan.csv").write_text("\n".join([text[0], ",".join(row), *text[2:]]))
    with pytest.raises(ImportFormatError, match="leave the cell empty for a target not seen") as e:
        import_targets_csv(tmp_path / "s", tmp_path / "nan.csv", "r", ROBOT_HASH, N, np.eye(3) * 0.1)
    assert e.value.column == "t1_x"
    two = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    with pytest.raises(ImportFormatError, match=r"target column\(s\) \['t3_x', 't3_y', 't3_z'\].* 2 target"):
        import_targets_csv(tmp_path / "s", path, "r", ROBOT_HASH, N, two)


def test_targets_files_with_one_to_k_points(tmp_path):
    p = tmp_path / "t.toml"
    p.write_text('unit = "mm"\npoints = [[0, 0, 0], [100, 0, 0], [0, 100, 0], [50, 50, 30]]\n')
    assert load_targets(p).shape == (4, 3)
    p.write_text('unit = "m"\npoints = [[0, 0, 0], [0, 0, 0.1]]\n')
    assert load_targets(p).shape == (2, 3)
    p.write_text('unit = "m"\npoints = [[0, 0, 0], [0.1, 0, 0], [0, 0, 0.0002], [0, 0.1, 0]]\n')
    with pytest.raises(TargetsError, match="t1 and t3 coincide"):
        load_targets(p)
    # A bar of reflectors is a set-up, not a typo: accepted, and named for what it cannot measure.
    p.write_text('unit = "mm"\npoints = [[0, 0, 0], [100, 0, 0], [200, 0.1, 0]]\n')
    bar = load_targets(p)
    assert [target_layout(t) for t in (bar[:1], bar[:2], bar, np.eye(3), np.vstack([np.eye(3), np.zeros(3)]))] == [
        "point", "line", "line", "plane", "solid"
    ]  # fmt: skip


def test_the_import_notes_what_one_target_or_a_line_of_targets_cannot_measure(tmp_path):
    spec = load("ur10")
    for targets, note in ((np.array([[0.0, 0.0, 0.045]]), "one target"), (np.array([[0.0, 0.0, 0.0],
                          [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]]), "lie on one line")):  # fmt: skip
        q, pts = _robot_points(spec, targets, 20, seed=6)
        path = _points_csv(tmp_path / f"{len(targets)}.csv", q, pts)
        ref = import_targets_csv(tmp_path / "s", path, spec.name, spec.hash, N, targets, robot=spec)
        notes = SessionStore(tmp_path / "s").manifest(ref)["provenance"]["import"]["checks"]["notes"]
        assert any(note in n for n in notes), notes


# ------------------------------------------------------------------------------------------------- the table


def test_normalize_table_names_the_row_and_column_of_a_partly_empty_target():
    q = np.zeros((3, 2))
    cols = {"pose": [0, 1, 2], "q1": q[:, 0], "q2": q[:, 1], "split": ["", "", ""]}
    t = {"t1_x": [0.0, 1.0, np.nan], "t1_y": [0.0, 1.0, np.nan], "t1_z": [0.0, np.nan, np.nan]}
    t2 = {"t2_x": [1.0, 1.0, 1.0], "t2_y": [1.0, 1.0, 1.0], "t2_z": [1.0, 1.0, 1.0]}
    with pytest.raises(DatasetError, match=r"row 1, column 't1_z': target t1 is partly empty"):
        normalize_table(pd.DataFrame({**cols, **t, **t2}), 2, 2)
    t["t1_z"][1] = 1.0
    table = normalize_table(pd.DataFrame({**cols, **t, **t2}), 2, 2)
    assert list(table.columns) == ["pose", "q1", "q2", *target_columns(2), "split"]
    with pytest.raises(DatasetError, match="row 2: no target seen"):
        normalize_table(pd.DataFrame({**cols, **t, **{k: [1.0, 1.0, np.nan] for k in t2}}), 2, 2)
    with pytest.raises(DatasetError, match=r"target column\(s\) \['t2_x', 't2_y', 't2_z'\] but the session has 1"):
        normalize_table(pd.DataFrame({**cols, **t, **t2}), 2, 1)


# ---------------------------------------------------------------------------------------------------- journal


def test_a_journal_stores_null_for_a_target_not_seen_and_seals_it_as_nan(tmp_path):
    store = SessionStore(tmp_path)
    rng = np.random.default_rng(0)
    targets = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    with new_journal(store, targets=targets) as j:
        good = fake_measurement(rng)
        pts = good["points"][:2].copy()
        pts[1] = np.nan
        doc = j.append_measurement(pose_index=0, **{**good, "points": pts, "spread": np.array([1e-5, np.nan])})
        j.append_measurement(pose_index=1, **{**good, "points": good["points"][:2], "spread": good["spread"][:2]})
        with pytest.raises(JournalError, match="no seen target"):
            j.append_measurement(pose_index=2, **{**good, "points": np.full((2, 3), np.nan), "spread": None})
        half = pts.copy()
        half[0, 2] = np.nan
        with pytest.raises(JournalError, match="non-finite value in target t1"):
            j.append_measurement(pose_index=2, **{**good, "points": half, "spread": None})
        with pytest.raises(JournalError, match=r"shape \(2, 3\)"):
            j.append_measurement(pose_index=2, **good)
        j.stop("success")
    line = json.loads(Path(j.path).read_text().splitlines()[1])
    assert line["points"][1] is None and line["spread"] == [1e-5, None] and line["points"][0] == pts[0].tolist()
    assert MeasurementDoc.from_json(line) == doc
    np.testing.assert_array_equal(doc.points_array(2), pts)
    ds = store.load(store.seal(j.session_id).ref)
    assert ds.points.shape == (2, 2, 3) and ds.seen.tolist() == [[True, False], [True, True]]
    np.testing.assert_array_equal(ds.points[0], pts)
    assert np.isnan(ds.spread[0, 1]) and ds.spread[0, 0] == 1e-5


def test_a_session_refuses_rows_of_another_target_count(tmp_path):
    store = SessionStore(tmp_path)
    with new_journal(store, targets=np.array([[0.0, 0.0, 0.05]])) as j:
        assert j.n_targets == 1
        j.append_measurement(pose_index=0, q_commanded=None, q_actual=np.zeros(6), points=[[1.0, 2.0, 3.0]])
        j.stop("success")
    sid = j.session_id
    ref = store.seal(sid).ref
    assert store.load(ref).points.tolist() == [[[1.0, 2.0, 3.0]]]
    rows = pd.DataFrame({"pose": [0], **{f"q{i}": [0.0] for i in range(1, 7)}, "split": [""],
                         **{c: [0.0] for c in target_columns(3)}})  # fmt: skip
    meta = {**store.session_meta(sid), "targets": np.eye(3).tolist()}
    with pytest.raises(DatasetError, match="targets"):
        store.append_rows(sid, rows, meta, source="test", provenance={})


def test_a_mapping_with_two_target_triples_imports_empty_cells_as_not_seen(tmp_path):
    spec = load("ur10")
    targets = np.array([[0.0, 0.0, 0.045], [0.0, 0.06, 0.045]])
    q, pts = _robot_points(spec, targets, 24, seed=5)
    pts[::3, 1] = np.nan
    df = pd.DataFrame(np.degrees(q), columns=[f"J{j}" for j in range(1, 7)])
    for i, a in enumerate("XYZ"):
        df[f"A{a}"], df[f"B{a}"] = pts[:, 0, i] * 1e3, pts[:, 1, i] * 1e3
    df.to_csv(tmp_path / "lab.csv", sep=";", index=False, float_format="%.17g", na_rep="")
    mapping = tmp_path / "lab.toml"
    mapping.write_text(
        'form = "targets"\nseparator = ";"\njoint_unit = "deg"\nframe = "base"\n'
        'joints = ["J1", "J2", "J3", "J4", "J5", "J6"]\n'
        '[targets]\nunit = "mm"\ncolumns = [["AX", "AY", "AZ"], ["BX", "BY", "BZ"]]\n'
    )
    store = SessionStore(tmp_path / "s")
    ref = import_mapped(store, tmp_path / "lab.csv", mapping, spec.name, spec.hash, N, targets=targets, robot=spec)
    ds = store.load(ref)
    assert ds.n_targets == 2 and ds.seen[:, 1].tolist() == [i % 3 != 0 for i in range(24)]
    np.testing.assert_allclose(ds.points, pts, rtol=1e-12, equal_nan=True)
    with pytest.raises(TargetsError, match="2 target column triple"):
        import_mapped(store, tmp_path / "lab.csv", mapping, spec.name, spec.hash, N, targets=targets[:1])


def test_a_journal_line_with_another_target_count_stops_sealing_with_its_seq(tmp_path):
    store = SessionStore(tmp_path)
    with new_journal(store) as j:
        j.append_measurement(pose_index=0, **fake_measurement(np.random.default_rng(1)))
        j.stop("success")
    path = Path(j.path)
    lines = path.read_text().splitlines()
    doc = json.loads(lines[1])
    doc["points"] = doc["points"][:2]  # edited by hand: two targets in a three-target session
    path.write_text("\n".join([lines[0], json.dumps(doc), *lines[2:]]) + "\n")
    with pytest.raises(DatasetError, match="seq 1 is valid but has 2 target"):
        store.seal(j.session_id)
