"""Bad-input cases (issue 12 acceptance): every mistake we could think of, fed through the real CLI.

Each case writes its files into a fresh temporary folder and store and runs the commands a user would run —
``labcal session import … → labcal fit … → labcal export …`` (default options: ``fit`` chooses with ``auto``,
``export`` without ``--force``) — or the session / compensator command the fault is about. It prints one row per
case: where the mistake was stopped (``import`` / ``fit`` / ``export`` / the command of a special case / ``NOT
stopped`` when a compensator came out), the first line of the message, the exit code, and whether a Python
traceback reached the user.

Expectations: ``must-stop`` — issue 12's independent check: no compensator may come out of a unit slip, identical
poses or pure noise without ``--force``; ``stop`` — a mistake that should be refused or gated; ``pass`` — good data
that must go through untouched (no stop, no ``--force``); ``clean-error`` — a fault that must end in a one-line
error (no traceback) with a non-zero exit code. The verdict column says ``ok``, ``FAIL`` (a must-stop case got
through, a pass case was stopped, a clean-error case printed a traceback or exited 0) or ``open`` (a ``stop``
case got through).

Data: a simulated ``ur10`` (``ErrorSpec.default``) measured at 60 random non-singular poses, three targets
(``TARGETS`` of benchmarks/scenarios.py) in a targets TOML in mm, CSV in metres and radians unless the case
says otherwise; the corruptions come from benchmarks/scenarios.py.

The acceptance suite (tests/acceptance/test_bad_inputs.py) runs each case as one test that fails unless the verdict
is ``ok``; ``python benchmarks/bad_inputs.py [--cases NAME …] [--method auto] [--out FILE]`` prints them as one
table. Each case takes a few seconds (``fit`` with ``auto``).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import scenarios as S
from labcal.robots import builtin_path
from labcal.simulation import ErrorSpec

TIMEOUT = 900.0  # s per command: fit with auto on a loaded machine
MEMORY_LIMIT = 3 * 1024**3  # bytes of address space for a child that might try to allocate without bound


def labcal_command() -> list[str]:
    """The ``labcal`` console script of this interpreter's environment (else ``python -c`` on the same entry)."""
    script = Path(sys.executable).with_name("labcal")
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from labcal.cli.app import main; sys.exit(main())"]


@dataclass
class Outcome:
    stage: str  # where it was stopped, or "NOT stopped"
    message: str
    code: int | None
    traceback: bool = False


@dataclass
class Run:
    code: int | None
    out: str
    err: str

    @property
    def traceback(self) -> bool:
        return "Traceback (most recent call last)" in self.err or "Traceback (most recent call last)" in self.out

    def first_line(self) -> str:
        """The line a user reads first: the first 'error…' line, else the first stderr line, else stdout's last."""
        lines = [ln.strip() for ln in (self.err + "\n" + self.out).splitlines() if ln.strip()]
        for i, ln in enumerate(lines):
            low = ln.lower()
            if low.startswith(("error", "refus", "warning")) or " error:" in low:
                # A summary line ("3 sanity checks failed") is followed by the named checks: show the first.
                detail = lines[i + 1] if i + 1 < len(lines) and lines[i + 1].startswith("[") else ""
                return (ln + (" | " + detail if detail else ""))[:220]
        errs = [ln.strip() for ln in self.err.splitlines() if ln.strip()]
        if errs:
            return errs[-1][:160] if self.traceback else errs[0][:160]
        outs = [ln.strip() for ln in self.out.splitlines() if ln.strip()]
        return outs[-1][:160] if outs else ""


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def _interruptible() -> None:
    """_limit_memory, and SIGINT back to its default: a benchmark started in the background (`nohup … &`) ignores
    SIGINT, the child would inherit that, and Python then never raises KeyboardInterrupt (the Ctrl-C case hung)."""
    _limit_memory()
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run(args: list[str], *, cwd: Path, timeout: float = TIMEOUT, env: dict | None = None) -> Run:
    """Run one labcal command (bounded in time and memory); never raises."""
    try:
        p = subprocess.run(
            labcal_command() + args, cwd=cwd, capture_output=True, text=True, timeout=timeout,
            env={**os.environ, "COLUMNS": "200", **(env or {})}, preexec_fn=_limit_memory,
        )  # fmt: skip
    except subprocess.TimeoutExpired as e:
        return Run(None, str(e.stdout or ""), f"killed after {timeout:g} s (timeout)")
    return Run(p.returncode, p.stdout, p.stderr)


