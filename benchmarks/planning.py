"""Does choosing configurations help? Scenario A (paper Section V) with local POE: 25 optimised vs 25 and 50 random.

fanuc-m1000ia, ErrorSpec.paper() (0.5 mm / 0.5 mrad geometric errors, 0.05 mm tracker noise), the paper
benchmark's targets, full joint ranges, the paper benchmark's conditioning limit. Held-out: 1,000 fresh random
configurations per simulated robot; error = calibrated predicted pose vs the true pose.

    python benchmarks/planning.py --seeds 24     # about 1.5 min; output kept in benchmarks/results/planning.txt
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from labcal.calibration import Observations
from labcal.calibration.local_poe import fit_local_poe
from labcal.kinematics import se3
from labcal.robots import load
from labcal.sessions.planning import (
    identifiable_basis,
    identification_jacobian,
    optimal_configurations,
    random_configurations,
    target_weights,
    weighted_rows,
)
from labcal.simulation import ErrorSpec, simulate
from paper import MAX_CONDITION, TARGETS


@dataclass(frozen=True)
class Observability:
    """Observability of the identifiable frame errors from a set of configurations.

    o1: (σ_1⋯σ_r)^(1/r)/√rows, m (Borm & Menq O1; 0 if rank-deficient); log_det: log det(GᵀG) on the
    identifiable subspace (−inf if singular); rank: numerical rank of the reduced G; parameters: r; rows: the
    measured coordinates, 3 per target seen (expected, with a drop-out probability).
    """

    o1: float
    log_det: float
    rank: int
    parameters: int
    rows: float


# Numeric indices of a set of configurations, for this benchmark and the planner's tests (the planner maximises
# them, it never reports them); labcal.calibration.metrics.observability is another concept: the orientation
# claims a target set supports (words for a fit's report).
def observability(model, q, targets, *, basis: np.ndarray | None = None, seen=None, dropout=None) -> Observability:
    """O1 and log-det indices of the configurations q (k, n) for targets (m, 3), on ``basis`` (default
    :func:`identifiable_basis` with its default seed, so indices of different sets are comparable).

    ``seen``: (k, m) bool, the targets actually measured in each configuration (only their rows count);
    ``dropout``: probability that a target is lost (scalar or (m,)): the expected information and row count."""
    basis = identifiable_basis(model, targets) if basis is None else np.asarray(basis, dtype=float)
    G = identification_jacobian(model, q, targets)
    k, m = G.shape[0], G.shape[1] // 3
    rows: float = float(G.shape[0] * G.shape[1])
    if seen is not None or dropout is not None:
        w = np.broadcast_to(target_weights(m, dropout), (k, m))
        if seen is not None:
            mask = np.asarray(seen, dtype=bool)
            if mask.shape != (k, m):
                raise ValueError(f"seen must be a ({k}, {m}) bool array, got {mask.shape}")
            w = w * mask
        rows = float(3 * w.sum())
        keep = np.repeat(w > 0, 3, axis=1)
        R = (weighted_rows(G, w) @ basis)[keep]
    else:
        R = (G @ basis).reshape(-1, basis.shape[1])
    s = np.linalg.svd(R, compute_uv=False) if R.size else np.zeros(0)
    r = basis.shape[1]
    if s.size < r:
        s = np.concatenate([s, np.zeros(r - s.size)])
    rank = int(np.sum(s > 1e-12 * max(s[0], 1e-300)))
    with np.errstate(divide="ignore"):
        logs = np.log(s)
    full = rank == r
    return Observability(
        o1=float(np.exp(logs.mean()) / np.sqrt(rows)) if full else 0.0,
        log_det=float(2 * logs.sum()) if full else float("-inf"),
        rank=rank,
        parameters=r,
        rows=int(rows) if rows == int(rows) else rows,
    )


def prediction_variance(model, q, targets, workspace, *, basis: np.ndarray | None = None) -> float:
    """Average prediction variance of the target positions over ``workspace`` (k_w, n) configurations after
    identifying the frame errors from q (k, n): ``trace(F⁻¹ W)`` in units of the tracker noise variance per
    coordinate (m² / m²), F the information of q, W the mean information of one workspace configuration, both
    on the identifiable subspace (``basis``, default :func:`identifiable_basis`). ``inf`` if q cannot identify
    every direction. The I-optimality criterion the ``"i"`` planner lowers: lower is better; the expected mean
    squared prediction error of one target coordinate is σ² · this / (3 · targets).
    """
    basis = identifiable_basis(model, targets) if basis is None else np.asarray(basis, dtype=float)
    G = identification_jacobian(model, q, targets) @ basis
    H = identification_jacobian(model, workspace, targets) @ basis
    F = np.einsum("kmr,kms->rs", G, G)
    W = np.einsum("kmr,kms->rs", H, H) / H.shape[0]
    if np.linalg.matrix_rank(F) < F.shape[0]:
        return float("inf")
    return float(np.trace(np.linalg.solve(F, W)))


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
