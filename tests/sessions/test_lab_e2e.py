"""`labcal session new / resume` with the real `ur` and `serial` drivers, end to end, against the fakes.

The command runs in its own process, as a lab runs it; the fake UR controller (RTDE, dashboard, script ports) runs
in another, on a loopback address; the fake NDI tracker is on a pty served from this process; both see one
simulated robot (:class:`labcal_fakes.rehearse.Rehearsal`). Faults are injected once the first measurement is in
the journal. Each test reads the journal itself (JSON lines: start, measurements, pause/resume, stop) and the exit
code. Poses are few and the cell small (a robot file whose joint limits are ±0.1 rad about the home pose), so a
session takes a few seconds; how fast each fault stops a run is measured by ``benchmarks/lab_faults.py``, not here.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from labcal.robots import builtin_path
from labcal_fakes.rehearse import HOME, Rehearsal

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[2]
TARGETS = REPO / "drivers" / "targets-example.toml"
UR_PROFILE = REPO / "drivers" / "ur10-lab.toml"
NDI_PROFILE = REPO / "drivers" / "ndi-polaris.toml"
HANG = 60  # s: a run still going after this is hung (the fault table measures the real times)


def cell_robot(folder: Path, half: float = 0.1) -> Path:
    """The ur10 with every joint limited to HOME ± half rad: short moves, so a pose takes about a second."""
    text = builtin_path("ur10").read_text().replace('name = "ur10"', 'name = "ur10-cell"', 1)
    centres = iter(HOME)
    text = re.sub(r"(?m)^limits = .*$", lambda _: (lambda c: f"limits = [{c - half}, {c + half}]")(next(centres)), text)
    path = folder / "ur10-cell.toml"
    path.write_text(text)
    return path


def quick_profile(folder: Path) -> Path:
    """drivers/ur10-lab.toml without its settle wait (the plan's own settle stays): a second less per run."""
    text = re.sub(r"(?m)^settle_time_s = .*$", "settle_time_s = 0.0", UR_PROFILE.read_text())
    path = folder / "ur10-quick.toml"
    path.write_text(text)
    return path


def labcal(*args: str) -> list[str]:
    return [sys.executable, "-m", "labcal.cli.app", *args]


def new_args(store: Path, robot: Path | str, rig: Rehearsal, poses: int, profile: Path | None = None) -> list[str]:
    profile = profile or quick_profile(store.parent)
    return labcal(
        "session", "new", "--robot", str(robot), "--targets", str(TARGETS), "--poses", str(poses),
        "--robot-driver", "ur", "--tracker-driver", "serial", "--profile", str(profile),
        "--tracker-profile", str(NDI_PROFILE), "--store", str(store), *rig.session_args(),
    )  # fmt: skip


def journal(store: Path) -> list[dict]:
    (path,) = store.glob("*/journal.jsonl")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def measured(docs: list[dict]) -> dict[int, str]:
    return {d["pose_index"]: d["status"] for d in docs if d.get("type") == "measurement"}


def stop(docs: list[dict]) -> dict:
    stops = [d for d in docs if d.get("type") == "stop"]
    assert stops, f"no stop document in {[d.get('type') for d in docs]}"
    return stops[-1]


def run_with_fault(command: list[str], store: Path, inject, process=None) -> subprocess.CompletedProcess:
    """Run ``command`` (or watch ``process``, running it); once the journal holds a measurement, call ``inject()``;
    wait for the command to end."""
    if process is None:
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + HANG
    while not any('"measurement"' in p.read_text() for p in store.glob("*/journal.jsonl")):
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            out, err = process.communicate()
            pytest.fail(f"the run ended (or hung) before its first measurement: {out}\n{err}")
        time.sleep(0.02)
    inject()
    try:
        out, err = process.communicate(timeout=HANG)
    except subprocess.TimeoutExpired:
        process.kill()
        pytest.fail("the run did not stop after the fault")
    return subprocess.CompletedProcess(command, process.returncode, out, err)


def run(command: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, timeout=HANG)


def resume_hint(result: subprocess.CompletedProcess) -> list[str]:
    """The resume command a failed or paused run printed (its arguments after `labcal`)."""
    found = re.search(r"continue with: labcal (session resume .*)$", result.stderr, re.M)
    assert found, result.stderr
    return found.group(1).split()


@pytest.fixture
def cell(tmp_path):
    return cell_robot(tmp_path)


@pytest.fixture
def rig(cell):
    with Rehearsal(TARGETS, robot=str(cell)) as rehearsal:
        yield rehearsal


def test_a_small_session_records_every_pose_on_the_real_drivers(tmp_path, cell, rig):
    store = tmp_path / "store"
    result = run(new_args(store, cell, rig, poses=3))
    assert result.returncode == 0, result.stderr
    docs = journal(store)
    assert measured(docs) == {0: "valid", 1: "valid", 2: "valid"}
    assert stop(docs)["exit_status"] == "success"
    start = docs[0]
    assert start["metadata"]["overrides"] == {"robot_host": rig.host, "tracker_port": rig.port}
    assert start["metadata"]["unit"] == "20185500001"  # the fake controller's serial, over the dashboard
    assert result.stdout.strip().splitlines()[-1].endswith("@v001")


def test_a_profile_narrowed_to_the_cell_records_every_pose(tmp_path, rig):
    profile = tmp_path / "ur10-cell-profile.toml"
    lower = ", ".join(f"{v * 57.29577951308232 - 5.0:.3f}" for v in HOME)
    upper = ", ".join(f"{v * 57.29577951308232 + 5.0:.3f}" for v in HOME)
    text = re.sub(r"(?ms)^\[joint_limits_deg\].*?(?=^\[|\Z)", "", UR_PROFILE.read_text())
    profile.write_text(text + f"\n[joint_limits_deg]\nlower = [{lower}]\nupper = [{upper}]\n")
    store = tmp_path / "store"
    result = run(new_args(store, "ur10", rig, poses=3, profile=profile))
    docs = journal(store)
    assert stop(docs)["exit_status"] == "success", stop(docs)["reason"]
    assert measured(docs) == {0: "valid", 1: "valid", 2: "valid"}
    assert result.returncode == 0


def test_a_tracker_that_dies_fails_the_run_and_the_session_resumes_on_a_new_port(tmp_path, cell, rig):
    store = tmp_path / "store"
    first = run_with_fault(new_args(store, cell, rig, poses=3), store, rig.kill_tracker)
    assert first.returncode == 1, first.stderr
    docs = journal(store)
    assert stop(docs)["exit_status"] == "failed" and "ConnectionFailed" in stop(docs)["reason"]
    kept = measured(docs)
    assert kept and set(kept.values()) == {"valid"}
    hint = resume_hint(first)
    assert hint[:3] == ["session", "resume", docs[0]["session_id"]] and "--store" in hint

    gone = run(labcal(*hint, "--tracker-port", str(tmp_path / "ttyGONE")))  # not plugged in yet: one line
    assert gone.returncode == 2
    (line,) = gone.stderr.strip().splitlines()
    assert line.startswith(f"error: cannot use the tracker on {tmp_path / 'ttyGONE'}: ")
    assert line.endswith(f"No such file or directory: '{tmp_path / 'ttyGONE'}' (check --tracker-port)")
    port = rig.start_tracker()  # plugged in again, on another port
    second = run(labcal(*hint, "--tracker-port", port))
    assert second.returncode == 0, second.stderr
    docs = journal(store)
    assert measured(docs) == dict.fromkeys(range(3), "valid")
    assert [d["type"] for d in docs].count("resume") == 1
    assert stop(docs)["exit_status"] == "success"


def test_a_controller_that_dies_mid_run_fails_the_run_with_a_stop_document(tmp_path, cell, rig):
    store = tmp_path / "store"
    result = run_with_fault(new_args(store, cell, rig, poses=3), store, rig.kill_controller)
    assert result.returncode == 1, result.stderr  # not -11 (SIGSEGV), not a hang
    docs = journal(store)
    end = stop(docs)
    assert end["exit_status"] == "failed"
    assert rig.host in end["reason"]
    assert len(measured(docs)) < 3 and set(measured(docs).values()) == {"valid"}
    assert "Traceback" not in result.stderr

    host = rig.start_controller()  # the controller is back (perhaps on another address)
    again = run(labcal(*resume_hint(result), "--robot-host", host))
    assert again.returncode == 0, again.stderr
    assert measured(journal(store)) == dict.fromkeys(range(3), "valid")


def test_an_rtde_connection_drop_fails_the_run_without_a_crash(tmp_path, cell, rig):
    store = tmp_path / "store"
    result = run_with_fault(new_args(store, cell, rig, poses=3), store, rig.drop_rtde)
    assert result.returncode == 1, result.stderr  # the old driver crashed here with SIGSEGV (-11)
    docs = journal(store)
    assert stop(docs)["exit_status"] == "failed"
    assert set(measured(docs).values()) == {"valid"}
    assert "Traceback" not in result.stderr


def test_a_protective_stop_pauses_the_run_and_it_resumes_once_cleared(tmp_path, cell, rig):
    store = tmp_path / "store"
    result = run_with_fault(new_args(store, cell, rig, poses=3), store, rig.protective_stop_next_move)
    assert result.returncode == 1, result.stderr
    docs = journal(store)
    assert stop(docs)["exit_status"] == "paused"
    assert [d["type"] for d in docs].count("pause") == 1
    hint = resume_hint(result)

    refused = run(labcal(*hint))  # still stopped: refused before anything moves
    assert refused.returncode == 2 and "protective stop" in refused.stderr
    rig.clear_protective_stop()
    again = run(labcal(*hint))
    assert again.returncode == 0, again.stderr
    docs = journal(store)
    assert measured(docs) == dict.fromkeys(range(3), "valid")
    assert stop(docs)["exit_status"] == "success"


def test_ctrl_c_in_the_terminal_stops_the_robot_and_the_run_resumes(tmp_path, cell, rig):
    # A terminal's Ctrl-C reaches the whole process group: labcal and its ur-rtde processes.
    store = tmp_path / "store"
    command = new_args(store, cell, rig, poses=3)
    # SIGINT back to its default in the child: a test run started in the background ignores it, and so would the child
    default = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=default
    )
    result = run_with_fault(command, store, lambda: os.killpg(process.pid, signal.SIGINT), process)
    assert result.returncode == 130, result.stderr
    docs = journal(store)
    assert stop(docs)["exit_status"] == "aborted"
    log = rig.controller.snapshot()["log"]
    assert ["command", 34] in log or ["dashboard", "stop"] in log, log[-6:]  # stopJ, or the program stopped
    again = run(labcal(*resume_hint(result)))
    assert again.returncode == 0, again.stderr
    assert measured(journal(store)) == dict.fromkeys(range(3), "valid")


