"""Import of three-target CSVs, 6-DOF probe CSVs and mapped CSVs; targets files; precise errors on bad input."""

from __future__ import annotations

import textwrap

import numpy as np
import pandas as pd
import pytest
from datasets_testutil import ROBOT_HASH, TARGETS
from scipy.spatial.transform import Rotation

from labcal.datasets import (
    DatasetError,
    ImportFormatError,
    MappingError,
    SessionStore,
    TargetsError,
    import_mapped,
    import_probe_csv,
    import_targets_csv,
    load_targets,
    load_version,
)

N = 6


def _targets_frame(k: int, seed: int = 0) -> pd.DataFrame:
    """k rows of random joints and the targets carried by a random rigid motion (so the import's target-distance
    check passes; no robot is given, so the model checks do not run)."""
    rng = np.random.default_rng(seed)
    df = pd.DataFrame(rng.uniform(-3, 3, (k, N)), columns=[f"q{j}" for j in range(1, N + 1)])
    R = Rotation.random(k, random_state=rng).as_matrix()
    pts = (np.einsum("kab,mb->kma", R, TARGETS) + rng.normal(0, 0.7, (k, 1, 3))).reshape(k, 9)
    for c, col in enumerate(f"t{i}_{a}" for i in (1, 2, 3) for a in "xyz"):
        df[col] = pts[:, c]
    return df


def _write(df: pd.DataFrame, path, sep=",", decimal="."):
    # repr-precision text so that parsing gives back the very same floats
    df.to_csv(path, sep=sep, decimal=decimal, index=False, float_format="%.17g")
    return path


def _no_session_left(store: SessionStore) -> bool:
    return not store.root.exists() or not any(store.root.iterdir())


def test_targets_csv_in_si_round_trips_exactly(tmp_path):
    df = _targets_frame(12)
    df["split"] = ["train", "val", "test", ""] * 3
    store = SessionStore(tmp_path / "store")
    ref = import_targets_csv(store, _write(df, tmp_path / "m.csv"), "ur10", ROBOT_HASH, N, TARGETS, frame="base")
    assert ref.endswith("@v001") and "-ur10-" in ref
    ds = load_version(store, ref)
    assert ds.q.tobytes() == df[[f"q{j}" for j in range(1, 7)]].to_numpy().tobytes()
    assert ds.points.tobytes() == df.iloc[:, N : N + 9].to_numpy().reshape(-1, 3, 3).tobytes()
    assert ds.split.tolist() == df["split"].fillna("").tolist()
    assert np.array_equal(ds.targets, TARGETS) and ds.frame == "base" and ds.pose.tolist() == list(range(12))
    prov = ds.manifest["provenance"]["import"]
    assert ds.manifest["source"] == f"import:{prov['sha256']}" and prov["file"] == "m.csv"


def test_targets_csv_units_are_converted_at_the_edge(tmp_path):
    df = _targets_frame(12)
    raw = df.copy()
    raw[[f"q{j}" for j in range(1, 7)]] = np.degrees(df[[f"q{j}" for j in range(1, 7)]])
    raw.iloc[:, N:] = df.iloc[:, N:] * 1000
    path = _write(raw, tmp_path / "mm.csv", sep=";", decimal=",")
    ref = import_targets_csv(
        tmp_path / "s",
        path,
        "ur10",
        ROBOT_HASH,
        N,
        TARGETS,
        length_unit="mm",
        angle_unit="deg",
        frame="tracker",
        separator=";",
        decimal=",",
    )
    ds = load_version(tmp_path / "s", ref)
    np.testing.assert_allclose(ds.q, df.iloc[:, :N], rtol=1e-14)
    np.testing.assert_allclose(ds.points.reshape(-1, 9), df.iloc[:, N:], rtol=1e-14, atol=1e-17)
    assert ds.frame == "tracker"