def python(code: str, *, cwd: Path, timeout: float = 300.0) -> Run:
    """Run a Python snippet with this interpreter (for the compensator API cases)."""
    try:
        p = subprocess.run(
            [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=timeout,
            preexec_fn=_limit_memory,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        return Run(None, "", f"killed after {timeout:g} s (timeout)")
    return Run(p.returncode, p.stdout, p.stderr)


# ----------------------------------------------------------------------------------------------------------------
# files
def write_targets(path: Path, targets: np.ndarray) -> Path:
    rows = ", ".join("[" + ", ".join(f"{v * 1e3:.6f}" for v in t) + "]" for t in targets)
    path.write_text(f'unit = "mm"\npoints = [{rows}]\n')
    return path


def write_csv(path: Path, q: np.ndarray, points: np.ndarray, *, length: float = 1.0, angle: float = 1.0) -> Path:
    """CSV with q1..qn and t1_x … t3_z; ``length`` and ``angle`` multiply the values (units of the file)."""
    n = q.shape[1]
    head = [f"q{j + 1}" for j in range(n)] + [f"t{i + 1}_{a}" for i in range(3) for a in "xyz"]
    lines = [",".join(head)]
    for qi, pi in zip(q * angle, points.reshape(len(points), 9) * length, strict=True):
        lines.append(",".join(repr(float(v)) for v in (*qi, *pi)))
    path.write_text("\n".join(lines) + "\n")
    return path


def robot_file_scaled(path: Path, *, lengths: float = 1.0, degrees: bool = False) -> Path:
    """The built-in ur10 file with its lengths multiplied (mm) or its angles written in degrees."""
    import re

    text = builtin_path("ur10").read_text()

    def scale(m: re.Match) -> str:
        key, value = m.group(1), float(m.group(2))
        if key in ("a", "d"):
            value *= lengths
        if key in ("alpha", "theta") and degrees:
            value = float(np.degrees(value))
        return f"{key} = {value!r}"

    text = re.sub(r"^(a|d|alpha|theta) = ([-0-9.e]+)", scale, text, flags=re.M)
    if degrees:

        def limits(m: re.Match) -> str:
            lo, hi = (float(np.degrees(float(v))) for v in m.groups())
            return f"limits = [{lo!r}, {hi!r}]"

        text = re.sub(r"limits = \[([-0-9.e]+), ([-0-9.e]+)\]", limits, text)
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------------------------------------------
# the pipeline a user runs
def pipeline(
    tmp: Path,
    csv: Path,
    targets: Path | None,
    import_args: list[str] = (),  # type: ignore[assignment]
    *,
    robot: str = "ur10",
    method: str = "auto",
    out_name: str = "compensator.json",
) -> tuple[Outcome, dict]:
    """import → fit → export (json, no --force). Returns the outcome and the refs/paths for follow-up steps."""
    store = tmp / "store"
    cmd = ["session", "import", str(csv), "--robot", robot, "--store", str(store), *import_args]
    if targets is not None:
        cmd += ["--targets", str(targets)]
    r = run(cmd, cwd=tmp)
    if r.code != 0:
        return Outcome("import", r.first_line(), r.code, r.traceback), {}
    ref = r.out.strip().splitlines()[-1].strip()
    ctx = {"ref": ref, "store": store, "import": r}
    r = run(["fit", ref, "--store", str(store), "--method", method], cwd=tmp)
    ctx["fit"] = r
    if r.code != 0:
        return Outcome("fit", r.first_line(), r.code, r.traceback), ctx
    out = tmp / out_name
    session = ref.split("@")[0]
    r = run(["export", session, "--format", "json", "--out", str(out), "--store", str(store)], cwd=tmp)
    ctx["export"], ctx["out"] = r, out
    if r.code != 0:
        return Outcome("export", r.first_line(), r.code, r.traceback), ctx
    fit_msg = ctx["fit"].first_line() if "warning" in ctx["fit"].first_line().lower() else ""
    return Outcome("NOT stopped", fit_msg or f"compensator written ({out.name})", 0, False), ctx


# ----------------------------------------------------------------------------------------------------------------
# the cases
@dataclass
class Case:
    name: str
    expect: str  # must-stop | stop | pass | clean-error | info
    what: str
    run: Callable[[Path, argparse.Namespace], Outcome]


def _base(seed: int = 0, k: int = 60) -> S.Scenario:
    return S.good("ur10", k, errors=ErrorSpec.default(), seed=seed)


def _data_case(make: Callable[[], S.Scenario], *, length=1.0, angle=1.0, import_args=(), robot="ur10", targets=None):
    """A case that writes a scenario's CSV (values × length / × angle) and runs the pipeline."""

    def go(tmp: Path, args) -> Outcome:
        scn = make()
        q = scn.q if scn.q_controller is None else scn.q_controller
        csv = write_csv(tmp / "data.csv", q, scn.points, length=length, angle=angle)
        tgt = write_targets(tmp / "targets.toml", scn.targets if targets is None else targets(scn))
        rob = robot(tmp) if callable(robot) else robot
        extra = list(getattr(args, "extra_import", ()))
        return pipeline(tmp, csv, tgt, [*import_args, *extra], robot=rob, method=args.method)[0]

    return go


def _good_then(follow: Callable[[Path, dict, argparse.Namespace], Outcome]):
    """Run the good pipeline, then a follow-up step on its store / compensator."""

    def go(tmp: Path, args) -> Outcome:
        scn = _base()
        csv = write_csv(tmp / "data.csv", scn.q, scn.points)
        tgt = write_targets(tmp / "targets.toml", scn.targets)
        outcome, ctx = pipeline(tmp, csv, tgt, method=args.local_method)
        forced = ""
        if outcome.stage == "export" and "fit" in ctx:
            # The follow-up is about the export / compensator, not the fit gate: force the setup's export.
            session, out = ctx["ref"].split("@")[0], tmp / "compensator.json"
            r = run(["export", session, "--format", "json", "--out", str(out), "--store", str(ctx["store"]), "--force"],
                    cwd=tmp)  # fmt: skip
            if r.code == 0:
                ctx["out"], outcome, forced = out, Outcome("NOT stopped", "", 0), " [setup export needed --force]"
        if outcome.stage != "NOT stopped":
            return Outcome(f"setup stopped at {outcome.stage}", outcome.message, outcome.code, outcome.traceback)
        result = follow(tmp, ctx, args)
        result.message += forced
        return result

    return go


def _export_again(tmp: Path, ctx: dict, args) -> Outcome:
    session = ctx["ref"].split("@")[0]
    before = ctx["out"].read_bytes()
    r = run(["export", session, "--format", "json", "--out", str(ctx["out"]), "--store", str(ctx["store"])], cwd=tmp)
    kept = ctx["out"].read_bytes() == before
    stage = "export" if r.code != 0 else "NOT stopped"
    return Outcome(stage, r.first_line() + ("" if kept else " [file changed]"), r.code, r.traceback)


def _unwritable_folder(tmp: Path) -> tuple[Path, Callable[[], None]]:
    """A folder this process cannot write into, and how to undo it.

    chmod does not stop root, so as root the folder is ``/proc`` (procfs refuses new files even to root).
    """
    if os.geteuid() == 0:
        return Path("/proc"), lambda: None
    locked = tmp / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
    return locked, lambda: locked.chmod(stat.S_IRWXU)


def _export_unwritable(tmp: Path, ctx: dict, args) -> Outcome:
    folder, undo = _unwritable_folder(tmp)
    try:
        session = ctx["ref"].split("@")[0]
        out = folder / "labcal-bad-inputs-c.json"
        r = run(["export", session, "--format", "json", "--out", str(out), "--store", str(ctx["store"]), "--force"],
                cwd=tmp)  # fmt: skip
    finally:
        undo()
    return Outcome("export" if r.code != 0 else "NOT stopped", r.first_line(), r.code, r.traceback)


def _compensator_api(snippet: str):
    def follow(tmp: Path, ctx: dict, args) -> Outcome:
        code = f"import json, numpy as np\nfrom labcal import compensator as C\npath = {str(ctx['out'])!r}\n{snippet}"
        r = python(code, cwd=tmp)
        stage = "compensator" if (r.code != 0 or "refused" in r.out) else "NOT stopped"
        msg = r.first_line()
        return Outcome(stage, msg, r.code, r.traceback)

    return follow


_EMPTY = """
comp = C.load(path)
out = comp.correct(np.zeros((0, 6)))
print("returned shape", np.asarray(out).shape)
"""
_PAPER = """
comp = C.load(path)
try:
    comp.correct(np.zeros(6) + 0.3, method="paper")
    print("no error: q returned uncorrected?")
except Exception as e:
    print("refused:", type(e).__name__, str(e).splitlines()[0])
"""


def _tamper(field: str, change: str) -> str:
    return f"""
data = json.loads(open(path).read())
{change}
open(path, "w").write(json.dumps(data))
try:
    comp = C.load(path)
    print("loaded the tampered file: {field} not covered")
except Exception as e:
    print("refused:", type(e).__name__, str(e).splitlines()[0])
"""


_TAMPER_RANGES = _tamper(
    "joint_ranges",
    """
def widen(d):
    for k, v in d.items():
        if k == "joint_ranges":
            d[k] = [[-10.0, 10.0] for _ in v]
            return True
        if isinstance(v, dict) and widen(v):
            return True
    return False
assert widen(data), "no joint_ranges field in the compensator file"
""",
)
_TAMPER_LENGTH = _tamper(
    "length_scale",
    """
def bump(d):
    for k, v in d.items():
        if k == "length_scale":
            d[k] = float(v) * 2
            return True
        if isinstance(v, dict) and bump(v):
            return True
    return False
assert bump(data), "no length_scale field in the compensator file"
""",
)


def _store_missing(tmp: Path, args) -> Outcome:
    r = run(["fit", "S@v001", "--store", str(tmp / "no-such-store")], cwd=tmp)
    return Outcome("fit" if r.code != 0 else "NOT stopped", r.first_line(), r.code, r.traceback)


def _store_readonly(tmp: Path, args) -> Outcome:
    scn = _base()
    folder, undo = _unwritable_folder(tmp)
    try:
        csv = write_csv(tmp / "data.csv", scn.q, scn.points)
        tgt = write_targets(tmp / "targets.toml", scn.targets)
        r = run(["session", "import", str(csv), "--robot", "ur10", "--targets", str(tgt), "--store", str(folder)],
                cwd=tmp)  # fmt: skip
    finally:
        undo()
    return Outcome("import" if r.code != 0 else "NOT stopped", r.first_line(), r.code, r.traceback)


def _huge_poses(tmp: Path, args) -> Outcome:
    tgt = write_targets(tmp / "targets.toml", S.TARGETS)
    r = run(["session", "new", "--robot", "ur10", "--targets", str(tgt), "--poses", "100000000",
             "--store", str(tmp / "store")], cwd=tmp, timeout=120)  # fmt: skip
    if r.code is None:
        return Outcome("NOT stopped", "still running after 120 s (killed by the benchmark)", None, r.traceback)
    return Outcome("session new" if r.code != 0 else "NOT stopped", r.first_line(), r.code, r.traceback)


def _journal_path(store: Path) -> Path | None:
    found = sorted(store.glob("*/journal.jsonl"))
    return found[0] if found else None


def _interrupted_session(tmp: Path, poses: int = 40) -> tuple[Run, Path]:
    """Start ``session new`` and send SIGINT (Ctrl-C) once a few measurements are journalled."""
    tgt = write_targets(tmp / "targets.toml", S.TARGETS)
    store = tmp / "store"
    cmd = [*labcal_command(), "session", "new", "--robot", "ur10", "--targets", str(tgt), "--poses", str(poses),
           "--store", str(store)]  # fmt: skip
    p = subprocess.Popen(cmd, cwd=tmp, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "COLUMNS": "200"}, preexec_fn=_interruptible)  # fmt: skip
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and p.poll() is None:
        j = _journal_path(store)
        if j is not None and j.is_file() and len(j.read_text().splitlines()) >= 6:
            break
        time.sleep(0.05)
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
    try:
        out, err = p.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
    return Run(p.returncode, out, err), store


def _ctrl_c(tmp: Path, args) -> Outcome:
    # Enough poses that the sim rig (milliseconds a pose on an idle machine) is still recording when SIGINT lands.
    r, _ = _interrupted_session(tmp, poses=20000)
    stage = "Ctrl-C" if r.code == 130 else ("NOT stopped" if r.code == 0 else "Ctrl-C (exit ≠ 130)")
    return Outcome(stage, r.first_line(), r.code, r.traceback)


def _corrupt_resume(tmp: Path, args) -> Outcome:
    r, store = _interrupted_session(tmp, poses=40)
    journal = _journal_path(store)
    if journal is None:
        return Outcome("setup failed", "no journal after the interrupted session", r.code, r.traceback)
    lines = journal.read_text().splitlines()
    measured = [i for i, ln in enumerate(lines) if '"measurement"' in ln]
    if len(measured) < 3:
        return Outcome("setup failed", f"only {len(measured)} measurements before Ctrl-C", r.code, r.traceback)
    middle = measured[len(measured) // 2]
    lines[middle] = lines[middle][: len(lines[middle]) // 2] + "#corrupt"
    journal.write_text("\n".join(lines) + "\n")
    before = len(lines)
    session = journal.parent.name
    r = run(["session", "resume", session, "--store", str(store)], cwd=tmp, timeout=600)
    grew = len(journal.read_text().splitlines()) - before
    note = f" [journal grew by {grew} lines: the robot moved]" if grew > 0 else " [no motion]"
    return Outcome("resume" if r.code != 0 and grew <= 0 else "NOT stopped", r.first_line() + note, r.code,
                   r.traceback)  # fmt: skip


def _coupled_map_robot(tmp: Path) -> str:
    path = builtin_path("coupled-elbow-6r")
    return str(path) if path.is_file() else "coupled-elbow-6r"


def _coupled_controller(mapped: bool) -> S.Scenario:
    """Good fanuc-m1000ia data whose joints are the coupled-elbow controller's (the example robot file's map)."""
    scn = S.good("fanuc-m1000ia", 60, errors=ErrorSpec.default(), seed=0)
    path = builtin_path("coupled-elbow-6r")
    if path.is_file():
        from labcal.robots import load

        q_ctrl = load(str(path)).joints.to_controller(scn.q)
    else:  # the example file is not there yet: the plain coupled elbow (model J3 = J2 + J3)
        q_ctrl = scn.q @ np.linalg.inv(S.coupled_map(6)).T
    return scn.changed("coupled", "controller joints", q_controller=q_ctrl)


def _one_outlier() -> S.Scenario:
    scn = _base()
    p = scn.points.copy()
    p[7] *= 1000.0
    return scn.changed("one-outlier", "row 7 in mm", points=p)


def _half_duplicated() -> S.Scenario:
    scn = _base(k=30)
    return scn.subset(np.repeat(np.arange(30), 2))


def _nan_row(tmp: Path, args) -> Outcome:
    scn = _base()
    p = scn.points.copy()
    p[5, 1, 2] = np.nan
    csv = write_csv(tmp / "data.csv", scn.q, p)
    return pipeline(tmp, csv, write_targets(tmp / "t.toml", scn.targets), method=args.method)[0]


def _tracker_as_base() -> S.Scenario:
    return S.in_tracker_frame(_base())


CASES: list[Case] = [
    Case("good", "pass", "60 good poses, m / rad, base frame", _data_case(_base)),
    Case("mm-as-m", "must-stop", "CSV in mm imported as m (points ×1000)", _data_case(_base, length=1000.0)),
    Case("m-as-mm", "must-stop", "CSV in m imported with --length-unit mm (×0.001)",
         _data_case(_base, import_args=("--length-unit", "mm"))),
    Case("inch-slip", "must-stop", "points ×25.4 (inches taken for mm)",
         _data_case(_base, length=25.4e3, import_args=("--length-unit", "mm"))),
    Case("deg-as-rad", "must-stop", "joints in degrees imported as radians", _data_case(_base, angle=180 / np.pi)),
    Case("rad-as-deg", "stop", "joints in radians imported with --angle-unit deg",
         _data_case(_base, import_args=("--angle-unit", "deg"))),
    Case("identical-60", "must-stop", "one pose measured 60 times", _data_case(lambda: S.identical_poses("ur10", 60))),
    Case("few-10", "stop", "only 10 poses", _data_case(lambda: S.few_poses("ur10", 10))),
    Case("pure-noise", "must-stop", "uniform random points", _data_case(lambda: S.pure_noise(_base(), seed=1))),
    Case("pure-noise-rigid", "must-stop", "the target triangle at random poses",
         _data_case(lambda: S.pure_noise(_base(), rigid=True, seed=1))),
    Case("shuffled-rows", "stop", "points paired with the wrong joints", _data_case(lambda: S.shuffled_rows(_base()))),
    Case("one-outlier-row", "stop", "one row of 60 in mm (×1000)", _data_case(_one_outlier)),
    Case("coupled-unconverted", "stop", "coupled-elbow controller joints imported for fanuc-m1000ia (no map)",
         _data_case(lambda: _coupled_controller(False), robot="fanuc-m1000ia")),
    Case("coupled-with-map", "pass", "the same controller joints with the coupled-elbow-6r robot file (joint map)",
         _data_case(lambda: _coupled_controller(True), robot=_coupled_map_robot)),
    Case("swapped-targets", "stop", "targets t1 and t2 swapped", _data_case(lambda: S.swapped_targets(_base()))),
    Case("wrong-targets", "stop", "targets file of another tool", _data_case(lambda: S.wrong_targets(_base()))),
    Case("tracker-as-base", "stop", "tracker-frame points imported as --frame base", _data_case(_tracker_as_base)),
    Case("tracker-frame", "pass", "tracker-frame points imported with --frame tracker",
         _data_case(_tracker_as_base, import_args=("--frame", "tracker"))),
    Case("sweeps-singular", "info", "36 poses in single-joint sweeps, most with q5 ≈ 0 (honest but hard)",
         _data_case(lambda: S.sweeps("ur10", 36, 4))),
    Case("duplicated-half", "info", "30 poses each measured twice (duplicates reported, kept in one fold)",
         _data_case(_half_duplicated)),
    Case("nan-in-row", "stop", "a NaN coordinate in row 5", _nan_row),
    Case("robot-in-mm", "stop", "robot file with lengths in mm",
         _data_case(_base, robot=lambda tmp: str(robot_file_scaled(tmp / "ur10-mm.toml", lengths=1000.0)))),
    Case("robot-in-deg", "stop", "robot file with angles in degrees",
         _data_case(_base, robot=lambda tmp: str(robot_file_scaled(tmp / "ur10-deg.toml", degrees=True)))),
    Case("export-existing", "stop", "export over an existing file without --force", _good_then(_export_again)),
    Case("export-unwritable", "clean-error", "export (--force) into a folder that cannot be written",
         _good_then(_export_unwritable)),
    Case("store-missing", "clean-error", "fit with --store pointing nowhere", _store_missing),
    Case("store-readonly", "clean-error", "import into a store folder that cannot be written", _store_readonly),
    Case("poses-1e8", "clean-error", "session new --poses 100000000", _huge_poses),
    Case("ctrl-c", "clean-error", "Ctrl-C during session new (exit 130 expected)", _ctrl_c),
    Case("journal-corrupt-resume", "clean-error", "corrupt middle journal line, then session resume", _corrupt_resume),
    Case("correct-empty", "pass", "compensator.correct(np.zeros((0, 6)))", _good_then(_compensator_api(_EMPTY))),
    Case("paper-on-local-poe", "stop", 'correct(q, method="paper") on a local-POE compensator',
         _good_then(_compensator_api(_PAPER))),
    Case("tampered-ranges", "stop", "compensator file with widened joint_ranges",
         _good_then(_compensator_api(_TAMPER_RANGES))),
    Case("tampered-length-scale", "stop", "compensator file with a changed length_scale",
         _good_then(_compensator_api(_TAMPER_LENGTH))),
]  # fmt: skip


#: Every import sanity check (``session import --allow CHECK``): the "+allow" cases let a mistake through the
#: import on purpose, so that the fit gates and the export gate are what must stop it.
IMPORT_CHECKS = (
    "target-distances", "target-outliers", "joint-limits", "joint-span", "nominal", "reach", "duplicates", "few-poses",
)  # fmt: skip
ALLOW_ALL = tuple(a for check in IMPORT_CHECKS for a in ("--allow", check))
_ALLOWED = {
    "mm-as-m": "must-stop", "m-as-mm": "must-stop", "deg-as-rad": "must-stop", "identical-60": "must-stop",
    "pure-noise": "must-stop", "pure-noise-rigid": "must-stop", "few-10": "stop", "shuffled-rows": "stop",
    "swapped-targets": "stop", "tracker-as-base": "stop", "coupled-unconverted": "stop",
}  # fmt: skip


def _with_allow(case: Case) -> Case:
    """The same data case imported with every sanity check overridden (--allow …): the fit/export must stop it."""
    inner = case.run

    def go(tmp: Path, args) -> Outcome:
        return inner(tmp, argparse.Namespace(**{**vars(args), "extra_import": ALLOW_ALL}))

    return Case(case.name + "+allow", _ALLOWED[case.name], case.what + "; import checks overridden (--allow all)", go)


CASES += [_with_allow(c) for c in CASES if c.name in _ALLOWED]


# ----------------------------------------------------------------------------------------------------------------
# labcal filter (issue 24 item 4): programs in the wrong units or dialects, singular rows, unsafe or failing writes.
# A compensator of a UR10 whose frames are off by ~0.5 mm / mrad is written directly (no fit), and a 4-row program
# on one well-conditioned branch; each case changes one thing.
FILTER_TIMEOUT = 120.0  # s: a filter of a few rows takes a second or two (before the fix, a FIFO --out blocked)
_FILTER_Q = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.4]) + np.linspace(0, 0.2, 4)[:, None] * [1, -1, 1, 1, -1, 1]


def _filter_setup(tmp: Path) -> tuple[Path, np.ndarray]:
    """The compensator file and the program's (4, 6) TCP poses (m, rotation vector rad)."""
    from labcal.compensator import CalibratedRobot, save
    from labcal.kinematics import se3
    from labcal.robots import load

    nominal = load("ur10").model
    model = nominal.perturbed(np.random.default_rng(7).normal(size=(nominal.n + 1, 6)) * 0.5e-3)
    comp = tmp / "ur10.json"
    save(CalibratedRobot(nominal, model, method="local-poe"), comp)
    T = nominal.fk(_FILTER_Q)
    return comp, np.concatenate([T[:, :3, 3], se3.log_so3(T[:, :3, :3])], axis=1)


def _rows(values: np.ndarray, head: str | None, sep: str = ",", decimal: str = ".") -> str:
    lines = [] if head is None else [head.replace(",", sep)]
    lines += [sep.join(repr(float(v)).replace(".", decimal) for v in row) for row in values]
    return "\n".join(lines) + "\n"


def _filter_outcome(r: Run) -> Outcome:
    return Outcome("filter" if r.code != 0 else "NOT stopped", r.first_line(), r.code, r.traceback)


def _filter_case(program: Callable[[np.ndarray], str], args: tuple[str, ...] = (), kind: str = "poses"):
    """A case that writes a program (from the poses, or from the joints for kind "joints") and runs filter."""

    def go(tmp: Path, _args) -> Outcome:
        comp, poses = _filter_setup(tmp)
        (tmp / "prog.csv").write_text(program(poses if kind == "poses" else _FILTER_Q))
        seed = ["--seed-joints", ",".join(repr(float(v)) for v in _FILTER_Q[0] + 0.02)] if kind == "poses" else []
        if "deg" in args and kind == "poses":
            seed = ["--seed-joints", ",".join(repr(float(v)) for v in np.degrees(_FILTER_Q[0] + 0.02))]
        r = run(["filter", "prog.csv", "--calibration", str(comp), "--kind", kind, *seed, *args, "--out", "out.csv"],
                cwd=tmp, timeout=FILTER_TIMEOUT)  # fmt: skip
        return _filter_outcome(r)

    return go


def _in_deg(poses: np.ndarray, length: float = 1.0) -> np.ndarray:
    return np.concatenate([poses[:, :3] * length, np.degrees(poses[:, 3:])], axis=1)


def _filter_unsafe_out(make: Callable[[Path], Path]):
    """filter --force onto a symlink or a device node: refused, and the thing there untouched."""

    def go(tmp: Path, _args) -> Outcome:
        comp, _ = _filter_setup(tmp)
        (tmp / "prog.csv").write_text(_rows(_FILTER_Q, "q1,q2,q3,q4,q5,q6"))
        target = make(tmp)
        before = os.lstat(target)
        r = run(["filter", "prog.csv", "--calibration", str(comp), "--kind", "joints", "--out", str(target),
                 "--force"], cwd=tmp, timeout=FILTER_TIMEOUT)  # fmt: skip
        after = os.lstat(target)
        kept = (before.st_mode, before.st_ino) == (after.st_mode, after.st_ino)
        if (tmp / "target.csv").exists():
            kept = kept and (tmp / "target.csv").read_text() == "keep me\n"
        o = _filter_outcome(r)
        if not kept:
            o.stage, o.message = "NOT stopped", o.message + " [replaced or written through]"
        return o

    return go


def _symlink_out(tmp: Path) -> Path:
    (tmp / "target.csv").write_text("keep me\n")
    (tmp / "link.csv").symlink_to(tmp / "target.csv")
    return tmp / "link.csv"


def _device_out(tmp: Path) -> Path:
    try:
        os.mknod(tmp / "null", 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except PermissionError:  # not root: a FIFO stands in for "not a regular file" (opened only if not refused)
        os.mkfifo(tmp / "null")
    return tmp / "null"


def _filter_full_disk(tmp: Path, _args) -> Outcome:
    """filter --force over an existing program when the disk fills mid-write (the file-size limit: EFBIG, as
    ENOSPC): the previous program must stay whole."""
    comp, _ = _filter_setup(tmp)
    (tmp / "prog.csv").write_text(_rows(np.repeat(_FILTER_Q, 750, axis=0), "q1,q2,q3,q4,q5,q6"))  # 3,000 rows
    out = tmp / "out.csv"
    out.write_text("previous program\n" * 100)
    before = out.read_bytes()

    def limit() -> None:
        _limit_memory()
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, resource.RLIM_INFINITY))

    p = subprocess.run(
        [*labcal_command(), "filter", "prog.csv", "--calibration", str(comp), "--kind", "joints", "--out", str(out),
         "--force"], cwd=tmp, capture_output=True, text=True, timeout=FILTER_TIMEOUT, preexec_fn=limit,
        env={**os.environ, "COLUMNS": "200"},
    )  # fmt: skip
    o = _filter_outcome(Run(p.returncode, p.stdout, p.stderr))
    if out.read_bytes() != before:
        lines = out.read_text(errors="replace").count("\n")
        o.stage, o.message = "NOT stopped", o.message + f" [previous program replaced by {lines} lines]"
    else:
        o.message += " [previous program intact]"
    return o


