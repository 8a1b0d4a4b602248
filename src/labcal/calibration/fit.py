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
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from labcal.calibration.local_poe import fit_local_poe, register
from labcal.calibration.metrics import observability, point_residual_warning, split_table
from labcal.calibration.observations import ObservationError, Observations
from labcal.calibration.tool import tool_lines
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.kinematics.poe import LocalPOEModel

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
    metrics: dict
    info: dict
    seed: int
    n_train: int
    n_val: int
    n_test: int
    fit_seconds: dict = field(default_factory=dict)
    obs: Observations | None = None
    warnings: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    cv: dict | None = None
    observability: dict = field(default_factory=dict)


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
    **options,
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
    # One BLAS thread: the fits multiply many small and medium matrices, where OpenBLAS's threads were measured
    # 3-20x slower on a loaded 2-core machine (local POE at 1,000 rows: 4.0 s threaded, 1.1 s single), and one
    # thread keeps the summation order, so the bits of a fit, independent of the core count.
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit(obs, nominal, method, seed, val_fraction, progress, local_poe_options, options, register_tool)


def _fit(
    obs, nominal, method, seed, val_fraction, progress, local_poe_options, options, register_tool=False
) -> FitResult:
    from labcal.calibration.cv import cross_validate, fold_plan

    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    obs.check_robot(nominal.n)
    say = progress or (lambda _msg: None)
    obs = obs.with_splits(val_fraction, seed)
    counts = {s: int(np.sum(obs.split == s)) for s in ("train", "val", "test")}
    if counts["train"] == 0:
        raise ValueError("no fitting rows: every row is labelled val or test")
    lp_opts = dict(local_poe_options or {})
    hybrid_opts = {key: options.pop(key) for key in ("stage2", "series_options") if key in options}
    stage2 = tuple(hybrid_opts.get("stage2", ("ann", "series")))
    if not stage2 or any(name not in ("ann", "series") for name in stage2):
        raise ValueError(f"stage2 must name 'ann' and/or 'series', got {stage2!r}")
    series_opts = hybrid_opts.get("series_options")
    fit_obs = obs.where("train")
    seconds: dict[str, float] = {}
    notes: list[str] = []

    def timed(name, fn):
        t = time.perf_counter()
        out = fn()
        seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t
        return out

    say("registering the nominal model")
    before, reg_info = timed("nominal", lambda: register(obs, nominal, estimate_tool=register_tool))
    if method == "nominal":
        return _result(
            method, "nominal", before, before, {"register": reg_info}, obs, counts, seed, seconds, [], [], None
        )

    stage1 = None
    if method != "ann":
        say("fitting local-poe on every fitting row")
        stage1 = timed("local-poe", lambda: fit_local_poe(fit_obs, nominal, **{**lp_opts, **(
            options if method == "local-poe" else {})}))  # fmt: skip
    if method == "local-poe":
        candidates: tuple[str, ...] = ("nominal", "local-poe")
    elif method == "ann":
        candidates = ("nominal", "ann")
    else:
        learned = tuple(c for c, s in (("hybrid+series", "series"), ("hybrid+ann", "ann")) if s in stage2)
        candidates = ("nominal", "local-poe", *learned)
        if method == "auto":
            candidates = (*candidates, "ann")
    folds, scheme = fold_plan(fit_obs, seed)
    series_full = None
    if "hybrid+series" in candidates:
        from labcal.calibration.hybrid import prefit_series

        series_full, skipped = timed(
            "series", lambda: prefit_series(fit_obs, stage1[0], candidates, seed, series_opts, say)
        )
        notes += skipped
        if series_full is None:
            candidates = tuple(c for c in candidates if c != "hybrid+series")
    cv = None
    if folds:
        from labcal.calibration.hybrid import series_fixed

        say(f"cross-validation: {len(folds)} folds ({scheme}) over {fit_obs.k} rows")
        ann_opts = {k: v for k, v in options.items()} if method != "local-poe" else {}
        cv = timed(
            "cross-validation",
            lambda: cross_validate(
                fit_obs,
                nominal,
                candidates,
                folds,
                scheme,
                seed=seed,
                start=None if stage1 is None else stage1[0],
                local_poe_options=lp_opts if method != "local-poe" else {**lp_opts, **options},
                series_options=series_opts,
                register_tool=register_tool,
                series_fixed=series_fixed(series_full),
                ann_options=ann_opts,
                progress=say,
            ),
        )
    else:
        notes.append(
            f"no cross-validation: {fit_obs.k} fitting rows hold fewer than 3 distinct poses (or groups); "
            "nothing was held out, so no error below is an honest estimate"
        )

    info: dict
    if method == "local-poe":
        robot, info, chosen = stage1[0], stage1[1], "local-poe"
    elif method == "ann":
        robot, info = timed("ann", lambda: _fit_ann_or_nominal(fit_obs, before, seed, options))
        chosen = "ann"
    else:
        from labcal.calibration.hybrid import STAGE2, finish_hybrid

        hybrid_cands = tuple(c for c in candidates if c in ("local-poe", *STAGE2.values()))
        if method == "hybrid":
            robot, info = timed("hybrid", lambda: finish_hybrid(
                fit_obs, obs, stage1, cv, hybrid_cands, seed=seed, series_full=series_full, ann_options=options,
                say=say))  # fmt: skip
            chosen = "hybrid"
            notes += info["notes"]
        else:
            robot, info, chosen = _auto(
                fit_obs,
                obs,
                nominal,
                before,
                stage1,
                cv,
                candidates,
                hybrid_cands,
                seed,
                series_full,
                options,
                say,
                notes,
                timed,
            )
    if cv is not None:
        chosen_key = _cv_key(chosen, info)
        info_cv = cv.summary(chosen_key)
    else:
        chosen_key, info_cv = chosen, None
    robot = _with_validity(robot, fit_obs.q)
    metrics = split_table(before, robot, obs)
    warnings = _checks(robot, before, fit_obs, obs, stage1, cv, chosen_key, info, metrics, seed, notes)
    if "no_network" in info:
        warnings.insert(0, {"code": "no-network", "message": info["no_network"] + ": use local-poe or hybrid"})
    for w in warnings:
        say(f"warning [{w['code']}]: {w['message']}")
    return _result(method, chosen, robot, before, info, obs, counts, seed, seconds, warnings, notes, info_cv, metrics)


