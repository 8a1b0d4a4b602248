"""`labcal session import`: read a CSV of measurements into a new session, refusing data that fail a sanity check."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, err, open_store, user_errors
from labcal.datasets.checks import CHECKS

_CHECK_LIST = "\n\n".join(f"  {name}: {what}" for name, what in CHECKS.items())

_HELP = f"""Import measurements from a CSV into a new session; prints SESSION@vNNN last.

The targets form has the columns q1..qn and t1_x … tm_z for the m points of the targets file; leave a target's three
cells empty in a row where it was not seen (a row needs at least one target).

Before anything is written the rows are checked against the targets file and the robot model. A failed check
stops the import (exit 2) with the bad rows and the likely fix; only --allow CHECK, naming the check, lets such
data through, and the override is recorded in the version's provenance. The checks:

{_CHECK_LIST}

Examples:

  labcal session import data.csv --robot ur10 --targets targets.toml

  labcal session import data.csv --robot ur10 --targets targets.toml --length-unit mm --angle-unit deg

  labcal session import tracker.csv --robot my_arm.toml --targets targets.toml --frame tracker

  labcal session import probe.csv --robot ur10 --form probe --length-unit mm --frame tracker

  labcal session import measurements_random_poses.csv --robot ur10 --mapping ipa-ur10

  labcal session import repeats.csv --robot ur10 --targets targets.toml --allow duplicates --allow nominal

  labcal session import data.csv --robot ur10 --targets targets.toml --store /data/sessions

  labcal session import data.csv --robot ur10 --targets targets.toml --unit 2018550001

--unit records which arm the data come from (its serial number, or your own id): `session list --unit` finds the
sessions of one arm, and `fit` refuses to pool sessions of different units unless given --pool-units.
"""


@user_errors
def import_(
    file: Path = typer.Argument(..., help="CSV file to import."),
    robot: str = typer.Option(..., "--robot", help="Robot model: built-in name or robot file (TOML / URDF)."),
    targets: Path | None = typer.Option(
        None, "--targets", help="Targets TOML, 1 or more points (required for --form targets)."
    ),
    mapping: str | None = typer.Option(None, "--mapping", help="Column mapping TOML or shipped name (ipa-ur10)."),
    length_unit: str = typer.Option("m", "--length-unit", help="Unit of the measured lengths: m | mm | in."),
    angle_unit: str = typer.Option("rad", "--angle-unit", help="Unit of the joint angles: rad | deg."),
    frame: str = typer.Option("base", "--frame", help="base | tracker: frame of the measured points."),
    form: str = typer.Option(
        "targets", "--form", help="targets (t1_x … tm_z, an empty cell = not seen) | probe (x y z rx ry rz)."
    ),
    allow: list[str] = typer.Option(
        [], "--allow", help=f"Let data through a failed check (repeatable): {', '.join(CHECKS)}.", show_default=False
    ),
    unit: str | None = typer.Option(
        None, "--unit", help="Id of the robot unit the data come from (e.g. the controller's serial number)."
    ),
    store: Path | None = StoreOption,
) -> None:
    from labcal.cli.ops.imports import import_session
    from labcal.datasets import load_version

    st = open_store(store, create=True)
    ref = import_session(
        st, file, robot=robot, targets_file=targets, mapping=mapping, length_unit=length_unit,
        angle_unit=angle_unit, frame=frame, form=form, allow=allow, unit=unit,
    )  # fmt: skip
    checks = load_version(st, ref).manifest.get("provenance", {}).get("import", {}).get("checks", {})
    for note in checks.get("notes", []):
        err.print(f"note: {note}")
    for f in checks.get("allowed", []):
        err.print(f"warning: check {f['check']} failed and was allowed (--allow {f['check']}): {f['message']}")
    print(ref)


import_.__doc__ = _HELP