def _singular_rows(q: np.ndarray) -> str:
    q = q.copy()
    q[2, 2] = 1e-5  # row 3 a few µrad from the stretched elbow
    return _rows(q, "q1,q2,q3,q4,q5,q6")


CASES += [
    Case("filter-rotvec-deg", "stop", "filter: rotation vectors in degrees (norms of about 170)",
         _filter_case(lambda p: _rows(_in_deg(p), "x,y,z,rx,ry,rz"))),
    Case("filter-joints-deg-as-rad", "stop", "filter: a joint program in degrees without --angle-unit deg",
         _filter_case(lambda q: _rows(np.degrees(q), "q1,q2,q3,q4,q5,q6"), kind="joints")),
    Case("filter-mm-as-m", "stop", "filter: a pose program in mm without --length-unit mm",
         _filter_case(lambda p: _rows(p * [1000, 1000, 1000, 1, 1, 1], "x,y,z,rx,ry,rz"))),
    Case("filter-near-singular", "stop", "filter: row 3 of a joint program 10 µrad from the elbow singularity",
         _filter_case(_singular_rows, kind="joints")),
    Case("filter-semicolon-comma", "pass", "filter: ';' separated, decimal commas, upper-case header (session "
         "import reads it)", _filter_case(lambda p: _rows(p, "X,Y,Z,RX,RY,RZ", sep=";", decimal=","))),
    Case("filter-headerless", "pass", "filter: a joint program without a header (6 columns)",
         _filter_case(lambda q: _rows(q, None), kind="joints")),
    Case("filter-robodk-mm-deg", "pass", "filter: a pose program in mm and degrees, with --length-unit mm "
         "--angle-unit deg", _filter_case(lambda p: _rows(_in_deg(p, 1000.0), "x,y,z,rx,ry,rz"),
                                          ("--length-unit", "mm", "--angle-unit", "deg"))),
    Case("filter-out-symlink", "clean-error", "filter --force --out a symlink to another file",
         _filter_unsafe_out(_symlink_out)),
    Case("filter-out-device", "clean-error", "filter --force --out a device node (a FIFO when not root)",
         _filter_unsafe_out(_device_out)),
    Case("filter-disk-full", "clean-error", "filter --force over a program when the disk fills mid-write (3,000 rows)",
         _filter_full_disk),
]  # fmt: skip


