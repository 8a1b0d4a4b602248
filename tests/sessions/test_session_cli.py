"""`labcal session …` through typer's CliRunner: store checks before any work, plan-size bound, exit codes of failed
runs, verify covering fits, resume refusing a corrupt journal before motion, seal --valid-prefix, and a custom robot
session refitted from the store alone."""

from __future__ import annotations

from pathlib import Path

import pytest
from sessions_testutil import TARGETS_TOML, write_custom_robot
from typer.testing import CliRunner

from labcal.cli.app import app
from labcal.datasets import SessionStore, read_journal
from labcal.sessions import RunSummary

runner = CliRunner()


def invoke(*args, store: Path | None = None):
    argv = [str(a) for a in args] + (["--store", str(store)] if store is not None else [])
    return runner.invoke(app, argv)


def one_line_error(result, *fragments: str) -> None:
    assert result.exit_code == 2, (result.exit_code, result.stdout, result.stderr)
    assert "Traceback" not in result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for f in fragments:
        assert f in lines[0], lines[0]


@pytest.fixture
def targets(tmp_path) -> Path:
    p = tmp_path / "targets.toml"
    p.write_text(TARGETS_TOML)
    return p


@pytest.fixture
def recorded(tmp_path, targets):
    """A finished 30-pose sim session of a custom robot whose file is deleted afterwards."""
    robot = write_custom_robot(tmp_path)
    store = tmp_path / "store"
    r = invoke("session", "new", "--robot", robot, "--targets", targets, "--poses", 30, store=store)
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = r.stdout.strip().splitlines()[-1]
    robot.unlink()
    return {"store": store, "ref": ref, "session": ref.split("@")[0]}


# ------------------------------------------------------------------------------------------------------ store checks


@pytest.mark.parametrize("command", [["session", "list"], ["session", "show", "20261122-031500-ur10-3f9a"],
                                     ["session", "verify", "20261122-031500-ur10-3f9a"],
                                     ["session", "seal", "20261122-031500-ur10-3f9a"],
                                     ["session", "resume", "20261122-031500-ur10-3f9a"]])  # fmt: skip
def test_a_missing_store_is_one_line_for_every_read_command(tmp_path, command):
    r = invoke(*command, store=tmp_path / "missing")
    one_line_error(r, "no session store at", "missing", "--store or LABCAL_STORE")
    assert not (tmp_path / "missing").exists()


def test_session_new_creates_a_missing_store(tmp_path, targets):
    r = invoke("session", "new", "--robot", "ur10", "--targets", targets, "--poses", 3, store=tmp_path / "a" / "b")
    assert r.exit_code == 0, r.stderr
    assert SessionStore(tmp_path / "a" / "b").session_ids()


def test_session_new_records_a_single_reflector_with_sim_dropout(tmp_path):
    one = tmp_path / "smr.toml"
    one.write_text('unit = "mm"\npoints = [[0, 0, 45], [0, 80, 45], [60, 0, 45]]\n')
    store = tmp_path / "s"
    r = invoke("session", "new", "--robot", "ur10", "--targets", one, "--poses", 12, "--sim-dropout", 0.4,
               store=store)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    ds = SessionStore(store).load(r.stdout.strip().splitlines()[-1])
    assert ds.points.shape == (12, 3, 3) and not ds.seen.all() and ds.seen.any(axis=1).all()
    assert "3 targets" in invoke("session", "show", ds.ref.split("@")[0], store=store).stdout
    one.write_text('unit = "mm"\npoints = [[0, 0, 45]]\n')
    r = invoke("session", "new", "--robot", "ur10", "--targets", one, "--poses", 8, store=store)
    assert r.exit_code == 0, r.stdout + r.stderr
    single = SessionStore(store).load(r.stdout.strip().splitlines()[-1])
    assert single.points.shape == (8, 1, 3) and single.seen.all()
    assert "1 target," in invoke("session", "show", single.ref.split("@")[0], store=store).stdout
    bad = invoke("session", "new", "--robot", "ur10", "--targets", one, "--poses", 8, "--sim-dropout", 1.5,
                 store=tmp_path / "never")  # fmt: skip
    one_line_error(bad, "--sim-dropout must be a probability")
    assert not (tmp_path / "never").exists()