def test_sigterm_to_labcal_alone_stops_the_robot_and_writes_the_stop_record(tmp_path, cell, rig):
    """A supervisor's `kill PID` reaches labcal only (its ur-rtde processes keep running): by default Python died on
    the spot, leaving the move in progress running and no stop record; it takes Ctrl-C's path instead."""
    store = tmp_path / "store"
    command = new_args(store, cell, rig, poses=3)
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    result = run_with_fault(command, store, lambda: process.send_signal(signal.SIGTERM), process)
    assert result.returncode == 128 + signal.SIGTERM, result.stderr
    assert "interrupted by SIGTERM" in result.stderr and "Traceback" not in result.stderr
    docs = journal(store)
    assert stop(docs)["exit_status"] == "aborted"
    assert "interrupted by SIGTERM" in stop(docs)["reason"]
    log = rig.controller.snapshot()["log"]
    assert ["command", 34] in log or ["dashboard", "stop"] in log, log[-6:]  # stopJ, or the program stopped
    again = run(labcal(*resume_hint(result)))
    assert again.returncode == 0, again.stderr
    assert measured(journal(store)) == dict.fromkeys(range(3), "valid")


def test_unreachable_devices_are_one_line_naming_what_to_fix(tmp_path, cell, rig):
    store = tmp_path / "store"
    refused = run([*new_args(store, cell, rig, poses=3)[:-4], "--robot-host", "127.0.0.1", "--tracker-port", rig.port])
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        "error: cannot use the UR controller at 127.0.0.1: cannot connect to 127.0.0.1:30004: Connection refused "
        "(check --robot-host)"
    ]
    missing = run([*new_args(store, cell, rig, poses=3)[:-2], "--tracker-port", str(tmp_path / "ttyNONE")])
    assert missing.returncode == 2
    (line,) = missing.stderr.strip().splitlines()
    assert line.startswith(f"error: cannot use the tracker on {tmp_path / 'ttyNONE'}: ") and "--tracker-port" in line
    assert not store.exists() or not list(store.glob("*/journal.jsonl"))  # nothing recorded, nothing moved