# hostile inputs to the exports (issue 24, items 2, 3, 5): names that would inject, output paths that are not
# regular files, crafted compensator files (checksums recomputed after the edit, as a crafter would)
_INJECTION = r"ur10\nmovej([0,-1.57,0,-1.57,0,0], a=3, v=3)\n#"


def _robot_name_injection(tmp: Path, args) -> Outcome:
    rob = tmp / "evil.toml"
    text = builtin_path("ur10").read_text()
    rob.write_text(text.replace('name = "ur10"', f'name = "{_INJECTION}"', 1))
    scn = _base()
    csv = write_csv(tmp / "data.csv", scn.q, scn.points)
    return pipeline(tmp, csv, write_targets(tmp / "t.toml", scn.targets), robot=str(rob), method=args.method)[0]


def _export_onto(kind: str):
    def follow(tmp: Path, ctx: dict, args) -> Outcome:
        victim, out = tmp / "victim.json", tmp / "out.json"
        victim.write_text("keep")
        if kind == "symlink":
            out.symlink_to(victim)
        else:
            try:  # a null device node private to this folder (root); else a FIFO, the other non-file a path can be
                os.mknod(out, stat.S_IFCHR | 0o666, os.makedev(1, 3))
            except PermissionError:
                os.mkfifo(out)
        mode = os.lstat(out).st_mode
        session = ctx["ref"].split("@")[0]
        r = run(["export", session, "--format", "json", "--out", str(out), "--store", str(ctx["store"]), "--force"],
                cwd=tmp, timeout=120)  # fmt: skip
        kept = os.lstat(out).st_mode == mode and victim.read_text() == "keep"
        stage = "export" if r.code not in (0, None) else "NOT stopped"
        return Outcome(stage, r.first_line() + ("" if kept else " [REPLACED]"), r.code, r.traceback)

    return follow


