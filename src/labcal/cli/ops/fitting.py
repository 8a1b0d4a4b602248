"""`labcal fit` as a function: fit on stored versions, store the fit, read stored fits back."""

from __future__ import annotations

import json
from dataclasses import dataclass

from labcal.cli.ops.common import UserError, jsonable, load_observations, robot_for
from labcal.compensator import CalibratedRobot, from_payload, to_payload
from labcal.datasets import SessionStore

ROBOT_FILE = "robot.json"  # the fitted robot, as a compensator payload
BEFORE_FILE = "before.json"  # the registered nominal (the "before" of every metric)


@dataclass
class FitOutcome:
    """What ``labcal fit`` produced: the fit result, its record in the store and the data it read."""

    result: object  # labcal.calibration.fit.FitResult
    fit_id: str
    ref: str
    refs: list[str]


def run_fit(
    store: SessionStore,
    refs: list[str],
    method: str,
    *,
    seed: int = 0,
    hidden: int | None = None,
    val_fraction: float = 0.5,
    robot: str | None = None,
    features: tuple[str, ...] | None = None,
    progress=None,
) -> FitOutcome:
    """Fit one method on the pooled versions and store it under the first version it read."""
    from labcal.calibration.fit import METHODS, fit

    if method not in METHODS:
        raise UserError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
    if not 0.0 <= val_fraction < 1.0:
        raise UserError(f"--val-fraction must be in [0, 1), got {val_fraction}")
    if hidden is not None and hidden < 1:
        raise UserError(f"--hidden must be a positive number of nodes, got {hidden}")
    obs, datasets = load_observations(store, refs)
    spec = robot_for(datasets[0].robot, robot)
    options = {}
    if hidden is not None:
        options["hidden"] = hidden
    if features is not None:
        options["features"] = tuple(features)
    result = fit(obs, spec.model, method, seed=seed, val_fraction=val_fraction, progress=progress, **options)
    meta = {
        "method": result.method,
        "chosen": result.chosen,
        "seed": seed,
        "val_fraction": val_fraction,
        "hidden": hidden,
        "robot": {"name": spec.name, "hash": spec.hash},
        "metrics": result.metrics,
        "rows": {"train": result.n_train, "val": result.n_val, "test": result.n_test},
        "split": list(map(str, result.obs.split)) if result.obs is not None else None,
        "fit_seconds": result.fit_seconds,
        "info": slim_info(result.info),
    }
    files = {
        ROBOT_FILE: json.dumps(to_payload(result.robot, {"sessions": [d.ref for d in datasets]})),
        BEFORE_FILE: json.dumps(to_payload(result.before)),
    }
    record = store.save_fit([d.ref for d in datasets], files, jsonable(meta))
    return FitOutcome(result, record.fit_id, record.ref, [d.ref for d in datasets])


_KEEP_INFO = {
    "curve", "stopped_at", "val_loss", "train_loss", "hidden", "features", "trainer", "std", "delta_zeta",
    "param_labels", "rank", "expected_rank", "sigma", "T_tracker_base_std", "kept", "val_error_local_poe",
    "val_error_hybrid", "candidates", "observations", "warnings", "iterations", "converged", "unidentifiable",
}  # fmt: skip


def slim_info(info, depth: int = 0):
    """The parts of a fit's diagnostics worth storing (curves, parameters and their std, choices)."""
    if not isinstance(info, dict) or depth > 3:
        return None
    out = {}
    for key, value in info.items():
        if isinstance(value, dict) and key not in ("curve", "candidates", "observations"):
            sub = slim_info(value, depth + 1)
            if sub:
                out[key] = sub
        elif key in _KEEP_INFO:
            out[key] = value
    return out


@dataclass
class StoredFit:
    """A fit read back from the store."""

    ref: str
    fit_id: str
    robot: CalibratedRobot
    before: CalibratedRobot
    meta: dict  # the metadata written by run_fit
    inputs: list[str]


def load_stored_fit(store: SessionStore, ref: str, fit_id: str | None = None) -> StoredFit:
    """A stored fit of ref (the newest if fit_id is None); the robot files are verified like an export."""
    r = store.resolve(ref)
    if fit_id is None:
        fits = store.list_fits(r)
        if not fits:
            raise UserError(f"{r} has no fits yet: run `labcal fit {r}` first")
        fit_id = fits[-1].fit_id
    record = store.load_fit(r, fit_id)
    if ROBOT_FILE not in record.files:
        raise UserError(f"fit {fit_id} of {r} has no {ROBOT_FILE} (not written by labcal fit)")
    robot, _ = from_payload(json.loads(record.read(ROBOT_FILE)), f"fit {fit_id}/{ROBOT_FILE}")
    before, _ = from_payload(json.loads(record.read(BEFORE_FILE)), f"fit {fit_id}/{BEFORE_FILE}")
    return StoredFit(str(r), fit_id, robot, before, record.metadata, [i["ref"] for i in record.inputs])
