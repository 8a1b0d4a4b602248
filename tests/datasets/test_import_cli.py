"""`labcal session import` with its sanity checks: a refused file is one `error: …` block on stderr, exit 2, no
traceback and nothing written; `--allow CHECK` lets it through with a warning and the override on record; the
documented UR10 command imports the real data cleanly."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from datasets_testutil import shared_data_dir
from typer.testing import CliRunner

import scenarios as sc
from labcal.cli.app import app
from labcal.datasets import SessionStore, load_version
from labcal.datasets.sanity import CHECKS

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The good scenario written as a user would (mm, degrees), plus a targets file."""
    root = tmp_path_factory.mktemp("imp")
    scn = sc.good("ur10", 30, seed=7)
    df = pd.DataFrame(np.degrees(scn.q), columns=[f"q{j + 1}" for j in range(6)])
    for i in range(3):
        for a, axis in enumerate("xyz"):
            df[f"t{i + 1}_{axis}"] = scn.points[:, i, a] * 1e3
    df.to_csv(root / "data.csv", index=False, float_format="%.17g")
    pts = ", ".join(f"[{x * 1e3:.17g}, {y * 1e3:.17g}, {z * 1e3:.17g}]" for x, y, z in scn.targets)
    (root / "targets.toml").write_text(f'unit = "mm"\npoints = [{pts}]\n')
    return root, scn


def test_help_shows_every_flag_and_check_with_examples():
    r = invoke("session", "import", "--help")
    assert r.exit_code == 0
    text = " ".join(r.stdout.split())
    for flag in ("--robot", "--targets", "--mapping", "--length-unit", "--angle-unit", "--frame", "--form", "--allow",
                 "--store"):  # fmt: skip
        assert "labcal session import" in text and flag in text.split("Examples:")[1], flag
    for check in CHECKS:
        assert check in text


def test_good_file_imports_cleanly(files, tmp_path):
    root, scn = files
    r = invoke("session", "import", root / "data.csv", "--robot", "ur10", "--targets", root / "targets.toml",
               "--length-unit", "mm", "--angle-unit", "deg", "--store", tmp_path / "s")  # fmt: skip
    assert r.exit_code == 0, r.stderr
    assert r.stderr == ""  # no notes, no warnings
    ds = load_version(SessionStore(tmp_path / "s"), r.stdout.strip().splitlines()[-1])
    np.testing.assert_allclose(ds.points, scn.points, rtol=1e-13, atol=1e-15)
    assert ds.manifest["session"]["robot"]["text"]  # the model travels with the data


def test_a_unit_slip_is_one_error_block_exit_2_nothing_written(files, tmp_path):
    root, _ = files
    r = invoke("session", "import", root / "data.csv", "--robot", "ur10", "--targets", root / "targets.toml",
               "--angle-unit", "deg", "--store", tmp_path / "s")  # fmt: skip
    assert r.exit_code == 2
    assert r.stderr.startswith("error: ") and "Traceback" not in r.stdout + r.stderr
    assert "mm imported as m — pass --length-unit mm" in r.stderr
    assert "--allow target-distances" in r.stderr
    assert r.stdout == ""
    store = tmp_path / "s"
    assert not store.exists() or SessionStore(store).session_ids() == []


def test_allow_lets_it_through_with_a_warning_on_record(files, tmp_path):
    root, _ = files
    args = ["session", "import", root / "data.csv", "--robot", "ur10", "--targets", root / "targets.toml",
            "--angle-unit", "deg", "--store", tmp_path / "s"]  # fmt: skip
    refused = invoke(*args)
    flags = [w for w in refused.stderr.split() if w in CHECKS]
    assert "target-distances" in flags
    allowed = [x for c in sorted(set(flags)) for x in ("--allow", c)]
    partial = invoke(*args, *allowed[:2])  # only the first check: still refused, naming the others
    assert partial.exit_code == 2 or len(set(flags)) == 1
    r = invoke(*args, *allowed)
    assert r.exit_code == 0, r.stderr
    assert "warning: check target-distances failed and was allowed (--allow target-distances)" in r.stderr
    ds = load_version(SessionStore(tmp_path / "s"), r.stdout.strip().splitlines()[-1])
    assert ds.manifest["provenance"]["import"]["options"]["allow"] == sorted(set(flags))


