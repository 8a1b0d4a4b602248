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
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from labcal.calibration.metrics import primary_error
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics.poe import LocalPOEModel


def validation_error(robot: CalibratedRobot, obs: Observations) -> float:
    """Mean position error (m) of the robot's prediction on the validation rows (NaN when there are none); the
    mean target-point error when those rows do not all fix a pose (:func:`~labcal.calibration.metrics.
    primary_error`)."""
    mask = obs.split == "val"
    if not mask.any():
        return float("nan")
    return primary_error(robot, obs.subset(mask))[0]


STAGE2 = {"series": "hybrid+series", "ann": "hybrid+ann"}


def fit_hybrid(
    obs: Observations,
    nominal: LocalPOEModel,
    *,
    seed: int = 0,
    local_poe_options: dict | None = None,
    stage2: tuple[str, ...] = ("ann", "series"),
    series_options: dict | None = None,
    progress=None,
    **ann_options,
) -> tuple[CalibratedRobot, dict]:
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
    stage's info.
    """
    from labcal.calibration.fit import fit  # fit() runs the hybrid's stages; this is its (robot, info) view

    result = fit(
        obs, nominal, "hybrid", seed=seed, progress=progress, local_poe_options=local_poe_options, stage2=stage2,
        series_options=series_options, **ann_options,
    )  # fmt: skip
    return result.robot, {**result.info, "notes": list(result.notes)}


def prefit_series(fit_obs, robot1, candidates, seed, series_options, say):
    """The joint series on all fitting rows (its order is then fixed in the folds), or None with a note."""
    if "hybrid+series" not in candidates:
        return None, []
    from labcal.calibration.joint_series import fit_joint_series
    from labcal.calibration.observations import ObservationError

    say("hybrid: joint series on every fitting row (chooses its order)")
    try:
        return fit_joint_series(fit_obs, robot1, seed=seed, **(series_options or {})), []
    except ObservationError as err:
        return None, [f"stage-skipped: hybrid+series: {err}"]


def series_fixed(series_full) -> dict | None:
    """The order and gravity switch the folds reuse (see labcal.calibration.cv.cross_validate)."""
    if series_full is None or not {"harmonics", "gravity"} <= set(series_full[1]):
        return None
    info = series_full[1]
    return {"harmonics": int(info["harmonics"]), "gravity": bool(info["gravity"])}


def finish_hybrid(fit_obs, obs, stage1, cv, candidates, *, seed, series_full, ann_options, say, choice=None):
    """Choose (unless ``choice`` is given) among the hybrid's candidates; the kept one fitted on all rows."""
    from labcal.calibration.cv import choose

    robot1, info1 = stage1
    notes: list[str] = []
    skipped: dict[str, str] = {}
    if cv is None:
        notes.append(
            f"stage-skipped: the learned stages need cross-validation, which needs at least 3 distinct poses "
            f"(or groups); {fit_obs.k} rows give fewer: kept local POE"
        )
        skipped = {c: "too few distinct poses to cross-validate" for c in candidates if c != "local-poe"}
        kept = "local-poe"
    else:
        for c in candidates:
            if c != "local-poe" and not cv.available(c):
                skipped[c] = cv.failures.get(c, "not evaluated")
                notes.append(f"stage-skipped: {c}: {skipped[c]}")
        if cv.available("local-poe"):
            kept = choice or choose(cv, candidates)
        else:  # not even local POE could be fitted on a fold's rows: nothing to compare a learned stage with
            notes.append(f"stage-skipped: no fold could fit local POE ({cv.failures.get('local-poe', '')}): kept it")
            kept = "local-poe"
    robot, stage_info = robot1, {}
    if kept == "hybrid+series":
        robot, stage_info = series_full
    elif kept == "hybrid+ann":
        from labcal.calibration.ann import fit_ann
        from labcal.calibration.observations import ObservationError

        try:
            robot, stage_info = fit_ann(fit_obs, robot1, seed=seed, **{"loss": "task", **(ann_options or {})})
        except ObservationError as err:  # too few usable rows on all rows (the folds could): keep local POE
            notes.append(f"stage-skipped: hybrid+ann on all rows: {err}")
            kept, robot = "local-poe", robot1
    # Every row the fit used, not only those a learned stage kept (issue 13.3).
    robot = dataclasses.replace(robot, method="hybrid", joint_ranges=_ranges(fit_obs.q, robot))
    errors = {name: (cv.mean(STAGE2[name]) if cv is not None and STAGE2[name] in cv.rows else float("nan"))
              for name in ("series", "ann") if STAGE2[name] in candidates}  # fmt: skip
    e1 = cv.mean("local-poe") if cv is not None else float("nan")
    finite = {k: v for k, v in errors.items() if math.isfinite(v)}
    info = {
        "kept": "local-poe" if kept == "local-poe" else "local-poe+" + kept.split("+")[1],
        "selection": "cross-validation" if cv is not None else "none (too few poses)",
        "val_error_local_poe": e1,
        "val_error_hybrid": min(finite.values()) if finite else float("nan"),
        "val_errors": errors,
        "val_error": validation_error(robot, obs),
        "cv": None if cv is None else cv.summary("hybrid" if kept != "local-poe" else "local-poe"),
        "skipped": skipped,
        "notes": notes,
        "local_poe": info1,
    }
    if kept != "local-poe":
        info[kept.split("+")[1]] = stage_info
    summary = ", ".join(f"{name} {e * 1e3:.4f} mm" for name, e in errors.items())
    say(f"hybrid: cross-validated mean point error local-poe {e1 * 1e3:.4f} mm, {summary}; kept {info['kept']}")
    return robot, info


def _ranges(q: np.ndarray, robot: CalibratedRobot) -> np.ndarray:
    """Joint ranges of the fitting rows for a learned model; a purely geometric one keeps the robot's limits."""
    if robot.network is None:
        return robot.joint_ranges
    return np.stack([q.min(axis=0), q.max(axis=0)], axis=1)
