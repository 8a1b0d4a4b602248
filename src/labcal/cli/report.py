"""`labcal report`: a Markdown report with PNG plots of the fits stored under a version."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, open_store, user_errors


@user_errors
def report(
    session: str = typer.Argument(..., help="SESSION or SESSION@vN (default version: the latest)."),
    out: Path = typer.Option(..., "--out", help="Output folder (created)."),
    fit_id: list[str] = typer.Option([], "--fit", help="Fit id(s) to include (default: every fit of the version)."),
    store: Path | None = StoreOption,
) -> None:
    """Write report.md and its plots; prints the report's path last.

    The report starts with every fit's warnings (the ones `labcal export` refuses without --force), then per
    fit: pose and per-target point errors before/after (tables and plots), the training curve, the identified
    parameters (± σ where identifiable on their own, "—" where not, and the identifiable combinations), and the
    stored `labcal evaluate` results. The warnings are also printed on stderr.

    Examples:

      labcal report S@v1 --out report/

      labcal report S --fit 20261122-040000-123456-ab12cd --out report-fit/
    """
    from labcal.cli.common import print_gates
    from labcal.cli.ops.common import load_observations, split_ref
    from labcal.cli.ops.exporting import stored_warnings
    from labcal.reports import write_session_report

    st = open_store(store, create=False)
    ref = split_ref(session)
    # A stored fit already decided whether to pool sessions of different units: the report reads what it fitted.
    path = write_session_report(
        st, ref, out, fit_ids=fit_id or None, load_obs=lambda refs: load_observations(st, refs, pool_units=True)[0]
    )
    for record in st.list_fits(ref):
        if fit_id and record.fit_id not in fit_id:
            continue
        meta = record.metadata
        print_gates({"warnings": stored_warnings(meta), "notes": meta.get("notes")}, what=f"fit {record.fit_id}")
    print(path)
