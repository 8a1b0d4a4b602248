"""One entry point for every calibration method: fit on every row, choose by cross-validation, measure, warn.

Methods (:data:`METHODS`):

- ``nominal``: the registered nominal (only T_tracker_base estimated, for tracker-frame data) — the baseline;
- ``local-poe``: model-based identification of the frame errors (:mod:`labcal.calibration.local_poe`);
- ``ann``: the paper's method — equivalent robot + network on the registered nominal
  (:mod:`labcal.calibration.ann`);
- ``hybrid``: local POE, then a learned term on the identified robot (joint series or network), kept only when
  cross-validation supports it (:mod:`labcal.calibration.hybrid`);
- ``auto``: cross-validates local-poe, hybrid (+series, +ann) and ann in the same folds and keeps the simplest
  within a near-tie of the best (order local-poe < hybrid+series < hybrid+ann < ann; :mod:`labcal.calibration.cv`).

ann and hybrid learn the joint motion errors of the equivalent robot: six for n ≤ 6 (virtual joints for n < 6), the
n joints of a redundant arm (n > 6), observed without self-motion (:mod:`labcal.calibration.equivalent`); auto
considers them for every n.

**Rows.** By default (``val_fraction=0``) every row that is not labelled "val" or "test" is a fitting row: local
POE and the registration use all of them, and the learned stages are chosen by K-fold cross-validation over them
(:func:`labcal.calibration.cv.fold_plan`), then refitted on all of them. ``val_fraction > 0`` (or rows labelled
"val"/"test") gives a fixed hold-out that is only measured (``metrics``), never used to fit, choose or early-stop.

**Warnings** (``FitResult.warnings``, each ``{"code", "message"}``; every one should stop an export unless
forced) and **notes** (``FitResult.notes``, information). Codes:

- ``rank-deficient``: local POE's numerical rank is below the identifiable count; lists the unidentifiable
  directions;
- ``overfit``: the chosen model's cross-validated error is over :data:`OVERFIT_RATIO` (10) times its error on
  the rows it was fitted to (it interpolates them: 5 poses for 30 parameters), or a kept network has more
  weights than training numbers. Between 2× and 10× it is a note ("overfit-risk"): a cross-validated choice on
  50 real poses (hybrid + series, UR10) sits at 3–4× and is still the best model available;
- ``worse-than-nominal``: the cross-validated (or hold-out) error of the chosen model is not below the registered
  nominal's;
- ``poor-fit``: even on its own fitting rows the chosen model leaves a mean target-point error above
  :data:`POOR_FIT` (wrong units, a wrong or swapped targets file, pure noise: no calibration explains such data);
- ``point-residuals``: the target points are far off (> 10× the pose error, > 2 mm) while the pose fits: the
  targets file does not match the data (:func:`labcal.calibration.metrics.point_residual_warning`);
- ``narrow-joint``: the data moved a joint less than :data:`NARROW_JOINT` (5°, 10 mm) while the calibration
  claims a wider range for it (a geometric model: the robot's limits), so its axis is extrapolated; names it;
- ``frame-jump``: the fitted model's point residuals step between two blocks of a session's rows (recorded
  order) by more than :data:`FRAME_JUMP` and 4× their spread: the tracker moved during the session; names the row;
- ``large-correction``: ``robot.correct`` moves a joint by more than :data:`MAX_CORRECTION` (0.05 rad revolute,
  10 mm prismatic) and the nominal tool by more than :data:`MAX_TOOL_CORRECTION` (10 mm or 0.02 rad) at 10 % or
  more of the checked configurations — the data's own and 256 random ones in the validity region (near a
  singular wrist a tiny orientation error needs tenths of a radian at joints 4 and 6 but hardly moves the tool,
  so the joint bound alone would flag good fits); the message gives the largest and names the cause the evidence
  shows (:func:`_correction_cause`: a tool mismatch with the identified tool, a weakly determined direction, a unit
  slip or wrong model, or configurations outside the data). The validity region is the fitted configurations'
  neighbourhood that every fit attaches to its robot (:mod:`labcal.compensator.validity`). Real calibration corrections
  are milliradians and millimetres; unit slips produced 0.1–0.6 rad;
- ``rows-dropped``: a kept network was trained without more than 10 % of the rows (condition filter), with the
  cause of each group; when no network is kept the same count is a note (the dropped rows only ever feed the
  network);
- ``stage-skipped``: reported as a note ("stage-skipped: …") when hybrid or auto drops a learned stage that could
  not be fitted (too few rows after the condition filter, too few poses to cross-validate): what is kept is
  still a complete model;
- ``few-poses``: fewer than 2 distinct poses per joint were fitted (the import's ``few-poses`` check, which
  ``--allow few-poses`` overrides at import but not here);
- ``no-network``: ``ann`` alone could not train its network (the same causes): the fit is the registered nominal;
- ``weak`` (a note): local POE held directions the data determine worse than ``error_bound`` at the tracker noise
  at the nominal (:mod:`labcal.calibration.local_poe`, "Weak directions"); names them;
- ``unobservable`` (a note): the targets cannot show some rotations of the tool (one target: the tool's
  orientation; targets on a line: the rotation about it), named in words. It is a note, not a warning: those
  directions are a property of the measuring set-up, not a failure of the data, and the fit leaves them at the
  nominal (the minimum-norm step), so the compensator makes no correction along them — it does not invent one.
  What it cannot do is promise the tool's orientation; ``FitResult.observability`` says what orientation
  accuracy can be claimed. A direction the *robot's* parameters lose for lack of poses is still
  ``rank-deficient`` (blocking).

**Any number of targets.** Every method fits point residuals (:mod:`labcal.calibration.local_poe`,
:mod:`labcal.calibration.equivalent`), so 1 … m targets per row and targets missing in some rows all fit; with
fewer than three targets in a row the network trains on the point loss (eq. 20) and the metrics' primary figures
are point errors (:mod:`labcal.calibration.metrics`).

``FitResult.cv``: ``{"folds", "scheme": "kfold"|"group", "errors": {candidate: [per-fold mean target-point
error m, None where skipped]}, "mean", "std", "chosen", "pruned_after", "failures"}``, None for ``nominal`` or
when there are too few distinct poses (< 3). Same data and seed ⇒ bit-identical parameters.

Example::

    >>> from labcal.robots import load
    >>> from labcal.simulation import ErrorSpec, simulate
    >>> spec = load("scara4"); actual = simulate(spec, ErrorSpec.paper(), seed=1)
    >>> rng = np.random.default_rng(0)
    >>> q = rng.uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(40, 4))
    >>> targets = np.array([[0.05, 0, 0], [0, 0.05, 0], [-0.04, -0.03, 0.01]])
    >>> obs = Observations(q, actual.measure(q, targets, rng), targets)
    >>> result = fit(obs, spec.model, "local-poe")
    >>> result.n_train, result.n_val, result.cv["folds"], result.cv["mean"]["local-poe"] < 1e-4
    (40, 0, 10, True)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from threadpoolctl import threadpool_limits

from labcal.calibration.candidates import (
    BY_NAME,
    NETWORKS,
    STAGE2,
    TABLE,
    AutoInfo,
    Candidates,
    FitContext,
    NominalInfo,
    NoNetworkInfo,
    Outcome,
    Stage,
)
from labcal.calibration.cv import CVRecord, CVResult, choose, cross_validate, fold_plan, row_errors
from labcal.calibration.hybrid import HybridInfo, finish_hybrid, prefit_series, series_fixed
from labcal.calibration.local_poe import LocalPOEInfo, RegisterInfo, fit_local_poe, register
from labcal.calibration.metrics import (
    FitWarning,
    Observability,
    SplitEntry,
    observability,
    point_residual_warning,
    point_residuals,
    split_table,
)
from labcal.calibration.observations import ObservationError, Observations
from labcal.calibration.tool import tool_lines
from labcal.compensator import CalibratedRobot
from labcal.compensator.validity import ValidityRegion
from labcal.kinematics import se3
from labcal.kinematics.poe import LocalPOEModel

if TYPE_CHECKING:
    from labcal.calibration.ann import ANNInfo
    from labcal.calibration.candidates import MethodInfo

METHODS = ("nominal", "local-poe", "ann", "hybrid", "auto")
OVERFIT_RATIO = 10.0  # CV error / in-sample error above which the model interpolates its rows: blocking
OVERFIT_NOTE_RATIO = 2.0  # above this a note: CV error ≫ fit error, the in-sample numbers flatter the model
POOR_FIT = 5e-3  # m: mean target-point error on the fitting rows above which no model explains the data
MAX_CORRECTION = {"revolute": 0.05, "prismatic": 0.01}  # rad, m: largest joint correction accepted silently
MIN_POSES_PER_JOINT = 2  # as labcal.datasets.sanity's few-poses check: below it a fit is a warning
NARROW_JOINT = {"revolute": np.deg2rad(5.0), "prismatic": 0.01}  # rad, m: a joint that moved less is not calibrated
FRAME_JUMP = 1e-3  # m: a step this large (and 4× the spread) in the residuals between two blocks of rows: blocking
FRAME_JUMP_BLOCK = 10  # rows: the shortest block on either side of a step
DROPPED_SHARE = 0.10  # share of rows a kept network may miss before it is a warning
_CORRECTION_SAMPLES = 256  # random configurations within the data's joint ranges for the correction check
# m, rad: a correction that moves the nominal tool less than this is the size of real robot errors (mm, < 1°)
MAX_TOOL_CORRECTION = (0.01, 0.02)
# Share of the checked configurations that must exceed both bounds: a unit slip or a wrong model exceeds them
# nearly everywhere, a good fit at most in a few extrapolated corners of its data's joint ranges.
_CORRECTION_SHARE = 0.10


@dataclass(frozen=True, eq=False)
class FitResult:
    """The outcome of :func:`fit`.

    method: what was asked; chosen: what was fitted ("local-poe", "hybrid", "ann" for "auto"); robot: the
    calibrated robot; before: the registered nominal; metrics: ``split_table(before, robot, obs)`` (per split,
    before/after); info: method diagnostics (hybrid: ``kept``, ``val_errors`` … ; auto: ``candidates``
    {method: CV error m} and each candidate's info); seed; n_train / n_val / n_test: row counts (train = the
    fitting rows); fit_seconds: wall time per step; obs: the split data; warnings: blocking findings
    [{code, message}]; notes: information; cv: the cross-validation record (module docstring) or None;
    observability: what orientation accuracy the targets support (:func:`labcal.calibration.metrics.
    observability`: ``orientation`` "measured" | "partial" | "none", ``unobservable`` in words, ``claim`` text).
    """

    method: str
    chosen: str
    robot: CalibratedRobot
    before: CalibratedRobot
    metrics: dict[str, SplitEntry]
    info: MethodInfo
    seed: int
    n_train: int
    n_val: int
    n_test: int
    fit_seconds: dict[str, float]
    obs: Observations
    warnings: list[FitWarning]
    notes: list[str]
    cv: CVRecord | None
    observability: Observability


def fit(
    obs: Observations,
    nominal: LocalPOEModel,
    method: str = "auto",
    *,
    seed: int = 0,
    val_fraction: float = 0.0,
    progress: Callable[[str], None] | None = None,
    local_poe_options: dict | None = None,
    register_tool: bool = False,
    **options: Any,
) -> FitResult:
    """Fit one method (or choose one with "auto"), measure it against the registered nominal, and check it.

    options: keyword options of the method's fitting function — ``fit_local_poe`` for "local-poe", ``fit_ann``
    for "ann", "hybrid" and "auto" (their network stage); ``local_poe_options`` go to the local-POE stage of
    "hybrid" and "auto"; ``stage2`` and ``series_options`` go to the hybrid only (see ``fit_hybrid``).
    val_fraction: share of the unlabelled rows held out (only measured); 0 fits on every row.
    progress: optional callable receiving one status line per step.
    register_tool: the registered nominal ("before", and the base of the paper's ANN method) also estimates the
    measurement tool (probe data: the probe's mount is the tool, not a robot error the network should learn).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    obs.check_robot(nominal.n)
    obs = obs.with_splits(val_fraction, seed)
    if not np.any(obs.split == "train"):
        raise ValueError("no fitting rows: every row is labelled val or test")
    # The hybrid's options taken out of the network's.
    stage2 = tuple(options.pop("stage2", ("ann", "series")))
    series_options = options.pop("series_options", None)
    if not stage2 or any(name not in STAGE2 for name in stage2):
        raise ValueError(f"stage2 must name 'ann' and/or 'series', got {stage2!r}")
    ctx = FitContext(
        obs=obs,
        fit_obs=obs.where("train"),
        nominal=nominal,
        method=method,
        seed=seed,
        options=options,
        local_poe_options=dict(local_poe_options or {}),
        series_options=series_options,
        stage2=stage2,
        register_tool=register_tool,
        say=progress or (lambda _msg: None),
    )
    # One BLAS thread: the fits multiply many small and medium matrices, where OpenBLAS's threads were measured
    # 3-20x slower on a loaded 2-core machine (local POE at 1,000 rows: 4.0 s threaded, 1.1 s single), and one
    # thread keeps the summation order, so the bits of a fit, independent of the core count.
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit(ctx)


def fit_hybrid(
    obs: Observations,
    nominal: LocalPOEModel,
    *,
    seed: int = 0,
    local_poe_options: dict | None = None,
    stage2: tuple[str, ...] = ("ann", "series"),
    series_options: dict | None = None,
    progress: Callable[[str], None] | None = None,
    **ann_options: Any,
) -> tuple[CalibratedRobot, HybridInfo]:
    """Local POE on every fitting row, then the learned term that cross-validation supports, refitted on all rows.

    ``fit(obs, nominal, "hybrid", …)`` without its metrics and checks: (robot, info). Fitting rows: "train" and
    unassigned; "val" rows are only measured (``val_error`` in the info), "test" rows ignored. stage2: the learned
    terms to try ("ann", "series"). ann_options go to ``fit_ann`` (hidden, features, trainer, restarts, loss —
    default "task" here); series_options to ``fit_joint_series``.

    Returns the kept robot (method "hybrid"; the local-POE robot relabelled when no learned term helped) and
    info: ``kept`` ("local-poe+ann", "local-poe+series" or "local-poe"), ``val_error_local_poe`` and
    ``val_error_hybrid`` (cross-validated error of local POE and of the best stage-2 candidate, m — the names
    predate cross-validation), ``val_errors`` per stage-2 candidate (CV, m; NaN when it could not run),
    ``cv`` (:meth:`CVResult.summary`), ``skipped`` {candidate: why}, ``notes``, ``local_poe`` and the kept
    stage's info (:mod:`labcal.calibration.hybrid`).
    """
    result = fit(
        obs, nominal, "hybrid", seed=seed, progress=progress, local_poe_options=local_poe_options, stage2=stage2,
        series_options=series_options, **ann_options,
    )  # fmt: skip
    return result.robot, {**cast(HybridInfo, result.info), "notes": list(result.notes)}


def _fit(ctx: FitContext) -> FitResult:
    """fit() inside its BLAS limit: the registered nominal, the candidates, the method, the checks."""
    ctx.say("registering the nominal model")
    before = Stage(*ctx.timed("nominal", lambda: register(ctx.obs, ctx.nominal, estimate_tool=ctx.register_tool)))
    if ctx.method == "nominal":
        nominal: NominalInfo = {"register": before.info}
        return _result(ctx, Outcome(before.robot, nominal, "nominal", "nominal"), before.robot, None, [], None)
    table = _candidates(ctx, before)
    outcome = _run_method(ctx, table)
    # Every fit carries its validity region: the neighbourhood of the fitted configurations (scaled joint space).
    robot = dataclasses.replace(outcome.robot, validity=ValidityRegion.from_configurations(ctx.fit_obs.q))
    info_cv = None if table.cv is None else table.cv.summary(outcome.candidate)
    metrics = split_table(before.robot, robot, ctx.obs)
    warnings = _checks(ctx, table, outcome, robot, metrics)
    net = outcome.network  # "ann"'s record of no network is its info: a NoNetworkInfo with the reason
    if net is not None and "no_network" in net:
        warnings.insert(0, _warn("no-network", net["no_network"] + ": use local-poe or hybrid"))
    for w in warnings:
        ctx.say(f"warning [{w['code']}]: {w['message']}")
    return _result(ctx, dataclasses.replace(outcome, robot=robot), before.robot, table.stage1, warnings, info_cv,
                   metrics)  # fmt: skip


def _candidate_names(method: str, stage2: tuple[str, ...]) -> tuple[str, ...]:
    """The candidates a method compares, simplest first (labcal.calibration.candidates.TABLE)."""
    if method == "local-poe":
        return ("nominal", "local-poe")
    if method == "ann":
        return ("nominal", "ann")
    learned = tuple(m.name for m in TABLE if m.hybrid and m.learned in stage2)
    return ("nominal", "local-poe", *learned, *(("ann",) if method == "auto" else ()))


def _candidates(ctx: FitContext, before: Stage[RegisterInfo]) -> Candidates:
    """Local POE and the joint series on all fitting rows, then every candidate cross-validated."""
    fit_obs, method = ctx.fit_obs, ctx.method
    stage1 = None
    if method != "ann":
        ctx.say("fitting local-poe on every fitting row")
        lp_opts = {**ctx.local_poe_options, **(ctx.options if method == "local-poe" else {})}
        stage1 = Stage(*ctx.timed("local-poe", lambda: fit_local_poe(fit_obs, ctx.nominal, **lp_opts)))
    names = _candidate_names(method, ctx.stage2)
    series = None
    if "hybrid+series" in names and stage1 is not None:
        series = ctx.timed("series", lambda: prefit_series(ctx, stage1.robot))
        if series is None:
            names = tuple(c for c in names if c != "hybrid+series")
    folds, scheme = fold_plan(fit_obs, ctx.seed)
    cv = None
    if folds:
        ctx.say(f"cross-validation: {len(folds)} folds ({scheme}) over {fit_obs.k} rows")
        local = method == "local-poe"
        cv = ctx.timed("cross-validation", lambda: cross_validate(
            fit_obs, ctx.nominal, names, folds, scheme, seed=ctx.seed,
            start=None if stage1 is None else stage1.robot,
            local_poe_options={**ctx.local_poe_options, **ctx.options} if local else ctx.local_poe_options,
            series_options=ctx.series_options, register_tool=ctx.register_tool, series_fixed=series_fixed(series),
            ann_options={} if local else dict(ctx.options), progress=ctx.say,
        ))  # fmt: skip
    else:
        ctx.notes.append(
            f"no cross-validation: {fit_obs.k} fitting rows hold fewer than 3 distinct poses (or groups); "
            "nothing was held out, so no error below is an honest estimate"
        )
    return Candidates(names=names, before=before, stage1=stage1, series=series, cv=cv)


def _run_method(ctx: FitContext, table: Candidates) -> Outcome[MethodInfo]:
    """The asked method's model on all fitting rows (auto and hybrid: the candidate cross-validation chose)."""
    if ctx.method == "local-poe":
        assert table.stage1 is not None
        return Outcome(table.stage1.robot, table.stage1.info, "local-poe", "local-poe")
    if ctx.method == "ann":
        robot, info = ctx.timed("ann", lambda: _fit_ann_or_nominal(ctx, table.before.robot))
        return Outcome(robot, info, "ann", "ann", network=info)
    if ctx.method == "hybrid":
        outcome = ctx.timed("hybrid", lambda: finish_hybrid(ctx, table))
        ctx.notes.extend(outcome.info["notes"])
        return outcome
    return _auto(ctx, table)


def _result(
    ctx: FitContext,
    outcome: Outcome[MethodInfo],
    before: CalibratedRobot,
    stage1: Stage[LocalPOEInfo] | None,
    warnings: list[FitWarning],
    cv: CVRecord | None,
    metrics: dict[str, SplitEntry] | None = None,
) -> FitResult:
    """The FitResult, with the notes on what the targets cannot show and on the measurement tool."""
    obs, robot, notes = ctx.obs, outcome.robot, ctx.notes
    unseen = ", ".join(f"t{i + 1}" for i in np.flatnonzero(~ctx.fit_obs.seen.any(axis=0)))  # fit_obs has rows
    if unseen:
        notes.append(f"targets never seen in the fitting rows: {unseen} (they add nothing to this fit)")
    # The identification's own words when it ran (they include a point beside the last joint's axis), else the
    # target geometry's.
    words = stage1.info.get("unobservable") if stage1 is not None else None
    claims = observability(obs, words)
    notes.extend(f"unobservable: {text}" for text in claims["unobservable"])
    if robot.measurement_tool is not None:  # robot and tool apart: the fixture is reported, not corrected
        notes.append(" ".join(line.strip() for line in tool_lines(robot.measurement_tool, robot.measurement_tool_std)))
    return FitResult(
        method=ctx.method,
        chosen=outcome.chosen,
        robot=robot,
        before=before,
        metrics=split_table(before, robot, obs) if metrics is None else metrics,
        info=outcome.info,
        seed=ctx.seed,
        n_train=int(np.sum(obs.split == "train")),
        n_val=int(np.sum(obs.split == "val")),
        n_test=int(np.sum(obs.split == "test")),
        fit_seconds=ctx.seconds,
        obs=obs,
        warnings=warnings,
        notes=notes,
        cv=cv,
        observability=claims,
    )


def _fit_ann_or_nominal(ctx: FitContext, before: CalibratedRobot) -> tuple[CalibratedRobot, ANNInfo | NoNetworkInfo]:
    """The paper's network on the registered nominal; where too few rows can train it (a singular wrist in most
    poses …), the registered nominal itself, with the reason in ``info["no_network"]`` (a blocking warning): the
    method runs on any data, and what it could not learn is said, not exported by accident."""
    from labcal.calibration.ann import fit_ann  # torch only when a network is fitted

    try:
        robot, info = fit_ann(ctx.fit_obs, before, seed=ctx.seed, **ctx.options)
    except ObservationError as err:  # NetworkDataError: too few usable rows, the message names the cause
        reason = f"the paper's network could not be trained: {err}; this fit is the registered nominal (no correction)"
        return dataclasses.replace(before, method="ann"), {"method": "ann", "no_network": reason}
    return robot, info


def _auto_choice(ctx: FitContext, table: Candidates, pick: list[str]) -> str:
    """The candidate auto refits: cross-validation's choice, local POE when it cannot choose (noted)."""
    cv, notes = table.cv, ctx.notes
    if cv is None or not cv.available("local-poe"):
        why = "too few distinct poses" if cv is None else "too few poses in a fold to identify local POE"
        notes.append(f"auto fell back to local-poe: {why} to cross-validate the learned stages")
        return "local-poe"
    choice = choose(cv, tuple(pick))
    skipped = [c for c in pick if not cv.available(c)]
    for c in skipped:
        notes.append(f"stage-skipped: {c}: {cv.failures.get(c, 'not evaluated')}")
    if choice == "local-poe" and skipped and all(cv.available(c) is False for c in pick if c != "local-poe"):
        notes.append("auto fell back to local-poe: no learned stage could be fitted (see the notes above)")
    return choice


def _auto(ctx: FitContext, table: Candidates) -> Outcome[AutoInfo]:
    """auto: choose among every candidate by cross-validation and refit the chosen one on all rows."""
    assert table.stage1 is not None
    stage1 = table.stage1
    pick = [c for c in table.names if c != "nominal"]
    choice = _auto_choice(ctx, table, pick)
    errors = {name: table.cv_error(name) for name in pick}
    candidates_info = {
        "local-poe": errors.get("local-poe", float("nan")),
        "hybrid": min((errors[c] for c in pick if BY_NAME[c].hybrid and math.isfinite(errors[c])),
                      default=float("nan")),
    }  # fmt: skip
    if "ann" in pick:
        candidates_info["ann"] = errors["ann"]
    info: AutoInfo = {"candidates": candidates_info, "cv_errors": errors, "local-poe": stage1.info}
    outcome = Outcome(stage1.robot, info, "local-poe", "local-poe")
    if choice == "ann":
        robot, ann_info = ctx.timed("ann", lambda: _fit_ann_or_nominal(ctx, table.before.robot))
        info["ann"] = ann_info
        if "no_network" in ann_info:  # it cross-validated, yet the refit on all rows found too few usable rows
            ctx.notes.append(f"auto fell back to local-poe: {ann_info.pop('no_network')}")
        else:
            outcome = Outcome(robot, info, "ann", "ann", network=ann_info)
    elif choice != "local-poe":
        hybrid = ctx.timed("hybrid", lambda: finish_hybrid(ctx, table, choice=choice))
        info["hybrid"] = hybrid.info
        if hybrid.candidate != "local-poe":
            outcome = Outcome(hybrid.robot, info, "hybrid", hybrid.candidate, network=hybrid.network)
    if "hybrid" not in info:
        info["hybrid"] = {"kept": BY_NAME[choice].kept if BY_NAME[choice].hybrid else "local-poe"}
    ctx.say("auto: cross-validated mean point error " + ", ".join(f"{m} {e * 1e3:.4f} mm" for m, e in errors.items()))
    ctx.say(f"auto: chose {outcome.chosen}")
    return outcome


def _warn(code: str, message: str) -> FitWarning:
    return {"code": code, "message": message}


def _checks(
    ctx: FitContext,
    table: Candidates,
    outcome: Outcome[MethodInfo],
    robot: CalibratedRobot,
    metrics: dict[str, SplitEntry],
) -> list[FitWarning]:
    """The blocking findings of a fit (module docstring); appends non-blocking ones to ``ctx.notes``."""
    fit_obs, notes, key = ctx.fit_obs, ctx.notes, outcome.candidate
    warnings: list[FitWarning] = []
    distinct = len(np.unique(fit_obs.q, axis=0))
    few = _few_poses(distinct, fit_obs.n)
    if few:
        warnings.append(few)
    lp = table.stage1.info if table.stage1 is not None and key != "ann" else None
    if lp is not None:
        _identification_checks(lp, distinct, warnings, notes)
    in_sample = float(np.mean(row_errors(robot, fit_obs)))
    if table.cv is not None:
        _cv_checks(table.cv, key, in_sample, warnings, notes)
    _holdout_checks(metrics, warnings)
    net = outcome.network
    if net is not None and "loss_note" in net:  # a trained network, not "ann"'s record of none
        if net["loss_note"]:
            notes.append(f"network: {net['loss_note']}")
        warnings.extend(_warn("overfit", text) for text in net["warnings"] if "over-fitting" in text)
    for code, message in (
        ("poor-fit", _poor_fit(in_sample)),
        ("point-residuals", point_residual_warning(metrics.get("all"))),
        ("large-correction", _large_correction(robot, fit_obs.q, ctx.seed, lp)),
        ("narrow-joint", _narrow_joints(robot, fit_obs.q)),
        ("frame-jump", _frame_jump(robot, ctx.obs)),
    ):
        if isinstance(message, dict):  # point_residual_warning returns the finished warning
            warnings.append(message)
        elif message:
            warnings.append(_warn(code, message))
    _dropped(table, fit_obs, net, warnings, notes)
    return warnings


def _few_poses(distinct: int, n: int) -> FitWarning | None:
    """few-poses: fewer than MIN_POSES_PER_JOINT distinct poses per joint."""
    if distinct < MIN_POSES_PER_JOINT * n:
        return _warn(
            "few-poses",
            f"only {distinct} distinct pose(s) for a robot with {n} joints (fewer than "
            f"{MIN_POSES_PER_JOINT} per joint, the least the import checks accept): whatever the errors say, so few "
            f"poses pin down little of the robot; measure at least {MIN_POSES_PER_JOINT * n} spread poses",
        )
    return None


def _identification_checks(lp: LocalPOEInfo, distinct: int, warnings: list[FitWarning], notes: list[str]) -> None:
    """rank-deficient (a warning) and weak (a note) from local POE's info."""
    if lp["rank"] < lp["expected_rank"]:
        lines = lp["null_directions"]
        shown = "; ".join(lines[:8]) + (f"; … ({len(lines) - 8} more)" if len(lines) > 8 else "")
        warnings.append(_warn(
            "rank-deficient",
            f"local POE identified numerical rank {lp['rank']} of {lp['expected_rank']} identifiable parameters "
            f"from {lp['rows']} rows ({distinct} distinct poses): "
            f"{lp['expected_rank'] - lp['rank']} identifiable direction(s) are not excited by the data and "
            f"were left at the nominal. Unidentifiable parameter combinations (largest components): {shown}. "
            "Measure more, better spread configurations (every joint moved, not only single-joint sweeps)",
        ))  # fmt: skip
    if lp["weak"]:
        lines = lp["weak_directions"]
        notes.append(
            f"weak: {lp['weak']} of {lp['rank']} identifiable direction(s) are held at the nominal — the data "
            f"determine them worse than ±{lp['error_bound'] * 1e3:g} mm at {lp['noise'] * 1e3:g} mm tracker "
            f"noise, so the calibration corrects nothing along them ({lp['identified']} identified): "
            + "; ".join(lines[:4])
            + (f"; … ({len(lines) - 4} more)" if len(lines) > 4 else "")
        )


def _cv_checks(cv: CVResult, key: str, in_sample: float, warnings: list[FitWarning], notes: list[str]) -> None:
    """worse-than-nominal (cross-validated), overfit (a warning) and overfit-risk (a note)."""
    if not cv.available(key):
        notes.append(f"no cross-validated error for {key}: {cv.failures.get(key, 'no fold could fit it')}")
    if key not in cv.rows:
        return
    e_cv = cv.mean(key)
    common = np.isfinite(cv.rows.get("nominal", np.nan)) & np.isfinite(cv.rows[key])
    if np.any(common):
        e_c, e_n = float(np.mean(cv.rows[key][common])), float(np.mean(cv.rows["nominal"][common]))
        if e_c >= e_n:
            warnings.append(_warn(
                "worse-than-nominal",
                f"the cross-validated mean target-point error of {key} is {e_c * 1e3:.4g} mm, not below "
                f"the registered nominal's {e_n * 1e3:.4g} mm: the calibration does not generalise "
                "(too few or too similar poses, or data that do not match the robot/targets)",
            ))  # fmt: skip
    text = f"{key} fits its own rows to {in_sample * 1e3:.4g} mm but cross-validates to {e_cv * 1e3:.4g} mm"
    # e_cv is NaN when every fold failed for the chosen model (its notes say why): nothing to compare
    if math.isfinite(e_cv) and e_cv - in_sample > 1e-5:
        if e_cv > OVERFIT_RATIO * in_sample:
            warnings.append(_warn("overfit", f"{text} (over {OVERFIT_RATIO:g}×): it interpolates too few poses"))
        elif e_cv > OVERFIT_NOTE_RATIO * in_sample:
            notes.append(f"overfit-risk: {text}; trust the cross-validated error, not the fit error")


def _holdout_checks(metrics: dict[str, SplitEntry], warnings: list[FitWarning]) -> None:
    """worse-than-nominal on the held-out "val" / "test" rows (once: not after the cross-validated one)."""
    for part in ("val", "test"):
        if part in metrics and not any(w["code"] == "worse-than-nominal" for w in warnings):
            entry = metrics[part]
            if entry.get("primary", "pose") == "pose":
                what, after, bef = "position", entry["after"]["pos_mean"], entry["before"]["pos_mean"]
            else:
                what, after, bef = "target-point", entry["points"]["after"]["mean"], entry["points"]["before"]["mean"]
            if after >= bef:
                warnings.append(_warn(
                    "worse-than-nominal",
                    f"on the held-out {part!r} rows the mean {what} error is {after * 1e3:.4g} mm after "
                    f"calibration against {bef * 1e3:.4g} mm for the registered nominal",
                ))  # fmt: skip


def _poor_fit(in_sample: float) -> str | None:
    """poor-fit: the model leaves a mean target-point error above POOR_FIT on its own fitting rows."""
    if in_sample > POOR_FIT:
        return (
            f"the calibrated model leaves a mean target-point error of {in_sample * 1e3:.4g} mm on the very rows it "
            f"was fitted to (above {POOR_FIT * 1e3:g} mm): no robot calibration explains these data — check the "
            "length and angle units, the targets file (order of t1, t2, t3) and the frame (base/tracker)"
        )
    return None


def _narrow_joints(robot, q: np.ndarray) -> str | None:
    """A message naming the joints the data moved less than NARROW_JOINT while the calibration claims a wider range
    (robot.joint_ranges: the robot's limits for a geometric model), else None. Such a joint's axis is fitted on a
    sliver of its travel, and the correction it extrapolates across the range can make the robot worse than none,
    while the cross-validation, whose folds hold the same sliver, cannot see it."""
    if robot.network is None and robot.model is robot.nominal:
        return None  # no correction to extrapolate
    span = q.max(axis=0) - q.min(axis=0)
    claimed = np.asarray(robot.joint_ranges, dtype=float)
    if robot.validity is not None:  # correct() refuses configurations outside the region: that is what it claims
        reach = robot.validity.reach()
        claimed = np.stack([np.maximum(claimed[:, 0], reach[:, 0]), np.minimum(claimed[:, 1], reach[:, 1])], axis=1)
    names = []
    for j, kind in enumerate(robot.model.joint_types):
        least = NARROW_JOINT.get(kind, NARROW_JOINT["revolute"])
        if span[j] < least and claimed[j, 1] - claimed[j, 0] > span[j] + least:
            unit, factor = ("°", 180 / np.pi) if kind != "prismatic" else (" mm", 1e3)
            names.append(
                f"joint {j + 1} moved over {span[j] * factor:.3g}{unit} where the calibration claims "
                f"[{claimed[j, 0] * factor:.4g}, {claimed[j, 1] * factor:.4g}]{unit}"
            )
    if not names:
        return None
    return (
        "; ".join(names) + ": a joint's axis fitted on a sliver of its travel is extrapolated over the rest, where "
        "the correction can make the robot worse. Measure with every joint moved over its working range"
    )


def _frame_jump(robot, obs) -> str | None:
    """A message when the fitted model's point residuals step, in recorded order, between two blocks of rows of one
    session by more than FRAME_JUMP and 4× their spread within the blocks, else None.

    A tracker bumped or re-registered (or a part re-clamped) half-way through a session moves every later point by
    the same offset, which no robot calibration explains: the fit spreads it over its parameters, cross-validates
    better than the nominal, and makes the robot worse. Robot errors depend on the configuration, not on when it
    was measured, so in a session of spread poses they leave no such step.
    """
    if obs.k < 2 * FRAME_JUMP_BLOCK:
        return None
    seen = obs.seen[:, :, None]  # every row saw a target (Observations refuses rows that saw none)
    residual = np.sum(np.where(seen, point_residuals(robot, obs), 0.0), axis=1) / seen.sum(axis=1)  # (k, 3)
    groups = np.zeros(obs.k, dtype=int) if obs.group is None else np.unique(obs.group, return_inverse=True)[1]
    worst = None
    for g in np.unique(groups):
        rows = np.flatnonzero(groups == g)
        k = len(rows)
        if k < 2 * FRAME_JUMP_BLOCK:
            continue
        r = residual[rows]
        total = np.cumsum(r, axis=0)
        split = np.arange(FRAME_JUMP_BLOCK, k - FRAME_JUMP_BLOCK + 1)  # the later block starts at row `split`
        before = total[split - 1] / split[:, None]
        after = (total[-1] - total[split - 1]) / (k - split)[:, None]
        step = np.linalg.norm(before - after, axis=1)
        best = int(np.argmax(step * np.sqrt(split * (k - split) / k)))  # the best-supported step, not an end effect
        at, size = int(split[best]), float(step[best])
        spread = float(np.sqrt(np.mean(np.concatenate([r[:at] - before[best], r[at:] - after[best]]) ** 2) * 3))
        if size > FRAME_JUMP and size > 4 * spread and (worst is None or size > worst[1]):
            where = f"row {at + 1}" + ("" if obs.group is None else f" of {obs.group[rows[at]]}")
            worst = (where, size, spread)
    if worst is None:
        return None
    where, size, spread = worst
    return (
        f"the calibrated model's point residuals step by {size * 1e3:.3g} mm from {where} on (spread within "
        f"the two blocks {spread * 1e3:.2g} mm): the tracker, or what it measures, moved during the session. No "
        "robot calibration explains that, and a fit across it makes the robot worse: fit the rows before and after "
        "the step as separate sessions, or re-measure"
    )


def _large_correction(robot, q_data: np.ndarray, seed: int, lp: LocalPOEInfo | None = None) -> str | None:
    """A message when robot.correct makes large corrections (module docstring: MAX_CORRECTION), else None.

    A correction is large when it moves a joint beyond MAX_CORRECTION *and* moves the nominal tool beyond
    MAX_TOOL_CORRECTION: near a singular wrist a milliradian of orientation error needs tenths of a radian at
    joints 4 and 6 while the tool barely moves, which is the geometry, not a bad fit; a unit slip or a wrong model
    moves both, nearly everywhere. The configurations checked are the data's own and random ones in the
    compensator's validity region (:mod:`labcal.compensator.validity`; the data's joint box without one). The
    message names the cause the evidence shows (:func:`_correction_cause`).
    """
    if robot.network is None and robot.model is robot.nominal:
        return None
    rng = np.random.default_rng([seed, 49979687])
    if robot.validity is not None:
        extra = robot.validity.sample(_CORRECTION_SAMPLES, rng)
    else:
        lo, hi = q_data.min(axis=0), q_data.max(axis=0)
        extra = rng.uniform(lo, hi, size=(_CORRECTION_SAMPLES, q_data.shape[1]))
    q = np.concatenate([q_data, extra])
    with np.errstate(all="ignore"):
        # An offline check, not a control loop: a damped row may travel as far as 30 clipped steps take it, so a
        # slipped joint shows as the largest correction even where its rows leave Gauss-Newton's range.
        q_cmd = robot.correct(q, extrapolate=True, damped_iterations=30)
        dq = np.abs(q_cmd - q)
        moved, turned = se3.pose_distance(robot.nominal.fk(q), robot.nominal.fk(np.nan_to_num(q_cmd)))
    bound = np.array([MAX_CORRECTION.get(t, MAX_CORRECTION["revolute"]) for t in robot.model.joint_types])
    over = np.nan_to_num(dq, nan=np.inf) / bound
    tool = (moved > MAX_TOOL_CORRECTION[0]) | (turned > MAX_TOOL_CORRECTION[1]) | ~np.isfinite(moved)
    large = np.any(over > 1.0, axis=1) & tool
    share = float(np.mean(large))
    if share < _CORRECTION_SHARE:
        return None
    # Name the joint the large corrections typically move most (a slipped joint moves in nearly all of them), not
    # the single largest entry, which a near-singular configuration's wrist can supply; then its worst case.
    j = int(np.argmax(np.median(np.nan_to_num(over[large], posinf=1e300), axis=0)))
    i = int(np.argmax(np.where(large, np.nan_to_num(over[:, j], posinf=1e300), -1.0)))
    unit, factor = ("rad", 1.0) if robot.model.joint_types[j] != "prismatic" else ("mm", 1e3)
    where = "in the data's validity region" if robot.validity is not None else "within the data's joint ranges"
    at_data = float(np.mean(large[: len(q_data)]))
    return (
        f"the compensator would move joint {j + 1} by {dq[i, j] * factor:.3g} {unit} and the tool by "
        f"{moved[i] * 1e3:.3g} mm / {np.degrees(turned[i]):.2g}° (bounds {bound[j] * factor:g} {unit}, "
        f"{MAX_TOOL_CORRECTION[0] * 1e3:g} mm / {np.degrees(MAX_TOOL_CORRECTION[1]):.2g}°; {share:.0%} of "
        f"{q.shape[0]} checked configurations {where} exceed both, {at_data:.0%} of the data's own): "
        "real calibration corrections are milliradians and millimetres — " + _correction_cause(robot, at_data, lp)
    )


TOOL_MISMATCH = 5e-3  # m: an identified tool frame this far from the robot file's is a different tool, not an error
WEAK_NOTE = 1e-3  # m: the noise's share of the least-determined identified direction that makes it the suspect


def _correction_cause(robot, at_data: float, lp: LocalPOEInfo | None) -> str:
    """The cause of large corrections the evidence shows, in words, in this order: a tool mismatch (the identified
    tool frame is far from the robot file's, and the data determine that offset: over 3 standard deviations); a
    weakly determined direction (the least-determined identified direction moves by more than WEAK_NOTE on the
    noise alone — a tool offset the data do not determine is one; its corrections are large at the data too, since
    the compensator corrects the pose the points cannot see); a unit slip or wrong model (large corrections at the
    measured configurations themselves, from well-determined parameters); else configurations outside the data."""
    delta = se3.log_se3(se3.inv(robot.nominal.frames[-1]) @ robot.model.frames[-1])
    offset, angle = float(np.linalg.norm(delta[:3])), float(np.linalg.norm(delta[3:]))
    std = None if lp is None else lp["std"][-1]
    determined = (
        std is None
        or not np.isfinite(std).all()
        or (offset > 3 * float(np.linalg.norm(std[:3])) or angle > 3 * float(np.linalg.norm(std[3:])))
    )
    if (offset > TOOL_MISMATCH or angle > MAX_TOOL_CORRECTION[1]) and determined:
        p = robot.model.frames[-1][:3, 3] * 1e3
        p0 = robot.nominal.frames[-1][:3, 3] * 1e3
        return (
            f"a tool mismatch: the identified tool frame sits at ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm from the "
            f"last joint's frame, {offset * 1e3:.3g} mm / {np.degrees(angle):.2g}° from the robot file's "
            f"({p0[0]:.1f}, {p0[1]:.1f}, {p0[2]:.1f}) mm, and the compensator moves the joints to bring the "
            "measurement fixture onto the nominal tool: give the fixture's tool in the robot file"
        )
    if lp is not None:  # local POE's info (typed: every key below is always there)
        s = lp["singular_values"]
        kept = s[s > max(lp["weak_threshold"], 1e-6 * float(s.max()))]
        noise = lp["noise"]
        if kept.size and noise / float(kept.min()) > WEAK_NOTE:
            tool = (
                f" (the identified tool is {offset * 1e3:.3g} mm from the robot file's, ±"
                f"{float(np.linalg.norm(std[:3])) * 1e3:.2g} mm)"
                if std is not None and offset > TOOL_MISMATCH
                else ""
            )
            return (
                f"a weakly determined direction{tool}: the least-determined identified direction moves by "
                f"±{noise / float(kept.min()) * 1e3:.2g} mm on the tracker noise alone, and the compensator corrects "
                "the pose along it though the points barely see it; measure more spread poses (other orientations), "
                "or fit with the default error_bound so it stays at the nominal"
            )
    if at_data >= _CORRECTION_SHARE:
        return (
            "the corrections are large at the measured configurations themselves: a unit slip (degrees as radians, "
            "mm as m) or a wrong robot model is likely"
        )
    return (
        "configurations outside the data: the corrections are small at the measured configurations and large "
        "only away from them; measure poses where the robot will work"
    )


def _dropped(
    table: Candidates,
    fit_obs: Observations,
    net: ANNInfo | NoNetworkInfo | None,
    warnings: list[FitWarning],
    notes: list[str],
) -> None:
    """rows-dropped: a warning when a kept network misses > DROPPED_SHARE of the rows, else a note."""
    cv = table.cv
    if net is not None and "dropped_causes" in net:
        count, causes = int(net["observations"]["dropped"]), net["dropped_causes"]
    elif cv is not None and any(c in cv.rows for c in NETWORKS):
        from labcal.calibration.equivalent import joint_error_observations

        base = table.stage1.robot if table.stage1 is not None and "hybrid+ann" in cv.rows else table.before.robot
        jeo = joint_error_observations(fit_obs, base)
        count = int(np.sum(~jeo.kept))
        causes = jeo.causes(base) if count else []
    else:
        return
    if count == 0:
        return
    why = "; ".join(f"{c['cause']}: {c['rows']} rows" for c in causes)
    text = f"{count} of {fit_obs.k} rows dropped from the network's observations by the condition filter ({why})"
    if net is not None and count > DROPPED_SHARE * fit_obs.k:
        warnings.append(_warn("rows-dropped", text + "; the kept network never saw them"))
    else:
        notes.append("rows-dropped: " + text + ("" if net is not None else "; no network was kept"))
