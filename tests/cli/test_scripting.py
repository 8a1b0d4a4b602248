"""The CLI as scripts use it (issue 17.2): --json documents (parsed, keys and types checked), --version, shell
completion with enumerated choices, exit codes (2 for a usage error or a missing store, 1 for damage), and the
light paths: importing the app, `--help` and listing sessions must not import numpy, pandas, pyarrow, torch,
scipy, matplotlib, nor pydantic or markdown-it (which typer would import)."""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys
import typing
from pathlib import Path

import pytest
from cli_testutil import TARGETS, invoke, last_line

HEAVY = ("pandas", "pyarrow", "torch", "scipy", "matplotlib")
LABCAL = Path(sys.executable).parent / "labcal"


def run(*code_or_args: str, env: dict | None = None, script: bool = False) -> subprocess.CompletedProcess:
    """A fresh interpreter (nothing imported yet): `python -c CODE`, or the installed `labcal ARGS` script."""
    argv = [str(LABCAL), *code_or_args] if script else [sys.executable, "-c", *code_or_args]
    return subprocess.run(argv, capture_output=True, text=True, env={**os.environ, **(env or {})}, timeout=300)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A store with one 14-pose sim session and a local-poe fit made with --json."""
    root = tmp_path_factory.mktemp("scripting")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"
    r = invoke(
        "session", "new", "--robot", "ur10", "--targets", root / "targets.toml", "--poses", 14, "--seed", 5,
        store=store,
    )  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = last_line(r)
    f = invoke("fit", ref, "--method", "local-poe", "--json", store=store)
    assert f.exit_code == 0, f.stdout + f.stderr
    return {"root": root, "store": store, "ref": ref, "session": ref.split("@")[0], "fit": f}


def document(result, schema: str) -> dict:
    """stdout is exactly one JSON document of this schema (nothing else on stdout)."""
    doc = json.loads(result.stdout)
    assert doc["schema"] == schema
    assert list(doc) == sorted(doc), "keys are sorted (a stable order)"
    return doc


# -- light paths ---------------------------------------------------------------------------------------------------


# Not needed to print help or list sessions: numpy and the table libraries (the data), pydantic (typer's option
# checks; labcal.cli.coercion does the plain ones), markdown-it and pygments (typer's markdown help, unused).
NOT_ON_LIGHT_PATHS = (*HEAVY, "numpy", "pydantic", "markdown_it", "pygments")


def light_path(
    *argv: str, unwanted: tuple[str, ...] = NOT_ON_LIGHT_PATHS, env: dict | None = None
) -> tuple[str, list[str]]:
    """Run `labcal ARGV` in a fresh interpreter: (its stdout, the ``unwanted`` modules it imported)."""
    code = (
        "import sys; from labcal.cli.app import main\n"
        f"sys.argv = ['labcal', *{list(argv)!r}]\n"
        "try:\n    main()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
        f"import json; print(json.dumps(sorted(m for m in {unwanted!r} if m in sys.modules)))"
    )
    r = run(code, env={"COLUMNS": "100", **(env or {})})
    assert r.returncode == 0, r.stderr
    *lines, loaded = r.stdout.strip().splitlines()
    return "\n".join(lines), json.loads(loaded)


def test_importing_the_app_imports_no_heavy_library():
    code = f"import labcal.cli.app, sys; print(sorted(m for m in {NOT_ON_LIGHT_PATHS!r} if m in sys.modules))"
    r = run(code)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


@pytest.mark.parametrize("argv", [["--help"], ["session", "--help"], ["fit", "--help"], ["session", "list", "--help"]])
def test_help_imports_no_heavy_library(argv):
    out, loaded = light_path(*argv)
    assert "Usage: labcal" in out
    assert loaded == []


def test_completing_a_choice_imports_no_heavy_library():
    env = {"_LABCAL_COMPLETE": "complete_bash", "COMP_WORDS": "labcal fit S --method a", "COMP_CWORD": "4"}
    out, loaded = light_path(env=env)
    assert set(out.split()) == {"ann", "auto"}
    assert loaded == []


@pytest.fixture(scope="module")
def two_sessions(tmp_path_factory):
    """A store with two small sim sessions (recorded, so each has a journal as well as a manifest)."""
    root = tmp_path_factory.mktemp("listing")
    (root / "targets.toml").write_text(TARGETS)
    refs = []
    for seed in (1, 2):
        r = invoke("session", "new", "--robot", "ur10", "--targets", root / "targets.toml", "--poses", 10, "--seed",
                   seed, store=root / "store")  # fmt: skip
        assert r.exit_code == 0, r.stdout + r.stderr
        refs.append(last_line(r).split("@")[0])
    return root / "store", refs


@pytest.mark.parametrize("json_flag", [[], ["--json"]])
def test_session_list_on_a_store_imports_no_heavy_library(two_sessions, json_flag):
    store, sessions = two_sessions
    # JSON is printed without rich (the table and the consoles import it when they are used)
    unwanted = (*NOT_ON_LIGHT_PATHS, "rich.console") if json_flag else NOT_ON_LIGHT_PATHS
    out, loaded = light_path("session", "list", *json_flag, "--store", str(store), unwanted=unwanted)
    assert all(s in out for s in sessions)  # it did list them
    assert loaded == []


@pytest.mark.parametrize("json_flag", [[], ["--json"]])
def test_session_list_of_an_empty_store_imports_no_heavy_library(tmp_path, json_flag):
    (tmp_path / "empty").mkdir()
    out, loaded = light_path("session", "list", *json_flag, "--store", str(tmp_path / "empty"))
    assert ('"sessions": []' if json_flag else "sessions in") in out
    assert loaded == []


def test_the_store_names_the_journal_file_as_the_journal_does():
    from labcal.datasets import journal, store

    assert store.JOURNAL_NAME == journal.JOURNAL_NAME


def test_the_option_choices_are_the_librarys():
    from labcal.calibration.fit import METHODS
    from labcal.cli import common
    from labcal.cli.ops.sessions import PLANNERS, ROBOT_DRIVERS, SIM_ERRORS, TRACKER_DRIVERS
    from labcal.export import FORMATS

    def choices(alias):
        return set(typing.get_args(alias))

    assert choices(common.Method) == set(METHODS)
    assert choices(common.ExportFormat) == set(FORMATS)
    assert choices(common.RobotDriver) == set(ROBOT_DRIVERS)
    assert choices(common.TrackerDriver) == set(TRACKER_DRIVERS)
    assert choices(common.Planner) == set(PLANNERS)
    assert choices(common.SimErrors) == set(SIM_ERRORS)


# -- version, completion, usage errors -----------------------------------------------------------------------------


def test_version_flag_prints_the_installed_version():
    r = invoke("--version")
    assert r.exit_code == 0
    assert r.stdout.strip() == f"labcal {importlib.metadata.version('labcal')}"


def test_completion_options_exist():
    r = invoke("--help")
    assert r.exit_code == 0
    assert "--show-completion" in r.stdout and "--install-completion" in r.stdout


@pytest.mark.parametrize(
    "words, expected",
    [
        ("labcal fit S --method ", {"nominal", "local-poe", "ann", "hybrid", "auto"}),
        ("labcal fit S --method a", {"ann", "auto"}),
        ("labcal export S --format ur", {"urscript", "urscript-program", "urdf", "ur-kinematics"}),
        ("labcal session new --robot-driver ", {"sim", "ur"}),
        ("labcal filter p.csv --kind ", {"poses", "joints"}),
        ("labcal ses", {"session"}),
        ("labcal session new --robot ur1", {"ur10", "ur10e"}),
    ],
)
def test_bash_completion_lists_the_choices(words, expected):
    """typer's bash protocol: the script run with _LABCAL_COMPLETE=complete_bash, COMP_WORDS and COMP_CWORD."""
    cword = len(words.split()) - (0 if words.endswith(" ") else 1)
    env = {"_LABCAL_COMPLETE": "complete_bash", "COMP_WORDS": words, "COMP_CWORD": str(cword)}
    r = run(env=env, script=True)
    assert r.returncode == 0, r.stderr
    assert set(r.stdout.split()) == expected


