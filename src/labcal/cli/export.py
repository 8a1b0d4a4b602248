"""`labcal export`: write a stored fit as a compensator file, a URScript function or a calibrated URDF."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, store_of, user_errors


@user_errors
def export(
    session: str = typer.Argument(..., help="SESSION[@vN] the fit is stored under."),
    fmt: str = typer.Option(..., "--format", help="json | npz | urscript | urdf"),
    out: Path = typer.Option(..., "--out", help="Output file (.json / .npz for the compensator)."),
    fit_id: str | None = typer.Option(None, "--fit", help="Fit id (default: the newest fit of the version)."),
    store: Path | None = StoreOption,
) -> None:
    """Export a fit; prints the written path last.

    Examples:

      labcal export S@v1 --format json --out ur10.json

      labcal export S --fit 20261122-0400-ab12 --format urscript --out labcal_correct.script
    """
    from labcal.cli.ops import export_fit, split_ref

    path = export_fit(store_of(store), split_ref(session), fmt, out, fit_id)
    print(path)