def _crafted(change: str, target: str = "path") -> str:
    """A snippet: edit the JSON export, recompute its checksums, load ``target``; exit 2 on a clean refusal."""
    return f"""
import sys
def reseal(edit):
    data = json.loads(open(path).read())
    edit(data)
    data["checksums"] = C.field_checksums(data)
    open(path, "w").write(json.dumps(data))
{change}
try:
    C.load({target})
    print("loaded the crafted file: accepted")
except C.CompensatorFileError as e:
    print("refused:", str(e).splitlines()[0])
    sys.exit(2)
"""


_NPZ_HUGE = _crafted(
    """
import io, zipfile
npz = path[:-5] + ".npz"
C.load(path).save(npz)
with zipfile.ZipFile(npz) as zf:
    members = {i.filename: zf.read(i) for i in zf.infolist()}
head = io.BytesIO()
np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (20000, 30000)})
members["joint_ranges.npy"] = head.getvalue() + bytes(4096)
with zipfile.ZipFile(npz, "w", zipfile.ZIP_DEFLATED) as zf:
    for name, blob in members.items():
        zf.writestr(name, blob)
""",
    "npz",
)
_NAN_RANGES = _crafted('reseal(lambda d: d["joint_ranges"].__setitem__(0, [float("nan"), 1.0]))')
_HUGE_RANGES = _crafted('reseal(lambda d: d["joint_ranges"].__setitem__(0, [-1e300, 1e300]))')
_SAME_NAMES = _crafted('reseal(lambda d: d["robot"]["joint_names"].__setitem__(3, d["robot"]["joint_names"][1]))')
_NAME_INJECTION = _crafted(f'reseal(lambda d: d["robot"].__setitem__("name", {_INJECTION!r}))')
_DEEP_JSON = _crafted(
    'open(path, "w").write(\'{"format": "labcal-compensator", "provenance": \' + "[" * 100000 + "]" * 100000 + "}")'
)