def _result(method, chosen, robot, before, info, obs, counts, seed, seconds, warnings, notes, cv, metrics=None):
    seen = obs.seen[obs.split == "train"]
    unseen = ", ".join(f"t{i + 1}" for i in np.flatnonzero(~seen.any(axis=0))) if seen.size else ""
    if unseen:
        notes.append(f"targets never seen in the fitting rows: {unseen} (they add nothing to this fit)")
    # The identification's own words when it ran (they include a point beside the last joint's axis), else the
    # target geometry's.
    lp = next((d for d in (info, info.get("local-poe"), info.get("local_poe")) if isinstance(d, dict) and
               "unobservable" in d), None)  # fmt: skip
    claims = observability(obs, None if lp is None else lp["unobservable"])
    notes.extend(f"unobservable: {text}" for text in claims["unobservable"])
    if robot.measurement_tool is not None:  # robot and tool apart: the fixture is reported, not corrected
        notes.append(" ".join(line.strip() for line in tool_lines(robot.measurement_tool, robot.measurement_tool_std)))
    return FitResult(
        method=method,
        chosen=chosen,
        robot=robot,
        before=before,
        metrics=split_table(before, robot, obs) if metrics is None else metrics,
        info=info,
        seed=seed,
        n_train=counts["train"],
        n_val=counts["val"],
        n_test=counts["test"],
        fit_seconds=seconds,
        obs=obs,
        warnings=warnings,
        notes=notes,
        cv=cv,
        observability=claims,
    )


def _cv_key(chosen: str, info: dict) -> str:
    """The cross-validation candidate that the returned model is."""
    if chosen == "hybrid":
        kept = info.get("kept") or info.get("hybrid", {}).get("kept", "local-poe")
        return "local-poe" if kept == "local-poe" else "hybrid+" + kept.split("+")[1]
    return chosen


