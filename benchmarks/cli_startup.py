"""Wall time of the light CLI paths (issue 17.2): `labcal --help`, `session --help`, `fit --help`, `session list`.

Each command runs in a fresh interpreter exactly as the console script runs it (``from labcal.cli.app import main;
main()``), N times, with the "before" and "after" source trees interleaved run by run so that the machine's load
(2 cores shared with other jobs) falls on both alike; the table gives the median and the spread (min … max).

    git worktree add /tmp/before65 65c384c
    .venv/bin/python benchmarks/cli_startup.py --before /tmp/before65/src --runs 15

"before" runs with ``PYTHONPATH=<before>``, "after" with this checkout's ``src``. The stores are made once by the
after code: an empty folder, and one with three small sim sessions (imported by both trees). Where the time goes:
``python -X importtime -c "import labcal.cli.app"``.
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


def labcal(src: Path, args: list[str] | None, *, check: bool = True) -> tuple[tuple[float, float], Any]:
    """((wall s, CPU s), result): CPU = the child's user + system time, which a busy machine inflates far less than
    the wall time (waiting for a core counts in wall time only). ``args`` None: a bare interpreter (the floor)."""
    env = {**os.environ, "PYTHONPATH": str(src), "COLUMNS": "100"}
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--before", type=Path, default=Path("/tmp/before65/src"), help="src/ of the before tree")
    p.add_argument("--runs", type=int, default=15)
    p.add_argument("--sessions", type=int, default=3, help="sessions in the non-empty store")
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
        trees = {"before": a.before, "after": AFTER_SRC}
        times: dict[tuple[str, str], list[tuple[float, float]]] = {}
        for name, args in commands.items():
            for tree, src in trees.items():
                _, r = labcal(src, args, check=False)  # warm the file cache; before may lack an option
                times[(name, tree)] = [] if r.returncode == 0 else None  # None: this tree lacks the command
            for _ in range(a.runs):
                for tree, src in trees.items():
                    if times[(name, tree)] is not None:
                        times[(name, tree)].append(labcal(src, args)[0])
        load = os.getloadavg()
        print(f"CLI time, s: median (min … max) of {a.runs} runs, fresh interpreter each, before/after interleaved; "
              f"before = {a.before}, after = {AFTER_SRC}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} "
              f"on {os.cpu_count()} cores; python {sys.version.split()[0]}")  # fmt: skip
        print("wall: elapsed time; CPU: the process's user + system time (less sensitive to other jobs' load)")
        width = max(len(n) for n in commands)
        for k, what in ((0, "wall"), (1, "CPU")):
            print()
            print(f"{what + ' s':<{width}}  {'before':>22}  {'after':>22}  {'after/before':>12}")
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
                print(f"{name:<{width}}  {cells[0]:>22}  {cells[1]:>22}  {ratio:>12}")
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