def test_garbage_from_the_tracker_stops_the_run_after_the_bounded_count(tmp_path, cell, rig):
    rig.garbage = True
    store = tmp_path / "store"
    result = run([*new_args(store, cell, rig, poses=8), "--max-failed-poses", "2"])
    assert result.returncode == 1
    docs = journal(store)
    assert measured(docs) == {0: "rejected", 1: "rejected"}  # not all 8 poses
    assert "2 consecutive poses rejected" in stop(docs)["reason"]


def test_the_hardware_test_options_work_as_the_readme_says(rig):
    # README: `pytest -m hardware --tracker-port=/dev/ttyUSB0 … FILES`, run against the fakes. (Written
    # `--tracker-port /dev/ttyUSB0` without a test path, pytest takes the existing device for the rootdir, never
    # loads tests/conftest.py and refuses the option: the README's old line.)
    env = {**os.environ, "LABCAL_TRACKER_TARGETS": str(TARGETS), "LABCAL_ALLOW_MOTION": "1"}
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-m", "hardware",
         f"--tracker-port={rig.port}", f"--robot-host={rig.host}", "tests/drivers/test_serial_hardware.py",
         "tests/drivers/test_ur_hardware.py"],
        capture_output=True, text=True, timeout=HANG, cwd=REPO, env=env,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    assert re.search(r"\b5 passed", result.stdout), result.stdout  # 2 tracker, 3 robot tests (one moves the fake)


def test_ctrl_c_stops_the_rehearsal_quietly():
    """The rehearsal's one instruction is "Ctrl-C stops the fakes": the terminal's SIGINT reaches the fake
    controller's own process too, which must leave stopping to the rig instead of dying with a traceback."""
    default = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
    command = [sys.executable, "-m", "labcal_fakes.rehearse", "--targets", str(TARGETS)]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=default
    )
    try:
        assert process.stdout is not None
        deadline = time.monotonic() + HANG
        # The first line, not the last: Ctrl-C while the instructions are still being printed must stop it as quietly.
        while "fake UR controller on" not in process.stdout.readline():
            assert time.monotonic() < deadline and process.poll() is None, "the rehearsal did not start"
        os.killpg(process.pid, signal.SIGINT)
        _, err = process.communicate(timeout=HANG)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 0, err
    assert "Traceback" not in err, err
