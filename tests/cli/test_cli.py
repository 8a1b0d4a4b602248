"""Every command through typer's CliRunner on the sim rig: happy paths, created ids printed last, and bad input
giving a one-line error on stderr with a non-zero exit code and no traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_testutil import TARGETS, invoke, last_line

from labcal.compensator import Compensator
from labcal.datasets import SessionStore
from labcal.kinematics.conversions import from_urdf


def assert_user_error(result, *fragments: str) -> None:
    assert result.exit_code != 0, result.stdout
    assert "Traceback" not in result.stdout + result.stderr
    assert result.stderr.startswith("error: "), result.stderr
    for f in fragments:
        assert f in result.stderr, result.stderr


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A store with one 40-pose sim session and one local-poe fit."""
    root = tmp_path_factory.mktemp("cli")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"
    r = invoke(
        "session", "new", "--robot", "ur10", "--robot-driver", "sim", "--tracker-driver", "sim",
        "--targets", root / "targets.toml", "--poses", 40, "--seed", 3, store=store,
    )  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = last_line(r)
    f = invoke("fit", ref, "--method", "local-poe", store=store)
    assert f.exit_code == 0, f.stdout + f.stderr
    return {"root": root, "store": store, "ref": ref, "session": ref.split("@")[0], "fit": last_line(f)}


@pytest.mark.parametrize(
    "cmd",
    [
        *([], ["session"], ["session", "new"], ["session", "import"], ["fit"], ["export"], ["report"], ["demo"]),
        *(["filter"], ["evaluate"], ["refit"]),
    ],
)
def test_help_everywhere_with_examples(cmd):
    r = invoke(*cmd, "--help")
    assert r.exit_code == 0
    assert "Example" in r.stdout


def test_session_new_prints_its_version_and_the_store_lists_it(world):
    assert world["ref"].endswith("@v001")
    r = invoke("session", "list", store=world["store"])
    assert r.exit_code == 0 and world["session"] in r.stdout
    r = invoke("session", "show", world["session"], store=world["store"])
    assert r.exit_code == 0 and "v001" in r.stdout and "ur10" in r.stdout
    r = invoke("session", "verify", world["ref"], store=world["store"])
    assert r.exit_code == 0 and "ok" in r.stdout


def test_fit_prints_metrics_table_and_stores_the_fit(world):
    r = invoke("fit", world["ref"], "--method", "nominal", "--seed", 1, store=world["store"])
    assert r.exit_code == 0, r.stderr
    assert "pos mean mm" in r.stdout and "before" in r.stdout and "after" in r.stdout
    fit_id = last_line(r)
    ids = [f.fit_id for f in SessionStore(world["store"]).list_fits(world["ref"])]
    assert fit_id in ids and world["fit"] in ids


def test_fit_pools_two_sessions_of_the_same_robot(world):
    r = invoke(
        "session", "new", "--robot", "ur10", "--targets", world["root"] / "targets.toml", "--poses", 12, "--seed", 3,
        store=world["store"],
    )  # fmt: skip
    second = last_line(r)
    f = invoke("fit", world["ref"], second, "--method", "local-poe", store=world["store"])
    assert f.exit_code == 0, f.stderr
    rec = SessionStore(world["store"]).load_fit(world["ref"], last_line(f))
    assert [i["ref"] for i in rec.inputs] == [world["ref"], second]
    assert rec.metadata["metrics"]["all"]["before"]["count"] == 52


