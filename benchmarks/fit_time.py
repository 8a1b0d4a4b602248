"""Benchmark ``fit-time``: wall time and peak memory of ``fit()`` vs the number of poses N, for every method.

Data: N random non-singular poses of a simulated ``ur10`` with geometric + non-geometric errors
(``ErrorSpec.default``, ``scenarios.good``, seed 0), base frame, default fit options
(``fit(obs, nominal, method, seed=0)``).

Each (method, N) cell runs in its own Python process, so one cell's memory never shows in another's: the child
imports labcal (and torch for the methods that train a network, so the import is not counted), builds the data,
records its resident set size (RSS), fits once, and reports the wall time of the fit, the peak RSS
(``resource.getrusage``) and the peak RSS growth during the fit. A cell over ``--timeout`` seconds is reported as
such. The 1-minute load average of the machine is printed with each cell: on a shared machine it is the main
source of spread in the times.

Goal (issue 13): ``auto`` ≤ 10 s at N = 1,000 and ≤ 30 s at N = 5,000 on this machine, close to linear in N.

Run: ``python benchmarks/fit_time.py [--sizes 50 200 1000 2000 5000] [--methods …] [--out FILE]``.
Committed results: benchmarks/results/fit_time_before.txt
(before the issue-13 changes) and fit_time.txt (after).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

METHODS = ("nominal", "local-poe", "ann", "hybrid", "auto")
SIZES = (50, 200, 1000, 2000, 5000)
GOALS = {1000: 10.0, 5000: 30.0}  # auto, seconds
_TORCH = ("ann", "hybrid", "auto")


def _rss_mb() -> float:
    import resource

    # ru_maxrss is in kB on Linux (bytes on macOS).
    scale = 1 / 1024 / 1024 if sys.platform == "darwin" else 1 / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def _current_rss_mb() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1024 / 1024
    except OSError:
        return _rss_mb()


def cell(method: str, n: int, seed: int = 0) -> dict:
    """Run one cell in this process and return its measurements (the child side)."""
    from labcal.calibration import Observations, fit
    from labcal.robots import load
    from labcal.simulation import ErrorSpec
    from scenarios import good

    if method in _TORCH:
        import torch  # noqa: F401  (imported before the baseline so the import is not counted as fit memory)
    scn = good("ur10", n, errors=ErrorSpec.default(), seed=seed)
    obs = Observations(**scn.arrays())
    nominal = load("ur10").model
    base = _current_rss_mb()
    t = time.perf_counter()
    result = fit(obs, nominal, method, seed=seed)
    seconds = time.perf_counter() - t
    peak = _rss_mb()
    return {
        "method": method,
        "n": n,
        "seconds": seconds,
        "peak_mb": peak,
        "growth_mb": max(peak - base, 0.0),
        "chosen": str(result.chosen),
        "stages": {k: round(float(v), 3) for k, v in (result.fit_seconds or {}).items()},
        "ok": bool(np.isfinite(seconds)),
    }


def run_cell(method: str, n: int, timeout: float) -> dict:
    """Run one cell in a child process; never raises (errors and timeouts come back as the cell's text)."""
    load = os.getloadavg()[0]
    cmd = [sys.executable, str(Path(__file__).resolve()), "--cell", method, str(n)]
    t = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"method": method, "n": n, "error": f"timeout > {timeout:g} s", "load": load}
    wall = time.perf_counter() - t
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"method": method, "n": n, "error": tail[:160], "load": load}
    out = json.loads(lines[-1])
    out.update(load=load, process_s=wall)
    return out


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(r):
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))

    return [line(header), "  ".join("-" * w for w in widths), *[line(r) for r in rows]]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fit-time", description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="numbers of poses")
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of " + ",".join(METHODS))
    p.add_argument("--timeout", type=float, default=600.0, help="seconds per cell (default 600)")
    p.add_argument("--out", help="also write the output to this file")
    p.add_argument("--note", help="a line printed under the command (e.g. which commit was measured)")
    p.add_argument("--cell", nargs=2, metavar=("METHOD", "N"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.cell:
        print(json.dumps(cell(args.cell[0], int(args.cell[1]))), flush=True)
        return 0
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    bad = set(methods) - set(METHODS)
    if bad:
        p.error(f"unknown method(s) {sorted(bad)}; known: {', '.join(METHODS)}")
    out: list[str] = []

    def say(line: str = "") -> None:
        print(line, flush=True)
        out.append(line)

    say("fit-time: wall time and peak memory of fit(obs, nominal, method, seed=0) vs N (simulated ur10, default)")
    say(f"command: python benchmarks/fit_time.py {' '.join(argv if argv is not None else sys.argv[1:])}".rstrip())
    if args.note:
        say(f"note: {args.note}")
    say(f"machine: {os.cpu_count()} cores; one child process per cell; load = 1-min load average at the cell's start")
    results = []
    for n in args.sizes:
        for m in methods:
            r = run_cell(m, n, args.timeout)
            results.append(r)
            if "error" in r:
                say(f"  N={n} {m}: {r['error']} (load {r['load']:.1f})")
            else:
                say(
                    f"  N={n} {m}: {r['seconds']:.2f} s, peak {r['peak_mb']:.0f} MB (+{r['growth_mb']:.0f} MB), "
                    f"chose {r['chosen']}, stages {r['stages']} (load {r['load']:.1f})"
                )
    say("")
    say("Fit wall time, s (peak RSS growth during the fit, MB)")
    rows = []
    for n in args.sizes:
        row = [str(n)]
        for m in methods:
            r = next(x for x in results if x["n"] == n and x["method"] == m)
            row.append(r["error"].split(":")[0][:24] if "error" in r else f"{r['seconds']:.2f} (+{r['growth_mb']:.0f})")
        rows.append(row)
    for line in _table(["N", *methods], rows):
        say(line)
    say("")
    say("Peak RSS of the child process, MB (labcal + numpy (+ torch) + data + fit)")
    rows = [
        [str(n)]
        + [
            "-" if "error" in r else f"{r['peak_mb']:.0f}"
            for r in (next(x for x in results if x["n"] == n and x["method"] == m) for m in methods)
        ]
        for n in args.sizes
    ]
    for line in _table(["N", *methods], rows):
        say(line)
    if "auto" in methods:
        say("")
        for n, limit in GOALS.items():
            r = next((x for x in results if x["n"] == n and x["method"] == "auto"), None)
            if r is None:
                continue
            got = "error" if "error" in r else f"{r['seconds']:.1f} s"
            ok = "error" not in r and r["seconds"] <= limit
            say(f"goal: auto at N = {n} ≤ {limit:g} s: {got} → {'met' if ok else 'NOT met'}")
        ok_sizes = [x for x in results if x["method"] == "auto" and "error" not in x]
        if len(ok_sizes) >= 2:
            a, b = ok_sizes[0], ok_sizes[-1]
            slope = np.log(b["seconds"] / a["seconds"]) / np.log(b["n"] / a["n"]) if a["seconds"] > 0 else float("nan")
            say(f"auto time growth exponent between N = {a['n']} and {b['n']}: {slope:.2f} (1 = linear)")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text("\n".join(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