CASES += [
    Case("robot-name-injection", "clean-error", "robot file name with a newline and a movej (URScript injection)",
         _robot_name_injection),
    Case("export-force-symlink", "clean-error", "export --force onto a symlink to another file",
         _good_then(_export_onto("symlink"))),
    Case("export-force-device", "clean-error", "export --force onto a device node (a FIFO when not root)",
         _good_then(_export_onto("device"))),
    Case("npz-member-gigabytes", "clean-error", "NPZ export whose joint_ranges member declares 20000 x 30000",
         _good_then(_compensator_api(_NPZ_HUGE))),
    Case("crafted-nan-ranges", "clean-error", "compensator with NaN joint_ranges, checksums recomputed",
         _good_then(_compensator_api(_NAN_RANGES))),
    Case("crafted-1e300-ranges", "clean-error", "compensator with +-1e300 joint_ranges, checksums recomputed",
         _good_then(_compensator_api(_HUGE_RANGES))),
    Case("crafted-same-joint-names", "clean-error", "compensator with a repeated joint name, checksums recomputed",
         _good_then(_compensator_api(_SAME_NAMES))),
    Case("crafted-name-injection", "clean-error", "compensator whose robot name holds a newline + movej, resealed",
         _good_then(_compensator_api(_NAME_INJECTION))),
    Case("crafted-deep-json", "clean-error", "compensator JSON nested 100000 deep",
         _good_then(_compensator_api(_DEEP_JSON))),
]  # fmt: skip