@pytest.mark.parametrize(
    "fmt,name",
    [
        *(("json", "c.json"), ("npz", "c.npz"), ("urscript", "c.script"), ("urdf", "c.urdf")),
        *(("urscript-program", "p.script"), ("ur-kinematics", "c.yaml")),
    ],
)
def test_export_every_format_round_trips(world, tmp_path, fmt, name):
    out = tmp_path / name
    r = invoke("export", world["ref"], "--fit", world["fit"], "--format", fmt, "--out", out, store=world["store"])
    assert r.exit_code == 0, r.stderr
    assert last_line(r) == str(out)
    stored = SessionStore(world["store"]).load_fit(world["ref"], world["fit"])
    payload = json.loads(stored.read("robot.json"))
    if fmt in ("json", "npz"):
        comp = Compensator.load(out)
        assert comp.provenance["fit_id"] == world["fit"] and comp.provenance["session"] == world["ref"]
        q = np.asarray(payload["golden"]["q"])
        np.testing.assert_allclose(comp.correct(q), payload["golden"]["q_cmd"], atol=1e-10)
    elif fmt == "urdf":
        # robot and tool apart: the robot ends at tool0, the identified measurement fixture is a link beyond it
        model = from_urdf(out.read_text(), tip_link="tool0")
        q = np.asarray(payload["golden"]["q"])
        np.testing.assert_allclose(model.fk(q)[:, :3, 3], np.asarray(payload["golden"]["pose"])[:, :3, 3], atol=1e-12)
        if payload.get("measurement_tool") is not None:
            fixture = from_urdf(out.read_text(), tip_link="measurement_tool").fk(q)
            tool = np.asarray(payload["golden"]["pose"]) @ np.asarray(payload["measurement_tool"])
            np.testing.assert_allclose(fixture, tool, atol=1e-12)
    elif fmt == "ur-kinematics":
        text = out.read_text()
        assert all(f"{seg}:" in text for seg in ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3"))
    elif fmt == "urscript-program":
        assert "def labcal_program():" in out.read_text()
    else:
        assert "def labcal_correct(q):" in out.read_text()


def test_report_writes_markdown_and_plots(world, tmp_path):
    r = invoke("report", world["ref"], "--out", tmp_path / "rep", store=world["store"])
    assert r.exit_code == 0, r.stderr
    md = Path(last_line(r))
    assert md.name == "report.md" and "## Fit" in md.read_text()
    assert (tmp_path / "rep" / "histogram.png").stat().st_size > 1000
    assert list((tmp_path / "rep").glob("errors-*.png"))


def test_import_a_csv_into_a_new_session(world, tmp_path):
    ds = SessionStore(world["store"]).load(world["ref"])
    cols = {f"q{j + 1}": np.degrees(ds.q[:, j]) for j in range(6)}
    for i in range(3):
        for a, axis in enumerate("xyz"):
            cols[f"t{i + 1}_{axis}"] = ds.points[:, i, a] * 1e3
    lines = [",".join(cols)] + [",".join(repr(float(cols[c][k])) for c in cols) for k in range(len(ds))]
    (tmp_path / "data.csv").write_text("\n".join(lines) + "\n")
    r = invoke(
        "session", "import", tmp_path / "data.csv", "--robot", "ur10", "--targets", world["root"] / "targets.toml",
        "--length-unit", "mm", "--angle-unit", "deg", store=tmp_path / "store2",
    )  # fmt: skip
    assert r.exit_code == 0, r.stderr
    imported = SessionStore(tmp_path / "store2").load(last_line(r))
    np.testing.assert_allclose(imported.points, ds.points, atol=1e-12)


def test_resume_of_a_finished_sim_session_has_nothing_left(world):
    r = invoke("session", "resume", world["session"], store=world["store"])
    assert r.exit_code == 0, r.stderr
    assert "nothing left" in r.stdout


# -- bad input -----------------------------------------------------------------------------------------------------


def test_unknown_session(world):
    assert_user_error(invoke("fit", "nope-session", "--method", "local-poe", store=world["store"]), "no session")
    assert_user_error(invoke("export", world["session"] + "@v9", "--format", "json", "--out", "x.json",
                             store=world["store"]), "no version v009")  # fmt: skip
    assert_user_error(invoke("session", "show", "nope", store=world["store"]), "no session")


def test_bad_flag_values(world, tmp_path):
    s = world["store"]
    assert_user_error(invoke("fit", world["ref"], "--method", "magic", store=s), "--method")
    assert_user_error(invoke("fit", world["ref"], "--val-fraction", "1.5", store=s), "--val-fraction")
    assert_user_error(
        invoke("export", world["ref"], "--format", "xml", "--out", tmp_path / "a.xml", store=s), "--format"
    )
    assert_user_error(invoke("export", world["ref"], "--format", "npz", "--out", tmp_path / "a.json", store=s), ".npz")
    assert_user_error(invoke("export", world["ref"], "--fit", "nofit", "--format", "json", "--out", tmp_path / "a.json",
                             store=s), "no fit")  # fmt: skip
    t = world["root"] / "targets.toml"
    assert_user_error(invoke("session", "new", "--robot", "ur10", "--targets", t, "--poses", 0, store=s), "--poses")
    assert_user_error(invoke("session", "new", "--robot", "ur10", "--targets", t, "--poses", 3, "--robot-driver", "abb",
                             store=s), "--robot-driver")  # fmt: skip
    assert_user_error(invoke("session", "new", "--robot", "ur10", "--targets", t, "--poses", 3, "--planner", "best",
                             store=s), "--planner")  # fmt: skip
    assert_user_error(invoke("session", "new", "--robot", "nobot", "--targets", t, "--poses", 3, store=s), "nobot")


def test_missing_files(world, tmp_path):
    assert_user_error(invoke("session", "import", tmp_path / "none.csv", "--robot", "ur10", "--targets",
                             world["root"] / "targets.toml", store=tmp_path / "s"), "no such file")  # fmt: skip
    assert_user_error(invoke("session", "new", "--robot", "ur10", "--targets", tmp_path / "none.toml", "--poses", 3,
                             store=tmp_path / "s"))  # fmt: skip


def test_wrong_robot_for_a_session(world):
    r = invoke("fit", world["ref"], "--method", "local-poe", "--robot", "ur5e", store=world["store"])
    assert_user_error(r, "not the model the session was recorded with")


def test_corrupt_version_is_refused(world, tmp_path):
    import shutil

    store = tmp_path / "copy"
    shutil.copytree(world["store"], store)
    parquet = store / world["session"] / "v001" / "measurements.parquet"
    parquet.chmod(0o644)
    data = bytearray(parquet.read_bytes())
    data[len(data) // 2] ^= 0xFF
    parquet.write_bytes(bytes(data))
    r = invoke("session", "verify", world["ref"], store=store)
    assert r.exit_code == 1 and "measurements.parquet" in r.stdout
    assert_user_error(invoke("fit", world["ref"], "--method", "local-poe", store=store))


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    r = invoke("demo", "--out", tmp_path / "demo", "--poses", 60)
    assert r.exit_code == 0, r.stdout + r.stderr
    root = Path(last_line(r))
    assert root == tmp_path / "demo"
    for m in ("local-poe", "ann", "hybrid"):
        assert m in r.stdout
    comp = Compensator.load(root / "exports" / "ur10-hybrid.json")
    assert comp.method == "hybrid"
    assert (root / "exports" / "ur10-hybrid.script").read_text().count("def labcal_correct") == 1
    from_urdf((root / "exports" / "ur10-local-poe.urdf").read_text())
    assert (root / "report" / "report.md").is_file()


@pytest.mark.parametrize(
    "args,message",
    [
        (("--poses", 3), "--poses must be at least 12"),
        (("--held-out", 0), "--held-out must be at least 1"),
        (("--seed", -1), "--seed must be a non-negative integer"),
    ],
)
def test_demo_checks_its_options_before_recording(tmp_path, args, message):
    # found late, these wasted a recording and the fits, and named another command's flag
    r = invoke("demo", "--out", tmp_path / "demo", *args)
    assert r.exit_code == 2 and r.stderr.startswith(f"error: {message}"), r.stdout + r.stderr
    assert "recording" not in r.stdout and not (tmp_path / "demo").exists()


def test_demo_refuses_an_out_folder_it_cannot_own(tmp_path):
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "exports").mkdir()
    (tmp_path / "a-file").write_text("x")
    for out, what in (("used", "is not empty"), ("a-file", "is not a folder")):
        r = invoke("demo", "--out", tmp_path / out)
        assert r.exit_code == 2 and what in r.stderr and "recording" not in r.stdout, r.stdout + r.stderr


@pytest.mark.parametrize("command", [("fit", "S"), ("refit", "S", "--method", "local-poe")])
def test_a_negative_seed_is_a_usage_error_naming_the_flag(tmp_path, command):
    store = tmp_path / "store"
    r = invoke("session", "new", "--robot", "ur10", "--targets", _targets(tmp_path), "--poses", 12, store=store)
    assert r.exit_code == 0, r.stderr
    args = [last_line(r) if a == "S" else a for a in command]
    r = invoke(*args, "--seed", -1, store=store)
    assert r.exit_code == 2 and "--seed must be a non-negative integer, got -1" in r.stderr, r.stdout + r.stderr
    r = invoke("session", "new", "--robot", "ur10", "--targets", _targets(tmp_path), "--poses", 12, "--sim-seed", -2,
               store=store)  # fmt: skip
    assert r.exit_code == 2 and "--sim-seed must be a non-negative integer, got -2" in r.stderr


def _targets(tmp_path: Path) -> Path:
    path = tmp_path / "targets.toml"
    path.write_text(TARGETS)
    return path


def test_the_allow_help_names_every_check():
    from labcal.cli.session import ALLOW_HELP
    from labcal.datasets.checks import CHECKS

    assert all(name in ALLOW_HELP for name in CHECKS)


def test_a_folder_given_as_the_csv_is_named_as_a_folder(tmp_path):
    (tmp_path / "data.csv").mkdir()
    (tmp_path / "targets.toml").write_text(TARGETS)
    r = invoke("session", "import", tmp_path / "data.csv", "--robot", "ur10", "--targets", tmp_path / "targets.toml",
               store=tmp_path / "store")  # fmt: skip
    assert_user_error(r, "is a folder, not a CSV file")


def test_a_mistyped_session_or_fit_id_gets_a_suggestion(world):
    store, ref = world["store"], world["ref"]
    session = ref.split("@")[0]
    typo = session[:-1] + ("0" if session[-1] != "0" else "1")
    assert_user_error(invoke("session", "show", typo, store=store), f"did you mean {session!r}?")
    fit_id = last_line(invoke("fit", ref, "--method", "local-poe", store=store))
    typo = fit_id[:-1] + ("0" if fit_id[-1] != "0" else "1")
    assert_user_error(invoke("evaluate", typo, "--data", ref, store=store), f"did you mean {fit_id!r}?")
    assert_user_error(invoke("export", ref, "--fit", typo, "--format", "json", "--out", "x.json", store=store),
                      f"did you mean {fit_id!r}?")  # fmt: skip


def test_text_that_looks_like_markup_prints_as_it_is(tmp_path):
    """A store path (or any message) with '[/x]' in it is text: the consoles parse no markup (a table title with it
    was a rich MarkupError traceback)."""
    store = tmp_path / "[" / "x]"
    store.mkdir(parents=True)
    r = invoke("session", "list", store=store)
    assert r.exit_code == 0, r.stdout + r.stderr
    assert f"sessions in {store}" in " ".join(r.stdout.split())
    r = invoke("session", "show", "20261122-031500-ur10-3f9a", store=store)
    assert r.exit_code == 2 and "[/x]" in r.stderr and "Traceback" not in r.stderr
