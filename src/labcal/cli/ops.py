"""The workflows behind the commands, as plain functions (usable from Python; the command modules only parse).

Every function takes an opened :class:`~labcal.datasets.SessionStore` and returns data; nothing here prints.
Errors the user can fix are raised as :class:`UserError` (or the library's ValueError subclasses) with a message
that names the bad input.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot, from_payload, to_payload
from labcal.datasets import Dataset, SessionStore, parse_ref
from labcal.robots import BUILTINS, RobotSpec, load

ROBOT_FILE = "robot.json"  # the fitted robot, as a compensator payload
BEFORE_FILE = "before.json"  # the registered nominal (the "before" of every metric)


class UserError(ValueError):
    """A problem with the command's input that the user can fix (the message says what)."""


def open_store(path: str | Path | None) -> SessionStore:
    """The store at path, else $LABCAL_STORE, else ./sessions."""
    if path is None:
        path = os.environ.get("LABCAL_STORE") or "sessions"
    return SessionStore(Path(path))


def robot_for(dataset_robot: dict, robot: str | None = None) -> RobotSpec:
    """The robot model a data set was taken with: ``robot`` (name or file) if given, else the built-in of that name.

    Raises UserError when the model's hash differs from the one recorded with the data (a different robot, or an
    edited model file).
    """
    name, recorded = dataset_robot.get("name"), dataset_robot.get("hash")
    if robot is None:
        if name not in BUILTINS:
            raise UserError(f"the data were taken with robot model {name!r}: pass its file with --robot PATH")
        robot = name
    spec = load(robot)
    if recorded and spec.hash != recorded:
        raise UserError(
            f"robot model {robot!r} (hash {spec.hash[:12]}…) is not the model the session was recorded with "
            f"({name!r}, hash {recorded[:12]}…)"
        )
    return spec


def load_observations(store: SessionStore, refs: list[str]) -> tuple[Observations, list[Dataset]]:
    """Load (and verify) one or more versions of the same robot and pool them into one Observations."""
    if not refs:
        raise UserError("name at least one SESSION[@vN]")
    datasets = [store.load(ref) for ref in refs]
    first = datasets[0]
    for ds in datasets[1:]:
        if ds.robot.get("hash") != first.robot.get("hash"):
            raise UserError(
                f"{ds.ref} was recorded with robot {ds.robot.get('name')!r}, {first.ref} with "
                f"{first.robot.get('name')!r}: only sessions of the same robot model can be pooled"
            )
        if not np.allclose(ds.targets, first.targets, atol=1e-9):
            raise UserError(f"{ds.ref} and {first.ref} have different targets: they cannot be pooled")
        if ds.frame != first.frame:
            raise UserError(f"{ds.ref} is in the {ds.frame} frame, {first.ref} in the {first.frame} frame")
    obs = Observations(
        q=np.concatenate([d.q for d in datasets]),
        points=np.concatenate([d.points for d in datasets]),
        targets=first.targets,
        frame=first.frame,
        split=np.concatenate([d.split for d in datasets]).astype(object),
    )
    return obs, datasets


def jsonable(obj, depth: int = 0):
    """numpy-free JSON data: arrays → lists, non-finite floats → None, unknown objects → their str."""
    if depth > 12:
        return None
    if isinstance(obj, dict):
        return {str(k): jsonable(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v, depth + 1) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), depth + 1)
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return float(obj) if np.isfinite(obj) else None
    if obj is None or isinstance(obj, str):
        return obj
    return str(obj)


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


def export_fit(store: SessionStore, ref: str, fmt: str, out: str | Path, fit_id: str | None = None) -> Path:
    """Write a stored fit as json | npz | urscript | urdf, with provenance (session, fit id, data hashes)."""
    from labcal.export import FORMATS, export

    if fmt not in FORMATS:
        raise UserError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    stored = load_stored_fit(store, ref, fit_id)
    record = store.load_fit(stored.ref, stored.fit_id, check_files=False)
    provenance = {
        "session": stored.ref,
        "fit_id": stored.fit_id,
        "inputs": ", ".join(i["ref"] for i in record.inputs),
        "data_sha256": ", ".join(i["manifest_sha256"] for i in record.inputs),
        "method": stored.robot.method,
    }
    out = Path(out)
    if out.parent and not out.parent.exists():
        raise UserError(f"output folder {out.parent} does not exist")
    return export(stored.robot, fmt, out, provenance)


def split_ref(text: str) -> str:
    """Validate SESSION[@vN] syntax early (a clear message before touching the store)."""
    try:
        parse_ref(text)
    except ValueError as err:
        raise UserError(str(err)) from err
    return text


# -- sessions ------------------------------------------------------------------------------------------------------
ROBOT_DRIVERS = ("sim", "ur")
TRACKER_DRIVERS = ("sim", "serial")
PLANNERS = ("random", "optimal")
SIM_ERRORS = ("paper", "default", "none")


def sim_actual(spec: RobotSpec, errors: str, seed: int):
    """The simulated actual robot of a sim session (recreated identically on resume from errors + seed)."""
    from labcal.simulation import ErrorSpec, simulate

    if errors not in SIM_ERRORS:
        raise UserError(f"--sim-errors must be one of {', '.join(SIM_ERRORS)}, got {errors!r}")
    spec_errors = {"paper": ErrorSpec.paper, "default": ErrorSpec.default, "none": ErrorSpec.none}[errors]()
    return simulate(spec, spec_errors, seed=seed)