@pytest.mark.parametrize(
    "args, option, allowed",
    [
        (["fit", "S", "--method", "magic"], "--method", "'local-poe'"),
        (["export", "S", "--format", "xml", "--out", "x"], "--format", "'urscript-program'"),
        (["session", "new", "--robot", "ur10", "--targets", "t.toml", "--poses", "3", "--planner", "best"],
         "--planner", "'optimal'"),
        (["filter", "p.csv", "--calibration", "c.json", "--out", "o.csv", "--length-unit", "cm"],
         "--length-unit", "'mm'"),
    ],
)  # fmt: skip
def test_a_bad_choice_is_one_line_naming_the_allowed_values(args, option, allowed):
    r = invoke(*args)
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert option in lines[0] and allowed in lines[0]
    assert r.stdout == ""


def test_choices_ignore_case(world):
    r = invoke("session", "list", "--json", store=world["store"])
    assert r.exit_code == 0
    r = invoke("export", world["ref"], "--format", "JSON", "--out", world["root"] / "c.json", store=world["store"])
    assert r.exit_code == 0, r.stderr
    assert json.loads((world["root"] / "c.json").read_text())  # written as the json format


def test_an_unknown_option_is_a_usage_error_exit_2():
    r = invoke("session", "list", "--colour")
    assert r.exit_code == 2 and r.stderr.startswith("error: No such option: --colour")


