"""Cross-validated choice of the learned stages: folds, honest held-out errors, the simpler-on-a-tie rule.

Every row a fit is given is used (issue 13): the hyperparameter-free stages (registration, local POE) are fitted
on all of them, and whether a learned stage is worth keeping — the hybrid's network or joint series, the paper's
network, ``auto``'s choice — is decided by K-fold cross-validation over the same rows. Inside a fold every stage
is refitted on the fold's training rows only, local POE included (started from the all-rows identification,
which only saves iterations: the minimum is the same — unless the fold's rows leave a direction unidentified,
then it starts from the nominal, see :func:`cross_validate`), so a held-out error never contains a row its model
saw.
The network's early stopping uses an inner split of the fold's training rows (:func:`~labcal.calibration.ann.
fit_ann`), never the held-out fold.

**Folds** (:func:`fold_plan`). The unit of a fold is an :meth:`~labcal.calibration.observations.Observations.
units` unit: all rows of one ``group`` label (a session of a pooled fit) and repeated measurements of one pose
stay together. With U units:

- U < 3: no cross-validation (the learned stages are skipped, the fit says so);
- U ≤ 10: leave-one-unit-out (K = U) — with groups, leave-one-group-out;
- U < 50: K = 10 (each fold trains on 90 % of a small data set, so the fold models are close to the final one);
- otherwise K = 5.

Units are drawn in a seeded random order and each goes to the fold with the fewest rows so far. Single-joint
sweeps are *not* turned into groups: leaving a whole sweep out asks every model to extrapolate over a joint range
it never saw — which the exported compensator refuses anyway (its joint ranges) — so it would rank models on a
use they are never put to.

**Error.** The held-out error of a row is the mean distance (m) between its measured and predicted target points
(in the observation frame; over the targets the row saw), the quantity every fit minimises; a candidate's CV error
is its mean over all rows.

**Choice** (:func:`choose`). Candidates are ordered from the simplest: nominal < local-poe < hybrid+series <
hybrid+ann < ann. The simplest candidate whose CV error is within a near-tie of the best is chosen: its paired
per-row difference to the best must not exceed ``max(1 % of the best's error, one standard error of the
difference)``. So a learned stage is kept only for a gain the data support, not for noise of the fold draw.

**Time.** The joint series' order (and gravity terms) is chosen once on all rows; each fold refits the
series at that order and re-chooses its ridge λ (see :func:`cross_validate`). A network candidate is trained
inside the folds with one restart, at most 40 Levenberg-Marquardt iterations and at most 1,000 (seeded) rows
(which bound a fold's network time; ``benchmarks/fit_time.py`` measures it) and is dropped from the remaining
folds once, after at least two folds, it is more than 10 % worse than the best other candidate on the rows
evaluated so far (``pruned_after`` in the result); its CV error is then the mean over the folds it ran.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from labcal.calibration.candidates import BY_NAME, NETWORKS, ORDER
from labcal.calibration.local_poe import IdentificationError, fit_local_poe, register
from labcal.calibration.metrics import point_errors
from labcal.calibration.observations import ObservationError, Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics.poe import LocalPOEModel

__all__ = ["NETWORKS", "ORDER", "CVRecord", "CVResult", "choose", "cross_validate", "fold_plan", "row_errors"]
NEAR_TIE = 0.01  # relative: a gain below 1 % of the error is never worth a more complex model
PRUNE_MARGIN = 0.10  # a network > 10 % worse than the best other candidate after two folds is not pursued
CV_RESTARTS = 1  # network restarts inside a fold (the final refit uses the caller's, default 3)
CV_MAX_ITER = 40  # Levenberg-Marquardt iterations inside a fold (LM converges in tens; the paper's Fig. 4: 11)
CV_MAX_ROWS = 1000  # training rows of a fold's network (seeded subsample; the final refit takes up to 2,000)


def fold_count(units: int) -> int:
    """K for U units (module docstring); 0 when cross-validation is impossible (U < 3)."""
    if units < 3:
        return 0
    if units <= 10:
        return units
    return 10 if units < 50 else 5


def fold_plan(obs: Observations, seed: int = 0) -> tuple[list[np.ndarray], str]:
    """Held-out row indices of each fold (sorted) and the scheme ("group" with group labels, else "kfold").

    Empty list when cross-validation is impossible. Deterministic in (data, seed).
    """
    units = obs.units()
    n_units = int(units.max()) + 1 if units.size else 0
    k = fold_count(n_units)
    scheme = "group" if obs.group is not None else "kfold"
    if k == 0:
        return [], scheme
    sizes = np.bincount(units, minlength=n_units)
    load = np.zeros(k, dtype=int)
    fold_of_unit = np.empty(n_units, dtype=int)
    for u in np.random.default_rng([seed, 2147483647]).permutation(n_units):
        f = int(np.argmin(load))  # the emptiest fold, lowest index on a tie
        fold_of_unit[u] = f
        load[f] += sizes[u]
    fold_of_row = fold_of_unit[units]
    return [np.flatnonzero(fold_of_row == f) for f in range(k)], scheme


def row_errors(robot: CalibratedRobot, obs: Observations) -> np.ndarray:
    """(k,) mean distance (m) between measured and predicted target points of each row (over the targets the row
    saw), observation frame: the row means of :func:`labcal.calibration.metrics.point_errors`."""
    d = point_errors(robot, obs)
    if obs.complete:
        return np.mean(d, axis=1)
    return np.sum(np.where(obs.seen, d, 0.0), axis=1) / obs.seen.sum(axis=1)


class CVRecord(TypedDict):
    """:meth:`CVResult.summary`: ``FitResult.cv``, saved with a fit (errors: per fold, None where skipped)."""

    folds: int
    scheme: str
    errors: dict[str, list[float | None]]
    mean: dict[str, float]
    std: dict[str, float]
    chosen: str
    metric: str
    pruned_after: dict[str, int]
    failures: dict[str, str]


@dataclass
class CVResult:
    """Per-row held-out errors of every candidate (NaN where not evaluated) and how the folds went."""

    folds: list[np.ndarray]
    scheme: str
    rows: dict[str, np.ndarray]  # candidate → (k,) held-out errors (m)
    failures: dict[str, str] = field(default_factory=dict)  # candidate → why it could not be fitted in a fold
    pruned_after: dict[str, int] = field(default_factory=dict)  # candidate → folds run before it was dropped

    def fold_errors(self, name: str) -> list[float | None]:
        """Mean held-out error per fold (None where the candidate did not run)."""
        out = []
        for rows in self.folds:
            e = self.rows[name][rows]
            out.append(float(np.mean(e)) if np.all(np.isfinite(e)) else None)
        return out

    def mean(self, name: str) -> float:
        e = self.rows[name]
        e = e[np.isfinite(e)]
        return float(np.mean(e)) if e.size else math.nan

    def available(self, name: str) -> bool:
        return name in self.rows and bool(np.any(np.isfinite(self.rows[name])))

    def summary(self, chosen: str) -> CVRecord:
        """The ``FitResult.cv`` record plus pooled means, fold spread and pruning."""
        names = [n for n in ORDER if n in self.rows]
        errors = {n: self.fold_errors(n) for n in names}
        ran = {n: [v for v in errors[n] if v is not None] for n in names}  # the folds each candidate ran
        return {
            "folds": len(self.folds),
            "scheme": self.scheme,
            "errors": errors,
            "mean": {n: self.mean(n) for n in names},
            "std": {n: float(np.std(ran[n])) if ran[n] else math.nan for n in names},
            "chosen": chosen,
            "metric": "mean target-point distance on the held-out fold",
            "pruned_after": dict(self.pruned_after),
            "failures": dict(self.failures),
        }


ROUNDING = 1e-12  # m: errors that differ by less are the same to floating point (a noise-free fit's residuals)


def choose(result: CVResult, candidates: tuple[str, ...]) -> str:
    """The simplest candidate within a near-tie of the best (module docstring). Raises if none ran."""
    names = [n for n in ORDER if n in candidates and result.available(n)]
    if not names:
        raise ValueError("no candidate could be cross-validated")
    best = min(names, key=lambda n: (result.mean(n), ORDER.index(n)))
    eb = result.rows[best]
    for name in names:
        if name == best:
            return name
        e = result.rows[name]
        common = np.isfinite(e) & np.isfinite(eb)
        if not common.any():
            continue
        d = e[common] - eb[common]
        se = float(np.std(d, ddof=1) / math.sqrt(d.size)) if d.size > 1 else 0.0
        # ROUNDING: a difference of errors at the round-off of a noise-free fit is a tie, not an improvement
        if float(np.mean(d)) <= max(NEAR_TIE * float(np.mean(eb[common])), se, ROUNDING):
            return name
    return best


@dataclass(frozen=True)
class FoldOptions:
    """What every fold fits with (:func:`cross_validate`'s arguments, the network's with the fold budget)."""

    nominal: LocalPOEModel
    seed: int
    start: CalibratedRobot | None
    local_poe_options: dict
    series_options: dict
    network_options: dict
    register_tool: bool


def cross_validate(
    obs: Observations,
    nominal: LocalPOEModel,
    candidates: tuple[str, ...],
    folds: list[np.ndarray],
    scheme: str,
    *,
    seed: int = 0,
    start: CalibratedRobot | None = None,
    local_poe_options: dict | None = None,
    series_options: dict | None = None,
    series_fixed: dict | None = None,
    ann_options: dict | None = None,
    progress: Callable[[str], None] | None = None,
    register_tool: bool = False,
) -> CVResult:
    """Held-out errors of the candidates over the folds of ``obs`` (all its rows are fitting rows).

    start: the local-POE fit on all rows (each fold's identification starts from it). series_fixed: the series
    order and gravity switch chosen on all rows (``{"harmonics": H, "gravity": bool}``); the folds then only
    re-choose λ by their own inner cross-validation, which costs one eigen-decomposition per inner fold instead
    of one per (inner fold, order) — the keep/drop question is whether a series helps, and the order chosen on
    all rows is the series that would be kept. ann_options go to
    ``fit_ann`` for both network candidates (the hybrid's uses the task loss unless told otherwise).
    """
    say = progress or (lambda _msg: None)
    unknown = [c for c in candidates if c not in ORDER]
    if unknown:
        raise ValueError(f"unknown candidates {unknown}; known: {ORDER}")
    k = obs.k
    rows = {c: np.full(k, np.nan) for c in candidates}
    res = CVResult(folds, scheme, rows)
    options = FoldOptions(
        nominal=nominal,
        seed=seed,
        start=start,
        local_poe_options=dict(local_poe_options or {}),
        series_options={**(series_options or {}), **(series_fixed or {})},
        network_options=_fold_network_options(ann_options),
        register_tool=register_tool,
    )
    active = set(candidates)
    train_split = np.full(k, "train", dtype=object)
    for f, held in enumerate(folds):
        mask = np.ones(k, bool)
        mask[held] = False
        train = obs.subset(mask).with_split(train_split[mask])
        fold_robots = _fold_models(train, active, options, res, f)
        if fold_robots is None:
            continue
        test = obs.subset(held)
        for name, robot in fold_robots.items():
            rows[name][held] = row_errors(robot, test)
        say(
            f"cross-validation fold {f + 1}/{len(folds)}: "
            + ", ".join(f"{n} {np.mean(rows[n][held]) * 1e3:.4f} mm" for n in ORDER if n in fold_robots)
        )
        if f >= 1 and len(folds) >= 4:
            _prune(res, active, f + 1)
    return res


def _fold_models(
    train: Observations, active: set[str], options: FoldOptions, res: CVResult, f: int
) -> dict[str, CalibratedRobot] | None:
    """Every active candidate fitted on one fold's training rows; a candidate that cannot be fitted is recorded in
    ``res.failures``. None when the fold's registration or identification fails (then every candidate is)."""
    try:
        before, stage1 = _fold_bases(train, active, options)
    except (IdentificationError, ObservationError) as err:
        for c in active:
            res.failures.setdefault(c, f"fold {f + 1}: {err}")
        return None
    robots: dict[str, CalibratedRobot] = {}
    for name in ORDER:
        if name not in active:
            continue
        try:
            robots[name] = fold_model(name, train, before, stage1, options)
        except ObservationError as err:
            res.failures.setdefault(name, f"fold {f + 1}: {err}")
    return robots


def _fold_bases(
    train: Observations, active: set[str], options: FoldOptions
) -> tuple[CalibratedRobot | None, CalibratedRobot | None]:
    """The registered nominal and the local-POE robot of a fold's training rows, each when a candidate needs it."""
    before = stage1 = None
    if any(BY_NAME[c].base == "registered" for c in active):
        before = register(train, options.nominal, estimate_tool=options.register_tool)[0]  # as fit()'s registration
    if any(c == "local-poe" or BY_NAME[c].hybrid for c in active):
        lp_opts = options.local_poe_options
        stage1, lp_info = fit_local_poe(train, options.nominal, start=options.start, **lp_opts)
        if lp_info["rank"] < lp_info["expected_rank"]:
            # Directions the fold's rows do not identify keep their starting values; started from the
            # all-rows fit those would carry the held-out rows into the fold model. Start from the nominal.
            stage1 = fit_local_poe(train, options.nominal, **lp_opts)[0]
    return before, stage1


def fold_model(
    name: str,
    train: Observations,
    before: CalibratedRobot | None,
    stage1: CalibratedRobot | None,
    options: FoldOptions,
) -> CalibratedRobot:
    """One candidate fitted on a fold's training rows, on its base (the registered nominal or local POE)."""
    if name == "nominal" and before is not None:
        return before
    if name == "local-poe" and stage1 is not None:
        return stage1
    if name == "hybrid+series" and stage1 is not None:
        from labcal.calibration.joint_series import fit_joint_series

        return fit_joint_series(train, stage1, seed=options.seed, **options.series_options)[0]
    base, extra = (stage1, {"loss": "task"}) if name == "hybrid+ann" else (before, {})
    if name in NETWORKS and base is not None:
        from labcal.calibration.ann import fit_ann  # torch only when a network is fitted

        return fit_ann(train, base, seed=options.seed, **{**extra, **options.network_options})[0]
    raise ValueError(f"no fold fit for candidate {name!r}")


def _fold_network_options(ann_options: dict | None) -> dict:
    """The caller's network options with the fold budget: one restart, ≤ 40 LM iterations, ≤ 1,000 rows."""
    opts = {**dict(ann_options or {}), "restarts": CV_RESTARTS}
    if opts.get("trainer", "lm") == "lm":
        opts["max_iter"] = min(int(opts.get("max_iter") or CV_MAX_ITER), CV_MAX_ITER)
    rows = opts.get("max_rows", CV_MAX_ROWS)
    opts["max_rows"] = CV_MAX_ROWS if rows is None else min(int(rows), CV_MAX_ROWS)
    return opts


def _prune(res: CVResult, active: set[str], done: int) -> None:
    """Stop fitting a network candidate that is clearly worse than the best other one on the rows so far."""
    others = [n for n in active if n not in NETWORKS and n != "nominal"]
    for name in [n for n in NETWORKS if n in active]:
        e = res.rows[name]
        seen = np.isfinite(e)
        if not seen.any():
            continue
        rivals = [float(np.mean(res.rows[o][seen])) for o in others if np.all(np.isfinite(res.rows[o][seen]))]
        if rivals and float(np.mean(e[seen])) > (1.0 + PRUNE_MARGIN) * min(rivals):
            active.discard(name)
            res.pruned_after[name] = done
