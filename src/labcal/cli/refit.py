"""`labcal refit`: refit many stored sessions with one method and seed, serially or on a Dask cluster."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from labcal.cli.common import StoreOption, err, mm, open_store, out, table, user_errors

if TYPE_CHECKING:
    from rich.table import Table


@user_errors
def refit(
    sessions: list[str] = typer.Argument(
        None, help="Only these SESSION or SESSION@vN … (the options narrow them further)."
    ),
    everything: bool = typer.Option(False, "--all", help="Every session in the store (other options narrow it)."),
    robot: str | None = typer.Option(None, "--robot", help="Only sessions of this robot (the name stored with them)."),
    unit: str | None = typer.Option(
        None, "--unit", help="Only sessions of this unit (session metadata 'unit'; sessions without one never match)."
    ),
    since: str | None = typer.Option(None, "--since", help="Only sessions started at or after DATE (UTC)."),
    every_version: bool = typer.Option(
        False, "--every-version", help="Refit every version of a session, not only its latest."
    ),
    method: str = typer.Option("auto", "--method", help="local-poe | ann | hybrid | auto | nominal"),
    seed: int = typer.Option(0, "--seed", help="Seed of the split and the network initialisation."),
    hidden: int | None = typer.Option(None, "--hidden", help="Hidden nodes of the network (default √(6·inputs))."),
    val_fraction: float = typer.Option(0.0, "--val-fraction", help="As `labcal fit --val-fraction`."),
    robot_file: str | None = typer.Option(
        None, "--robot-file", help="Robot model file for sessions whose model is neither stored nor built in."
    ),
    jobs: int = typer.Option(1, "--jobs", "-j", help="Worker processes of a local Dask cluster (1: in this process)."),
    scheduler: str | None = typer.Option(
        None, "--scheduler", help="Address of a Dask scheduler (tcp://host:8786) to run on instead."
    ),
    store: Path | None = StoreOption,
) -> None:
    """Refit many sessions with one method and seed; print a before/after table; exit 1 if any fit failed.

    Each fit is stored under its version exactly as `labcal fit SESSION@vN --method M --seed S` stores it (the
    same bytes but for the fit id and times). "before" is the version's latest earlier fit, "after" the new one;
    the error is the held-out mean point error (a test/val split's, else cross-validation). A session whose fit
    fails is reported and the others go on. A fit with warnings is stored and listed with its warning codes.
    --jobs N runs N worker processes on this machine (a Dask LocalCluster); with --scheduler the cluster's workers
    need labcal installed and the store at the same path (a shared file system). Exit 0 all fitted, 1 any failed,
    2 bad options, 130 Ctrl-C (every stored fit complete).

    Examples:

      labcal refit --all --method local-poe

      labcal refit --robot ur10 --since 2026-11-01 --method auto --seed 3 --jobs 4

      labcal refit --unit arm-17 --scheduler tcp://10.0.0.5:8786

      labcal refit S1 S2@v2 --method hybrid
    """
    from labcal.cli.ops.common import split_ref
    from labcal.cli.ops.refit import FITTED, Selection, parse_since, run_refit, select_versions

    refs = tuple(split_ref(s) for s in sessions or ())
    selection = Selection(everything, robot, unit, parse_since(since) if since else None, refs, every_version)
    selection.check()
    st = open_store(store, create=False, write=True)
    chosen, skipped = select_versions(st, selection)
    for what, why in skipped:
        err.print(f"left out {what}: {why}")
    if not chosen:
        err.print("no session matches the selection")
        raise typer.Exit(0)

    def progress(row, done, total):
        tail = f"  {row.message}" if row.status != FITTED or row.message else ""
        out.print(f"  [{done}/{total}] {row.ref} {row.status}{tail}")

    report = run_refit(
        st, chosen, method, seed=seed, hidden=hidden, val_fraction=val_fraction, robot_file=robot_file, jobs=jobs,
        scheduler=scheduler, skipped=skipped, progress=progress,
    )  # fmt: skip
    out.print(summary_table(report, f"refit --method {method} --seed {seed} ({report.executor})"))
    fitted = sum(r.status == FITTED for r in report.rows)
    line = f"{fitted} of {len(report.rows)} fitted"
    if report.interrupted:
        err.print(f"interrupted (Ctrl-C): {line}; every stored fit is complete")
    elif report.failed:
        err.print(f"{line}; {len(report.failed)} failed (see the table)")
    else:
        out.print(line)
    raise typer.Exit(report.exit_code)


def summary_table(report, title: str) -> Table:
    """One row per task: the version, before (fit, method, error) and after, the warning codes or the failure."""

    def err_cell(s):
        return "—" if s.error is None else f"{mm(s.error)} ({s.source})"

    rows = [
        (r.ref, r.before.fit_id or "—", r.before.method or "—", err_cell(r.before), r.after.fit_id or "—",
         r.after.method or "—", err_cell(r.after), r.status,
         r.message or ("warnings: " + ", ".join(r.after.warnings) if r.after.warnings else ""))
        for r in report.rows
    ]  # fmt: skip
    head = ("version", "before fit", "method", "error mm", "after fit", "method", "error mm", "status", "notes")
    return table(head, rows, title, right=(3, 6))