def _fit_ann_or_nominal(fit_obs, before, seed, options):
    """The paper's network on the registered nominal; where too few rows can train it (a singular wrist in most
    poses …), the registered nominal itself, with the reason in ``info["no_network"]`` (a blocking warning): the
    method runs on any data, and what it could not learn is said, not exported by accident."""
    from labcal.calibration.ann import fit_ann

    try:
        robot, info = fit_ann(fit_obs, before, seed=seed, **options)
    except ObservationError as err:  # NetworkDataError: too few usable rows, the message names the cause
        reason = f"the paper's network could not be trained: {err}; this fit is the registered nominal (no correction)"
        return dataclasses.replace(before, method="ann"), {"method": "ann", "no_network": reason}
    return dataclasses.replace(robot, joint_ranges=_data_ranges(fit_obs.q)), info


def _with_validity(robot: CalibratedRobot, q: np.ndarray) -> CalibratedRobot:
    """The robot with its validity region: the neighbourhood of the fitted configurations (scaled joint space)."""
    from labcal.compensator.validity import ValidityRegion

    return dataclasses.replace(robot, validity=ValidityRegion.from_configurations(q))


def _data_ranges(q: np.ndarray) -> np.ndarray:
    return np.stack([q.min(axis=0), q.max(axis=0)], axis=1)


def _auto(fit_obs, obs, nominal, before, stage1, cv, candidates, hybrid_cands, seed, series_full, options, say,
          notes, timed):  # fmt: skip
    """auto: choose among every candidate by cross-validation and refit the chosen one on all rows."""
    from labcal.calibration.cv import choose
    from labcal.calibration.hybrid import finish_hybrid

    pick = [c for c in candidates if c != "nominal"]
    if cv is None or not cv.available("local-poe"):
        choice = "local-poe"
        why = "too few distinct poses" if cv is None else "too few poses in a fold to identify local POE"
        notes.append(f"auto fell back to local-poe: {why} to cross-validate the learned stages")
    else:
        choice = choose(cv, tuple(pick))
        skipped = [c for c in pick if not cv.available(c)]
        for c in skipped:
            notes.append(f"stage-skipped: {c}: {cv.failures.get(c, 'not evaluated')}")
        if choice == "local-poe" and skipped and all(cv.available(c) is False for c in pick if c != "local-poe"):
            notes.append("auto fell back to local-poe: no learned stage could be fitted (see the notes above)")
    errors = {name: (cv.mean(name) if cv is not None and name in cv.rows else float("nan")) for name in pick}
    candidates_info = {
        "local-poe": errors.get("local-poe", float("nan")),
        "hybrid": min((errors[c] for c in pick if c.startswith("hybrid+") and math.isfinite(errors[c])),
                      default=float("nan")),
    }  # fmt: skip
    if "ann" in pick:
        candidates_info["ann"] = errors["ann"]
    info = {"candidates": candidates_info, "cv_errors": errors, "local-poe": stage1[1]}
    if choice == "ann":
        robot, ann_info = timed("ann", lambda: _fit_ann_or_nominal(fit_obs, before, seed, options))
        info["ann"] = ann_info
        chosen = "ann"
        if "no_network" in ann_info:  # it cross-validated, yet the refit on all rows found too few usable rows
            notes.append(f"auto fell back to local-poe: {ann_info.pop('no_network')}")
            robot, chosen = stage1[0], "local-poe"
    elif choice == "local-poe":
        robot, chosen = stage1[0], "local-poe"
    else:
        robot, h_info = timed("hybrid", lambda: finish_hybrid(
            fit_obs, obs, stage1, cv, hybrid_cands, seed=seed, series_full=series_full, ann_options=options,
            say=say, choice=choice))  # fmt: skip
        info["hybrid"] = h_info
        chosen = "hybrid" if h_info["kept"] != "local-poe" else "local-poe"
        if chosen == "local-poe":
            robot = stage1[0]
    if "hybrid" not in info:
        info["hybrid"] = {"kept": choice.replace("hybrid+", "local-poe+") if "+" in choice else "local-poe"}
    say("auto: cross-validated mean point error " + ", ".join(f"{m} {e * 1e3:.4f} mm" for m, e in errors.items()))
    say(f"auto: chose {chosen}")
    return robot, info, chosen