@pytest.mark.parametrize(
    ("rotation", "sequence", "unit"), [("rotvec", None, "rad"), ("euler", "XYZ", "deg"), ("euler", "zyx", "rad")]
)
def test_probe_csv_becomes_three_virtual_targets(tmp_path, rotation, sequence, unit):
    rng = np.random.default_rng(3)
    k = 12
    r = Rotation.random(k, random_state=rng)
    t = rng.uniform(-1, 1, (k, 3))
    angles = r.as_rotvec() if rotation == "rotvec" else r.as_euler(sequence)
    if unit == "deg":
        angles = np.degrees(angles)
    q = rng.uniform(-3, 3, (k, N))
    df = pd.DataFrame(q, columns=[f"q{j}" for j in range(1, N + 1)])
    df[["x", "y", "z"]] = t * 1000
    df[["rx", "ry", "rz"]] = angles
    offsets = np.array([[0.01, 0.0, 0.05], [0.12, 0.0, 0.05], [0.0, 0.09, 0.06]])
    ref = import_probe_csv(
        tmp_path / "s",
        _write(df, tmp_path / "p.csv"),
        "ur10",
        ROBOT_HASH,
        N,
        length_unit="mm",
        angle_unit="rad",
        rotation_unit=unit,
        rotation=rotation,
        euler_sequence=sequence,
        offsets=offsets,
        frame="base",
    )
    ds = load_version(tmp_path / "s", ref)
    expected = np.stack([r.apply(v) + t for v in offsets], axis=1)
    np.testing.assert_allclose(ds.points, expected, atol=1e-12)
    assert np.array_equal(ds.targets, offsets)  # the offsets are the session's targets


def test_probe_default_offsets(tmp_path):
    df = pd.DataFrame(
        [[0.0] * N + [1.0, 2.0, 3.0, 0.0, 0.0, np.pi / 2]],
        columns=[*(f"q{j}" for j in range(1, N + 1)), "x", "y", "z", "rx", "ry", "rz"],
    )
    path = _write(df, tmp_path / "p.csv")
    ds = load_version(tmp_path / "s", import_probe_csv(tmp_path / "s", path, "r", ROBOT_HASH, N, allow=["few-poses"]))
    np.testing.assert_allclose(ds.points[0], [[1, 2, 3], [1, 2.1, 3], [0.9, 2, 3]], atol=1e-12)


def test_generic_mapping_with_renamed_columns_extras_and_split(tmp_path):
    df = _targets_frame(6, seed=4)
    raw = pd.DataFrame({"J1": df.q1, "J2": df.q2, "J3": df.q3})
    for i in (1, 2, 3):
        for a in "xyz":
            raw[f"P{i}{a.upper()}"] = df[f"t{i}_{a}"] * 1000
    raw["Temp"] = [20.5, 21, "", 22, 22.5, 23]
    raw["note"] = list("abcdef")
    raw["set"] = ["train", "train", "val", "val", "test", "test"]
    path = _write(raw, tmp_path / "gen.txt", sep="\t")
    mapping = tmp_path / "gen.toml"
    mapping.write_text(
        textwrap.dedent("""
        form = "targets"
        separator = "\\t"
        frame = "tracker"
        joints = ["J1", "J2", "J3"]
        joint_unit = "rad"
        split_column = "set"
        [targets]
        columns = [["P1X", "P1Y", "P1Z"], ["P2X", "P2Y", "P2Z"], ["P3X", "P3Y", "P3Z"]]
        unit = "mm"
        [tracker]
        model = "some tracker"
        [[extra]]
        column = "Temp"
        name = "temperature"
        unit = "degC"
        [[extra]]
        column = "note"
        type = "str"
    """)
    )
    ref = import_mapped(tmp_path / "s", path, mapping, "scara", ROBOT_HASH, 3, targets=TARGETS)
    ds = load_version(tmp_path / "s", ref)
    np.testing.assert_allclose(ds.points.reshape(-1, 9), df.iloc[:, N:], rtol=1e-14, atol=1e-17)
    assert ds.q.tobytes() == df[["q1", "q2", "q3"]].to_numpy().tobytes()
    assert ds.split.tolist() == raw["set"].tolist()
    temps = ds.table["x_temperature"].to_numpy()
    assert temps[[0, 1, 3]].tolist() == [20.5, 21.0, 22.0] and np.isnan(temps[2])
    assert ds.table["x_note"].tolist() == list("abcdef")
    assert ds.manifest["session"]["tracker"] == {"model": "some tracker"}
    assert ds.manifest["provenance"]["import"]["options"]["mapping_content"]["joints"] == ["J1", "J2", "J3"]