# -- a missing store -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "args",
    [
        ["session", "list"],
        ["session", "show", "20261122-031500-ur10-3f9a"],
        ["session", "verify", "20261122-031500-ur10-3f9a"],
        ["session", "seal", "20261122-031500-ur10-3f9a"],
        ["fit", "20261122-031500-ur10-3f9a", "--method", "local-poe"],
        ["export", "20261122-031500-ur10-3f9a", "--format", "json", "--out", "OUT/x.json"],
        ["report", "20261122-031500-ur10-3f9a", "--out", "OUT/report"],
        ["filter", "p.csv", "--calibration", "20261122-031500-ur10-3f9a", "--out", "OUT/c.csv"],
        ["evaluate", "20261122-040000-123456-ab12cd", "--data", "20261122-031500-ur10-3f9a"],
        ["session", "resume", "20261122-031500-ur10-3f9a"],
        ["refit", "--all"],
    ],
)
def test_a_missing_store_is_an_error_naming_it(tmp_path, args):
    store = tmp_path / "no-such-store"
    r = invoke(*[a.replace("OUT", str(tmp_path)) for a in args], store=store)
    assert r.exit_code == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(store) in lines[0], r.stderr
    assert not store.exists()  # reading commands never create a store


# -- JSON documents ------------------------------------------------------------------------------------------------


def test_session_list_json(world):
    from labcal.datasets import SessionStore

    r = invoke("session", "list", "--json", store=world["store"])
    assert r.exit_code == 0, r.stderr
    doc = document(r, "labcal.session-list/1")
    assert doc["store"] == str(world["store"])
    (s,) = doc["sessions"]
    assert s["session"] == world["session"]
    assert s["robot"]["name"] == "ur10" and s["robot"]["n_joints"] == 6 and s["robot"]["file_stored"] is True
    assert len(s["robot"]["hash"]) == 64
    assert s["frame"] == "base" and s["status"] == "success" and s["n_targets"] == 3
    assert s["rows"] == 14 and s["measurements"] >= 14
    recorded = SessionStore(world["store"]).session_meta(world["session"]).get("metadata", {}).get("unit")
    assert s["unit"] == recorded  # the sim rig records one (sim-<seed>); older sessions have none (null)
    assert set(s["identity"]) == {"robot", "tracker"}
    (v,) = s["versions"]
    assert v["version"] == "v001" and v["rows"] == 14 and v["fits"] >= 1 and v["parent"] is None
    assert isinstance(v["created"], str) and v["source"] == "journal"
    assert s["warnings"] == []


