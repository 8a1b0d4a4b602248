"""The hybrid method: local-POE identification, then the paper's equivalent robot + network on its residuals.

Stage 1 identifies the frame errors (:func:`labcal.calibration.local_poe.fit_local_poe`): it explains every
geometric error down to the noise floor. Stage 2 treats the *identified* robot as the base of an equivalent robot
and learns its remaining configuration-dependent joint motion errors δρ(q) (compliance, gear errors …) with
:func:`labcal.calibration.ann.fit_ann`. With purely geometric errors, or too few configurations, stage 2 can only
fit noise, so it is kept only when it lowers the mean position error on the validation split (the rows neither
stage fitted on; the network uses them for early stopping too, so the gate is slightly optimistic — the test
split, when present, is the unbiased check). Torch is imported only when stage 2 runs.
"""

from __future__ import annotations

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
    progress=None,
    **ann_options,
) -> tuple[CalibratedRobot, dict]:
    """Local POE, then the ANN on the identified robot's residual joint motion errors, gated on validation.

    obs must have a non-empty "val" split (the gate needs it): use :func:`labcal.calibration.fit.fit`, which
    assigns splits, or ``obs.with_splits``. stage1: an already computed ``fit_local_poe`` result to reuse.
    ann_options go to ``fit_ann`` (hidden, features, trainer, restarts …).

    Returns the kept robot (method "hybrid" when the second stage was kept, else the local-POE robot relabelled
    "hybrid") and info: ``kept`` ("local-poe+ann" or "local-poe"), ``val_error_local_poe`` and
    ``val_error_hybrid`` (mean position error on the validation split, m), ``local_poe`` and ``ann`` (the
    stages' info dicts).
    """
    if not np.any(obs.split == "val"):
        raise ValueError("fit_hybrid needs validation rows (split == 'val') to decide whether to keep the network")
    say = progress or (lambda _msg: None)
    if stage1 is None:
        say("hybrid: stage 1, local-POE identification")
        stage1 = fit_local_poe(obs, nominal, **(local_poe_options or {}))
    robot1, info1 = stage1
    from labcal.calibration.ann import fit_ann  # torch is imported only here

    say("hybrid: stage 2, network on the identified robot's joint motion errors")
    robot2, info2 = fit_ann(obs, robot1, seed=seed, **ann_options)
    e1, e2 = validation_error(robot1, obs), validation_error(robot2, obs)
    keep = bool(e2 < e1)
    chosen = robot2 if keep else robot1
    chosen = _relabel(chosen, "hybrid")
    info = {
        "kept": "local-poe+ann" if keep else "local-poe",
        "val_error_local_poe": e1,
        "val_error_hybrid": e2,
        "local_poe": info1,
        "ann": info2,
    }
    say(f"hybrid: validation mean position error {e1 * 1e3:.4f} mm → {e2 * 1e3:.4f} mm; kept {info['kept']}")
    return chosen, info


def _relabel(robot: CalibratedRobot, method: str) -> CalibratedRobot:
    return CalibratedRobot(
        nominal=robot.nominal,
        model=robot.model,
        network=robot.network,
        T_tracker_base=robot.T_tracker_base,
        joint_ranges=robot.joint_ranges,
        length_scale=robot.length_scale,
        method=method,
    )