def plan_configurations(spec: RobotSpec, poses: int, planner: str, seed: int, targets, samples: int = 2000):
    from labcal.sessions import optimal_configurations, random_configurations

    if poses < 1:
        raise UserError(f"--poses must be at least 1, got {poses}")
    if planner == "random":
        return random_configurations(spec.model, poses, seed=seed, targets=targets)
    if planner == "optimal":
        return optimal_configurations(spec.model, poses, seed=seed, targets=targets, candidates=samples)
    raise UserError(f"--planner must be one of {', '.join(PLANNERS)}, got {planner!r}")


def _drivers(robot_driver, tracker_driver, spec, targets, *, profile, tracker_profile, sim_errors, seed):
    """(robot, tracker, frame, metadata, closers) for the chosen drivers."""
    if robot_driver not in ROBOT_DRIVERS:
        raise UserError(f"--robot-driver must be one of {', '.join(ROBOT_DRIVERS)}, got {robot_driver!r}")
    if tracker_driver not in TRACKER_DRIVERS:
        raise UserError(f"--tracker-driver must be one of {', '.join(TRACKER_DRIVERS)}, got {tracker_driver!r}")
    if (robot_driver == "sim") != (tracker_driver == "sim"):
        raise UserError("the sim robot and the sim tracker go together: use --robot-driver sim --tracker-driver sim")
    if robot_driver == "sim":
        from labcal.drivers.sim import SimRig

        rig = SimRig(sim_actual(spec, sim_errors, seed), targets, seed=seed)
        return rig.robot(), rig.tracker(), "base", {"sim": {"errors": sim_errors, "seed": seed}}
    from labcal.drivers.serial_tracker import open_tracker
    from labcal.drivers.ur import URRobot, load_ur_profile

    if profile is None or tracker_profile is None:
        raise UserError("real drivers need --profile drivers/<robot>.toml and --tracker-profile drivers/<tracker>.toml")
    robot = URRobot.connect(load_ur_profile(profile))
    tracker = open_tracker(tracker_profile, targets)
    return robot, tracker, "tracker", {"profiles": {"robot": str(profile), "tracker": str(tracker_profile)}}


def new_session(
    store: SessionStore,
    *,
    robot: str,
    targets_file: str | Path,
    poses: int,
    robot_driver: str = "sim",
    tracker_driver: str = "sim",
    profile: str | None = None,
    tracker_profile: str | None = None,
    planner: str = "random",
    samples: int = 2000,
    seed: int = 0,
    sim_errors: str = "default",
    progress=None,
):
    """Plan and record a session; returns the runner's RunSummary (its .ref is the new SESSION@vNNN)."""
    from labcal.datasets import load_targets
    from labcal.sessions import make_plan, run

    spec = load(robot)
    targets = load_targets(targets_file)
    if sim_errors not in SIM_ERRORS:
        raise UserError(f"--sim-errors must be one of {', '.join(SIM_ERRORS)}, got {sim_errors!r}")
    q = plan_configurations(spec, poses, planner, seed, targets, samples)
    sim = robot_driver == "sim"
    plan = make_plan(q, samples=3 if sim else 5, settle=0.0 if sim else 0.5)
    rob, trk, frame, meta = _drivers(
        robot_driver, tracker_driver, spec, targets, profile=profile, tracker_profile=tracker_profile,
        sim_errors=sim_errors, seed=seed,
    )  # fmt: skip
    with rob, trk:
        return run(store, spec, targets, plan, rob, trk, frame=frame, progress=progress, metadata=meta)


def resume_session(store: SessionStore, session_id: str, *, robot: str | None = None, progress=None):
    """Resume a session; a sim session re-creates its simulated robot from the recorded errors and seed."""
    from labcal.drivers.sim import SimRig
    from labcal.sessions import resume

    meta = store.session_meta(session_id)
    spec = robot_for(meta["robot"], robot)
    sim = (meta.get("metadata") or {}).get("sim")
    if not sim:
        raise UserError(
            f"session {session_id} was not recorded on the sim rig; resume real-hardware sessions from Python with "
            "the same drivers (labcal.sessions.resume)"
        )
    targets = np.asarray(meta["targets"], dtype=float)
    rig = SimRig(sim_actual(spec, sim["errors"], int(sim["seed"])), targets, seed=int(sim["seed"]))
    with rig.robot() as rob, rig.tracker() as trk:
        return resume(store, session_id, rob, trk, spec=spec, progress=progress)


def import_session(
    store: SessionStore,
    path: str | Path,
    *,
    robot: str,
    targets_file: str | Path | None = None,
    mapping: str | None = None,
    length_unit: str = "m",
    angle_unit: str = "rad",
    frame: str = "base",
    form: str = "targets",
) -> str:
    """Import a CSV into a new session; returns SESSION@vNNN."""
    from labcal.datasets import import_mapped, import_probe_csv, import_targets_csv, load_targets

    path = Path(path)
    if not path.is_file():
        raise UserError(f"no such file: {path}")
    spec = load(robot)
    if mapping is not None:
        targets = load_targets(targets_file) if targets_file else None
        return import_mapped(store, path, mapping, spec.name, spec.hash, spec.model.n, targets=targets)
    if form == "targets":
        if targets_file is None:
            raise UserError("--targets TARGETS.toml is required for --form targets")
        return import_targets_csv(
            store, path, spec.name, spec.hash, spec.model.n, load_targets(targets_file),
            length_unit=length_unit, angle_unit=angle_unit, frame=frame,
        )  # fmt: skip
    if form == "probe":
        return import_probe_csv(
            store, path, spec.name, spec.hash, spec.model.n, length_unit=length_unit, angle_unit=angle_unit,
            frame=frame,
        )  # fmt: skip
    raise UserError(f"--form must be 'targets' or 'probe', got {form!r}")