def test_session_list_of_an_empty_store(tmp_path):
    (tmp_path / "empty").mkdir()
    r = invoke("session", "list", "--json", store=tmp_path / "empty")
    assert r.exit_code == 0
    assert document(r, "labcal.session-list/1")["sessions"] == []


def test_session_list_unit_selects_the_sessions_of_one_unit(tmp_path):
    from labcal.datasets import SessionHeader, SessionStore
    from labcal.robots import load

    st = SessionStore(tmp_path / "units")
    record = load("ur10").record()
    made = {}
    for unit in ("UR10-A", "UR10-B", None):
        header = SessionHeader(
            robot=record, targets=[[0.1, 0.0, 0.05]], frame="base", metadata={"unit": unit} if unit else {}
        )
        journal = st.create_session(header)
        made[unit] = journal.session_id
        journal.close()
    r = invoke("session", "list", "--unit", "UR10-A", "--json", store=st.root)
    assert r.exit_code == 0, r.stderr
    sessions = document(r, "labcal.session-list/1")["sessions"]
    assert [(s["session"], s["unit"]) for s in sessions] == [(made["UR10-A"], "UR10-A")]
    human = invoke("session", "list", "--unit", "UR10-B", store=st.root)
    assert made["UR10-B"] in human.stdout and made["UR10-A"] not in human.stdout
    assert len(document(invoke("session", "list", "--json", store=st.root), "labcal.session-list/1")["sessions"]) == 3


def test_session_new_unit_is_what_list_unit_selects(world):
    r = invoke("session", "new", "--robot", "ur10", "--targets", world["root"] / "targets.toml", "--poses", 14,
               "--seed", 8, "--unit", "CELL-7", store=world["root"] / "units-cli")  # fmt: skip
    assert r.exit_code == 0, r.stderr
    doc = document(invoke("session", "list", "--unit", "CELL-7", "--json", store=world["root"] / "units-cli"),
                   "labcal.session-list/1")  # fmt: skip
    assert [s["session"] for s in doc["sessions"]] == [last_line(r).split("@")[0]]
    shown = invoke("session", "show", last_line(r).split("@")[0], store=world["root"] / "units-cli")
    assert "unit CELL-7" in shown.stdout


def test_session_show_json(world):
    r = invoke("session", "show", world["session"], "--json", store=world["store"])
    assert r.exit_code == 0, r.stderr
    doc = document(r, "labcal.session-show/1")
    assert doc["session"] == world["session"] and doc["n_targets"] == 3
    assert [v["version"] for v in doc["versions"]] == ["v001"]


def test_session_verify_json_ok_and_damaged(world, tmp_path):
    import shutil

    r = invoke("session", "verify", world["session"], "--json", store=world["store"])
    assert r.exit_code == 0, r.stderr
    doc = document(r, "labcal.session-verify/1")
    assert doc["ok"] is True and doc["session"] == world["session"]
    (v,) = doc["versions"]
    assert v["ref"] == world["ref"] and v["ok"] is True and v["problems"] == []
    assert v["files_checked"] >= 2 and v["fits_checked"] >= 1 and v["fit_files_checked"] >= 1

    store = tmp_path / "copy"
    shutil.copytree(world["store"], store)
    parquet = store / world["session"] / "v001" / "measurements.parquet"
    parquet.chmod(0o644)
    parquet.write_bytes(parquet.read_bytes() + b"x")
    r = invoke("session", "verify", world["ref"], "--json", store=store)
    assert r.exit_code == 1  # verification failure, and still a document
    doc = document(r, "labcal.session-verify/1")
    assert doc["ok"] is False and doc["versions"][0]["ok"] is False
    assert any("measurements.parquet" in p for p in doc["versions"][0]["problems"])


