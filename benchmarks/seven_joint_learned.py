"""Learned terms on a redundant arm: held-out error of local POE, hybrid and auto on a simulated 7-joint arm.

``python benchmarks/seven_joint_learned.py [--seeds 3] [--poses 300] [--robot FILE] [--out F]``

The arm is the Franka Emika Panda from its published modified-DH parameters (Franka Control Interface
documentation: a, d, alpha, flange d = 0.107 m, joint limits; link masses are rough values of a few kg that only
shape the simulated gravity deflection), or any robot file given with ``--robot``. The true robot is
``labcal.simulation.simulate(spec, ErrorSpec.default(), seed)``: geometric, compliance and gear errors, 0.05 mm
tracker noise. Per seed: ``--poses`` uniform configurations inside the joint limits, the last third held out
(labelled "test": never fitted, never used to choose); measured once with three targets and once with one
reflector. Every method is ``fit(obs, nominal, method, seed=seed)`` with default options; the independent plain
least-squares fit (:mod:`labcal.bench.plain_lsq`, global POE by scipy) is the measuring stick. Score: the mean
distance (mm) between predicted and measured target points over every held-out target point.

    python benchmarks/seven_joint_learned.py --out benchmarks/results/seven_joint_learned.txt
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from labcal.bench.plain_lsq import fit_plain
from labcal.calibration import Observations, fit
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

PANDA_MDH = (  # a (m), d (m), alpha (rad), limits (rad): Franka Control Interface documentation
    (0.0, 0.333, 0.0, (-2.8973, 2.8973)),
    (0.0, 0.0, -np.pi / 2, (-1.7628, 1.7628)),
    (0.0, 0.316, np.pi / 2, (-2.8973, 2.8973)),
    (0.0825, 0.0, np.pi / 2, (-3.0718, -0.0698)),
    (-0.0825, 0.384, -np.pi / 2, (-2.8973, 2.8973)),
    (0.0, 0.0, np.pi / 2, (-0.0175, 3.7525)),
    (0.088, 0.0, np.pi / 2, (-2.8973, 2.8973)),
)
PANDA_FLANGE_D = 0.107
MASSES = (4.0, 4.0, 3.0, 3.0, 2.0, 1.5, 0.5)  # kg, rough: they only shape the simulated gravity deflection
TARGET_SETS = {
    "three targets": np.array([[0.12, 0.0, 0.05], [-0.06, 0.15, 0.05], [-0.07, -0.11, 0.04]]),
    "one reflector": np.array([[0.03, 0.02, 0.06]]),
}
METHODS = ("local-poe", "hybrid", "auto")


def panda_spec(folder: Path):
    """The Panda as a robot file (modified DH) in ``folder``, loaded."""
    text = 'name = "panda-mdh"\nkinematics = "mdh"\n'
    for j, (a, d, alpha, (lo, hi)) in enumerate(PANDA_MDH):
        text += (
            f"[[joints]]\nname = 'panda_joint{j + 1}'\ntype = 'revolute'\na = {a}\nalpha = {alpha!r}\nd = {d}\n"
            f"theta = 0.0\nlimits = [{lo}, {hi}]\nmass = {MASSES[j]}\n"
        )
    path = folder / "panda-mdh.toml"
    path.write_text(text + f"[tool]\nxyz = [0.0, 0.0, {PANDA_FLANGE_D}]\n")
    return load(path)


def point_error(predicted: np.ndarray, measured: np.ndarray) -> float:
    """Mean distance (m) over every seen target point; predicted and measured (k, m, 3)."""
    d = np.linalg.norm(predicted - measured, axis=2)
    return float(np.nanmean(d))


def run_case(spec, targets: np.ndarray, seed: int, poses: int) -> dict[str, object]:
    """One seed, one target set: held-out mean point error (m) per method and the plain LSQ, what was kept."""
    actual = simulate(spec, ErrorSpec.default(), seed=seed)
    rng = np.random.default_rng(seed)
    lim = spec.model.limits
    q = rng.uniform(lim[:, 0], lim[:, 1], size=(poses, spec.model.n))
    test = np.arange(poses) >= poses - poses // 3
    split = np.where(test, "test", "").astype(object)
    obs = Observations(q, actual.measure(q, targets, rng), targets, split=split)
    out: dict[str, object] = {}
    for method in METHODS:
        t = time.perf_counter()
        result = fit(obs, spec.model, method, seed=seed)
        robot = result.robot
        pred = robot.predict_points(q[test], targets)
        pred = np.einsum("ab,kmb->kma", robot.T_tracker_base[:3, :3], pred) + robot.T_tracker_base[:3, 3]
        out[method] = point_error(pred, obs.points[test])
        kept = result.info.get("kept") if method == "hybrid" else result.chosen
        if method == "auto" and result.chosen == "hybrid":
            kept = "hybrid/" + str(result.info.get("kept", result.info.get("hybrid", {}).get("kept", "?")))
        out[method + " kept"] = kept
        out[method + " s"] = time.perf_counter() - t
    t = time.perf_counter()
    plain = fit_plain(spec.model, q[~test], obs.points[~test], targets)
    out["plain LSQ"] = point_error(plain.predict_points(q[test], targets), obs.points[test])
    out["plain LSQ s"] = time.perf_counter() - t
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="seeds (true robots and pose sets), default 3")
    parser.add_argument("--poses", type=int, default=300, help="poses per seed, a third held out (default 300)")
    parser.add_argument("--robot", type=Path, help="a robot file instead of the built-in Panda MDH table")
    parser.add_argument("--out", type=Path, help="also write the table here")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        spec = load(args.robot) if args.robot else panda_spec(Path(tmp))
    lines = [
        f"{spec.name} ({spec.model.n} joints), ErrorSpec.default() (geometric + compliance + gears, 0.05 mm noise), "
        f"{args.poses} uniform poses per seed, {args.poses // 3} held out, seeds 0..{args.seeds - 1}, default options",
        "held-out mean target-point error (mm); kept: the hybrid's learned term / auto's choice",
        "",
        f"{'targets':14} {'seed':>4} {'local-poe':>10} {'hybrid':>10} {'auto':>10} {'plain LSQ':>10}  "
        f"{'hybrid kept':18} {'auto chose':26} {'fit s (lp/hy/auto/lsq)'}",
    ]
    print("\n".join(lines), flush=True)
    for name, targets in TARGET_SETS.items():
        rows = []
        for seed in range(args.seeds):
            r = run_case(spec, targets, seed, args.poses)
            rows.append(r)
            secs = "/".join(f"{r[k + ' s']:.1f}" for k in (*METHODS, "plain LSQ"))
            line = (
                f"{name:14} {seed:>4} {1e3 * r['local-poe']:>10.4f} {1e3 * r['hybrid']:>10.4f} "
                f"{1e3 * r['auto']:>10.4f} {1e3 * r['plain LSQ']:>10.4f}  {r['hybrid kept']!s:18} "
                f"{r['auto kept']!s:26} {secs}"
            )
            lines.append(line)
            print(line, flush=True)
        mean = {k: 1e3 * float(np.mean([r[k] for r in rows])) for k in (*METHODS, "plain LSQ")}
        line = (
            f"{name:14} {'mean':>4} {mean['local-poe']:>10.4f} {mean['hybrid']:>10.4f} {mean['auto']:>10.4f} "
            f"{mean['plain LSQ']:>10.4f}"
        )
        lines.append(line)
        print(line, flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
