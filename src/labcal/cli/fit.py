"""`labcal fit`: fit a calibration method on one or more stored versions and store the fit."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, metrics_table, out, store_of, user_errors


@user_errors
def fit(
    sessions: list[str] = typer.Argument(..., help="SESSION[@vN] …; several sessions of the same robot are pooled."),
    method: str = typer.Option("auto", "--method", help="local-poe | ann | hybrid | auto | nominal"),
    seed: int = typer.Option(0, "--seed", help="Seed of the split and the network initialisation."),
    hidden: int | None = typer.Option(None, "--hidden", help="Hidden nodes of the network (default √(6·inputs))."),
    val_fraction: float = typer.Option(0.5, "--val-fraction", help="Fraction of unlabelled rows used to validate."),
    robot: str | None = typer.Option(None, "--robot", help="Robot model file when the session's is not built in."),
    store: Path | None = StoreOption,
) -> None:
    """Fit a calibration, print its metrics table (mm, degrees) and store it; prints the fit id last.

    Examples:

      labcal fit 20261122-031500-ur10-3f9a --method local-poe

      labcal fit S1@v2 S2 --method hybrid --seed 3 --hidden 12
    """
    from labcal.cli.ops import run_fit, split_ref

    refs = [split_ref(s) for s in sessions]
    outcome = run_fit(
        store_of(store), refs, method, seed=seed, hidden=hidden, val_fraction=val_fraction, robot=robot,
        progress=lambda msg: out.print(f"  {msg}", markup=False),
    )  # fmt: skip
    r = outcome.result
    title = (
        f"{r.chosen} on {', '.join(outcome.refs)} (seed {seed}; rows train {r.n_train}, val {r.n_val}, test {r.n_test})"
    )
    out.print(metrics_table(r.metrics, title))
    out.print(f"stored under {outcome.ref}", markup=False)
    print(outcome.fit_id)
