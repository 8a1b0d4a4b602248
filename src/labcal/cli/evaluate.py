"""`labcal evaluate`: score a held-out CSV file or stored session with a stored fit."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import StoreOption, open_store, out, print_gates, print_json, print_metrics, user_errors


@user_errors
def evaluate(
    fit_id: str = typer.Argument(..., help="Fit id (as printed by `labcal fit`)."),
    data: str = typer.Option(
        ..., "--data", help="Held-out data: a CSV file (imported first) or SESSION or SESSION@vN (stored)."
    ),
    robot: str | None = typer.Option(None, "--robot", help="Robot model for a file (default: the fit's model)."),
    targets: Path | None = typer.Option(None, "--targets", help="Targets TOML of a file (--form targets)."),
    mapping: str | None = typer.Option(None, "--mapping", help="Column mapping TOML or shipped name of a file."),
    length_unit: str = typer.Option("m", "--length-unit", help="Unit of the file's lengths: m | mm | in (a file)."),
    angle_unit: str = typer.Option("rad", "--angle-unit", help="rad | deg (a file)"),
    frame: str = typer.Option("base", "--frame", help="base | tracker: frame of a file's points."),
    form: str = typer.Option("targets", "--form", help="targets | probe (a file)"),
    allow: list[str] = typer.Option([], "--allow", help="Override a failed import sanity check (as session import)."),
    as_json: bool = typer.Option(False, "--json", help="Print the evaluation as JSON (only) on stdout."),
    store: Path | None = StoreOption,
) -> None:
    """Score held-out data with a stored fit: per-target point and pose errors before (registered nominal) and
    after, and what the data let it claim about orientation (the point errors lead when fewer than three targets
    are seen in some rows); the evaluation is stored under the fit. Prints the evaluation id last (or JSON with --json).

    A FILE goes through `labcal session import` first (same options, same sanity checks and --allow overrides) and
    becomes a new session, so the evaluated data are stored and traceable. Nothing of the calibration is refitted
    on the evaluation data; for tracker-frame data only the 6-DOF base pose T_tracker_base is estimated on them
    (the tracker stands elsewhere in every session), for the nominal and the calibrated robot separately.

    Examples:

      labcal evaluate 20261122-040000-123456-ab12cd --data S2@v1

      labcal evaluate FIT --data heldout.csv --targets t.toml --length-unit mm --angle-unit deg --frame tracker

      labcal evaluate FIT --data S2 --json > evaluation.json
    """
    from labcal.cli.ops.evaluating import evaluate_fit

    options = {
        "targets_file": targets, "mapping": mapping, "length_unit": length_unit, "angle_unit": angle_unit,
        "frame": frame, "form": form, "allow": list(allow),
    }  # fmt: skip
    outcome = evaluate_fit(open_store(store, create=False), fit_id, data, robot=robot, import_options=options)
    ev = outcome.evaluation
    if as_json:
        print_json("labcal.evaluate/1", _counts_as_integers({**ev, "stored_at": str(outcome.path)}))
        return
    d = ev["data"]
    if outcome.imported:
        out.print(f"imported {data} as {outcome.data_ref}")
    title = (
        f"fit {ev['fit_id']} ({ev['method']}, fitted on {', '.join(ev['fit_inputs'])}) on {d['ref']}: "
        f"{d['rows']} rows, {d['frame']} frame"
    )
    # Fewer than three targets seen in some rows: the point errors are what was measured, so they lead.
    lead = "primary figures: the per-target point errors (pose errors only over rows that fix a pose)"
    print_metrics(ev["metrics"], title, points_lead=lead if ev.get("primary") == "points" else None)
    _print_notes(ev)
    print_gates({"warnings": ev.get("warnings")}, footer=False)
    out.print(f"stored at {outcome.path}")
    print(ev["evaluation_id"])


def _print_notes(ev: dict) -> None:
    """What the evaluation lets the numbers claim: orientation, what was fitted on the data, overlap with the fit's
    own data, rows outside the calibrated ranges."""
    d = ev["data"]
    claim = (ev.get("observability") or {}).get("claim")
    if claim:
        out.print(f"orientation: {claim}")
        for words in (ev.get("observability") or {}).get("unobservable") or []:
            out.print(f"  not determined by these data: {words}")
    out.print(f"fitted on the evaluation data: {ev['registration']['fitted']}")
    if ev["overlap_with_fit"] and d["ref"] in ev["fit_inputs"]:
        out.print(f"note: {d['ref']} is one of the fit's own inputs: this is not a held-out score")
    elif ev["overlap_with_fit"]:
        out.print(
            f"note: {ev['overlap_rows']} of {d['rows']} rows are configurations the fit was fitted on (a later version "
            "or a re-import of its data?): this is not a held-out score"
        )
    if ev["outside_calibrated_ranges"]:
        out.print(
            f"note: {ev['outside_calibrated_ranges']} of {d['rows']} rows are outside the fit's calibrated joint "
            "ranges (the model extrapolates there; the compensator refuses them without extrapolate)"
        )


def _counts_as_integers(doc):
    """The stored metrics keep their counts as floats (the stats are one float table); JSON says integers."""
    if isinstance(doc, dict):
        return {k: int(v) if k == "count" and v is not None else _counts_as_integers(v) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_counts_as_integers(v) for v in doc]
    return doc
