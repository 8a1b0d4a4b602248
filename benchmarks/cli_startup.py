"""Wall time of the light CLI paths (issue 17.2): `labcal --help`, `session --help`, `fit --help`, `session list`.

Each command runs in a fresh interpreter exactly as the console script runs it (``from labcal.cli.app import main;
main()``), N times, with the "before" and "after" source trees interleaved run by run so that the machine's load
(2 cores shared with other jobs) falls on both alike; the table gives the median and the spread (min … max).

    git worktree add /tmp/before65 65c384c
    .venv/bin/python benchmarks/cli_startup.py --before /tmp/before65/src --runs 15

"before" runs with ``PYTHONPATH=<before>``, "after" with this checkout's ``src`` (or ``--after SRC``: e.g. a copy of
this tree with a change tried out, as issue 29 timed the CLI without labcal.cli.coercion and labcal.cli.helprender:

    git archive HEAD src | tar -x -C /tmp/lean_before        # the tree as committed
    mkdir /tmp/nopatch && cp -r src /tmp/nopatch/   # then delete the coercion.install(self) and
    # helprender.import_help_renderer() calls from /tmp/nopatch/src/labcal/cli/app.py
    .venv/bin/python benchmarks/cli_startup.py --before /tmp/lean_before/src --after /tmp/nopatch/src --runs 9
). The stores are made once by the
after code: an empty folder, and one with three small sim sessions (imported by both trees). Where the time goes:
``python -X importtime -c "import labcal.cli.app"``.

Bytecode (``--bytecode``): "compiled" runs every command with no cached bytecode for labcal's own modules, so each
run compiles the ones it imports (as every run does where PYTHONDONTWRITEBYTECODE is set, e.g. this repository's
sandbox); "cached" lets the warm-up run write it (under a private PYTHONPYCACHEPREFIX, not into the trees) and the
timed runs reuse it, as an installed labcal does; "both" (default) prints a table for each. The third-party
packages of the venv have their bytecode either way.

``--out FILE`` also writes the tables to FILE, under a header naming the command, the commit and the load.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
AFTER_SRC = HERE.parent / "src"
RUNNER = "import sys; sys.argv[0] = 'labcal'; from labcal.cli.app import main; main()"
TARGETS = 'unit = "mm"\npoints = [[120.0, 0.0, 60.0], [-60.0, 100.0, 60.0], [-60.0, -100.0, 90.0]]\n'


def labcal(
    src: Path, args: list[str] | None, *, check: bool = True, bytecode: dict | None = None
) -> tuple[tuple[float, float], Any]:
    """((wall s, CPU s), result): CPU = the child's user + system time, which a busy machine inflates far less than
    the wall time (waiting for a core counts in wall time only). ``args`` None: a bare interpreter (the floor).
    ``bytecode``: the environment of a bytecode mode (:func:`bytecode_env`)."""
    env = {**os.environ, "PYTHONPATH": str(src), "COLUMNS": "100"}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env.pop("PYTHONPYCACHEPREFIX", None)
    env.update(bytecode or {"PYTHONDONTWRITEBYTECODE": "1"})
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    argv = [sys.executable, "-c", "pass"] if args is None else [sys.executable, "-c", RUNNER, *args]
    r = subprocess.run(argv, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if check and r.returncode != 0:
        raise SystemExit(f"{src}: labcal {' '.join(args or [])} exited {r.returncode}:\n{r.stderr[-2000:]}")
    return (wall, cpu), r


def make_stores(root: Path, sessions: int) -> tuple[Path, Path]:
    empty = root / "empty"
    empty.mkdir()
    full = root / "store"
    (root / "targets.toml").write_text(TARGETS)
    for seed in range(sessions):
        labcal(AFTER_SRC, ["session", "new", "--robot", "ur10", "--targets", str(root / "targets.toml"),
                           "--poses", "14", "--seed", str(seed), "--store", str(full)])  # fmt: skip
    return empty, full


def bytecode_env(mode: str, root: Path) -> dict:
    """Environment of a bytecode mode. "cached" writes to a private folder (a prefix applies to every module, so
    the warm-up run caches the standard library's and the venv's there too); "compiled" writes nothing and reads
    the usual __pycache__ folders, which hold the third-party packages' bytecode and none of the trees' (see
    :func:`stray_bytecode`)."""
    if mode == "compiled":
        return {"PYTHONDONTWRITEBYTECODE": "1"}
    cache = root / "pycache"
    cache.mkdir(exist_ok=True)
    return {"PYTHONPYCACHEPREFIX": str(cache)}


def stray_bytecode(trees: dict) -> list[str]:
    """The trees holding a __pycache__ (written by a run without PYTHONDONTWRITEBYTECODE): "compiled" reads it."""
    return [f"{tree} ({src})" for tree, src in trees.items() if next(Path(src).rglob("__pycache__"), None)]


def time_commands(commands: dict, trees: dict, runs: int, bytecode: dict) -> dict:
    """(command, tree) → [(wall, CPU)] of ``runs`` timed runs after one warm-up, or None where the tree lacks it."""
    times: dict[tuple[str, str], list[tuple[float, float]] | None] = {}
    for name, args in commands.items():
        for tree, src in trees.items():
            # warm the file cache (and, "cached", write the bytecode); before may lack an option
            _, r = labcal(src, args, check=False, bytecode=bytecode)
            times[(name, tree)] = [] if r.returncode == 0 else None
        for _ in range(runs):
            for tree, src in trees.items():
                if times[(name, tree)] is not None:
                    times[(name, tree)].append(labcal(src, args, bytecode=bytecode)[0])
    return times


def table(commands: dict, trees: dict, times: dict, k: int, title: str) -> list[str]:
    """One table: a row per command, median (min … max) of value ``k`` (0 wall, 1 CPU) per tree, and the ratio."""
    width = max(len(n) for n in commands)
    lines = [f"{title:<{width}}  {'before':>22}  {'after':>22}  {'after/before':>12}"]
    for name in commands:
        cells, med = [], {}
        for tree in trees:
            t = times[(name, tree)]
            if t is None:
                cells.append("n/a")
                continue
            v = [x[k] for x in t]
            med[tree] = statistics.median(v)
            cells.append(f"{med[tree]:6.3f} ({min(v):.3f} … {max(v):.3f})")
        ratio = f"{med['after'] / med['before']:.2f}" if len(med) == 2 else "—"
        lines.append(f"{name:<{width}}  {cells[0]:>22}  {cells[1]:>22}  {ratio:>12}")
    return lines


def commit() -> str:
    """This checkout's commit, with "+changes" if labcal's sources differ from it."""
    git = ["git", "-C", str(HERE.parent)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run([*git, "status", "--porcelain", "--", "src"], capture_output=True, text=True).stdout
    return (head or "?") + (" +changes in src/" if dirty.strip() else "")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--before", type=Path, default=Path("/tmp/before65/src"), help="src/ of the before tree")
    p.add_argument("--after", type=Path, default=AFTER_SRC, help="src/ of the after tree (default: this checkout's)")
    p.add_argument("--runs", type=int, default=15)
    p.add_argument("--sessions", type=int, default=3, help="sessions in the non-empty store")
    p.add_argument("--bytecode", choices=("compiled", "cached", "both"), default="both", help="see above")
    p.add_argument("--out", type=Path, help="also write the tables to this file, with a header")
    a = p.parse_args()
    if not (a.before / "labcal" / "cli" / "app.py").is_file():
        raise SystemExit(f"{a.before}: not a labcal src/ folder (git worktree add /tmp/before65 65c384c)")

    root = Path(tempfile.mkdtemp(prefix="labcal-cli-startup-"))
    try:
        empty, full = make_stores(root, a.sessions)
        commands = {
            "python -c pass (the floor)": None,
            "labcal --help": ["--help"],
            "labcal session --help": ["session", "--help"],
            "labcal fit --help": ["fit", "--help"],
            "labcal session list (empty store)": ["session", "list", "--store", str(empty)],
            f"labcal session list ({a.sessions} sessions)": ["session", "list", "--store", str(full)],
            f"labcal session list --json ({a.sessions} sessions)": ["session", "list", "--json", "--store", str(full)],
        }
        trees = {"before": a.before, "after": a.after}
        modes = ("compiled", "cached") if a.bytecode == "both" else (a.bytecode,)
        results = {m: time_commands(commands, trees, a.runs, bytecode_env(m, root)) for m in modes}
        load = os.getloadavg()
        lines = [
            f"CLI time, s: median (min … max) of {a.runs} runs, fresh interpreter each, before/after interleaved; "
            f"before = {a.before}, after = {a.after}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} "
            f"on {os.cpu_count()} cores; python {sys.version.split()[0]}",
            "wall: elapsed time; CPU: the process's user + system time (less sensitive to other jobs' load)",
        ]
        about = {
            "compiled": "labcal's modules compiled in every run (no cached bytecode, as with PYTHONDONTWRITEBYTECODE)",
            "cached": "labcal's modules' bytecode cached by the warm-up run (as an installed labcal)",
        }
        if "compiled" in results and (stray := stray_bytecode(trees)):
            about["compiled"] += f"; NOTE: a __pycache__ in {', '.join(stray)} made some of it cached"
        for mode, times in results.items():
            lines += ["", f"== bytecode {mode}: {about[mode]}"]
            for k, what in ((0, "wall"), (1, "CPU")):
                lines += ["", *table(commands, trees, times, k, f"{what} s")]
        print("\n".join(lines))
        if a.out is not None:
            argv = " ".join([".venv/bin/python", "benchmarks/cli_startup.py", *sys.argv[1:]])
            when = time.strftime("%Y-%m-%dT%H:%MZ", time.gmtime())
            after = commit() if a.after.resolve() == AFTER_SRC else a.after
            header = f"# {argv}   (after = {after}, before = {a.before}; {when})"
            a.out.write_text(header + "\n" + "\n".join(lines) + "\n", encoding="utf-8")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
