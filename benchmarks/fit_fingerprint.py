"""Fingerprints of fits: do restructurings leave every fitted number unchanged?

Fits a fixed collection of data sets (simulated UR10, FANUC-class paper scenario, SCARA, tracker-frame data, the
real UR10 data when it is found) with every method and prints, per (data set, method), the sha256 of the fitted
parameters (the export payload without its golden vectors and checksums, which depend on the runtime solver)
and the corrected joints of 200 fixed configurations. ``--save`` writes the corrections to an ``.npz`` beside the
text; ``--compare FILE`` re-runs and prints, per case, whether the parameters are bit-identical and the largest
difference of ``correct()`` from the saved run, and exits 1 when a hash changed or a correction moved by more than
``--tol`` rad. The correction rule binds the configurations where the saved run had converged; a configuration
near a singularity where it had not is shown but may change. Converged means: the saved command reaches the nominal
pose within 1e-9 (m and rad) on a robot with six or more joints; with fewer joints, where a correction is a
least-squares fit and never exact, that one Gauss-Newton step of the fit from the saved command is below 1e-9 rad
(the saved command is the solver's fixed point).

    python benchmarks/fit_fingerprint.py --save benchmarks/results/fit_fingerprint_before.txt
    python benchmarks/fit_fingerprint.py --compare benchmarks/results/fit_fingerprint_before.txt
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import scenarios
from labcal.calibration.fit import fit
from labcal.calibration.local_poe import register
from labcal.calibration.observations import Observations
from labcal.compensator import to_payload
from labcal.kinematics import metric, se3
from labcal.robots import load


def _cases():
    """(name, factory of (observations, nominal model), methods)."""

    def scn(make):
        def build():
            s = make()
            return Observations(s.q, s.points, s.targets, s.frame), load(s.robot).model

        return build

    def real():
        from real_ur10 import load_observations, locate_data

        with tempfile.TemporaryDirectory() as tmp:
            obs, _ = load_observations(locate_data(), Path(tmp) / "store")
        obs = obs.subset(np.sort(np.random.default_rng(0).permutation(obs.k)[:150]))
        # As `labcal fit` does for probe data: the probe's mount on the flange becomes the nominal tool, so the
        # correction aims at the probe's nominal pose instead of turning the wrist to put the probe on the flange.
        bare = load("ur10").model
        registered, _ = register(obs, bare, estimate_tool=True)
        return obs, bare.with_tool(np.linalg.solve(bare.frames[-1], registered.measurement_model.frames[-1]))

    return [
        ("ur10-good-60", scn(lambda: scenarios.good("ur10", 60, seed=1)), ("local-poe", "ann", "hybrid", "auto")),
        ("fanuc-good-100", scn(lambda: scenarios.good("fanuc-m1000ia", 100, seed=2)), ("local-poe", "ann", "hybrid")),
        ("scara4-good-40", scn(lambda: scenarios.good("scara4", 40, seed=3)), ("local-poe", "auto")),
        (
            "ur10-tracker-frame-50",
            scn(lambda: scenarios.in_tracker_frame(scenarios.good("ur10", 50, seed=4))),
            ("local-poe", "hybrid"),
        ),
        ("ur10-sweeps", scn(lambda: scenarios.sweeps("ur10", seed=5)), ("local-poe", "auto")),
        ("real-ur10-150", real, ("local-poe", "ann", "hybrid", "auto")),
    ]


def _digest(robot) -> str:
    payload = to_payload(robot)
    for volatile in ("golden", "checksums"):
        payload.pop(volatile, None)
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _configurations(robot, count: int = 200) -> np.ndarray:
    lo, hi = np.asarray(robot.joint_ranges, float).T
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * 0.9
    return mid + half * np.random.default_rng(12345).uniform(-1, 1, (count, robot.n))


def converged(robot, q: np.ndarray, q_cmd: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """(k,) bool: q_cmd puts the calibrated robot at q's nominal pose within ``tol`` (m and rad); for a robot with
    fewer than six joints, whose correction is a least-squares fit and never exact: one Gauss-Newton step of that
    fit (in the length-scaled metric) from q_cmd is below ``tol``."""
    if robot.n < 6:
        w = metric.twist_weights(robot.length_scale)
        r, J = robot.residual(q_cmd, robot.nominal.fk(q))
        Jw = J * w[:, None]
        steps = np.stack([np.linalg.lstsq(Jw[i], r[i] * w, rcond=None)[0] for i in range(len(q))])
        return np.abs(steps).max(axis=1) < tol
    gap = se3.log_se3(se3.inv(robot.nominal.fk(q)) @ robot.predict_pose(q_cmd))
    return np.abs(gap).max(axis=1) < tol


def run() -> tuple[list[tuple[str, str, str, float]], dict[str, np.ndarray], dict]:
    lines, corrections, robots = [], {}, {}
    for name, build, methods in _cases():
        try:
            obs, nominal = build()
        except FileNotFoundError as exc:
            print(f"{name}: skipped ({exc})", file=sys.stderr)
            continue
        for method in methods:
            t0 = time.perf_counter()
            res = fit(obs, nominal, method, seed=0)
            q = _configurations(res.robot)
            corrections[f"{name}/{method}"] = res.robot.correct(q, extrapolate=True)
            robots[f"{name}/{method}"] = (res.robot, q)
            lines.append((name, method, res.chosen, _digest(res.robot)))
            print(f"{name:24s} {method:10s} {res.chosen:10s} {lines[-1][3][:16]}  {time.perf_counter() - t0:5.1f} s",
                  file=sys.stderr)  # fmt: skip
    return lines, corrections, robots


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--save", type=Path, help="write the fingerprints here (and the corrections to .npz beside it)")
    ap.add_argument("--compare", type=Path, help="compare with a saved run; exit 1 on any difference")
    ap.add_argument("--tol", type=float, default=1e-9, help="allowed |correct() - saved| in rad (default 1e-9)")
    args = ap.parse_args(argv)
    lines, corrections, robots = run()
    text = "".join(f"{n} {m} {c} {h}\n" for n, m, c, h in lines)
    if args.save:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        args.save.write_text(text)
        np.savez(args.save.with_suffix(".npz"), **corrections)
    if not args.compare:
        print(text, end="")
        return 0
    saved = {tuple(ln.split()[:2]): ln.split()[2:] for ln in args.compare.read_text().splitlines() if ln.strip()}
    before = np.load(args.compare.with_suffix(".npz"))
    failed = 0
    print(f"{'data set':24s} {'method':10s} {'parameters':14s} {'max |Δ correct()| rad':>22s}  (rows converged before)")
    for name, method, chosen, digest in lines:
        old = saved.get((name, method))
        key = f"{name}/{method}"
        same = old is not None and old == [chosen, digest]
        if key in before.files:
            robot, q = robots[key]
            bound = converged(robot, q, before[key])
            diff = np.abs(corrections[key] - before[key]).max(axis=1)
            delta = float(diff[bound].max(initial=0.0))
            free = float(diff[~bound].max(initial=0.0))
            shown = f"{delta:22.3g}  ({bound.sum()} of {len(q)}" + (f"; others moved ≤ {free:.3g})" if free else ")")
        else:
            delta, shown = float("nan"), f"{'nan':>22s}"
        ok = same and delta <= args.tol
        failed += not ok
        status = "identical" if same else ("NEW" if old is None else "CHANGED")
        print(f"{name:24s} {method:10s} {status:14s} {shown}{'' if ok else '   <-- FAIL'}")
    missing = set(saved) - {(n, m) for n, m, _, _ in lines}
    for name, method in sorted(missing):
        print(f"{name:24s} {method:10s} {'NOT RUN':14s}")
    print(f"{len(lines) - failed} of {len(lines)} cases unchanged")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