def test_fit_json(world):
    r = world["fit"]
    doc = document(r, "labcal.fit/1")
    assert doc["method"] == "local-poe" and doc["chosen"] == "local-poe" and doc["seed"] == 0
    assert doc["stored_under"] == world["ref"] and doc["inputs"] == [world["ref"]]
    assert doc["rows"] == {"train": 14, "val": 0, "test": 0}
    stored = invoke("session", "show", world["session"], "--json", store=world["store"])
    assert document(stored, "labcal.session-show/1")["versions"][0]["fits"] >= 1
    after = doc["metrics"]["all"]["after"]
    assert isinstance(after["pos_mean_m"], float) and isinstance(after["ori_mean_rad"], float)
    assert after["count"] == 14 and not any(k in after for k in ("pos_mean", "ori_mean"))
    points = doc["metrics"]["all"]["points"]["after"]
    assert isinstance(points["mean_m"], float) and len(points["per_target"]) == 3
    assert doc["metrics"]["all"]["before"]["pos_mean_m"] > after["pos_mean_m"]  # the fit improved the robot
    assert isinstance(doc["warnings"], list) and isinstance(doc["notes"], list)
    assert doc["cv"]["chosen"] == "local-poe" and len(doc["cv"]["fold_errors_m"]["local-poe"]) == doc["cv"]["folds"]
    assert doc["observability"]["orientation"] == "measured" and doc["observability"]["targets"] == 3
    assert all(isinstance(v, float) for v in doc["fit_time_s"].values())
    assert "cross-validation" in r.stderr  # progress went to stderr


def test_fit_json_id_is_the_stored_fit(world):
    from labcal.datasets import SessionStore

    doc = document(world["fit"], "labcal.fit/1")
    fits = SessionStore(world["store"]).list_fits(world["ref"])
    assert doc["fit_id"] in {f.fit_id for f in fits}


def test_evaluate_json(world):
    fit_id = document(world["fit"], "labcal.fit/1")["fit_id"]
    r = invoke("evaluate", fit_id, "--data", world["ref"], "--json", store=world["store"])
    assert r.exit_code == 0, r.stderr
    doc = document(r, "labcal.evaluate/1")
    assert doc["fit_id"] == fit_id and doc["data"]["ref"] == world["ref"] and doc["data"]["rows"] == 14
    assert doc["overlap_with_fit"] is True  # scored on its own data, and it says so
    counts = doc["metrics"]["all"]["after"]["count"], doc["metrics"]["all"]["points"]["after"]["count"]
    assert all(type(c) is int for c in counts)  # docs/cli-json.md: counts are integers
    assert isinstance(doc["metrics"]["all"]["after"]["pos_mean"], float) and doc["stored_at"]


def test_fit_pools_two_units_only_when_asked(world):
    store = world["root"] / "two-units"
    refs = []
    for seed, unit in ((11, "ARM-1"), (12, "ARM-2")):
        r = invoke("session", "new", "--robot", "ur10", "--targets", world["root"] / "targets.toml", "--poses", 14,
                   "--seed", seed, "--unit", unit, store=store)  # fmt: skip
        assert r.exit_code == 0, r.stderr
        refs.append(last_line(r))
    refused = invoke("fit", *refs, "--method", "local-poe", store=store)
    assert refused.exit_code == 2 and refused.stderr.startswith("error: ") and "ARM-1" in refused.stderr
    pooled = invoke("fit", *refs, "--method", "local-poe", "--pool-units", "--json", store=store)
    assert pooled.exit_code == 0, pooled.stderr
    assert document(pooled, "labcal.fit/1")["inputs"] == refs
