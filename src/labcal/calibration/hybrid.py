"""The hybrid method: local-POE identification, then a learned term for the identified robot's residual errors.

Stage 1 identifies the frame errors (:func:`labcal.calibration.local_poe.fit_local_poe`): it explains every
geometric error down to the noise floor. Stage 2 treats the *identified* robot as the base of an equivalent robot
and learns its remaining configuration-dependent joint motion errors δρ(q) (compliance, gear errors …). Two
learned terms compete on the validation split:

- ``ann``: the paper's network (:func:`labcal.calibration.ann.fit_ann`), trained here on the task-space loss of
  eq. (20) — measured on the simulator, the joint-space loss of eq. (21) spends the network on the very uneven
  noise of the δρ observations and makes the hybrid worse at every sample size, while eq. (20) weights each
  direction by its effect on the measured points (pass ``loss="joint"`` to get eq. 21 anyway);
- ``series``: per-joint Fourier series of the joint errors (:func:`labcal.calibration.joint_series.fit_joint_series`),
  the structure of transmission errors, fitted in closed form.

With purely geometric errors, or too few configurations, stage 2 can only fit noise, so the best candidate is
kept only when it lowers the mean position error on the validation split (the rows neither stage fitted on; the
network also uses them for early stopping, so the gate is slightly optimistic — the test split, when present, is
the unbiased check). Torch is imported only when the ANN candidate runs.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from labcal.calibration.local_poe import fit_local_poe
from labcal.calibration.metrics import prediction_errors
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics.poe import LocalPOEModel


def validation_error(robot: CalibratedRobot, obs: Observations) -> float:
    """Mean position error (m) of the robot's prediction on the validation rows (NaN when there are none)."""
    mask = obs.split == "val"
    if not mask.any():  # checked first: selecting zero rows is not supported by Observations.subset
        return float("nan")
    return float(np.mean(prediction_errors(robot, obs.subset(mask))[0]))


def fit_hybrid(
    obs: Observations,
    nominal: LocalPOEModel,
    *,
    seed: int = 0,
    stage1: tuple[CalibratedRobot, dict] | None = None,
    local_poe_options: dict | None = None,
    stage2: tuple[str, ...] = ("ann", "series"),
    series_options: dict | None = None,
    progress=None,
    **ann_options,
) -> tuple[CalibratedRobot, dict]:
    """Local POE, then the best learned term on the identified robot's residual joint motion errors, gated.

    obs must have a non-empty "val" split (the gate needs it): use :func:`labcal.calibration.fit.fit`, which
    assigns splits, or ``obs.with_splits``. stage1: an already computed ``fit_local_poe`` result to reuse.
    stage2: the learned terms to try ("ann", "series"). ann_options go to ``fit_ann`` (hidden, features,
    trainer, restarts, loss — default "task" here); series_options to ``fit_joint_series``.

    Returns the kept robot (method "hybrid"; the local-POE robot relabelled when no learned term helped) and
    info: ``kept`` ("local-poe+ann", "local-poe+series" or "local-poe"), ``val_error_local_poe``,
    ``val_error_hybrid`` (the best stage-2 candidate's, kept or not) and ``val_errors`` per candidate (mean
    position error on the validation split, m), ``local_poe`` and one info dict per candidate.
    """
    if not np.any(obs.split == "val"):
        raise ValueError("fit_hybrid needs validation rows (split == 'val') to decide whether to keep the network")
    say = progress or (lambda _msg: None)
    if stage1 is None:
        say("hybrid: stage 1, local-POE identification")
        stage1 = fit_local_poe(obs, nominal, **(local_poe_options or {}))
    robot1, info1 = stage1
    unknown = [name for name in stage2 if name not in ("ann", "series")]
    if unknown or not stage2:
        raise ValueError(f"stage2 must name 'ann' and/or 'series', got {stage2!r}")
    candidates: dict[str, tuple[CalibratedRobot, dict]] = {}
    if "series" in stage2:
        from labcal.calibration.joint_series import fit_joint_series

        say("hybrid: stage 2, per-joint series of the identified robot's joint motion errors")
        candidates["series"] = fit_joint_series(obs, robot1, seed=seed, **(series_options or {}))
    if "ann" in stage2:
        from labcal.calibration.ann import fit_ann  # torch is imported only here

        say("hybrid: stage 2, network on the identified robot's joint motion errors")
        candidates["ann"] = fit_ann(obs, robot1, seed=seed, **{"loss": "task", **ann_options})
    e1 = validation_error(robot1, obs)
    errors = {name: validation_error(robot, obs) for name, (robot, _) in candidates.items()}
    best = min(errors, key=lambda name: (errors[name], stage2.index(name)))
    keep = bool(errors[best] < e1)
    chosen = _relabel(candidates[best][0] if keep else robot1, "hybrid")
    info = {
        "kept": f"local-poe+{best}" if keep else "local-poe",
        "val_error_local_poe": e1,
        "val_error_hybrid": errors[best],
        "val_errors": errors,
        "local_poe": info1,
        **{name: cand_info for name, (_, cand_info) in candidates.items()},
    }
    summary = ", ".join(f"{name} {e * 1e3:.4f} mm" for name, e in errors.items())
    say(f"hybrid: validation mean position error local-poe {e1 * 1e3:.4f} mm, {summary}; kept {info['kept']}")
    return chosen, info


def _relabel(robot: CalibratedRobot, method: str) -> CalibratedRobot:
    return dataclasses.replace(robot, method=method)
