"""`labcal session import`: read a CSV of measurements into a new session."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, store_of, user_errors


@user_errors
def import_(
    file: Path = typer.Argument(..., help="CSV file to import."),
    robot: str = typer.Option(..., "--robot", help="Robot model: built-in name or path."),
    targets: Path | None = typer.Option(None, "--targets", help="Targets TOML (required for --form targets)."),
    mapping: str | None = typer.Option(None, "--mapping", help="Column mapping TOML or shipped name (ipa-ur10)."),
    length_unit: str = typer.Option("m", "--length-unit", help="m | mm"),
    angle_unit: str = typer.Option("rad", "--angle-unit", help="rad | deg"),
    frame: str = typer.Option("base", "--frame", help="base | tracker: frame of the measured points."),
    form: str = typer.Option("targets", "--form", help="targets (t1_x … t3_z) | probe (x y z rx ry rz)."),
    store: Path | None = StoreOption,
) -> None:
    """Import measurements from a CSV into a new session; prints SESSION@vNNN last.

    Example: labcal session import data.csv --robot ur10 --targets t.toml --length-unit mm --angle-unit deg
    """
    from labcal.cli.ops import import_session

    ref = import_session(
        store_of(store), file, robot=robot, targets_file=targets, mapping=mapping, length_unit=length_unit,
        angle_unit=angle_unit, frame=frame, form=form,
    )  # fmt: skip
    print(ref)
