"""`labcal fit` as a function: fit on stored versions, store the fit, read stored fits back."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np

from labcal.calibration.metrics import point_residual_warning
from labcal.cli.common import UserError, plain
from labcal.cli.ops.common import check_choice, check_seed, load_observations
from labcal.compensator import CalibratedRobot, from_payload, to_payload
from labcal.datasets import SessionStore
from labcal.reports import BEFORE_FILE, ROBOT_FILE


@dataclass
class FitOutcome:
    """What ``labcal fit`` produced: the fit result, its record in the store and the data it read."""

    result: object  # labcal.calibration.fit.FitResult
    fit_id: str
    ref: str
    refs: list[str]
    metrics: dict | None = None  # the stored split table (with per-target point errors)
    gates: dict | None = None  # {"warnings", "notes", "cv"} as stored


def _check_one_version_per_session(store: SessionStore, refs: list[str]) -> None:
    """Refuse a session named twice: the same version twice counts its rows twice, and two versions of one session
    share their rows (a later version holds the earlier one's), so either would weigh those poses double and make
    the cross-validation score poses it was fitted on."""
    seen: dict[str, str] = {}
    for ref in refs:
        resolved = store.resolve(ref)
        if resolved.session_id in seen:
            first = seen[resolved.session_id]
            what = "the same version" if first == str(resolved) else "two versions of one session, which share rows"
            raise UserError(f"{first} and {resolved} are {what}: name each session once (its latest version holds all)")
        seen[resolved.session_id] = str(resolved)


def check_fit_options(method: str, seed: int, hidden: int | None, val_fraction: float) -> None:
    """The options of a fit that need no data: a bad one is a usage error before anything is read."""
    from labcal.calibration.fit import METHODS

    check_choice("--method", method, METHODS)
    check_seed(seed)
    if not 0.0 <= val_fraction < 1.0:
        raise UserError(f"--val-fraction must be in [0, 1), got {val_fraction}")
    if hidden is not None and hidden < 1:
        raise UserError(f"--hidden must be a positive number of nodes, got {hidden}")


def run_fit(
    store: SessionStore,
    refs: list[str],
    method: str,
    *,
    seed: int = 0,
    hidden: int | None = None,
    val_fraction: float = 0.0,
    robot: str | None = None,
    progress=None,
    pool_units: bool = False,
    fit_id: str | None = None,
) -> FitOutcome:
    """Fit one method on the pooled versions and store it under the first version it read.

    pool_units: fit sessions of different robot units as one (by default load_observations refuses them: one
    unit, one calibration); recorded in the fit's metadata. fit_id: store the fit under this id (default: a new
    one; `labcal refit` draws its tasks' ids before they run)."""
    from labcal.calibration.fit import fit

    check_fit_options(method, seed, hidden, val_fraction)
    _check_one_version_per_session(store, refs)
    obs, datasets, spec = load_observations(store, refs, robot, with_spec=True, pool_units=pool_units)
    options = {} if hidden is None else {"hidden": hidden}
    tool_note = probe_mount_note(obs, datasets, spec.model)
    probe = tool_note is not None  # the registered nominal then carries the probe as its measurement tool
    result = fit(
        obs, spec.model, method, seed=seed, val_fraction=val_fraction, progress=progress, register_tool=probe, **options
    )
    # What fit.json stores of the checks: each warning blocks `labcal export` unless --force.
    gates = {
        "warnings": [_as_warning(w) for w in result.warnings],
        "notes": ([tool_note] if probe else []) + [str(n) for n in result.notes],
        "cv": result.cv,
    }
    meta = {
        "method": result.method,
        "chosen": result.chosen,
        "seed": seed,
        "val_fraction": val_fraction,
        "hidden": hidden,
        "pool_units": pool_units,
        "robot": {"name": spec.name, "hash": spec.hash},
        "metrics": result.metrics,
        **gates,  # warnings, notes, cv
        "rows": {"train": result.n_train, "val": result.n_val, "test": result.n_test},
        "split": list(map(str, result.obs.split)) if result.obs is not None else None,
        "fit_seconds": result.fit_seconds,
        "info": slim_info(result.info),
        # What the targets let this fit claim about orientation (15.3): the report and evaluate print its claim.
        "observability": result.observability,
    }
    # The fit works in model joints; its compensator takes controller joints through the robot file's map.
    fitted = dataclasses.replace(result.robot, joint_map=spec.joint_map)
    before = dataclasses.replace(result.before, joint_map=spec.joint_map)
    files = {
        ROBOT_FILE: json.dumps(to_payload(fitted, {"sessions": [d.ref for d in datasets]})),
        BEFORE_FILE: json.dumps(to_payload(before)),
    }
    record = store.save_fit([d.ref for d in datasets], files, plain(meta), fit_id=fit_id)
    return FitOutcome(result, record.fit_id, record.ref, [d.ref for d in datasets], meta["metrics"], gates)


def probe_mount_note(obs, datasets, model) -> str | None:
    """For probe data, a note on the probe's mount the fit registers; None for other data.

    Probe data (a 6-DOF probe's pose per row) give the targets in the probe's frame, but where the probe sits on
    the flange is not part of the robot file. Robot and tool apart: the fits identify that mount as the measurement
    tool (the registered nominal too, ``fit(register_tool=True)``), so no method counts it as a robot error and the
    compensator and the exports keep the robot to its flange. The note says how large the mount is.
    """
    from labcal.calibration.local_poe import register

    forms = {((d.manifest.get("provenance") or {}).get("import") or {}).get("form") for d in datasets}
    if "probe" not in forms:
        return None
    registered, _ = register(obs, model, estimate_tool=True)
    mount = np.eye(4) if registered.measurement_tool is None else registered.measurement_tool
    angle = float(np.degrees(np.arccos(np.clip((np.trace(mount[:3, :3]) - 1) / 2, -1.0, 1.0))))
    return (
        f"probe data: the probe's mount on the tool frame was registered ({np.linalg.norm(mount[:3, 3]) * 1e3:.1f} mm, "
        f"{angle:.1f}°): it is the measurement tool of this fit, not part of the robot"
    )


def _as_warning(w) -> dict:
    if isinstance(w, dict):  # extra keys (details the calibration adds) are kept
        return {**w, "code": str(w.get("code") or "warning"), "message": str(w.get("message") or "")}
    return {"code": "warning", "message": str(w)}


def _relevant_infos(info: dict, chosen: str | None):
    """The diagnostics of the stages that make up the chosen model (auto's losing candidates do not count)."""
    if not isinstance(info, dict):
        return
    if isinstance(info.get("candidates"), dict) and chosen in info:
        yield from _relevant_infos(info[chosen], chosen)
        return
    if "kept" in info:  # hybrid: the local-POE stage always, a stage-2 model only when kept
        yield from _relevant_infos(info.get("local_poe") or {}, "local-poe")
        kept = str(info.get("kept") or "")
        for stage in ("ann", "series"):
            if kept.endswith("+" + stage) and isinstance(info.get(stage), dict):
                yield from _relevant_infos(info[stage], stage)
        return
    yield info


def info_warnings(info: dict, chosen: str | None = None) -> list[dict]:
    """Warnings the methods already compute in their info dicts, as {code, message}.

    Local POE: ``warning`` (rank deficiency) with the unidentifiable directions; the network: ``warnings`` (e.g.
    over-fitting). Works on a fresh info dict and on a stored (slimmed) one, so fits stored before the gates
    existed are gated the same way.
    """
    out: list[dict] = []
    for part in _relevant_infos(info, chosen):
        msg = part.get("warning")
        rank, need = part.get("rank"), part.get("expected_rank")
        if not msg and isinstance(rank, int) and isinstance(need, int) and rank < need:
            # Fits stored before the gates kept rank and expected_rank but not the warning text.
            msg = f"numerical rank {rank} < {need} identifiable parameters"
        if msg:
            if part.get("rank_deficient") or "rank" in str(msg):
                head = "" if "rank" in str(msg) or rank is None else f"rank {rank} of {need}: "
                missing = need - rank if isinstance(rank, int) and isinstance(need, int) else None
                tail = (
                    f" ({missing} identifiable combination(s) not excited; `labcal report` lists the unidentifiable"
                    " directions)"
                    if missing
                    else ""
                )
                out.append({"code": "rank-deficient", "message": f"{head}{msg}{tail}"})
            else:
                out.append({"code": "fit-warning", "message": str(msg)})
        for w in part.get("warnings") or []:
            if msg and str(w) == str(msg):
                continue  # the same rank warning, also listed under "warnings"
            code = "overfit" if "over-fitting" in str(w) or "overfit" in str(w) else "fit-warning"
            out.append(_as_warning(w) if isinstance(w, dict) else {"code": code, "message": str(w)})
    return out


def metric_warnings(metrics: dict) -> list[dict]:
    """Warnings read off a split table (an evaluation's): worse than nominal on held-out rows; point residuals (the
    calibration's own check)."""
    out = []
    for split in ("test", "val"):
        m = metrics.get(split)
        if not m:
            continue
        b, a = m["before"].get("pos_mean"), m["after"].get("pos_mean")
        if b is not None and a is not None and a >= b:
            out.append({
                "code": "worse-than-nominal",
                "message": f"{split} mean position error {a * 1e3:.4f} mm after calibration is not below the "
                f"registered nominal's {b * 1e3:.4f} mm: the calibration does not generalize (too few or badly "
                "spread poses, or a model that over-fits)",
            })  # fmt: skip
            break
    points = point_residual_warning(metrics.get("all"))
    if points:
        out.append(points)
    return out


_KEEP_INFO = {
    "curve", "stopped_at", "val_loss", "train_loss", "hidden", "features", "trainer", "std", "delta_zeta",
    "param_labels", "rank", "expected_rank", "sigma", "T_tracker_base_std", "kept", "val_error_local_poe",
    "val_error_hybrid", "candidates", "observations", "warnings", "iterations", "converged", "unidentifiable",
    "warning", "rank_deficient", "null_directions", "null_space", "n_params", "singular_values", "cov",
    "loss",  # which loss a network trained on: the report labels its training curve with it
    "measurement_tool", "measurement_tool_std",  # robot and tool apart: the identified fixture, for the report
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
    robot, _ = from_payload(json.loads(record.read(ROBOT_FILE)), f"fit {fit_id}/{ROBOT_FILE}", stored=True)
    before, _ = from_payload(json.loads(record.read(BEFORE_FILE)), f"fit {fit_id}/{BEFORE_FILE}", stored=True)
    return StoredFit(str(r), fit_id, robot, before, record.metadata, [i["ref"] for i in record.inputs])
