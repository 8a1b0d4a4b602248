"""Does the emitted URScript return only what ``Compensator.correct()`` returns? Prints a table; not a test.

    python benchmarks/urscript_agreement.py [--configs 1000] [--no-real] > benchmarks/results/urscript_agreement.txt

Exports (default options): a local-POE and a hybrid fit of the simulated UR10 (``scenarios.good``, 200 poses,
``ErrorSpec.default()``, seed 1, fit seed 0), and a local-POE fit of the real UR10 data (all 1,000 poses of
../shared/data/ipa-robot-accuracy-ur10, imported as ``benchmarks/real_ur10.py`` does), unless ``--no-real``.
For each export, ``4 × --configs`` configurations: uniform in the compensator's validity region and joint ranges
(:meth:`~labcal.compensator.validity.ValidityRegion.sample`: where ``correct()`` answers without extrapolating),
uniform in the compensator's joint ranges (clipped to ±π, which
hold every pose of a ±2π joint), the same with the wrist q5 uniform in ±0.05 rad, and with the elbow q3 uniform in
±0.05 rad. Each runs through ``labcal_correct`` in the URScript interpreter of :mod:`urscript_subset` (this folder)
in float64 and in float32 (the controller's precision) and is sorted into:

- **agree**: returned, within 1e-4 rad of ``correct()`` (max over joints);
- **stopped**: the script halted (popup + halt) or failed at run time (a controller stops the program too);
- **differ**: returned, more than 1e-4 rad from ``correct()`` — a silent wrong command (must be 0);
- **worse**: returned, farther from ``correct()`` than q itself (worse than no correction; part of "differ");
- **residual rounding** (below the table): the largest ``|J_s (q_script − correct())|∞`` over the returned
  answers in float32 (J_s: the length-scaled Jacobian at correct()'s answer), in machine epsilons (2⁻²³): the
  rounding the script's residual carried, which its precision check takes as at most 5 ε (RESIDUAL_ROUNDING);
- **stopped where correct() damps**: stopped where ``correct()``'s Gauss-Newton fails and its damped fallback
  answers (``correct(q, damped_iterations=0)`` differs from ``correct(q)``), and of those, how many damped answers
  are exact (weighted residual L1 < 1e-8 rad: the rest leave a residual, a least-squares compromise).

The exporter and the fits come from whatever ``labcal`` is on the path, the interpreter always from this file's
folder, so the code before a change is measured by pointing PYTHONPATH at a worktree of it:

    git worktree add /tmp/urs-before 5770eeb
    PYTHONPATH=/tmp/urs-before/src python benchmarks/urscript_agreement.py \
        > benchmarks/results/urscript_agreement_before.txt
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import labcal
import urscript_subset
from labcal.calibration import Observations
from labcal.calibration.fit import fit
from labcal.export.urscript import urscript_text
from labcal.kinematics.metric import scaled_condition
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec
from scenarios import good

AGREE = 1e-4  # rad
NEAR = 0.05  # rad from the singular value of the wrist (q5) and the elbow (q3)
MAX_CORRECTION = 0.1  # rad: the exporter's default bound on |q_cmd - q| (the code before had none)


def exports(real: bool) -> dict:
    """name → CalibratedRobot of every export measured."""
    nominal = load("ur10").model
    scn = good("ur10", 200, errors=ErrorSpec.default(), seed=1)
    obs = Observations(**scn.arrays())
    out = {
        "sim local-POE": fit(obs, nominal, "local-poe", seed=0).robot,
        "sim hybrid": fit(obs, nominal, "hybrid", seed=0).robot,
    }
    if real:
        from real_ur10 import DataNotFound, load_observations, locate_data

        try:
            data = locate_data()
        except DataNotFound as e:
            print(f"(real UR10 data skipped: {e})")
            return out
        with tempfile.TemporaryDirectory() as store:
            obs, _ = load_observations(data, Path(store))
        out["real UR10 local-POE"] = fit(obs, nominal, "local-poe", seed=0).robot
    return out


def configurations(robot, k: int, seed: int = 0) -> dict:
    """set name → (k, 6) configurations (module docstring)."""
    rng = np.random.default_rng(seed)
    lo = np.maximum(robot.joint_ranges[:, 0], -np.pi)
    hi = np.minimum(robot.joint_ranges[:, 1], np.pi)
    sets = {}
    if getattr(robot, "validity", None) is not None:  # where correct() answers without extrapolating
        q = robot.validity.sample(20 * k, rng)  # the balls reach past the joint ranges: keep what is in both
        q = q[_in_box(robot, q)][:k]
        if len(q) < k:
            raise SystemExit(f"fewer than {k} of {20 * k} samples of the validity region are in the joint ranges")
        sets["in the validity region"] = q
    for name, joint in (("in range", None), ("wrist q5 in ±0.05", 4), ("elbow q3 in ±0.05", 2)):
        q = rng.uniform(lo, hi, size=(k, robot.n))
        if joint is not None:
            q[:, joint] = rng.uniform(max(lo[joint], -NEAR), min(hi[joint], NEAR), size=k)
        sets[name] = q
    return sets


def run(subset, script: str, q: np.ndarray, float32: bool) -> tuple[np.ndarray, np.ndarray]:
    """(k, n) outputs (NaN rows where the script stopped), (k,) stopped."""
    ns = subset.load(script, float32=float32)
    out = np.full(q.shape, np.nan)
    stopped = np.zeros(len(q), dtype=bool)
    with np.errstate(all="ignore"):
        for i, row in enumerate(q):
            try:
                out[i] = np.asarray(ns["labcal_correct"](list(map(float, row))), dtype=float)
            except (subset.Halted, ZeroDivisionError, OverflowError, ValueError):
                stopped[i] = True
    return out, stopped


def _cells(counts: np.ndarray) -> str:
    return " | ".join(map(str, counts[:5])) + f" | {counts[5]} ({counts[6]}) |"[:-2]


def _in_box(robot, q) -> np.ndarray:
    return np.all((q >= robot.joint_ranges[:, 0]) & (q <= robot.joint_ranges[:, 1]), axis=1)


def _in_region(robot, q) -> np.ndarray:
    """Which configurations correct() accepts without extrapolating (all of them for a robot without a region)."""
    if getattr(robot, "validity", None) is None:
        return np.ones(len(q), dtype=bool)
    return robot.validity.inside(q)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--configs", type=int, default=1000, help="configurations per set (three sets per export)")
    ap.add_argument("--no-real", action="store_true", help="skip the real UR10 data")
    args = ap.parse_args()
    t0 = time.perf_counter()
    print(f"exporter: {Path(labcal.__file__).parent}; agreement bound {AGREE:g} rad; configurations per set "
          f"{args.configs}")  # fmt: skip
    header = (
        "| export | set | precision | configurations | agree | stopped | **differ** | worse than none "
        "| stopped where correct() damps (its answer exact) |"
    )
    rows, totals = [header, "|---|---|---|---|---|---|---|---|---|"], []
    for name, robot in exports(not args.no_real).items():
        script = urscript_text(robot)
        sets = configurations(robot, args.configs)
        for precision in ("float64", "float32"):
            total = np.zeros(7, dtype=int)
            rounding = 0.0  # largest |J_s (q_script - correct())|inf / eps: the residual rounding answers carried
            eps = np.finfo(np.float32 if precision == "float32" else np.float64).eps
            for set_name, q in sets.items():
                # The box sets leave the validity region, where the script stops as correct() refuses: compare
                # with correct() extrapolating, and count below what it returned outside the region (must be 0).
                expected = robot.correct(q, extrapolate=True)
                damped = np.max(np.abs(robot.correct(q, extrapolate=True, damped_iterations=0) - expected), axis=1)
                damped = damped > 1e-12
                r, _ = robot.residual(expected, robot.nominal.fk(q), jacobian=False)
                exact = np.sum(np.abs(r) * np.array([1 / robot.length_scale] * 3 + [1.0] * 3), axis=1) < 1e-8
                got, stopped = run(urscript_subset, script, q, precision == "float32")
                with np.errstate(invalid="ignore"):
                    err = np.max(np.abs(got - expected), axis=1)
                    none = np.max(np.abs(q - expected), axis=1)
                    returned = ~stopped
                    agree = returned & (err <= AGREE)
                    differ = returned & ~(err <= AGREE)
                    worse = returned & ~(err <= none)
                if returned.any():
                    w = np.array([1 / robot.length_scale] * 3 + [1.0] * 3)
                    Js = w[:, None] * robot.model.equivalent_jacobian(expected[returned])
                    dr = np.einsum("kij,kj->ki", Js, got[returned] - expected[returned])
                    rounding = max(rounding, float(np.max(np.abs(dr))) / eps)
                d, e = (stopped & damped).sum(), (stopped & damped & exact).sum()
                counts = np.array([len(q), agree.sum(), stopped.sum(), differ.sum(), worse.sum(), d, e])
                total += counts
                rows.append(f"| {name} | {set_name} | {precision} | {_cells(counts)} |")
                if set_name in ("in the validity region", "in range"):
                    J = robot.model.equivalent_jacobian(q, length_scale=robot.length_scale)
                    tame = scaled_condition(J, robot.length_scale) <= 100
                    large = ~damped & (np.max(np.abs(expected - q), axis=1) > MAX_CORRECTION)
                    totals.append(
                        f"{name}, {precision}: {stopped.sum()} of {len(q)} configurations {set_name} stopped "
                        f"({100 * stopped.mean():.1f} %: {(stopped & damped).sum()} where correct() damps, "
                        f"{(stopped & large).sum()} where its correction exceeds {MAX_CORRECTION:g} rad); "
                        f"{(stopped & tame).sum()} of the {tame.sum()} with scaled condition <= 100; "
                        f"{(stopped & ~_in_box(robot, q)).sum()} outside the joint ranges; "
                        f"{(returned & ~_in_region(robot, q)).sum()} returned outside the validity region"
                    )
            rows.append(f"| {name} | **all** | {precision} | {_cells(total)} |")
            if precision == "float32":  # in float64 correct()'s own stopping rule, not rounding, dominates
                totals.append(f"{name}, {precision}: residual rounding of the returned answers <= {rounding:.2f} eps")
    print("\n".join(rows))
    print()
    print("\n".join(totals))
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
