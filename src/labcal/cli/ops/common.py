"""What every workflow shares: the robot model a session was recorded with, the pooled observations, the checks of
seeds and units. ``UserError``, ``open_store`` and the JSON converter ``plain`` are
:mod:`labcal.cli.common`'s (one definition each, light enough for `labcal --help`)."""

from __future__ import annotations

import numpy as np

from labcal.calibration.observations import Observations, pooled
from labcal.cli.common import UserError, session_unit
from labcal.datasets import Dataset, SessionStore, parse_ref
from labcal.robots import BUILTINS, RobotSpec, from_record, load


def robot_for(dataset_robot: dict, robot: str | None = None) -> RobotSpec:
    """The robot model a data set was taken with.

    1. ``robot`` (built-in name or file) if given: an override, which must have the recorded hash;
    2. else the robot file text stored with the data (self-contained versions), read back with
       :func:`labcal.robots.from_record` and checked against the recorded hash;
    3. else (sessions written before the text was stored) the built-in of the recorded name.

    Raises UserError naming the model and both hashes when they differ (a different robot, an edited file, or a
    built-in that changed since the data were recorded), or when no model can be found.
    """
    name, recorded = dataset_robot.get("name"), dataset_robot.get("hash")
    short = f"{recorded[:12]}…" if recorded else "none recorded"
    if robot is not None:
        spec = load(robot)
        if recorded and spec.hash != recorded:
            raise UserError(
                f"robot model {robot!r} (hash {spec.hash[:12]}…) is not the model the session was recorded with "
                f"({name!r}, hash {short})"
            )
        return spec
    try:
        stored = from_record(dataset_robot, f"<robot file stored with the session: {name}>")
    except ValueError as e:
        raise UserError(f"the robot file stored with the session ({name!r}) cannot be read: {e}") from None
    if stored is not None:
        if recorded and stored.hash != recorded:
            raise UserError(
                f"the robot file stored with the session ({name!r}) has hash {stored.hash[:12]}… but the session "
                f"records {short}: this labcal reads the file differently from the one that recorded it; pass the "
                "original model with --robot PATH"
            )
        return stored
    if name not in BUILTINS:
        raise UserError(
            f"the data were taken with robot model {name!r}, which is not a built-in and was not stored with the "
            "session (recorded before labcal stored robot files): pass its file with --robot PATH"
        )
    spec = load(name)
    if recorded and spec.hash != recorded:
        raise UserError(
            f"the built-in robot model {name!r} (hash {spec.hash[:12]}…) changed since the session was recorded "
            f"(hash {short}), and the session predates stored robot files: pass the original file with --robot PATH"
        )
    return spec


def check_choice(flag: str, value: object, choices: tuple[str, ...]) -> None:
    """An option's value must be one of ``choices`` (the CLI's Literal options check this too; library callers not)."""
    if value not in choices:
        raise UserError(f"{flag} must be one of {', '.join(choices)}, got {value!r}")


def check_seed(seed: int | None, flag: str = "--seed") -> None:
    """A seed is a non-negative integer (numpy's generators refuse others with a message naming no flag)."""
    if seed is None:
        return
    if isinstance(seed, bool) or not hasattr(seed, "__index__") or seed.__index__() < 0:  # numpy integers pass
        raise UserError(f"{flag} must be a non-negative integer, got {seed!r}")


def check_unit_option(unit: str | None) -> str | None:
    """--unit: None, or an id as the session stores it (printable, at most 64 characters)."""
    from labcal.datasets.documents import check_unit
    from labcal.datasets.errors import JournalError

    if unit is None:
        return None
    try:
        return check_unit(unit, "--unit")
    except JournalError as e:
        raise UserError(str(e)) from None


def check_units(datasets: list[Dataset], pool_units: bool = False) -> list[str]:
    """The distinct robot units of the versions to pool, in order of first appearance; UserError if there are two
    or more and ``pool_units`` is False.

    A calibration belongs to one arm: two arms of one model differ by their own geometric errors, so a fit of both
    is a compromise that fits neither (``--pool-units`` asks for exactly that, e.g. a model-wide nominal). Versions
    without a unit (recorded before units, or imported without ``--unit``) pool with anything, as they always did.
    """
    units: dict[str, list[str]] = {}
    for ds in datasets:
        unit = session_unit(ds.manifest["session"])
        if unit is not None:
            units.setdefault(unit, []).append(ds.ref)
    if len(units) > 1 and not pool_units:
        which = "; ".join(f"{unit}: {', '.join(refs)}" for unit, refs in units.items())
        raise UserError(
            f"the sessions are of {len(units)} different robot units ({which}): fit one unit at a time, or pass "
            "--pool-units to fit them as one"
        )
    return list(units)


def load_observations(
    store: SessionStore,
    refs: list[str],
    robot: str | None = None,
    *,
    with_spec: bool = False,
    pool_units: bool = False,
) -> tuple[Observations, list[Dataset]] | tuple[Observations, list[Dataset], RobotSpec]:
    """Load (and verify) one or more versions of the same robot and pool them into one Observations.

    The robot model is resolved with :func:`robot_for` (stored file text, else built-in; ``robot`` overrides) and
    the stored controller joints are converted to model joints with its joint map: this is the ONE place where
    that conversion happens. When several sessions are pooled, ``Observations.group`` holds each row's session
    ref, so cross-validation keeps a session in one fold. ``Observations.points`` is (rows, m, 3) for the m targets of
    the sessions (m from their manifests), with a NaN row where a target was not seen; three-target sessions recorded
    before 1..k targets load exactly as they always did.
    ``with_spec=True`` also returns the RobotSpec (callers that fit need it; the 2-tuple stays for old callers).
    Sessions of different robot units (``metadata["unit"]``) are refused unless ``pool_units`` (see
    :func:`check_units`).
    """
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
        if ds.targets.shape != first.targets.shape or not np.allclose(ds.targets, first.targets, atol=1e-9):
            raise UserError(f"{ds.ref} and {first.ref} have different targets: they cannot be pooled")
        if ds.frame != first.frame:
            raise UserError(f"{ds.ref} is in the {ds.frame} frame, {first.ref} in the {first.frame} frame")
    check_units(datasets, pool_units)
    try:
        spec = robot_for(first.robot, robot)
    except UserError:
        if with_spec or robot is not None or first.robot.get("text"):
            raise
        # Old 2-tuple callers resolve the model themselves afterwards (with their --robot override, and its
        # error if there is none). Such a session predates stored robot files and joint maps: identity.
        spec = None
    q_controller = np.concatenate([d.q for d in datasets])
    if spec is not None and q_controller.shape[1] != spec.model.n:
        raise UserError(
            f"{first.ref} has {q_controller.shape[1]} joint columns, "
            f"robot model {spec.name!r} has {spec.model.n} joints"
        )
    # Pooled sessions: cross-validation keeps each session's rows in one fold.
    group = np.concatenate([np.full(len(d), d.ref, dtype=object) for d in datasets]) if len(datasets) > 1 else None
    obs = pooled(datasets, spec.joints.to_model(q_controller) if spec is not None else q_controller, group)
    return (obs, datasets, spec) if with_spec else (obs, datasets)


def split_ref(text: str) -> str:
    """Validate SESSION[@vN] syntax early (a clear message before touching the store: the ValueError of
    :func:`labcal.datasets.parse_ref`)."""
    parse_ref(text)
    return text