def test_import_into_an_existing_session_makes_a_child_version(tmp_path):
    store = SessionStore(tmp_path / "s")
    a, b = _targets_frame(12, seed=1), _targets_frame(3, seed=2)  # 3 new rows: enough poses with the 12 there
    r1 = import_targets_csv(store, _write(a, tmp_path / "a.csv"), "ur10", ROBOT_HASH, N, TARGETS, session_id="lab")
    r2 = import_targets_csv(store, _write(b, tmp_path / "b.csv"), "ur10", ROBOT_HASH, N, TARGETS, session_id="lab")
    assert (r1, r2) == ("lab@v001", "lab@v002")
    d1, d2 = store.load(r1), store.load(r2)
    assert d2.manifest["parent"] == "v001" and len(d2) == 15 and d2.pose.tolist() == list(range(15))
    pd.testing.assert_frame_equal(d2.table.iloc[:12], d1.table)
    with pytest.raises(DatasetError, match="robot"):
        import_targets_csv(store, tmp_path / "b.csv", "ur10", "0" * 64, N, TARGETS, session_id="lab")
    with pytest.raises(DatasetError, match="targets"):
        import_targets_csv(store, tmp_path / "b.csv", "ur10", ROBOT_HASH, N, TARGETS * 2, session_id="lab")
    assert store.versions("lab") == [1, 2]


def _bad(tmp_path, edit):
    df = _targets_frame(5).astype(object)
    df["split"] = ["train"] * 5
    df = edit(df)
    return _write(df, tmp_path / "bad.csv")


@pytest.mark.parametrize(
    ("edit", "row", "column", "message"),
    [
        (lambda d: d.drop(columns=["t2_y"]), None, None, "missing target column"),
        (lambda d: d.assign(q4=d.q4.where(d.index != 2, "abc")), 3, "q4", "non-numeric value 'abc'"),
        (lambda d: d.assign(t1_z=d.t1_z.where(d.index != 4, "nan")), 5, "t1_z", "non-finite"),
        (lambda d: d.assign(q1=d.q1.where(d.index != 0, "")), 1, "q1", "missing value"),
        (lambda d: d.assign(q7=0.0), None, None, "n=6"),
        (lambda d: d.drop(columns=["q6"]), None, None, "missing joint column"),
        (lambda d: d.assign(split=d.split.where(d.index != 1, "validation")), 2, "split", "'validation'"),
    ],
)
def test_bad_files_name_row_and_column_and_write_nothing(tmp_path, edit, row, column, message):
    path = _bad(tmp_path, edit)
    store = SessionStore(tmp_path / "store")
    with pytest.raises(ImportFormatError, match=message) as e:
        import_targets_csv(store, path, "ur10", ROBOT_HASH, N, TARGETS)
    assert e.value.row == row and e.value.column == column
    if row is not None:
        assert e.value.line == row + 1 and f"data row {row} (line {row + 1} of the file)" in str(e.value)
    assert _no_session_left(store)


def test_ragged_row_and_blank_lines(tmp_path):
    df = _targets_frame(3)
    text = df.to_csv(index=False, float_format="%.17g").splitlines()
    good = tmp_path / "blank.csv"
    good.write_text("\n".join([text[0], text[1], "", text[2], text[3], "", ""]))
    bad = tmp_path / "ragged.csv"
    bad.write_text("\n".join([text[0], text[1], text[2] + ",1", text[3]]))
    store = SessionStore(tmp_path / "s")
    assert len(store.load(import_targets_csv(store, good, "r", ROBOT_HASH, N, TARGETS, allow=["few-poses"]))) == 3
    short = tmp_path / "short.csv"
    short.write_text("\n".join([text[0], text[1], "", ",".join(text[2].split(",")[:10])]))
    with pytest.raises(ImportFormatError, match="target t2 is partly empty") as e:
        import_targets_csv(store, short, "r", ROBOT_HASH, N, TARGETS)
    assert (e.value.row, e.value.line, e.value.column) == (2, 4, "t2_y")  # q1..q6, t1_x..t2_x present
    with pytest.raises(ImportFormatError, match="line 3"):
        import_targets_csv(store, bad, "r", ROBOT_HASH, N, TARGETS)


