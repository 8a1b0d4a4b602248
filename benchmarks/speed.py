"""Kinematics and compensator speed on one core: FK / Jacobian throughput, correct() latency and throughput.

Run: ``.venv/bin/python benchmarks/speed.py [--robot ur10] [--k 10000] [--repeat 5] [--singles 2000]``

Every section is a (name, callable) pair in :func:`sections`; add new ones there (e.g. fit time) and they get a row.
Batch sections are timed on k configurations drawn uniformly inside the joint limits (clipped to ±π), seeded; a
batch time is the best of ``--repeat`` runs (other processes only ever add time). Single-configuration latency is
the median over ``--singles`` calls, best of the repeats. The compensator is a ``CalibratedRobot`` whose identified
model is the nominal one with 0.5 mm / 0.5 mrad frame errors (local-POE calibration, no network), so ``correct``
runs its Newton iteration on a model that really differs from the nominal.

Rows marked "definition" evaluate :func:`labcal.kinematics.poe.poe_link_frames` (the plain product of exponentials);
set beside the kernels' rows they show what each fast kernel earns.

The issue's goal: FK + joint twists ≥ 200,000 configurations/s for a 6R robot on one core.
"""

from __future__ import annotations

import os

# One core: the BLAS/OpenMP pools must be sized before numpy is imported.
_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)
for _var in _THREAD_VARS:
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

from labcal.compensator import CalibratedRobot  # noqa: E402
from labcal.robots import load  # noqa: E402

GOAL_FK_TWISTS = 200_000  # configurations/s


@dataclass(frozen=True)
class Section:
    """One row of the table. ``batch``: run(q) is called on all k configurations at once; ``single``: run(q_i) is
    called once per configuration and the median call is reported."""

    name: str
    run: Callable[[np.ndarray], object]
    mode: str = "batch"


def sections(robot_name: str, seed: int = 0) -> tuple[list[Section], int]:
    """The benchmarked sections for a robot, and its number of joints."""
    model = load(robot_name).model
    rng = np.random.default_rng(seed)
    identified = model.perturbed(rng.normal(size=(model.n + 1, 6)) * 0.5e-3)
    compensator = CalibratedRobot(nominal=model, model=identified, method="local-poe")
    definition = []
    try:  # the readable product of exponentials the kernels are tested against: what the kernels earn
        from labcal.kinematics.poe import poe_joint_twists, poe_link_frames
    except ImportError:  # a labcal without it
        pass
    else:
        definition = [
            Section("FK, definition", lambda q: poe_link_frames(model.frames, model.twists, q)[:, -1]),
            Section("FK + twists, definition", lambda q: poe_joint_twists(model.frames, model.twists, q)),
            Section("one walk, definition", lambda q: poe_joint_twists(model.frames, model.twists, q), mode="single"),
        ]
    return [
        *definition,
        Section("FK", model.fk),
        Section("FK + joint twists", model.fk_and_twists),
        Section("frame_jacobian", model.frame_jacobian),
        Section("equivalent_jacobian", model.equivalent_jacobian),
        Section("correct() batched", compensator.correct),
        Section("correct() single", compensator.correct, mode="single"),
    ], model.n


def configurations(robot_name: str, k: int, seed: int = 1) -> np.ndarray:
    """(k, n) configurations uniform inside the joint limits, clipped to ±π for revolute ranges beyond a turn."""
    model = load(robot_name).model
    lo, hi = np.maximum(model.limits[:, 0], -np.pi), np.minimum(model.limits[:, 1], np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, size=(k, model.n))


def time_batch(run: Callable, q: np.ndarray, repeat: int) -> float:
    run(q[:10])  # warm caches and lazy imports outside the timing
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        run(q)
        best = min(best, time.perf_counter() - t0)
    return best


def time_single(run: Callable, q: np.ndarray, repeat: int) -> float:
    run(q[0])
    best = float("inf")
    for _ in range(repeat):
        calls = np.empty(len(q))
        for i, qi in enumerate(q):
            t0 = time.perf_counter()
            run(qi)
            calls[i] = time.perf_counter() - t0
        best = min(best, float(np.median(calls)))
    return best


def pin_to_one_core() -> str:
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned (no sched_setaffinity on this platform)"


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="ur10", help="built-in robot name or robot file (default ur10)")
    ap.add_argument("--k", type=int, default=10_000, help="configurations per batch (default 10000)")
    ap.add_argument("--repeat", type=int, default=5, help="repeats; the best is reported (default 5)")
    ap.add_argument("--singles", type=int, default=2000, help="calls for single-configuration latency")
    args = ap.parse_args(argv)

    pinned = pin_to_one_core()
    secs, n = sections(args.robot)
    q = configurations(args.robot, args.k)
    rows = []
    for sec in secs:
        if sec.mode == "batch":
            t = time_batch(sec.run, q, args.repeat)
            rows.append(
                {"section": sec.name, "batch_ms": t * 1e3, "per_s": args.k / t, "per_config_us": t / args.k * 1e6}
            )
        else:
            t = time_single(sec.run, q[: args.singles], args.repeat)
            rows.append({"section": sec.name, "batch_ms": None, "per_s": 1.0 / t, "per_config_us": t * 1e6})

    print(f"labcal speed — robot {args.robot} (n = {n}), k = {args.k:,} configurations, best of {args.repeat}")
    print(f"one core: {', '.join(_THREAD_VARS)} = 1 set before importing numpy; {pinned}")
    print(f"{cpu_name()}; Python {platform.python_version()}, numpy {np.__version__}")
    print(f"single-configuration rows: median of {min(args.singles, args.k):,} calls\n")
    header = ("section", "batch (ms)", "configurations/s", "µs / configuration")
    table = [header] + [
        (
            r["section"],
            "-" if r["batch_ms"] is None else f"{r['batch_ms']:.2f}",
            f"{r['per_s']:,.0f}",
            f"{r['per_config_us']:.2f}",
        )
        for r in rows
    ]
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]
    for i, row in enumerate(table):
        cells = [row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)]
        print("  ".join(cells))
        if i == 0:
            print("  ".join("-" * w for w in widths))
    fk_twists = next(r["per_s"] for r in rows if r["section"] == "FK + joint twists")
    verdict = "met" if fk_twists >= GOAL_FK_TWISTS else "NOT met"
    print(f"\ngoal: FK + joint twists ≥ {GOAL_FK_TWISTS:,} configurations/s — {verdict} ({fk_twists:,.0f})")
    return rows


if __name__ == "__main__":
    main()
