"""`labcal session import` as a function: read a CSV into a new session."""

from __future__ import annotations

from pathlib import Path

from labcal.cli.ops.common import UserError
from labcal.datasets import SessionStore
from labcal.robots import load


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
