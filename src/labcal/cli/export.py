"""`labcal export`: write a stored fit as a compensator file, a URScript function or a calibrated URDF."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import ExportFormat, StoreOption, UnknownDynamics, err, open_store, user_errors

_FORMAT = typer.Option(
    ...,
    "--format",
    case_sensitive=False,
    help="json | npz (the compensator) | urscript (function file for a Script node) | urscript-program (def "
    "program for the script port 30002) | urdf | ur-kinematics (ur_description's calibration YAML).",
)
_GEOMETRY_ONLY = typer.Option(
    False,
    "--geometry-only",
    help="urdf / ur-kinematics of a hybrid or ann fit: write the identified frames alone (refused without "
    "this flag, because the learned term is dropped; its size is printed).",
)
_UNKNOWN_DYNAMICS = typer.Option(
    "zero",
    "--unknown-dynamics",
    case_sensitive=False,
    help="urdf when the robot file gives no joint effort/velocity: zero (default: write 0, with a warning and a "
    "note in the file) or refuse.",
)


@user_errors
def export(
    session: str = typer.Argument(..., help="SESSION or SESSION@vN the fit is stored under."),
    fmt: ExportFormat = _FORMAT,
    out: Path = typer.Option(..., "--out", help="Output file (.json / .npz for the compensator)."),
    geometry_only: bool = _GEOMETRY_ONLY,
    ur_link_names: bool = typer.Option(
        False, "--ur-link-names", help="urdf: ur_description's link and joint names (base_link turned by pi)."
    ),
    unknown_dynamics: UnknownDynamics = _UNKNOWN_DYNAMICS,
    statements_per_sync: int = typer.Option(
        1000, "--statements-per-sync", help="urscript: at most this many statements between two sync() calls."
    ),
    fit_id: str | None = typer.Option(None, "--fit", help="Fit id (default: the newest fit of the version)."),
    force: bool = typer.Option(
        False, "--force", help="Replace an existing --out file, and export a fit that has warnings (recorded)."
    ),
    store: Path | None = StoreOption,
) -> None:
    """Export a fit; prints the written path last.

    Refused before any work: an existing --out file (unless --force), a device, a symbolic link, a folder or a
    FIFO at --out (even with --force: only a regular file is ever replaced), a missing or read-only output folder,
    and a fit with warnings (unless --force; the export then records `forced: true` and the warnings in its
    provenance). The file is written next to --out and moved into place atomically. The export names the arm's
    and the tracker's serial numbers recorded with the session. A urdf or ur-kinematics
    export of a fit with a learned term (hybrid, ann) is refused with the term's size unless --geometry-only.

    Examples:

      labcal export S@v1 --format json --out ur10.json

      labcal export S --fit 20261122-0400-ab12 --format urscript --out labcal_correct.script

      labcal export S --format json --out ur10.json --force     # replace ur10.json / accept the fit's warnings

      labcal export S --format ur-kinematics --out my_robot_calibration.yaml

      labcal export S --format urdf --ur-link-names --geometry-only --out ur10.urdf
    """
    from labcal.cli.common import print_gates
    from labcal.cli.ops.common import split_ref
    from labcal.cli.ops.exporting import export_fit, format_options, stored_warnings
    from labcal.cli.ops.fitting import load_stored_fit

    st = open_store(store, create=False)
    ref = split_ref(session)
    options = format_options(
        fmt,
        geometry_only=geometry_only,
        ur_names=ur_link_names,
        unknown_dynamics=unknown_dynamics,
        statements_per_sync=statements_per_sync,
    )
    path = export_fit(st, ref, fmt, out, fit_id, force=force, options=options, on_warning=err.print)
    if force:
        stored = load_stored_fit(st, ref, fit_id)
        warnings = stored_warnings(stored.meta)
        if warnings:
            print_gates({"warnings": warnings}, footer=False)
            err.print(
                f"fit {stored.fit_id} exported anyway (--force): the export records forced: true and these warnings"
            )
    print(path)
