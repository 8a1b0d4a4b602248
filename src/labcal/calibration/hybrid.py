"""The hybrid method: local-POE identification, then a learned term for the identified robot's residual errors.

Stage 1 identifies the frame errors (:func:`labcal.calibration.local_poe.fit_local_poe`): it explains every
geometric error down to the noise floor. Stage 2 treats the *identified* robot as the base of an equivalent robot
and learns its remaining configuration-dependent joint motion errors δρ(q) (compliance, gear errors …). Two
learned terms compete (chosen by cross-validation, see below):

- ``ann``: the paper's network (:func:`labcal.calibration.ann.fit_ann`), trained here on the task-space loss of
  eq. (20) — measured on the simulator, the joint-space loss of eq. (21) spends the network on the very uneven
  noise of the δρ observations and makes the hybrid worse at every sample size, while eq. (20) weights each
  direction by its effect on the measured points (pass ``loss="joint"`` to get eq. 21 anyway);
- ``series``: per-joint Fourier series of the joint errors (:func:`labcal.calibration.joint_series.fit_joint_series`),
  the structure of transmission errors, fitted in closed form.

With purely geometric errors, or too few configurations, stage 2 can only fit noise, so a learned term is kept
only when K-fold cross-validation over the fitting rows says it lowers the held-out error by more than a
near-tie (:mod:`labcal.calibration.cv`: every stage, local POE included, refitted inside each fold; the network's
early stopping on an inner split of the fold's training rows). The kept variant is then refitted on all fitting
rows. "val" rows, when a caller labels some, are only measured, never used to choose. Both stages fit point
residuals, so sessions with one or two targets, or targets missing in some rows, fit the same way (the learned
terms see only the joint-error directions the points show; the rest stays at the identified robot's). When the
condition filter leaves too few rows for the network (most poses at a singular wrist) the network is skipped and
the series still competes; torch is imported only when the ANN candidate runs.

:func:`labcal.calibration.fit.fit_hybrid` runs the method (``fit(…, "hybrid")`` without its checks); this module
holds its steps, which :mod:`labcal.calibration.fit` calls (never the reverse).
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, TypedDict

from labcal.calibration.candidates import BY_NAME, TABLE, Candidates, FitContext, Outcome, Stage
from labcal.calibration.cv import CVRecord, CVResult, choose
from labcal.calibration.local_poe import LocalPOEInfo
from labcal.calibration.metrics import validation_error
from labcal.calibration.observations import ObservationError
from labcal.compensator import CalibratedRobot

if TYPE_CHECKING:
    from labcal.calibration.ann import ANNInfo
    from labcal.calibration.joint_series import SeriesInfo


class Learned(TypedDict, total=False):
    """The kept learned stage's info, under its ``learned`` name (none when local POE is kept)."""

    ann: ANNInfo
    series: SeriesInfo


class HybridKept(TypedDict):
    """What auto records of the hybrid when it refitted none: the label of the kept candidate."""

    kept: str


class HybridInfo(HybridKept, Learned):
    """The hybrid's info (:func:`labcal.calibration.fit.fit_hybrid` says what each key holds; saved with a fit)."""

    selection: str
    val_error_local_poe: float
    val_error_hybrid: float
    val_errors: dict[str, float]
    val_error: float
    cv: CVRecord | None
    skipped: dict[str, str]
    notes: list[str]
    local_poe: LocalPOEInfo


def prefit_series(ctx: FitContext, robot1: CalibratedRobot) -> Stage[SeriesInfo] | None:
    """The joint series on all fitting rows (its order is then fixed in the folds), or None with a note."""
    from labcal.calibration.joint_series import fit_joint_series

    ctx.say("hybrid: joint series on every fitting row (chooses its order)")
    try:
        return Stage(*fit_joint_series(ctx.fit_obs, robot1, seed=ctx.seed, **(ctx.series_options or {})))
    except ObservationError as err:
        ctx.notes.append(f"stage-skipped: hybrid+series: {err}")
        return None


def series_fixed(series: Stage[SeriesInfo] | None) -> dict | None:
    """The order and gravity switch the folds reuse (see labcal.calibration.cv.cross_validate)."""
    if series is None or not {"harmonics", "gravity"} <= set(series.info):
        return None
    return {"harmonics": int(series.info["harmonics"]), "gravity": bool(series.info["gravity"])}


