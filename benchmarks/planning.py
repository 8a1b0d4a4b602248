"""Does choosing configurations help? Scenario A (paper Section V) with local POE: 25 optimised vs 25 and 50 random.

fanuc-m1000ia, ErrorSpec.paper() (0.5 mm / 0.5 mrad geometric errors, 0.05 mm tracker noise), the paper
benchmark's targets, full joint ranges, the paper benchmark's conditioning limit. Held-out: 1,000 fresh random
configurations per simulated robot; error = calibrated predicted pose vs the true pose.

    python benchmarks/planning.py --seeds 24     # about 1.5 min; output kept in benchmarks/results/planning.txt
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from labcal.calibration import Observations
from labcal.calibration.local_poe import fit_local_poe
from labcal.kinematics import se3
from labcal.robots import load
from labcal.sessions.planning import (
    identifiable_basis,
    observability,
    optimal_configurations,
    prediction_variance,
    random_configurations,
)
from labcal.simulation import ErrorSpec, simulate
from paper import MAX_CONDITION, TARGETS


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=6, help="number of simulated robots (default 6)")
    args = parser.parse_args(argv)

    spec = load("fanuc-m1000ia")
    model = spec.model
    basis = identifiable_basis(model, TARGETS)
    rows: dict[str, list] = {}
    for seed in range(1, args.seeds + 1):
        actual = simulate(spec, ErrorSpec.paper(), seed=seed)
        rng = np.random.default_rng(10_000 + seed)
        hold = random_configurations(model, 1000, seed=20_000 + seed, max_condition=MAX_CONDITION)
        sets = {
            "random-50": random_configurations(model, 50, seed=30_000 + seed, max_condition=MAX_CONDITION),
            "random-25": random_configurations(model, 25, seed=40_000 + seed, max_condition=MAX_CONDITION),
        }
        start = time.perf_counter()
        pool = random_configurations(model, 2000, seed=50_000 + seed, targets=TARGETS, max_condition=MAX_CONDITION)
        for criterion in ("d", "i"):
            sets[f"{criterion}-optimal-25"] = optimal_configurations(
                model, 25, seed=50_000 + seed, targets=TARGETS, pool=pool, criterion=criterion
            )
        t_opt = time.perf_counter() - start
        for name, q in sets.items():
            obs = Observations(q, actual.measure(q, TARGETS, rng), TARGETS, split=np.array(["train"] * len(q), object))
            robot, info = fit_local_poe(obs, model)
            dp, dr = se3.pose_distance(robot.predict_pose(hold), actual.true_pose(hold))
            o = observability(model, q, TARGETS, basis=basis)
            pv = prediction_variance(model, q, TARGETS, hold, basis=basis)
            rows.setdefault(name, []).append((dp.max(), dp.mean(), dr.max(), o.o1, o.log_det, info["rank"], pv))
        print(f"seed {seed}: both optimisations took {t_opt:.2f} s", flush=True)

    print(f"\nlocal POE on fanuc-m1000ia, paper errors, {args.seeds} simulated robots, mean ± std over robots")
    head = ("set", "held-out max pos mm", "mean pos mm", "max ori mrad", "O1 (m)", "log det", "rank", "pred. var")
    widths = (12, 22, 16, 16, 16, 9, 5, 10)
    print(" ".join(f"{h:{'<' if i == 0 else '>'}{w}s}" for i, (h, w) in enumerate(zip(head, widths, strict=True))))
    for name, r in rows.items():
        a = np.array(r)

        def fmt(c: int, s: float = 1.0, a=a) -> str:
            return f"{a[:, c].mean() * s:.4f} ± {a[:, c].std() * s:.4f}"

        print(
            f"{name:12s} {fmt(0, 1e3):>22s} {fmt(1, 1e3):>16s} {fmt(2, 1e3):>16s} {fmt(3):>16s} "
            f"{a[:, 4].mean():9.1f} {a[:, 5].min():5.0f} {a[:, 6].mean():10.3f}"
        )


if __name__ == "__main__":
    main()
