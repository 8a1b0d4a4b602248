"""The lab fault table (issue 25): what each hardware fault does to a `labcal session new` run on the real drivers.

    python benchmarks/lab_faults.py [--poses 8] [--out benchmarks/results/lab_faults.txt]
    python benchmarks/lab_faults.py --src /path/to/old/labcal/src --out benchmarks/results/lab_faults_before.txt

Every scenario starts the fakes (:class:`labcal_fakes.rehearse.Rehearsal`: the fake UR controller in its own
process on loopback, the fake NDI tracker on a pty), runs ``labcal session new --robot-driver ur --tracker-driver
serial`` in a child process on a small cell (the ur10 with ±0.1 rad joint ranges, so a pose takes about a second),
injects the fault once the first measurement is journaled (faults at open: before the run), and measures:

- seconds from the fault to the end of the process, and to the stop document (``-``: none was written);
- the exit code (negative: killed by that signal, e.g. -11 SIGSEGV), and whether the process had to be killed
  after ``--cap`` s (``hung``);
- measurements kept (valid documents in the journal);
- resumes?: the device is restored (a new controller or tracker, cleared stop) and ``labcal session resume`` runs;
  "yes" when it ends with exit 0 and every pose measured (poses rejected before the fault stopped the run stay
  rejected: a resume measures the poses without a final outcome); "reruns" for a fault at open (nothing was
  recorded: the same command is run again).

The drivers find the fakes through copies of drivers/ur10-lab.toml and drivers/ndi-polaris.toml whose ``host`` and
``[port] url`` are rewritten (no --robot-host / --tracker-port), so ``--src`` can time an older labcal the same way.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from labcal.robots import builtin_path
from labcal_fakes.rehearse import HOME, Rehearsal

REPO = Path(__file__).resolve().parents[1]
TARGETS = REPO / "drivers" / "targets-example.toml"


def cell_robot(folder: Path, half: float = 0.1) -> Path:
    text = builtin_path("ur10").read_text().replace('name = "ur10"', 'name = "ur10-cell"', 1)
    centres = iter(HOME)
    text = re.sub(r"(?m)^limits = .*$", lambda _: (lambda c: f"limits = [{c - half}, {c + half}]")(next(centres)), text)
    path = folder / "ur10-cell.toml"
    path.write_text(text)
    return path


def write_profiles(folder: Path, rig: Rehearsal, port: str | None = None) -> tuple[Path, Path]:
    """Profile copies pointing at the rig's current controller and tracker (rewritten when one is replaced)."""
    ur = re.sub(r"(?m)^host = .*$", f'host = "{rig.host}"', (REPO / "drivers" / "ur10-lab.toml").read_text())
    # the watchdog keys at their defaults, left out so that an older labcal (--src) reads the profile too
    ur = re.sub(r"(?m)^(watchdog_timeout_s|call_timeout_s) = .*\n", "", ur)
    url = port or rig.port
    ndi = re.sub(r"(?m)^url = .*$", f'url = "{url}"', (REPO / "drivers" / "ndi-polaris.toml").read_text())
    (folder / "ur.toml").write_text(ur)
    (folder / "ndi.toml").write_text(ndi)
    return folder / "ur.toml", folder / "ndi.toml"


