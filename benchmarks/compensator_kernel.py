"""Single-configuration ``correct()`` against one plain numpy DH forward-kinematics call (issue 29's goals).

Run: ``PYTHONPATH=src .venv/bin/python benchmarks/compensator_kernel.py [--calls 20000] [--export PATH]``

Goals, as ratios within one run: single-configuration ``correct()`` median ≤ 0.5× and p99.9 ≤ 5× one plain numpy
DH FK call, for local POE and for a real hybrid export.

- **Reference**: :func:`dh_fk`, the textbook 6-joint DH forward kinematics in numpy (one 4×4 ``np.array`` and one
  matmul per joint) of the UR10's nominal DH parameters, called once per configuration.
- **Real hybrid export**: the real UR10 tracker data, 150 random poses fitted with ``method="hybrid"`` (local POE,
  then the learned term the cross-validation keeps: the per-joint series, harmonics + gravity), saved as JSON and
  loaded with :meth:`Compensator.load` (benchmarks/compensator_tail.py's ``fit_export``; ``--export PATH`` reuses or
  first writes that file). **Local POE**: the same export's identified frames and validity region without the
  learned term.
- **Calls**: up to ``--calls`` configurations inside the export's joint ranges and validity region with a
  well-conditioned Jacobian (compensator_tail's ``configurations``),
  corrected one at a time in a loop as a control loop does
  (garbage collector on, no warm-up between calls), through ``Compensator.correct``; the reference is timed in the
  same loop over the same configurations, interleaved with the corrections in blocks so that the machine's load
  falls on both alike; ``--rounds`` times, and every row reports its quietest round (least median: other jobs on
  the machine only ever add time). p99.9 over one round of a few thousand calls is its few slowest: on a shared
  machine, preemption; the reference's own p99.9 shows how much.
- Rows ``numpy path``: the same calls with the compiled kernel switched off (what a labcal without numba runs: the
  batched definition with a batch of one), in the same run. On a labcal without :mod:`labcal.compensator.kernel`
  (before issue 29) only the rows of its own single-call path are printed.

Where a correction's time goes (``--profile``): the kernel alone (the compiled call, without ``correct()``'s
argument checks) for the hybrid export.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from compensator_tail import configurations, fit_export
from labcal.compensator import Compensator

# UR10 nominal DH parameters (Universal Robots' published values): d, a, α per joint
UR10_D = np.array([0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922])
UR10_A = np.array([0.0, -0.612, -0.5723, 0.0, 0.0, 0.0])
UR10_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])


def dh_fk(q: np.ndarray) -> np.ndarray:
    """Plain numpy DH forward kinematics of a 6-joint arm: q (6,) → (4, 4) tool pose. The reference call."""
    T = np.eye(4)
    for j in range(6):
        ct, st = np.cos(q[j]), np.sin(q[j])
        ca, sa = np.cos(UR10_ALPHA[j]), np.sin(UR10_ALPHA[j])
        A = np.array(
            [
                [ct, -st * ca, st * sa, UR10_A[j] * ct],
                [st, ct * ca, -ct * sa, UR10_A[j] * st],
                [0.0, sa, ca, UR10_D[j]],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        T = T @ A
    return T


def timed(fn, q: np.ndarray, out: np.ndarray, start: int) -> None:
    """Time fn(q[i]) for every row, one call each, into out[start:]."""
    clock = time.perf_counter
    for i, row in enumerate(q):
        t0 = clock()
        fn(row)
        out[start + i] = clock() - t0


def measure(fns: dict, q: np.ndarray, rounds: int, block: int = 500) -> dict[str, list[np.ndarray]]:
    """Per-call seconds of every function over q, ``rounds`` times, interleaved in blocks of ``block`` calls
    (gc on): {name: [one (k,) array per round]}."""
    for fn in fns.values():
        fn(q[0])  # build cached state (and compile or load the kernel) outside the timing
    times: dict[str, list[np.ndarray]] = {name: [] for name in fns}
    gc.enable()
    for _ in range(rounds):
        this = {name: np.empty(len(q)) for name in fns}
        for start in range(0, len(q), block):
            for name, fn in fns.items():
                timed(fn, q[start : start + block], this[name], start)
        for name in fns:
            times[name].append(this[name])
    return times


def stats(rounds: list[np.ndarray]) -> tuple[float, float, float, float]:
    """(median, p99, p99.9, max) seconds of the quietest round (least median: other jobs only ever add time)."""
    t = min(rounds, key=np.median)
    return float(np.median(t)), float(np.percentile(t, 99)), float(np.percentile(t, 99.9)), float(t.max())


def numpy_path(comp: Compensator) -> Compensator | None:
    """The same export with the compiled kernel switched off (a labcal without numba), or None on a labcal
    without the kernel (its single calls are already its own path)."""
    try:
        from labcal.compensator import kernel
    except ImportError:
        return None
    robot = dataclasses.replace(comp.robot)  # a fresh object: nothing cached
    object.__setattr__(robot, "_kernel", None)  # cached_property's slot: the batched numpy path for single calls
    assert kernel is not None
    return Compensator(robot, comp.provenance, comp.source)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=5000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--size", type=int, default=150)
    ap.add_argument("--export", type=Path, default=Path("/tmp/labcal_compensator_kernel_hybrid.json"))
    args = ap.parse_args(argv)

    if not args.export.exists():
        fit_export(args.export, args.size)
    hybrid = Compensator.load(args.export)
    local = Compensator(dataclasses.replace(hybrid.robot, network=None, method="local-poe"))
    q = configurations(hybrid, 4 * args.calls)
    q = q[hybrid.robot.validity.inside(q)][: args.calls] if hybrid.robot.validity is not None else q[: args.calls]

    fns = {"reference: plain numpy DH FK": dh_fk}
    for name, comp in (("local POE", local), ("real hybrid export", hybrid)):
        fns[f"{name}: correct()"] = comp.correct
        slow = numpy_path(comp)
        if slow is not None:
            fns[f"{name}: correct(), numpy path"] = slow.correct
    times = measure(fns, q, args.rounds)

    ref_med, _, ref_tail, _ = stats(times["reference: plain numpy DH FK"])
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = "?"
    print(
        f"single-configuration correct() vs one plain numpy DH FK — {len(q)} calls each, quietest of "
        f"{args.rounds} rounds, commit {commit},"
    )
    print(f"{platform.processor() or platform.machine()}, export {args.export.name}")
    print(f"{'call':40s} {'median µs':>10s} {'p99 µs':>9s} {'p99.9 µs':>9s} {'max µs':>9s} {'median/ref':>11s} "
          f"{'p99.9/ref':>10s}")  # fmt: skip
    for name, rounds in times.items():
        med, p99, p999, top = stats(rounds)
        print(
            f"{name:40s} {med * 1e6:10.1f} {p99 * 1e6:9.1f} {p999 * 1e6:9.1f} {top * 1e6:9.1f} "
            f"{med / ref_med:11.2f} {p999 / ref_med:10.2f}"
        )
    print(f"\ngoals: median ≤ 0.5× and p99.9 ≤ 5× the reference median ({ref_med * 1e6:.1f} µs; its p99.9 "
          f"{ref_tail * 1e6:.1f} µs)")  # fmt: skip
    for name in ("local POE", "real hybrid export"):
        med, _, p999, _ = stats(times[f"{name}: correct()"])
        med, p999 = med / ref_med, p999 / ref_med
        verdict = "met" if med <= 0.5 and p999 <= 5 else "NOT met"
        print(f"  {name}: median {med:.2f}×, p99.9 {p999:.2f}× — {verdict}")


if __name__ == "__main__":
    main()
