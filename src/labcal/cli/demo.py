"""`labcal demo`: simulated session → every method → exports → report, no hardware."""

from __future__ import annotations

import tempfile
from pathlib import Path

import typer
from rich.table import Table

from labcal.cli.common import deg, mm, out, user_errors

DEMO_TARGETS = 'unit = "mm"\npoints = [[120.0, 0.0, 60.0], [-60.0, 100.0, 60.0], [-60.0, -100.0, 90.0]]\n'
METHODS = ("local-poe", "ann", "hybrid")


@user_errors
def demo(
    out_dir: Path | None = typer.Option(
        None, "--out", help="Folder for the store, exports and report (default: a new temp folder)."
    ),
    poses: int = typer.Option(120, "--poses", help="Simulated configurations (half train, half validation)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated robot, planner and fits."),
) -> None:
    """A simulated UR10 with geometric and non-geometric errors: record, fit every method, export, report.

    Example: labcal demo --out /tmp/labcal-demo
    """
    from labcal.cli.ops import export_fit, new_session, open_store, run_fit
    from labcal.reports import write_session_report

    root = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="labcal-demo-"))
    root.mkdir(parents=True, exist_ok=True)
    store = open_store(root / "sessions")
    targets = root / "targets.toml"
    targets.write_text(DEMO_TARGETS)
    out.print(f"1/4 recording {poses} poses on the sim rig (ur10, geometric + compliance + gear errors)", markup=False)
    summary = new_session(store, robot="ur10", targets_file=targets, poses=poses, seed=seed, sim_errors="default")
    ref = summary.ref
    if ref is None:
        raise RuntimeError(f"the simulated session did not produce a version: {summary.reason}")
    table = Table(title=f"demo: {ref} — validation rows, after calibration (before → after)", title_justify="left")
    for col in ("method", "fit", "pos mean mm", "pos max mm", "ori mean °", "ori max °"):
        table.add_column(col)
    fits = {}
    for method in METHODS:
        out.print(f"2/4 fitting {method}", markup=False)
        outcome = run_fit(store, [ref], method, seed=seed)
        fits[method] = outcome.fit_id
        val = outcome.result.metrics.get("val") or outcome.result.metrics["all"]
        b, a = val["before"], val["after"]
        table.add_row(
            method, outcome.fit_id,
            f"{mm(b['pos_mean'])} → {mm(a['pos_mean'])}", f"{mm(b['pos_max'])} → {mm(a['pos_max'])}",
            f"{deg(b['ori_mean'])} → {deg(a['ori_mean'])}", f"{deg(b['ori_max'])} → {deg(a['ori_max'])}",
        )  # fmt: skip
    out.print("3/4 exporting (compensator json + URScript of the hybrid, URDF of local POE)", markup=False)
    exports = root / "exports"
    exports.mkdir(exist_ok=True)
    paths = [
        export_fit(store, ref, "json", exports / "ur10-hybrid.json", fits["hybrid"]),
        export_fit(store, ref, "urscript", exports / "ur10-hybrid.script", fits["hybrid"]),
        export_fit(store, ref, "urdf", exports / "ur10-local-poe.urdf", fits["local-poe"]),
    ]
    out.print("4/4 writing the report", markup=False)
    report = write_session_report(store, ref, root / "report")
    out.print(table)
    out.print(f"store:   {store.root}", markup=False)
    for p in paths:
        out.print(f"export:  {p}", markup=False)
    out.print(f"report:  {report}", markup=False)
    print(root)