@pytest.mark.parametrize("where", ["file", "file/sub"])
def test_an_unusable_store_fails_session_new_in_one_line_before_planning(tmp_path, targets, where):
    (tmp_path / "file").write_text("not a folder")
    r = invoke("session", "new", "--robot", "ur10", "--targets", targets, "--poses", 3, store=tmp_path / where)
    one_line_error(r, "session store")
    assert "recording" not in r.stderr  # nothing was planned or moved


def test_poses_beyond_the_bound_fail_at_once_with_the_reason(tmp_path, targets):
    r = invoke("session", "new", "--robot", "ur10", "--targets", targets, "--poses", 100_000_000,
               store=tmp_path / "s")  # fmt: skip
    one_line_error(r, "--poses 100,000,000", "100,000", "memory")
    assert not (tmp_path / "s").exists()  # refused before even the store was created


# ------------------------------------------------------------------------------------------------------- exit codes


@pytest.mark.parametrize(("status", "code"), [("failed", 1), ("paused", 1), ("aborted", 130), ("success", 0)])
def test_session_new_exit_code_follows_the_run(tmp_path, targets, monkeypatch, status, code):
    import labcal.cli.ops.sessions as ops

    summary = RunSummary("s", status, "the tracker did not answer", 0, 0, 3, 0, "s@v001" if code == 0 else None)
    monkeypatch.setattr(ops, "new_session", lambda *a, **k: summary)
    r = invoke("session", "new", "--robot", "ur10", "--targets", targets, "--poses", 3, store=tmp_path / "s")
    assert r.exit_code == code, (r.stdout, r.stderr)
    assert r.stdout.startswith(f"{status}:")
    if status in ("failed", "paused"):
        assert "the tracker did not answer" in r.stderr


# ----------------------------------------------------------------------------------------------------------- verify


def test_verify_checks_the_fits_too(recorded):
    store, ref = recorded["store"], recorded["ref"]
    r = invoke("fit", ref, "--method", "local-poe", store=store)  # the robot file is gone: the stored one is used
    assert r.exit_code == 0, r.stderr
    fit_id = r.stdout.strip().splitlines()[-1]
    assert invoke("session", "verify", ref, store=store).exit_code == 0
    fit_dir = next(SessionStore(store).version_dir(ref).glob(f"fits/{fit_id}"))
    victim = sorted(p for p in fit_dir.iterdir() if p.name != "fit.json")[0]
    victim.chmod(0o644)
    victim.write_bytes(victim.read_bytes() + b" ")
    r = invoke("session", "verify", ref, store=store)
    assert r.exit_code == 1
    assert f"fits/{fit_id}/{victim.name}: sha256 mismatch" in r.stdout


def test_report_and_export_work_from_the_store_alone(recorded, tmp_path):
    store, ref = recorded["store"], recorded["ref"]
    assert invoke("fit", ref, "--method", "local-poe", store=store).exit_code == 0
    # --force: this test is about finding the model without its file, not about the fit gates.
    r = invoke("export", ref, "--format", "json", "--out", tmp_path / "c.json", "--force", store=store)
    assert r.exit_code == 0, r.stderr
    r = invoke("report", ref, "--out", tmp_path / "rep", store=store)
    assert r.exit_code == 0, r.stderr


# ----------------------------------------------------------------------------------------------- corrupt journals


def _interrupted(tmp_path, targets) -> tuple[Path, str]:
    """A sim session stopped after 5 of 10 poses (aborted), not sealed yet (as after a crash)."""
    from sessions_testutil import record_interrupted

    from labcal.robots import load

    store = tmp_path / "store"
    summary = record_interrupted(SessionStore(store), load("ur10"), n_poses=10, interrupt_at=6, seal=False)
    return store, summary.session_id


