"""Batched ``correct()`` throughput: local POE, the synthetic hybrid and a real hybrid export (issue 29).

Run: ``.venv/bin/python benchmarks/compensator_batch.py [--batch 20000] [--repeats 5] [--export PATH]
[--src DIR --src DIR …] [--rounds 3]``

Models:

- ``local-poe`` and ``synthetic hybrid``: :func:`compensator_speed.make_models` (UR10, seeded frame errors; the
  hybrid's network is (sincos, gravity) → 12 tanh units → 6 with random weights), on ``--batch`` configurations
  uniform over ±π with a well-conditioned joint Jacobian (:func:`compensator_speed.well_conditioned`);
- ``real hybrid export``: the real UR10 tracker data fitted with ``method="hybrid"`` on 150 poses
  (:func:`compensator_tail.fit_export`: its learned term is the per-joint series, features ``gravity`` and
  ``harmonics:32``), saved as JSON and loaded with :meth:`Compensator.load`; ``--batch`` configurations drawn in
  its validity region (seed 1), inside its joint ranges, with length-scaled cond(J_ρ) < 1000, so ``correct(q)`` with
  its defaults accepts them all. ``--export PATH`` reuses (or first writes) that file.

Each number is ``--batch`` / (the best of ``--repeats`` calls of ``robot.correct(q)`` on the whole batch), timed
by the wall clock and by the process's CPU time (one thread: OPENBLAS_NUM_THREADS=1), which other jobs on a shared
machine inflate less.
``--src DIR`` (repeatable) times the labcal whose sources are in DIR (e.g. ``/work/main/src`` beside a worktree's
``src``) in a child process with that PYTHONPATH, the trees taking turns for ``--rounds`` rounds so the machine's
drift hits them alike; the table shows each tree's best, and how far every tree's corrections are from the first
tree's: over all configurations, and over those whose correction reaches the nominal pose (residual below 1e-9 m
and rad in the first tree: the rest stop at the 0.1 rad bound, in a damped search that rounding may steer).
Without ``--src`` the importable labcal is timed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from compensator_speed import make_models, well_conditioned  # a sibling script: benchmarks/ is sys.path[0]

MODELS = ("local-poe", "synthetic hybrid", "real hybrid export")


def export_configurations(robot, count: int, seed: int = 1, max_cond: float = 1e3) -> tuple[np.ndarray, np.ndarray]:
    """(count, n) configurations that ``robot.correct`` accepts without ``extrapolate``: inside the validity region
    and the joint ranges, with length-scaled cond(J_ρ) < max_cond; and their (count,) condition numbers."""
    rng = np.random.default_rng(seed)
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    D = np.array([1.0 / robot.length_scale] * 3 + [1.0] * 3)
    qs, conds, have = [], [], 0
    while have < count:
        q = robot.validity.sample(2 * count, rng)
        q = q[((q >= lo) & (q <= hi)).all(axis=1) & robot.validity.inside(q)]
        cond = np.linalg.cond(D[None, :, None] * robot.model.equivalent_jacobian(q, length_scale=robot.length_scale))
        keep = cond < max_cond
        qs.append(q[keep])
        conds.append(cond[keep])
        have += int(keep.sum())
    return np.concatenate(qs)[:count], np.concatenate(conds)[:count]


def cases(export: Path, batch: int) -> dict:
    """model name → (robot, configurations)."""
    from labcal.compensator import Compensator

    models = make_models("ur10")
    out = {}
    for name, key in (("local-poe", "local-poe"), ("synthetic hybrid", "hybrid")):
        out[name] = (models[key], well_conditioned(models[key], batch, seed=1))
    robot = Compensator.load(export).robot
    out["real hybrid export"] = (robot, export_configurations(robot, batch)[0])
    return out


def measure(export: Path, batch: int, repeats: int, save: Path | None = None) -> dict:
    """model name → [configurations per wall-clock second, per CPU second] (each the best of ``repeats``); the
    corrections go to ``save`` (.npz) when given."""
    rates, corrections = {}, {}
    for name, (robot, q) in cases(export, batch).items():
        robot.correct(q[:10])  # cached kernels and weights are built outside the timing
        wall = cpu = float("inf")
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            q_cmd = robot.correct(q)
            wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
        rates[name] = [len(q) / wall, len(q) / cpu]
        r, _ = robot.residual(q_cmd, robot.nominal.fk(q), jacobian=False)
        corrections[name], corrections[name + "/reached"] = q_cmd, np.abs(r).max(axis=1) < 1e-9
    if save is not None:
        np.savez(save, **corrections)
    return rates


def ensure_export(path: Path | None, tmp: Path) -> Path:
    from compensator_tail import fit_export

    path = path or tmp / "ur10-hybrid.json"
    if not path.exists():
        fit_export(path, 150)
    return path


def compare_trees(sources: list[str], export: Path, args, tmp: Path) -> None:
    """Time every tree in a child process, round by round; print the table and the corrections' agreement."""
    best = {src: {name: [0.0, 0.0] for name in MODELS} for src in sources}
    for round_ in range(args.rounds):
        for i, src in enumerate(sources):
            env = dict(os.environ, PYTHONPATH=src, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
            save = tmp / f"tree{i}.npz"
            cmd = [sys.executable, __file__, "--worker", str(save), "--export", str(export)]
            cmd += ["--batch", str(args.batch), "--repeats", str(args.repeats)]
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            for name, rates in json.loads(out.stdout.strip().splitlines()[-1]).items():
                best[src][name] = [max(a, b) for a, b in zip(best[src][name], rates, strict=True)]
        print(f"round {round_ + 1}/{args.rounds} done, load {os.getloadavg()[0]:.2f}", file=sys.stderr)
    print_header(args, f"trees (PYTHONPATH): {', '.join(sources)}; best of {args.rounds} rounds")
    print("configurations per second of wall-clock time / per second of CPU time (the process's own: other jobs on")
    print("the machine slow it less); ratio: last tree over first")
    print("| model | " + " | ".join(f"`{s}` (wall / CPU)" for s in sources) + " | ratio wall | ratio CPU |")
    print("|---|" + "---:|" * (len(sources) + 2))
    for name in MODELS:
        rates = [best[src][name] for src in sources]
        cells = " | ".join(f"{wall:,.0f} / {cpu:,.0f}" for wall, cpu in rates)
        ratios = " | ".join(f"{rates[-1][i] / rates[0][i]:.2f}×" for i in range(2))
        print(f"| {name} | {cells} | {ratios} |")
    first = np.load(tmp / "tree0.npz")
    for i, src in enumerate(sources[1:], start=1):
        other = np.load(tmp / f"tree{i}.npz")
        for name in MODELS:
            d = np.abs(other[name] - first[name]).max(axis=1)
            reached = first[name + "/reached"]
            print(
                f"{name}: max |Δq| `{src}` vs `{sources[0]}`: {d[reached].max():.1e} rad over the "
                f"{int(reached.sum()):,} corrections that reach the nominal pose, {d.max():.1e} rad over all "
                f"{len(d):,}; {int((d == 0).sum()):,} bit-identical"
            )


def print_header(args, what: str) -> None:
    print(f"compensator batch throughput — UR10, batch {args.batch:,}, best of {args.repeats} calls; {what}")
    print(
        f"{platform.processor() or platform.machine()}, python {platform.python_version()}, numpy {np.__version__}, "
        f"load {os.getloadavg()[0]:.2f}"
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3, help="turns each --src tree takes")
    ap.add_argument("--export", type=Path, help="real hybrid export to reuse (written first when missing)")
    ap.add_argument("--src", action="append", default=[], help="a labcal source tree to time (repeatable)")
    ap.add_argument("--worker", type=Path, help=argparse.SUPPRESS)  # a child of --src: print JSON, save corrections
    args = ap.parse_args(argv)
    if args.worker is not None:
        print(json.dumps(measure(args.export, args.batch, args.repeats, args.worker)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        export = ensure_export(args.export, Path(tmp))
        if args.src:
            compare_trees(args.src, export, args, Path(tmp))
            return
        rates = measure(export, args.batch, args.repeats)
        print_header(args, "the importable labcal")
        print("| model | correct() batched (configs per wall-clock s) | (per CPU s) |\n|---|---:|---:|")
        for name, (wall, cpu) in rates.items():
            print(f"| {name} | {wall:,.0f} | {cpu:,.0f} |")


if __name__ == "__main__":
    main()
