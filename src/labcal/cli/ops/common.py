"""What every workflow shares: the store, the robot model a session was recorded with, user errors, JSON."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from labcal.calibration.observations import Observations
from labcal.datasets import Dataset, SessionStore, parse_ref
from labcal.robots import BUILTINS, RobotSpec, load


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


def split_ref(text: str) -> str:
    """Validate SESSION[@vN] syntax early (a clear message before touching the store)."""
    try:
        parse_ref(text)
    except ValueError as err:
        raise UserError(str(err)) from err
    return text