def test_resume_refuses_a_corrupt_journal_before_motion_and_seal_valid_prefix_recovers(tmp_path, targets):
    store, sid = _interrupted(tmp_path, targets)
    journal = SessionStore(store).session_dir(sid) / "journal.jsonl"
    lines = journal.read_bytes().split(b"\n")
    lines[3] = b"{" + b"x" * (len(lines[3]) - 1)  # line 4: the measurement of pose 2
    journal.write_bytes(b"\n".join(lines))
    n_docs = len(read_journal(journal).documents)

    r = invoke("session", "resume", sid, store=store)
    one_line_error(r, "line 4", "nothing was moved", "--valid-prefix")
    assert len(read_journal(journal).documents) == n_docs  # no resume document, no measurement: nothing ran

    r = invoke("session", "seal", sid, store=store)
    one_line_error(r, "corrupt line(s) [4]", "--valid-prefix")

    r = invoke("session", "seal", sid, "--valid-prefix", store=store)
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = r.stdout.strip().splitlines()[-1]
    assert SessionStore(store).load(ref).pose.tolist() == [0, 1]  # lines 2 and 3; line 4 (pose 2) on: left out
    assert "left out line 4: unreadable" in r.stdout


def test_seal_valid_prefix_cli_prints_what_it_left_out(tmp_path, targets):
    from sessions_testutil import TARGETS

    from labcal.drivers.sim import SimRig
    from labcal.robots import load
    from labcal.sessions import make_plan, random_configurations, run
    from labcal.simulation import ErrorSpec, simulate

    spec = load("ur10")
    st = SessionStore(tmp_path / "store")
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0)
    plan = make_plan(random_configurations(spec.model, 5, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(st, spec, TARGETS, plan, robot, tracker, frame="base", seal=False)
    journal = st.session_dir(summary.session_id) / "journal.jsonl"
    data = journal.read_bytes().split(b"\n")
    data[4] = b"\xff" * len(data[4])  # line 5: pose 3
    journal.write_bytes(b"\n".join(data))
    r = invoke("session", "seal", summary.session_id, "--valid-prefix", store=st.root)
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = r.stdout.strip().splitlines()[-1]
    assert ref.endswith("@v001") and st.load(ref).pose.tolist() == [0, 1, 2]
    assert "left out line 5: unreadable" in r.stdout
    assert "left out line 6 (seq 5, pose 4): after the corrupt line 5" in r.stdout


def test_verify_of_a_session_checks_the_fits_of_every_version(tmp_path):
    from sessions_testutil import record_interrupted

    from labcal.cli.ops.sessions import resume_session
    from labcal.robots import load

    st = SessionStore(tmp_path / "store")
    first = record_interrupted(st, load("ur10"), n_poses=6, interrupt_at=4)
    record = st.save_fit(first.ref, {"model.json": b"{}"}, {"method": "test"})
    assert resume_session(st, first.session_id).ref.endswith("@v002")
    (record.path / "model.json").chmod(0o644)
    (record.path / "model.json").write_bytes(b"[]")
    r = invoke("session", "verify", first.session_id, store=st.root)
    assert r.exit_code == 1
    assert f"{first.ref}: fits/{record.fit_id}/model.json: sha256 mismatch" in r.stdout
    assert f"{first.session_id}@v002: ok" in r.stdout
    assert invoke("session", "verify", f"{first.session_id}@v2", store=st.root).exit_code == 0


def test_show_says_whether_the_robot_file_is_stored(recorded):
    r = invoke("session", "show", recorded["session"], store=recorded["store"])
    assert r.exit_code == 0 and "lab-arm" in r.stdout and "robot file stored" in r.stdout


def test_a_coupled_elbow_session_records_controller_joints_and_fits_in_model_joints(tmp_path, targets):
    import numpy as np

    from labcal.cli.ops.common import load_observations
    from labcal.robots import load
    from labcal.sessions import Plan

    spec = load("coupled-elbow-6r")
    store = tmp_path / "store"
    r = invoke("session", "new", "--robot", "coupled-elbow-6r", "--targets", targets, "--poses", 14, store=store)
    assert r.exit_code == 0, r.stdout + r.stderr  # the record-time sanity check passed: the data are consistent
    ref = r.stdout.strip().splitlines()[-1]
    st = SessionStore(store)
    contents = read_journal(st.session_dir(ref.split("@")[0]) / "journal.jsonl")
    q_plan = Plan.from_pose_documents(contents.start.plan).configurations  # model joints
    q_cmd = np.array([d.q_commanded for d in contents.measurements])
    np.testing.assert_allclose(q_cmd, spec.joints.to_controller(q_plan), atol=1e-12)
    obs, _ = load_observations(st, [ref])
    np.testing.assert_allclose(obs.q, q_plan, atol=1e-6)


def test_a_bad_argument_to_session_new_creates_no_store(tmp_path, targets):
    r = invoke("session", "new", "--robot", "no-such-robot", "--targets", targets, "--poses", 3, store=tmp_path / "s")
    one_line_error(r, "no-such-robot")
    r = invoke("session", "new", "--robot", "ur10", "--targets", tmp_path / "none.toml", "--poses", 3,
               store=tmp_path / "s")  # fmt: skip
    assert r.exit_code == 2 and "Traceback" not in r.stderr
    assert not (tmp_path / "s").exists()


def test_fit_refuses_two_versions_of_one_session(tmp_path):
    # a resumed session's v002 holds v001's rows: pooling both would count those poses twice
    from sessions_testutil import record_interrupted

    from labcal.cli.ops.sessions import resume_session
    from labcal.robots import load

    st = SessionStore(tmp_path / "store")
    first = record_interrupted(st, load("ur10"), n_poses=40, interrupt_at=30)
    second = resume_session(st, first.session_id).ref
    r = invoke("fit", first.ref, second, "--method", "local-poe", store=st.root)
    assert r.exit_code == 2 and r.stderr.startswith("error: ")
    assert f"{first.ref} and {second} are two versions of one session, which share rows" in r.stderr


def test_the_plan_keeps_to_the_workspace_of_the_profile_the_robot_was_opened_with(tmp_path, targets):
    # `session new` opens the robot from its profile, then plans; a profile edited in between must not give the
    # planner another cell than the one belonging to the limits the robot checks every move against.
    from labcal.cli.ops.sessions import SessionRequest, plan_cell
    from labcal.drivers.ur import URRobot, load_ur_profile
    from labcal.robots import load

    repo = Path(__file__).resolve().parents[2]
    text = (repo / "drivers" / "ur10-lab.toml").read_text()
    profile = tmp_path / "ur.toml"
    box = "\n[workspace]\nallowed_min_mm = [{0}, {0}, -300.0]\nallowed_max_mm = [{1}, {1}, 1500.0]\n"
    profile.write_text(text + box.format(-1000.0, 1000.0))
    robot = URRobot(load_ur_profile(profile), receive=None)  # planning reads no controller
    profile.write_text(text + box.format(-500.0, 500.0))  # edited while the session was starting
    request = SessionRequest(
        robot="ur10", targets_file=targets, poses=3, robot_driver="ur", tracker_driver="serial",
        profile=str(profile), tracker_profile=str(repo / "drivers" / "ndi-polaris.toml"),
    )  # fmt: skip
    cell = plan_cell(request, load("ur10"), None, robot)
    assert cell["safety"] is robot.limits
    assert cell["workspace"] == robot.profile.workspace
    assert cell["workspace"].allowed.hi[0] == pytest.approx(1.0)