def finish_hybrid(ctx: FitContext, table: Candidates, choice: str | None = None) -> Outcome[HybridInfo]:
    """Choose (unless ``choice`` is given) among the hybrid's candidates; the kept one fitted on all rows.

    The outcome's info is the hybrid's (:func:`labcal.calibration.fit.fit_hybrid`), its candidate the kept one.
    """
    assert table.stage1 is not None
    candidates = tuple(c for c in table.names if c == "local-poe" or BY_NAME[c].hybrid)  # local POE and its learned
    notes: list[str] = []
    if table.cv is None:
        notes.append(
            f"stage-skipped: the learned stages need cross-validation, which needs at least 3 distinct poses "
            f"(or groups); {ctx.fit_obs.k} rows give fewer: kept local POE"
        )
        skipped = {c: "too few distinct poses to cross-validate" for c in candidates if c != "local-poe"}
        kept = "local-poe"
    else:
        skipped, kept = _cv_choice(table.cv, candidates, choice, notes)
    kept, robot, learned = _refit_kept(ctx, table, kept, notes)
    # A learned stage's joint ranges are already every fitting row's, not only those it kept (issue 13.3).
    robot = dataclasses.replace(robot, method="hybrid")
    info = _hybrid_info(ctx, table, kept, robot, skipped, notes)
    info.update(learned)
    summary = ", ".join(f"{name} {e * 1e3:.4f} mm" for name, e in info["val_errors"].items())
    ctx.say(
        f"hybrid: cross-validated mean point error local-poe {info['val_error_local_poe'] * 1e3:.4f} mm, {summary}; "
        f"kept {info['kept']}"
    )
    return Outcome(robot, info, "hybrid", kept, network=learned.get("ann"))


def _cv_choice(
    cv: CVResult, candidates: tuple[str, ...], choice: str | None, notes: list[str]
) -> tuple[dict[str, str], str]:
    """The learned candidates cross-validation could not run ({name: why}, noted) and the one to keep."""
    skipped: dict[str, str] = {}
    for c in candidates:
        if c != "local-poe" and not cv.available(c):
            skipped[c] = cv.failures.get(c, "not evaluated")
            notes.append(f"stage-skipped: {c}: {skipped[c]}")
    if cv.available("local-poe"):
        return skipped, choice or choose(cv, candidates)
    # not even local POE could be fitted on a fold's rows: nothing to compare a learned stage with
    notes.append(f"stage-skipped: no fold could fit local POE ({cv.failures.get('local-poe', '')}): kept it")
    return skipped, "local-poe"


def _refit_kept(
    ctx: FitContext, table: Candidates, kept: str, notes: list[str]
) -> tuple[str, CalibratedRobot, Learned]:
    """The kept candidate on all fitting rows (the series is already fitted there) and its learned stage's info;
    local POE when the network cannot be trained on all rows (the folds could)."""
    assert table.stage1 is not None
    if kept == "hybrid+series" and table.series is not None:
        return kept, table.series.robot, {"series": table.series.info}
    if kept == "hybrid+ann":
        from labcal.calibration.ann import fit_ann  # torch only when a network is fitted

        try:
            options = {"loss": "task", **(ctx.options or {})}
            robot, info = fit_ann(ctx.fit_obs, table.stage1.robot, seed=ctx.seed, **options)
            return kept, robot, {"ann": info}
        except ObservationError as err:  # too few usable rows on all rows (the folds could): keep local POE
            notes.append(f"stage-skipped: hybrid+ann on all rows: {err}")
            return "local-poe", table.stage1.robot, {}
    return kept, table.stage1.robot, {}


def _hybrid_info(
    ctx: FitContext, table: Candidates, kept: str, robot: CalibratedRobot, skipped: dict[str, str], notes: list[str]
) -> HybridInfo:
    """The hybrid's info (saved with a fit: its keys do not change), without the kept stage's own info."""
    assert table.stage1 is not None
    errors = {m.learned: table.cv_error(m.name) for m in TABLE if m.hybrid and m.learned and m.name in table.names}
    finite = {k: v for k, v in errors.items() if math.isfinite(v)}
    cv = table.cv
    return {
        "kept": BY_NAME[kept].kept,
        "selection": "cross-validation" if cv is not None else "none (too few poses)",
        "val_error_local_poe": cv.mean("local-poe") if cv is not None else float("nan"),
        "val_error_hybrid": min(finite.values()) if finite else float("nan"),
        "val_errors": errors,
        "val_error": validation_error(robot, ctx.obs),
        "cv": None if cv is None else cv.summary("hybrid" if kept != "local-poe" else "local-poe"),
        "skipped": skipped,
        "notes": notes,
        "local_poe": table.stage1.info,
    }