def _warn(code: str, message: str) -> dict:
    return {"code": code, "message": message}


def _network_info(chosen_key: str, info: dict) -> dict | None:
    """The info dict of the network in the returned model, if it has one."""
    if chosen_key == "ann":
        return info.get("ann", info) if "ann" in info and isinstance(info["ann"], dict) else info
    if chosen_key == "hybrid+ann":
        return info.get("ann") or info.get("hybrid", {}).get("ann")
    return None


def _checks(robot, before, fit_obs, obs, stage1, cv, chosen_key, info, metrics, seed, notes) -> list[dict]:
    """The blocking findings of a fit (module docstring); appends non-blocking ones to ``notes``."""
    from labcal.calibration.cv import row_errors

    warnings: list[dict] = []
    distinct = len(np.unique(fit_obs.q, axis=0))
    if distinct < MIN_POSES_PER_JOINT * fit_obs.n:
        warnings.append(_warn(
            "few-poses",
            f"only {distinct} distinct pose(s) for a robot with {fit_obs.n} joints (fewer than "
            f"{MIN_POSES_PER_JOINT} per joint, the least the import checks accept): whatever the errors say, so few "
            f"poses pin down little of the robot; measure at least {MIN_POSES_PER_JOINT * fit_obs.n} spread poses",
        ))  # fmt: skip
    uses_stage1 = stage1 is not None and chosen_key != "ann"
    if uses_stage1:
        lp = stage1[1]
        if lp["rank"] < lp["expected_rank"]:
            lines = lp.get("null_directions", [])
            shown = "; ".join(lines[:8]) + (f"; … ({len(lines) - 8} more)" if len(lines) > 8 else "")
            warnings.append(_warn(
                "rank-deficient",
                f"local POE identified numerical rank {lp['rank']} of {lp['expected_rank']} identifiable parameters "
                f"from {lp['rows']} rows ({distinct} distinct poses): "
                f"{lp['expected_rank'] - lp['rank']} identifiable direction(s) are not excited by the data and "
                f"were left at the nominal. Unidentifiable parameter combinations (largest components): {shown}. "
                "Measure more, better spread configurations (every joint moved, not only single-joint sweeps)",
            ))  # fmt: skip
        if lp.get("weak"):
            lines = lp.get("weak_directions", [])
            notes.append(
                f"weak: {lp['weak']} of {lp['rank']} identifiable direction(s) are held at the nominal — the data "
                f"determine them worse than ±{lp['error_bound'] * 1e3:g} mm at {lp['noise'] * 1e3:g} mm tracker "
                f"noise, so the calibration corrects nothing along them ({lp['identified']} identified): "
                + "; ".join(lines[:4])
                + (f"; … ({len(lines) - 4} more)" if len(lines) > 4 else "")
            )
    in_sample = float(np.mean(row_errors(robot, fit_obs)))
    if cv is not None and not cv.available(chosen_key):
        notes.append(
            f"no cross-validated error for {chosen_key}: {cv.failures.get(chosen_key, 'no fold could fit it')}"
        )
    if cv is not None and chosen_key in cv.rows:
        e_cv = cv.mean(chosen_key)
        common = np.isfinite(cv.rows.get("nominal", np.nan)) & np.isfinite(cv.rows[chosen_key])
        if np.any(common):
            e_c, e_n = float(np.mean(cv.rows[chosen_key][common])), float(np.mean(cv.rows["nominal"][common]))
            if e_c >= e_n:
                warnings.append(_warn(
                    "worse-than-nominal",
                    f"the cross-validated mean target-point error of {chosen_key} is {e_c * 1e3:.4g} mm, not below "
                    f"the registered nominal's {e_n * 1e3:.4g} mm: the calibration does not generalise "
                    "(too few or too similar poses, or data that do not match the robot/targets)",
                ))  # fmt: skip
        text = f"{chosen_key} fits its own rows to {in_sample * 1e3:.4g} mm but cross-validates to {e_cv * 1e3:.4g} mm"
        if not math.isfinite(e_cv):
            pass  # every fold failed for the chosen model (its notes say why): nothing to compare
        elif e_cv > OVERFIT_RATIO * in_sample and e_cv - in_sample > 1e-5:
            warnings.append(_warn("overfit", f"{text} (over {OVERFIT_RATIO:g}×): it interpolates too few poses"))
        elif e_cv > OVERFIT_NOTE_RATIO * in_sample and e_cv - in_sample > 1e-5:
            notes.append(f"overfit-risk: {text}; trust the cross-validated error, not the fit error")
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
    net = _network_info(chosen_key, info)
    if net and net.get("loss_note"):
        notes.append(f"network: {net['loss_note']}")
    if net:
        for text in net.get("warnings", []):
            if "over-fitting" in text:
                warnings.append(_warn("overfit", text))
    if in_sample > POOR_FIT:
        warnings.append(_warn(
            "poor-fit",
            f"the calibrated model leaves a mean target-point error of {in_sample * 1e3:.4g} mm on the very rows it "
            f"was fitted to (above {POOR_FIT * 1e3:g} mm): no robot calibration explains these data — check the "
            "length and angle units, the targets file (order of t1, t2, t3) and the frame (base/tracker)",
        ))  # fmt: skip
    points = point_residual_warning(metrics.get("all"))
    if points:
        warnings.append(points)
    big = _large_correction(robot, fit_obs.q, seed, stage1[1] if uses_stage1 else None)
    if big:
        warnings.append(_warn("large-correction", big))
    narrow = _narrow_joints(robot, fit_obs.q)
    if narrow:
        warnings.append(_warn("narrow-joint", narrow))
    jump = _frame_jump(robot, obs)
    if jump:
        warnings.append(_warn("frame-jump", jump))
    _dropped(robot, before, fit_obs, stage1, cv, chosen_key, net, warnings, notes)
    return warnings


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
    from labcal.calibration.metrics import point_residuals

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


