"""`labcal session import` as a function: read a CSV into a new session, after the sanity checks."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from labcal.cli.common import UserError
from labcal.cli.ops.common import check_unit_option
from labcal.datasets import SessionStore
from labcal.robots import load

FORMS = ("targets", "probe")


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
    allow: Sequence[str] = (),
    unit: str | None = None,
) -> str:
    """Import a CSV into a new session; returns SESSION@vNNN.

    The rows pass :mod:`labcal.datasets.sanity` first (against the robot model, including its joint map); a failed
    check is a :class:`~labcal.datasets.sanity.SanityError` naming the fix and the ``--allow`` flag that overrides
    it. The robot's full record (file text included) is stored with the session; ``unit`` (the robot unit's id,
    e.g. the serial number on the controller) as the session metadata's ``"unit"``.
    """
    from labcal.datasets import ImportOptions, import_mapped, import_probe_csv, import_targets_csv, load_targets
    from labcal.datasets.sanity import check_names
    from labcal.tomlschema import input_file_problem

    path = Path(path)
    if not path.exists() or path.is_dir():
        raise UserError(f"{path} is a folder, not a CSV file" if path.is_dir() else f"no such file: {path}")
    why = input_file_problem(path)  # a device (/dev/zero) or a FIFO is named as such, not called missing
    if why is not None:
        raise UserError(f"{path} {why}")
    check_names(allow)  # an unknown --allow name is an error before any reading
    if form not in FORMS:
        raise UserError(f"--form must be 'targets' or 'probe', got {form!r}")
    unit = check_unit_option(unit)
    spec = load(robot)
    ident = (spec.name, spec.hash, spec.model.n)
    recording = ImportOptions(robot=spec, allow=tuple(allow), unit=unit)
    if mapping is not None:
        # A mapping fixes units, frame and form itself; a flag that would be ignored is a user's misunderstanding.
        ignored = [
            f"{flag} {value}"
            for flag, value, default in (
                ("--length-unit", length_unit, "m"),
                ("--angle-unit", angle_unit, "rad"),
                ("--frame", frame, "base"),
                ("--form", form, "targets"),
            )
            if value != default
        ]
        if ignored:
            raise UserError(
                f"{', '.join(ignored)} cannot be combined with --mapping: the mapping file sets units, frame and form "
                f"(keys [targets] unit / [probe] position_unit, joint_unit, frame, form); edit a copy of the mapping"
            )
        targets = load_targets(targets_file) if targets_file else None
        return import_mapped(store, path, mapping, *ident, recording, targets=targets)
    reading = recording.with_changes(length_unit=length_unit, angle_unit=angle_unit, frame=frame)
    if form == "targets":
        if targets_file is None:
            raise UserError("--targets TARGETS.toml is required for --form targets")
        return import_targets_csv(store, path, *ident, load_targets(targets_file), reading)
    if targets_file is not None:
        raise UserError(
            "--targets is not used with --form probe: the probe's pose is measured and three virtual targets 100 mm "
            "apart in the probe frame become the session's targets (a --mapping with [probe] offsets can change them)"
        )
    return import_probe_csv(store, path, *ident, reading)