def verdict(case: Case, o: Outcome) -> str:
    stopped = o.stage != "NOT stopped" and not o.stage.startswith("setup")
    if o.stage.startswith("setup"):
        return "FAIL (setup)"
    if case.expect == "pass":
        return "ok" if not stopped else "FAIL"
    if case.expect == "must-stop":
        return "ok" if stopped else "FAIL"
    if case.expect == "clean-error":
        return "ok" if (stopped and o.code not in (0, None) and not o.traceback) else "FAIL"
    if case.expect == "stop":
        return ("ok" if not o.traceback else "traceback") if stopped else "open"
    return "-"


def run_case(case: Case, args: argparse.Namespace | None = None) -> Outcome:
    """Run one case in a fresh temporary folder (removed after); a case that breaks is an outcome, never raises."""
    args = args or argparse.Namespace(method="auto", local_method="local-poe")
    tmp = Path(tempfile.mkdtemp(prefix=f"labcal-bad-{case.name}-"))
    try:
        return case.run(tmp, args)
    except Exception as err:  # a broken case is reported, the table goes on
        return Outcome("setup failed", f"{type(err).__name__}: {err}".splitlines()[0][:160], None)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ----------------------------------------------------------------------------------------------------------------
# issue 26: store damage and resume. A recorded sim session is damaged the way disks, file managers and people do;
# then the command a user runs next. "pass": an intact version stays usable (fit, seal, list go through);
# "clean-error": one line, exit ≠ 0, and for resume no motion (the journal does not grow).
def _recorded(tmp: Path, poses: int = 30) -> tuple[Path, str, Path]:
    """A complete sim session (v001 sealed): (store, session id, journal)."""
    tgt = write_targets(tmp / "targets.toml", S.TARGETS)
    store = tmp / "store"
    r = run(["session", "new", "--robot", "ur10", "--targets", str(tgt), "--poses", str(poses), "--store", str(store)],
            cwd=tmp, timeout=600)  # fmt: skip
    journal = _journal_path(store)
    if r.code != 0 or journal is None:
        raise RuntimeError(f"setup: session new exit {r.code}: {r.first_line()}")
    return store, journal.parent.name, journal


def _damage_journal_line(journal: Path, line_no: int) -> None:
    lines = journal.read_bytes().split(b"\n")
    lines[line_no - 1] = b"#" * len(lines[line_no - 1])
    journal.write_bytes(b"\n".join(lines))


def _flip_start_document(journal: Path) -> None:
    data = bytearray(journal.read_bytes())
    i = data.index(b'"targets":[[') + len(b'"targets":[[')
    data[i] = ord("7") if data[i] != ord("7") else ord("8")  # still JSON: another target position
    journal.write_bytes(bytes(data))


def _resume_after(damage: Callable[[Path, str, Path], None]):
    """Ctrl-C a session (v001 sealed, poses left), damage it, run `session resume`: refused before any motion?"""

    def go(tmp: Path, args) -> Outcome:
        r, store = _interrupted_session(tmp, poses=60)
        journal = _journal_path(store)
        if journal is None or r.code != 130 or not (journal.parent / "v001").is_dir():
            return Outcome("setup failed", f"no sealed interrupted session (exit {r.code})", r.code, r.traceback)
        damage(store, journal.parent.name, journal)
        before = len(journal.read_bytes().splitlines())
        r = run(["session", "resume", journal.parent.name, "--store", str(store)], cwd=tmp, timeout=600)
        grew = len(journal.read_bytes().splitlines()) - before
        note = f" [journal grew by {grew} lines: the robot moved]" if grew > 0 else " [no motion]"
        stage = "resume" if r.code != 0 and grew <= 0 else "NOT stopped"
        return Outcome(stage, r.first_line() + note, r.code, r.traceback)

    return go


def _flip_version_byte(store: Path, sid: str, journal: Path) -> None:
    p = store / sid / "v001" / "measurements.parquet"
    p.chmod(0o644)
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0x01
    p.write_bytes(bytes(data))


