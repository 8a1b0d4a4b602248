"""`labcal report`: a Markdown report with PNG plots of the fits stored under a version."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, store_of, user_errors


@user_errors
def report(
    session: str = typer.Argument(..., help="SESSION[@vN]."),
    out: Path = typer.Option(..., "--out", help="Output folder (created)."),
    fit_id: list[str] = typer.Option([], "--fit", help="Fit id(s) to include (default: every fit of the version)."),
    store: Path | None = StoreOption,
) -> None:
    """Write report.md and its plots (errors per configuration, training curve, histograms, parameters).

    Example: labcal report S@v1 --out report/
    """
    from labcal.cli.ops import split_ref
    from labcal.reports import write_session_report

    path = write_session_report(store_of(store), split_ref(session), out, fit_ids=fit_id or None)
    print(path)
