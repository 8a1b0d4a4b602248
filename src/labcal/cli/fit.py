"""`labcal fit`: fit a calibration method on one or more stored versions and store the fit."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import (
    Method,
    StoreOption,
    complete_robot,
    err,
    metrics_doc,
    open_store,
    out,
    print_gates,
    print_json,
    print_metrics,
    user_errors,
)


@user_errors
def fit(
    sessions: list[str] = typer.Argument(
        ..., help="SESSION or SESSION@vN …; several sessions of the same robot are pooled."
    ),
    method: Method = typer.Option(
        "auto", "--method", help="local-poe | ann | hybrid | auto | nominal", case_sensitive=False
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the split and the network initialisation."),
    hidden: int | None = typer.Option(None, "--hidden", help="Hidden nodes of the network (default √(6·inputs))."),
    val_fraction: float = typer.Option(
        0.0,
        "--val-fraction",
        help="Fraction of unlabelled rows held out as a fixed validation split that is only scored (default 0: every "
        "row is fitted; learned stages are chosen by K-fold cross-validation).",
    ),
    robot: str | None = typer.Option(
        None, "--robot", help="Robot model file when the session's is not built in.", autocompletion=complete_robot
    ),
    pool_units: bool = typer.Option(
        False,
        "--pool-units",
        help="Fit sessions of different robot units as one (by default fit refuses: one unit, one calibration).",
    ),
    as_json: bool = typer.Option(
        False,
        "--json",
        help="Print the fit as one JSON document on stdout (schema: docs/cli-json.md); progress "
        "and warnings go to stderr.",
    ),
    store: Path | None = StoreOption,
) -> None:
    """Fit a calibration, print its metrics table (mm, degrees) and store it; prints the fit id last.

    The table shows the tool-pose error and, beside it, the distance error of every measured target point (a
    targets file that does not match the data shows up there, not in the pose error). Every warning of the fit
    (rank deficiency, over-fitting, rows dropped, worse than the registered nominal, large corrections, point
    residuals …) is printed on stderr as `WARNING [code] …` and stored with the fit; `labcal export` refuses a
    fit with warnings unless --force.

    Examples:

      labcal fit 20261122-031500-ur10-3f9a --method local-poe

      labcal fit S1@v2 S2 --method hybrid --seed 3 --hidden 12

      labcal fit S --method auto --val-fraction 0.3     # also score a fixed 30 % hold-out

      labcal fit S --method hybrid --json | jq .metrics.all.after.pos_mean_m
    """
    from labcal.cli.ops.common import split_ref
    from labcal.cli.ops.fitting import run_fit

    refs = [split_ref(s) for s in sessions]
    say = err if as_json else out  # with --json stdout holds the document alone
    outcome = run_fit(
        open_store(store, create=False, write=True), refs, method, seed=seed, hidden=hidden,
        val_fraction=val_fraction, robot=robot, pool_units=pool_units,
        progress=lambda msg: say.print(f"  {msg}"),
    )  # fmt: skip
    r = outcome.result
    if as_json:
        print_gates(outcome.gates, what=f"fit {outcome.fit_id}")
        print_json("labcal.fit/1", fit_doc(outcome, val_fraction=val_fraction, hidden=hidden))
        return
    title = (
        f"{r.chosen} on {', '.join(outcome.refs)} (seed {seed}; rows train {r.n_train}, val {r.n_val}, test {r.n_test})"
    )
    print_metrics(outcome.metrics or r.metrics, title)
    cv = cv_line((outcome.gates or {}).get("cv"))
    if cv is not None:
        out.print(cv)
    print_gates(outcome.gates, what=f"fit {outcome.fit_id}")
    out.print(f"stored under {outcome.ref}")
    print(outcome.fit_id)


def cv_line(cv) -> str | None:
    """The cross-validation summary: mean ± std of the fold errors per method (mm) and the method chosen; None
    without fold errors."""
    if not (isinstance(cv, dict) and cv.get("errors")):
        return None
    parts = []
    for name, errs in cv["errors"].items():
        e = [x for x in errs or [] if x is not None]
        if e:
            m = sum(e) / len(e)
            sd = (sum((x - m) ** 2 for x in e) / len(e)) ** 0.5
            parts.append(f"{name} {m * 1e3:.4f} ± {sd * 1e3:.4f} mm")
        else:
            parts.append(f"{name} (no fold scored)")
    head = f"cross-validation ({cv.get('folds')} folds, {cv.get('scheme')})"
    return f"{head}: {', '.join(parts)}; chose {cv.get('chosen')}"


_CV_KEYS = {"errors": "fold_errors_m", "mean": "mean_m", "std": "std_m"}  # per method, metres


def fit_doc(outcome, *, val_fraction: float, hidden: int | None) -> dict:
    """`labcal fit --json` (labcal.fit/1, docs/cli-json.md): what run_fit returned, units in the key names."""
    r = outcome.result
    gates = outcome.gates or {}
    cv = gates.get("cv") if isinstance(gates.get("cv"), dict) else r.cv
    if isinstance(cv, dict):
        cv = {_CV_KEYS.get(k, k): v for k, v in cv.items()}
    return {
        "fit_id": outcome.fit_id,
        "stored_under": outcome.ref,
        "inputs": list(outcome.refs),
        "method": r.method,
        "chosen": r.chosen,
        "seed": r.seed,
        "val_fraction": val_fraction,
        "hidden": hidden,
        "rows": {"train": r.n_train, "val": r.n_val, "test": r.n_test},
        "metrics": metrics_doc(outcome.metrics or r.metrics),
        "warnings": [{"code": w.get("code"), "message": w.get("message")} for w in gates.get("warnings") or []],
        "notes": [str(n) for n in gates.get("notes") or []],
        "cv": cv,
        "observability": dict(r.observability or {}),
        "fit_time_s": dict(r.fit_seconds or {}),
    }