def _then(damage: Callable[[Path, str, Path], None], *commands: list[str]):
    """Damage a complete session, then run each command (SID, STORE substituted); stopped at the first that fails."""

    def go(tmp: Path, args) -> Outcome:
        store, sid, journal = _recorded(tmp)
        damage(store, sid, journal)
        last = None
        for cmd in commands:
            argv = [a.replace("SID", sid) for a in cmd] + ["--store", str(store)]
            last = run(argv, cwd=tmp, timeout=600)
            if last.code != 0:
                return Outcome(" ".join(cmd[:2]), last.first_line(), last.code, last.traceback)
        assert last is not None
        return Outcome("NOT stopped", last.first_line(), 0, last.traceback)

    return go


def _delete(name: str):
    def damage(store: Path, sid: str, journal: Path) -> None:
        target = store / sid / name
        if target.is_dir():
            for p in target.rglob("*"):
                p.chmod(0o755 if p.is_dir() else 0o644)
            shutil.rmtree(target)
        else:
            target.unlink()

    return damage


def _copy_session(store: Path, sid: str, journal: Path) -> None:
    shutil.copytree(store / sid, store / f"{sid} (copy)")
    (store / ".DS_Store").write_bytes(b"\0\0\0\1Bud1")
    (store / sid / "v001" / "Thumbs.db").write_bytes(b"\0")


def _truncate_sealed(store: Path, sid: str, journal: Path) -> None:
    with open(journal, "r+b") as f:
        f.truncate(journal.stat().st_size - 400)


def _input_case(write: Callable[[Path], Path], *, targets: Callable[[Path], Path] | None = None):
    """`session import` of one badly made input file (the good data otherwise)."""

    def go(tmp: Path, args) -> Outcome:
        scn = _base()
        csv = write_csv(tmp / "data.csv", scn.q, scn.points)
        tgt = write_targets(tmp / "targets.toml", scn.targets)
        csv = write(csv)
        tgt = targets(tgt) if targets is not None else tgt
        r = run(["session", "import", str(csv), "--robot", "ur10", "--targets", str(tgt), "--store", str(tmp / "s")],
                cwd=tmp, timeout=120)  # fmt: skip
        if r.code is None:
            return Outcome("NOT stopped", "still running after 120 s (killed by the benchmark)", None, r.traceback)
        return Outcome("import" if r.code != 0 else "NOT stopped", r.first_line(), r.code, r.traceback)

    return go


def _comment_line(csv: Path) -> Path:
    csv.write_text("# exported by the tracker software\n" + csv.read_text())
    return csv


def _semicolons(csv: Path) -> Path:
    csv.write_text(csv.read_text().replace(",", ";").replace(".", ","))
    return csv


def _latin1_byte(csv: Path) -> Path:
    data = csv.read_bytes()
    i = data.index(b"\n") + 1
    csv.write_bytes(data[:i] + b"\xe9" + data[i + 1 :])
    return csv


def _bom(toml: Path) -> Path:
    toml.write_bytes(b"\xef\xbb\xbf" + toml.read_bytes())
    return toml


def _fifo(csv: Path) -> Path:
    fifo = csv.with_name("fifo.csv")
    os.mkfifo(fifo)
    return fifo


def _metres_as_mm(toml: Path) -> Path:
    rows = ", ".join("[" + ", ".join(f"{v:.6f}" for v in t) + "]" for t in S.TARGETS)
    toml.write_text(f'unit = "mm"\npoints = [{rows}]\n')
    return toml


_FIT = ["fit", "SID@v001", "--method", "local-poe"]
STORE_CASES: list[Case] = [
    Case("resume-damaged-version", "clean-error", "a byte of v001's parquet flipped, then session resume",
         _resume_after(_flip_version_byte)),
    Case("resume-damaged-sealed-line", "clean-error", "a journal line inside v001's part damaged, then session resume",
         _resume_after(lambda store, sid, journal: _damage_journal_line(journal, 3))),
    Case("resume-start-flipped", "clean-error", "a byte of the start document flipped, then session resume",
         _resume_after(lambda store, sid, journal: _flip_start_document(journal))),
    Case("sealed-line-fit-seal", "pass", "a journal line inside v001's part damaged: fit v001, seal --valid-prefix",
         _then(lambda store, sid, journal: _damage_journal_line(journal, 3), _FIT,
               ["session", "seal", "SID", "--valid-prefix"])),
    Case("start-flipped-fit-seal", "pass", "a byte of the start document flipped: fit v001, seal --valid-prefix",
         _then(lambda store, sid, journal: _flip_start_document(journal), _FIT,
               ["session", "seal", "SID", "--valid-prefix"])),
    Case("journal-cut-fit-seal", "pass", "journal cut 400 bytes short of v001's part: fit v001, seal --valid-prefix",
         _then(_truncate_sealed, _FIT, ["session", "seal", "SID", "--valid-prefix"])),
    Case("verify-deleted-version", "clean-error", "v001 deleted, then session verify", _then(_delete("v001"),
         ["session", "verify", "SID"])),
    Case("verify-deleted-journal", "clean-error", "journal deleted, then session verify",
         _then(_delete("journal.jsonl"), ["session", "verify", "SID"])),
    Case("list-copied-session", "pass", "'ID (copy)' folder, .DS_Store, Thumbs.db in v001: session list, fit v001",
         _then(_copy_session, ["session", "list"], _FIT)),
    Case("csv-comment-line", "clean-error", "a '# …' comment line above the CSV header", _input_case(_comment_line)),
    Case("csv-semicolons", "clean-error", "';'-separated CSV, decimal commas, no mapping", _input_case(_semicolons)),
    Case("csv-latin1", "clean-error", "a Latin-1 byte in the CSV", _input_case(_latin1_byte)),
    Case("targets-bom", "pass", "targets TOML saved with a byte order mark", _input_case(lambda c: c, targets=_bom)),
    Case("csv-dev-zero", "clean-error", "import /dev/zero", _input_case(lambda c: Path("/dev/zero"))),
    Case("csv-fifo", "clean-error", "import a FIFO", _input_case(_fifo)),
    Case("targets-m-as-mm", "clean-error", "targets file in m declared as mm",
         _input_case(lambda c: c, targets=_metres_as_mm)),
]  # fmt: skip
CASES += STORE_CASES