def default_sigint() -> None:
    """In the child: SIGINT back to its default. Started in the background (`nohup … &`), this script ignores SIGINT,
    the child would inherit that, and Python then never raises KeyboardInterrupt (the Ctrl-C row would lie)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def journal(store: Path) -> list[dict]:
    paths = list(store.glob("*/journal.jsonl"))
    if not paths:
        return []
    return [json.loads(line) for line in paths[0].read_text().splitlines() if line.strip()]


def has_measurement(store: Path) -> bool:
    return any('"measurement"' in p.read_text() for p in store.glob("*/journal.jsonl"))


# fault -> (when, what injects it, what restores the device), the last two Rehearsal methods. when: "open" (before the
# run) or "run" (once the first measurement is journaled).
SCENARIOS = {
    "controller killed mid-run": ("run", "kill_controller", "start_controller"),
    "RTDE connections dropped mid-run": ("run", "drop_rtde", None),
    "controller hangs (timestamp frozen)": ("run", "freeze_controller", "start_controller"),
    "protective stop during a move": ("run", "protective_stop_next_move", "clear_protective_stop"),
    "tracker unplugged mid-run": ("run", "kill_tracker", "start_tracker"),
    "tracker sends garbage mid-run": ("run", "send_garbage", "send_points"),
    "Ctrl-C in the terminal mid-run": ("run", "ctrl-c", None),
    "controller refuses (nothing at host) at open": ("open", "kill_controller", "start_controller"),
    "serial port missing at open": ("open", "missing port", None),
    "tracker silent at open": ("open", "silence_tracker", "start_tracker"),
}


def run_scenario(name: str, poses: int, src: Path, cap: float) -> dict:
    when, inject_name, restore_name = SCENARIOS[name]
    env = {**os.environ, "PYTHONPATH": str(src)}
    with (
        tempfile.TemporaryDirectory(prefix="lab-faults-") as tmp,
        Rehearsal(TARGETS, robot=str(cell_robot(Path(tmp)))) as rig,
    ):
        folder, store = Path(tmp), Path(tmp) / "store"
        # a closed pty's name is soon another terminal's: a port that is missing is a path that never existed
        missing = str(folder / "ttyGONE") if inject_name == "missing port" else None
        if inject_name == "ctrl-c":  # a terminal's Ctrl-C reaches the whole process group
            inject = lambda: os.killpg(process.pid, signal.SIGINT)  # noqa: E731
        else:
            inject = getattr(rig, inject_name) if missing is None else lambda: None
        ur, ndi = write_profiles(folder, rig, missing)
        command = [
            sys.executable, "-m", "labcal.cli.app", "session", "new", "--robot", str(folder / "ur10-cell.toml"),
            "--targets", str(TARGETS), "--poses", str(poses), "--robot-driver", "ur", "--tracker-driver", "serial",
            "--profile", str(ur), "--tracker-profile", str(ndi), "--store", str(store),
        ]  # fmt: skip
        if when == "open":
            inject()
        process = subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
            preexec_fn=default_sigint,
        )  # fmt: skip
        if when == "run":
            while not has_measurement(store) and process.poll() is None:
                time.sleep(0.01)
            inject()
        fault_at = time.time()
        try:
            _, err = process.communicate(timeout=cap)
            hung = False
        except subprocess.TimeoutExpired:
            process.kill()
            _, err = process.communicate()
            hung = True
        ended = time.time() - fault_at
        docs = journal(store)
        stops = [d for d in docs if d.get("type") == "stop"]
        kept = sum(d.get("type") == "measurement" and d.get("status") == "valid" for d in docs)
        row = {
            "fault": name,
            "stopped_s": ended,
            "stop_doc_s": (stops[-1]["time"] - fault_at) if stops else None,
            "exit": "hung" if hung else process.returncode,
            "status": stops[-1]["exit_status"] if stops else "-",
            "kept": kept,
            "lines": len([ln for ln in err.splitlines() if ln.strip()]),
            "traceback": "Traceback" in err,
            "resumes": "-",
        }
        session = docs[0]["session_id"] if docs else None
        if restore_name is not None:
            getattr(rig, restore_name)()
        write_profiles(folder, rig)
        if session is None:
            # nothing was recorded: "resuming" is running the same command again
            again = subprocess.run(command, env=env, capture_output=True, text=True, timeout=cap)
            row["resumes"] = "reruns" if again.returncode == 0 else f"no (exit {again.returncode})"
        else:
            resumed = subprocess.run(
                [sys.executable, "-m", "labcal.cli.app", "session", "resume", session, "--store", str(store)],
                env=env, capture_output=True, text=True, timeout=cap,
            )  # fmt: skip
            docs = journal(store)
            done = {d["pose_index"] for d in docs if d.get("type") == "measurement"}
            valid = sum(d.get("type") == "measurement" and d.get("status") == "valid" for d in docs)
            ok = resumed.returncode == 0 and len(done) == poses
            last = (resumed.stderr.strip().splitlines() or [""])[-1][:160]
            row["resumes"] = f"yes ({valid}/{poses} valid)" if ok else f"no (exit {resumed.returncode}: {last})"
        return row


def table(rows: list[dict], poses: int, src: Path) -> str:
    lines = [
        f"lab fault table: `labcal session new` on the ur + serial drivers against the fakes, {poses} poses "
        f"(labcal from {src})",
        "",
        "| fault | s until the run stops | s until the stop document | exit code | run status | measurements kept "
        "| stderr lines (traceback?) | resumes? |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        stop_doc = "-" if r["stop_doc_s"] is None else f"{r['stop_doc_s']:.1f}"
        tb = " (traceback)" if r["traceback"] else ""
        lines.append(
            f"| {r['fault']} | {r['stopped_s']:.1f} | {stop_doc} | {r['exit']} | {r['status']} | {r['kept']} "
            f"| {r['lines']}{tb} | {r['resumes']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=8)
    parser.add_argument("--src", type=Path, default=REPO / "src", help="labcal source tree the CLI runs from")
    parser.add_argument("--cap", type=float, default=120.0, help="kill a run still going after this many s")
    parser.add_argument("--only", nargs="*", default=None, help="scenario names (substring match)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    names = [n for n in SCENARIOS if args.only is None or any(o in n for o in args.only)]
    rows = []
    for name in names:
        rows.append(run_scenario(name, args.poses, args.src.resolve(), args.cap))
        print(f"  {name}: {rows[-1]}", file=sys.stderr, flush=True)
    text = table(rows, args.poses, args.src.resolve())
    print(text, end="")
    if args.out is not None:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