def test_unknown_allow_name(files, tmp_path):
    root, _ = files
    r = invoke("session", "import", root / "data.csv", "--robot", "ur10", "--targets", root / "targets.toml",
               "--allow", "units", "--store", tmp_path / "s")  # fmt: skip
    assert r.exit_code == 2 and r.stderr.startswith("error: ") and "target-distances" in r.stderr


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty file"),
        ("q1,q2,q3,q4,q5,q6,t1_x,t1_y,t1_z,t2_x,t2_y,t2_z,t3_x,t3_y,t3_z\n", "no data rows"),
        ("q1,q2,q3,q4,q5,q6,t1_x,t1_y,t1_z,t2_x,t2_y,t2_z,t3_x,t3_y,t3_z\n" + "0," * 14 + "nan\n", "non-finite"),
        ("q1,q2,q3,q4,q5,q6,t1_x,t1_y,t1_z\n" + "0," * 8 + "0\n", "missing target column"),
        (
            "q1;q2;q3;q4;q5;q6;t1_x;t1_y;t1_z\n" + "0;" * 8 + "0\n",
            "looks ';'-separated: describe the file with a --mapping",
        ),
        (
            "q1,q2,q3,q4,q5,q6,t1_x,t1_y,t1_z,t2_x,t2_y,t2_z,t3_x,t3_y,t3_z\n" + "0," * 15 + "0\n",
            "line 2: a row has more fields than the 15 columns",  # the line the importer found, not dropped
        ),
    ],
)
def test_malformed_files_are_refused_before_the_checks(files, tmp_path, text, message):
    root, _ = files
    (tmp_path / "bad.csv").write_text(text)
    r = invoke("session", "import", tmp_path / "bad.csv", "--robot", "ur10", "--targets", root / "targets.toml",
               "--store", tmp_path / "s")  # fmt: skip
    assert r.exit_code == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr
    assert message in r.stderr, r.stderr


@pytest.mark.skipif(shared_data_dir() is None, reason="the public UR10 data set is not on this machine")
def test_the_documented_ur10_command_imports_the_real_data_cleanly(tmp_path):
    data = shared_data_dir() / "measurements_random_poses.csv"
    r = invoke("session", "import", data, "--robot", "ur10", "--mapping", "ipa-ur10", "--store", tmp_path / "s")
    assert r.exit_code == 0, r.stderr
    assert r.stderr == ""
    ds = load_version(SessionStore(tmp_path / "s"), r.stdout.strip().splitlines()[-1])
    checks = ds.manifest["provenance"]["import"]["checks"]
    assert len(ds) == 2773 and checks["allowed"] == [] and checks["notes"] == []
    assert checks["stats"]["nominal_mean_mm"] < 2.0  # the registered nominal UR10 is within ~1 mm of this robot


def test_unit_flags_with_a_mapping_are_refused_not_ignored(files, tmp_path):
    root, _ = files
    r = invoke("session", "import", root / "data.csv", "--robot", "ur10", "--mapping", "ipa-ur10", "--length-unit",
               "mm", "--store", tmp_path / "s")  # fmt: skip
    assert r.exit_code == 2 and "--length-unit mm cannot be combined with --mapping" in r.stderr


def test_empty_cells_and_a_single_target_through_the_cli(files, tmp_path):
    root, scn = files
    df = pd.read_csv(root / "data.csv")
    holes = df.astype(object)
    for i, row in ((2, 1), (5, 0), (5, 2), (9, 2)):  # whole targets not seen
        for a in "xyz":
            holes.loc[i, f"t{row + 1}_{a}"] = ""
    holes.to_csv(tmp_path / "holes.csv", index=False)
    r = invoke("session", "import", tmp_path / "holes.csv", "--robot", "ur10", "--targets", root / "targets.toml",
               "--length-unit", "mm", "--angle-unit", "deg", "--store", tmp_path / "s")  # fmt: skip
    assert r.exit_code == 0, r.stderr
    ds = load_version(SessionStore(tmp_path / "s"), r.stdout.strip().splitlines()[-1])
    assert (~ds.seen).sum() == 4 and not ds.seen[5, 0] and not ds.seen[5, 2] and ds.seen[5, 1]
    # One target: the t1 columns and a targets file with its point only.
    one = df[[f"q{j + 1}" for j in range(6)] + ["t1_x", "t1_y", "t1_z"]]
    one.to_csv(tmp_path / "one.csv", index=False, float_format="%.17g")
    x, y, z = scn.targets[0] * 1e3
    (tmp_path / "one.toml").write_text(f'unit = "mm"\npoints = [[{x:.17g}, {y:.17g}, {z:.17g}]]\n')
    r = invoke("session", "import", tmp_path / "one.csv", "--robot", "ur10", "--targets", tmp_path / "one.toml",
               "--length-unit", "mm", "--angle-unit", "deg", "--store", tmp_path / "s")  # fmt: skip
    assert r.exit_code == 0, r.stderr
    assert "note: one target: the points do not measure the tool's orientation" in r.stderr
    ds = load_version(SessionStore(tmp_path / "s"), r.stdout.strip().splitlines()[-1])
    np.testing.assert_allclose(ds.points[:, 0], scn.points[:, 0], rtol=1e-13, atol=1e-15)
    # A partly empty target is one error line naming row, line and column; nothing is written.
    holes.loc[3, "t2_z"] = ""
    holes.loc[3, "t2_x"] = 1.0
    holes.to_csv(tmp_path / "partly.csv", index=False)
    r = invoke("session", "import", tmp_path / "partly.csv", "--robot", "ur10", "--targets", root / "targets.toml",
               "--length-unit", "mm", "--angle-unit", "deg", "--store", tmp_path / "p")  # fmt: skip
    assert r.exit_code == 2 and "Traceback" not in r.stdout + r.stderr
    assert "data row 4 (line 5 of the file), column 't2_z': target t2 is partly empty" in r.stderr
