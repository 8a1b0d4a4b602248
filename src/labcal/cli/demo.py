"""`labcal demo`: simulated session → local POE, the paper's ANN and the hybrid → exports → report, no hardware."""

from __future__ import annotations

import tempfile
from pathlib import Path

import typer

from labcal.cli.common import UserError, deg, mm, open_store, out, table, user_errors

DEMO_TARGETS = 'unit = "mm"\npoints = [[120.0, 0.0, 60.0], [-60.0, 100.0, 60.0], [-60.0, -100.0, 90.0]]\n'
METHODS = ("local-poe", "ann", "hybrid")
MIN_POSES = 12  # 2 per joint: the least the import checks accept and the exports take without --force


@user_errors
def demo(
    out_dir: Path | None = typer.Option(
        None, "--out", help="Folder for the store, exports and report (default: a new temp folder)."
    ),
    poses: int = typer.Option(120, "--poses", help="Simulated configurations to calibrate on (every row is fitted)."),
    held_out: int = typer.Option(60, "--held-out", help="Fresh configurations, recorded apart, that score each fit."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated robot, planner and fits."),
) -> None:
    """A simulated UR10 with geometric and non-geometric errors: record, fit local POE, ANN and hybrid, export, report.

    Example: labcal demo --out /tmp/labcal-demo
    """
    from labcal.cli.ops.evaluating import evaluate_fit
    from labcal.cli.ops.exporting import export_fit
    from labcal.cli.ops.fitting import run_fit
    from labcal.cli.ops.sessions import new_session
    from labcal.reports import write_session_report

    _check_options(out_dir, poses, held_out, seed)
    root = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="labcal-demo-"))
    root.mkdir(parents=True, exist_ok=True)
    store = open_store(root / "sessions", create=True)
    targets = root / "targets.toml"
    targets.write_text(DEMO_TARGETS)
    sessions = {}
    for what, count, plan_seed in (("calibration", poses, seed), ("held-out", held_out, seed + 1000)):
        out.print(f"1/4 recording {count} {what} poses on the sim rig (ur10, geometric + compliance + gear errors)")
        # The same simulated robot (errors seeded by seed) at other planned configurations.
        summary = new_session(
            store, robot="ur10", targets_file=targets, poses=count, seed=plan_seed, sim_seed=seed, sim_errors="default"
        )
        if summary.ref is None:
            raise RuntimeError(f"the simulated {what} session did not produce a version: {summary.reason}")
        sessions[what] = summary.ref
    ref, held = sessions["calibration"], sessions["held-out"]
    fits, rows = {}, []
    for method in METHODS:
        out.print(f"2/4 fitting {method}, scoring it on the held-out poses")
        outcome = run_fit(store, [ref], method, seed=seed)
        fits[method] = outcome.fit_id
        scored = evaluate_fit(store, outcome.fit_id, held).evaluation["metrics"]["all"]
        b, a = scored["before"], scored["after"]
        pb, pa = scored["points"]["before"], scored["points"]["after"]
        rows.append((
            method, outcome.fit_id,
            f"{mm(pb['mean'])} → {mm(pa['mean'])}", f"{mm(pb['max'])} → {mm(pa['max'])}",
            f"{mm(b['pos_mean'])} → {mm(a['pos_mean'])}", f"{deg(b['ori_mean'])} → {deg(a['ori_mean'])}",
        ))  # fmt: skip
    out.print("3/4 exporting (compensator json + URScript of the hybrid, URDF of local POE)")
    exports = root / "exports"
    exports.mkdir(exist_ok=True)
    paths = [
        export_fit(store, ref, "json", exports / "ur10-hybrid.json", fits["hybrid"]),
        export_fit(store, ref, "urscript", exports / "ur10-hybrid.script", fits["hybrid"]),
        export_fit(store, ref, "urdf", exports / "ur10-local-poe.urdf", fits["local-poe"]),
    ]
    out.print("4/4 writing the report")
    report = write_session_report(store, ref, root / "report")
    head = ("method", "fit", "point mean mm", "point max mm", "pos mean mm", "ori mean °")
    out.print(table(head, rows, f"demo: fitted on {ref} (every row), scored on the held-out {held} (before → after)"))
    out.print(f"store:   {store.root}")
    for p in paths:
        out.print(f"export:  {p}")
    out.print(f"report:  {report}")
    print(root)


def _check_options(out_dir: Path | None, poses: int, held_out: int, seed: int) -> None:
    """Everything the demo needs is checked before it records: a bad option found after minutes of work wastes them."""
    from labcal.cli.ops.common import check_seed

    if poses < MIN_POSES:
        raise UserError(f"--poses must be at least {MIN_POSES} (2 per joint, or no fit is exported), got {poses}")
    if held_out < 1:
        raise UserError(f"--held-out must be at least 1, got {held_out}")
    check_seed(seed)
    if out_dir is not None and out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        what = "is not a folder" if not out_dir.is_dir() else "is not empty (a demo writes a new store there)"
        raise UserError(f"--out {out_dir} {what}: name a new or empty folder")
