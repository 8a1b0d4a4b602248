"""`labcal export`: write a stored fit as a compensator file, a URScript function or a calibrated URDF."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, err, store_of, user_errors


@user_errors
def export(
    session: str = typer.Argument(..., help="SESSION or SESSION@vN the fit is stored under."),
    fmt: str = typer.Option(..., "--format", help="json | npz | urscript | urdf"),
    out: Path = typer.Option(..., "--out", help="Output file (.json / .npz for the compensator)."),
    fit_id: str | None = typer.Option(None, "--fit", help="Fit id (default: the newest fit of the version)."),
    force: bool = typer.Option(
        False, "--force", help="Replace an existing --out file, and export a fit that has warnings (recorded)."
    ),
    store: Path | None = StoreOption,
) -> None:
    """Export a fit; prints the written path last.

    Refused before any work: an existing --out file (unless --force), a missing or read-only output folder, and
    a fit with warnings (unless --force; the export then records `forced: true` and the warnings in its
    provenance). The file is written next to --out and moved into place atomically.

    Examples:

      labcal export S@v1 --format json --out ur10.json

      labcal export S --fit 20261122-0400-ab12 --format urscript --out labcal_correct.script

      labcal export S --format json --out ur10.json --force     # replace ur10.json / accept the fit's warnings
    """
    from labcal.cli.common import print_gates
    from labcal.cli.ops import export_fit, split_ref
    from labcal.cli.ops.exporting import stored_warnings
    from labcal.cli.ops.fitting import load_stored_fit

    st = store_of(store)
    path = export_fit(st, split_ref(session), fmt, out, fit_id, force=force)
    if force:
        stored = load_stored_fit(st, split_ref(session), fit_id)
        warnings = stored_warnings(stored.meta)
        if warnings:
            print_gates({"warnings": warnings}, footer=False)
            err.print(
                f"fit {stored.fit_id} exported anyway (--force): the export records forced: true and these warnings",
                markup=False,
            )
    print(path)