def test_decimal_mark_mismatch_is_reported(tmp_path):
    path = _write(_targets_frame(2), tmp_path / "dot.csv", sep=";")
    with pytest.raises(ImportFormatError, match="decimal mark") as e:
        import_targets_csv(tmp_path / "s", path, "r", ROBOT_HASH, N, TARGETS, separator=";", decimal=",")
    assert e.value.row == 1 and e.value.column == "q1"


def test_import_is_atomic_when_writing_fails(tmp_path, monkeypatch):
    import labcal.datasets.store as store_mod

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(store_mod, "publish_dir", boom)
    store = SessionStore(tmp_path / "s")
    # The OS error surfaces raw or as the store's one-line DatasetError; either way nothing is left behind.
    with pytest.raises((OSError, DatasetError), match="disk full"):
        import_targets_csv(store, _write(_targets_frame(12), tmp_path / "a.csv"), "r", ROBOT_HASH, N, TARGETS)
    assert _no_session_left(store) and store.session_ids() == []


def test_load_targets(tmp_path):
    p = tmp_path / "t.toml"
    p.write_text('unit = "mm"\npoints = [[0, 0, 0], [100, 0, 0], [0, 80, 20]]\n')
    np.testing.assert_allclose(load_targets(p), TARGETS, rtol=1e-15)
    cases = {
        'unit = "m"\npoints = []': "at least 1",
        'unit = "m"\npoints = [[0, 0, 0], [0.0001, 0, 0]]': "t1 and t2 coincide",
        'unit = "m"\npoints = [[0, 0, 0], [0.1, 0, 0], [0, "a", 0]]': "t3 coordinate y",
        'unit = "m"\npoints = [[0, 0, 0], [0, 0, 0], [0, 0.1, 0]]': "t1 and t2 coincide",
        'unit = "cm"\npoints = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]': "unit must be",
        "points = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]": "unit is missing",
        'unit = "m"\npoint = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]': "unknown key 'point' \\(did you mean 'points'\\?\\)",
        'unit = "m"\npoints = [[0, 0, 0], [1, 0, 0], [0, 1]]': r"t3 must be \[x, y, z\]",
        'unit = "m"\npoints = [[0, 0, 0], [1, 0, 0], [0, 1, nan]]': "not a finite number",
        "unit = ": "not valid TOML",
    }
    for text, msg in cases.items():
        p.write_text(text)
        with pytest.raises(TargetsError, match=msg):
            load_targets(p)
    with pytest.raises(TargetsError, match="not found"):
        load_targets(tmp_path / "none.toml")


def test_mapping_errors_are_clear(tmp_path):
    path = tmp_path / "data.csv"
    path.write_text("a\n1\n")
    m = tmp_path / "m.toml"
    cases = {
        'form = "probe"\njoints = ["a"]\nseperator = ";"\n[probe]\n'
        'position=["x","y","z"]\nrotation=["a","b","c"]': r"unknown key 'seperator' \(did you mean 'separator'\?\)",
        'form = "probe"\njoints = ["a"]\n[probe]\nposition=["x","y","z"]\nrotation=["a","b","c"]\n'
        'convention="euler"\neuler_sequence="XyZ"': "Euler sequence",
        'form = "targets"\njoints = ["a"]': r"needs a \[targets\] table",
        'form = "probe"\njoints = ["a"]\n[probe]\nposition=["x","y"]\nrotation=["a","b","c"]': "position must be",
        'form = "pose"\njoints = ["a"]': "form must be",
        'form = "targets"\njoints = ["a"]\n[targets]\ncolumns = [["x", "y"]]': r"entry 1 \(target t1\) must be three",
        'form = "targets"\njoints = ["a"]\n[targets]\ncolumns = [["x", "y", "z"]]\nunit = "cm"': "unit must be one of",
        'form = "targets"\njoints = []\n[targets]\ncolumns = [["x", "y", "z"]]': "joints must list",
    }
    for text, msg in cases.items():
        m.write_text(text)
        with pytest.raises(MappingError, match=msg):
            import_mapped(tmp_path / "s", path, m, "r", ROBOT_HASH, 1)
    with pytest.raises(MappingError, match="ipa-ur10"):
        import_mapped(tmp_path / "s", path, "no-such-mapping", "r", ROBOT_HASH, 1)
    with pytest.raises(ImportFormatError, match="n=5"):
        import_mapped(tmp_path / "s", path, "ipa-ur10", "r", ROBOT_HASH, 5)