def _large_correction(robot, q_data: np.ndarray, seed: int, lp: dict | None = None) -> str | None:
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


def _correction_cause(robot, at_data: float, lp: dict | None) -> str:
    """The cause of large corrections the evidence shows, in words, in this order: a tool mismatch (the identified
    tool frame is far from the robot file's, and the data determine that offset: over 3 standard deviations); a
    weakly determined direction (the least-determined identified direction moves by more than WEAK_NOTE on the
    noise alone — a tool offset the data do not determine is one; its corrections are large at the data too, since
    the compensator corrects the pose the points cannot see); a unit slip or wrong model (large corrections at the
    measured configurations themselves, from well-determined parameters); else configurations outside the data."""
    delta = se3.log_se3(se3.inv(robot.nominal.frames[-1]) @ robot.model.frames[-1])
    offset, angle = float(np.linalg.norm(delta[:3])), float(np.linalg.norm(delta[3:]))
    std = None if lp is None or lp.get("std") is None else np.asarray(lp["std"], float)[-1]
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
    if lp is not None and lp.get("singular_values") is not None and lp.get("weak_threshold") is not None:
        s = np.asarray(lp["singular_values"], float)
        kept = s[s > max(float(lp["weak_threshold"]), 1e-6 * float(s.max()))]
        noise = float(lp.get("noise", 0.05e-3))
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


def _dropped(robot, before, fit_obs, stage1, cv, chosen_key, net, warnings, notes) -> None:
    """rows-dropped: a warning when a kept network misses > DROPPED_SHARE of the rows, else a note."""
    if net is not None and "dropped_causes" in net:
        count, causes = int(net["observations"]["dropped"]), net["dropped_causes"]
    elif cv is not None and any(c in cv.rows for c in ("hybrid+ann", "ann")):
        from labcal.calibration.equivalent import joint_error_observations

        base = stage1[0] if stage1 is not None and "hybrid+ann" in cv.rows else before
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
