"""`labcal session …`: record, list, show, resume, verify and import sessions."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import typer

from labcal.cli.common import (
    TERMINATED_BY,
    VERIFY_FAILED,
    Planner,
    RobotDriver,
    SimErrors,
    StoreOption,
    TrackerDriver,
    complete_robot,
    err,
    open_store,
    out,
    print_json,
    session_unit,
    table,
    user_errors,
)
from labcal.cli.session_import import import_

JsonOption = typer.Option(False, "--json", help="Print one JSON document on stdout (schema: docs/cli-json.md).")

# Exit codes of a recording run: success 0; failed / paused (nothing or not everything recorded) 1; Ctrl-C 130,
# as a shell reports a command ended by SIGINT (SIGTERM 143, SIGHUP 129). User errors stay 2 (user_errors).
_EXIT = {"success": 0, "failed": 1, "paused": 1, "aborted": 130}
ALLOW_HELP = (
    "Override a record-time sanity check by name (repeatable): "
    "target-distances, target-outliers, joint-limits, joint-span, nominal, reach, duplicates, few-poses. "
    "Recorded with the session."
)


def _end_run(summary, line: str, resume_flags: list[str] | None = None) -> None:
    """Print the outcome line, then the version ref (last line of stdout) if one exists; exit with the run's code.

    A run that did not finish (paused, failed, aborted) with poses left names its session and the command that
    continues it (``resume_flags``: --store and the like, passed on as given)."""
    out.print(line)
    code = _EXIT.get(summary.exit_status, 1)
    if summary.exit_status == "aborted" and TERMINATED_BY:  # SIGTERM / SIGHUP, not Ctrl-C: 128 + its number
        code = 128 + TERMINATED_BY[0]
    if code and summary.exit_status != "aborted":
        err.print(f"error: the run ended {summary.exit_status}: {summary.reason}")
    if code and summary.remaining:
        import shlex

        command = shlex.join(["labcal", "session", "resume", summary.session_id, *(resume_flags or [])])
        err.print(f"session {summary.session_id}: {summary.remaining} pose(s) left; continue with: {command}")
    if summary.ref is not None:
        print(summary.ref)
    if code or summary.ref is None:
        raise typer.Exit(code or 1)


def _resume_flags(store: Path | None, robot_host: str | None = None, tracker_port: str | None = None) -> list[str]:
    """The flags a resume needs to find this store and these devices again, as the user gave them."""
    flags = [] if store is None else ["--store", str(store)]
    flags += ["--robot-host", robot_host] if robot_host else []
    return flags + (["--tracker-port", tracker_port] if tracker_port else [])


ROBOT_HOST_HELP = "Address of the UR controller: replaces the robot profile's `host` (e.g. a fake controller)."
TRACKER_PORT_HELP = (
    "Serial port (pyserial URL) of the tracker: replaces the tracker profile's `[port] url` (e.g. a fake's pty)."
)

app = typer.Typer(
    help="Record, inspect and import measurement sessions.\n\n"
    "Examples:\n\n"
    "  labcal session new --robot ur10 --robot-driver sim --tracker-driver sim --targets targets.toml --poses 60\n\n"
    "  labcal session list\n\n"
    "  labcal session import data.csv --robot ur10 --targets targets.toml --length-unit mm --angle-unit deg\n\n"
    "  labcal session seal SESSION --valid-prefix",
    no_args_is_help=True,
)


@contextmanager
def _run_progress():
    """A rich progress bar on stderr (pose k/N, ETA, last status and triangle residual); stdout stays for ids.
    Yields the runner's progress callback.

    Rejections and retries are also printed as lines, so they stay visible after the bar moves on.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(
        TextColumn("recording"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("poses  ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[status]}"),
        console=Console(stderr=True, markup=False),  # messages print as they are
        transient=False,
    )
    task = None

    def show(p) -> None:
        nonlocal task
        if task is None:  # started on the first event: argument errors before it print nothing extra
            bar.start()
            task = bar.add_task("poses", total=p.total, completed=p.done, status="")
        residual = "" if p.residual is None else f", target distance residual {p.residual * 1e3:.3f} mm"
        where = "" if p.pose is None else f"pose {p.pose}: "
        bar.update(task, completed=p.done, total=p.total, status=f"{where}{p.status}{residual}")
        if p.status in ("retry", "rejected", "paused", "aborted", "failed"):
            bar.console.print(f"  {where}{p.status} {p.message}")

    try:
        yield show
    finally:
        if task is not None:
            bar.stop()


_TARGETS = typer.Option(
    ..., "--targets", help="Targets TOML: unit and the points in the tool frame (1 or more; one for a single SMR)."
)
_SIM_SEED = typer.Option(
    None, "--sim-seed", help="Seed of the simulated robot's errors (default --seed): measure the same robot again."
)
_SIM_DROPOUT = typer.Option(
    0.0, "--sim-dropout", help="Sim tracker: probability (0 to <1) that a target is not seen in a pose."
)
_UNIT = typer.Option(
    None,
    "--unit",
    help="Id of the robot unit (recorded as the session's unit; default: the controller's serial number, "
    "sim-<seed> on the sim rig).",
)
_MAX_FAILED_POSES = typer.Option(
    5,
    "--max-failed-poses",
    help="Stop the run (failed, resumable) after this many consecutive rejected poses (0: never); a pose the "
    "robot refuses to move to does not count.",
)


@app.command("new")
@user_errors
def new(
    robot: str = typer.Option(
        ..., "--robot", help="Robot model: built-in name or TOML/URDF path.", autocompletion=complete_robot
    ),
    targets: Path = _TARGETS,
    poses: int = typer.Option(..., "--poses", help="Number of configurations to measure."),
    robot_driver: RobotDriver = typer.Option("sim", "--robot-driver", help="sim | ur", case_sensitive=False),
    tracker_driver: TrackerDriver = typer.Option("sim", "--tracker-driver", help="sim | serial", case_sensitive=False),
    profile: str | None = typer.Option(None, "--profile", help="Robot driver profile, e.g. drivers/ur10-lab.toml."),
    tracker_profile: str | None = typer.Option(None, "--tracker-profile", help="Tracker profile TOML (serial)."),
    planner: Planner = typer.Option("random", "--planner", help="random | optimal", case_sensitive=False),
    samples: int = typer.Option(2000, "--samples", help="Candidate pool size of the optimal planner."),
    seed: int = typer.Option(0, "--seed", help="Seed of the planner and the simulator."),
    sim_errors: SimErrors = typer.Option(
        "default", "--sim-errors", help="Sim robot errors: paper | default | none.", case_sensitive=False
    ),
    sim_seed: int | None = _SIM_SEED,
    sim_dropout: float = _SIM_DROPOUT,
    allow: list[str] = typer.Option([], "--allow", help=ALLOW_HELP),
    unit: str | None = _UNIT,
    robot_host: str | None = typer.Option(None, "--robot-host", help=ROBOT_HOST_HELP),
    tracker_port: str | None = typer.Option(None, "--tracker-port", help=TRACKER_PORT_HELP),
    max_failed_poses: int = _MAX_FAILED_POSES,
    store: Path | None = StoreOption,
) -> None:
    """Plan and record a new session; prints the new SESSION@vNNN last.

    The targets file gives the number of targets (1 or more). A target the tracker does not see in a pose is
    recorded as not seen (an empty cell); a pose where it sees none is retried, then rejected.

    Once 2n poses are valid, the data pass the same sanity checks as an import (target distances, joint limits,
    nominal model, reach): a failure stops the run before the next motion.

    Exit 0 on success, 1 when the run failed (e.g. no valid measurement) or paused, 130 after Ctrl-C, 2 for a bad
    argument or an unusable store (checked before anything is planned or moved).

    Examples:

      labcal session new --robot ur10 --robot-driver sim --tracker-driver sim --targets t.toml --poses 60

      labcal session new --robot ur10 --targets t.toml --poses 40 --seed 7 --sim-seed 0   # same sim robot, new poses

      labcal session new --robot ur10 --targets one-smr.toml --poses 120 --sim-dropout 0.1

      labcal session new --robot ur10 --targets t.toml --poses 40 --robot-driver ur --tracker-driver serial
        --profile drivers/ur10-lab.toml --tracker-profile drivers/ndi-polaris.toml --robot-host 127.0.0.5
        --tracker-port /dev/pts/3   # rehearsal: the fakes of `python -m labcal_fakes.rehearse`
    """
    from labcal.cli.ops.sessions import SessionRequest, new_session

    request = SessionRequest(
        robot=robot, targets_file=targets, poses=poses, robot_driver=robot_driver, tracker_driver=tracker_driver,
        profile=profile, tracker_profile=tracker_profile, planner=planner, samples=samples, seed=seed,
        sim_errors=sim_errors, sim_seed=sim_seed, sim_dropout=sim_dropout, allow=tuple(allow), unit=unit,
        robot_host=robot_host, tracker_port=tracker_port, max_failed_poses=max_failed_poses,
    )  # fmt: skip
    request.check()
    request.inputs()  # a typo in the robot or targets file fails here, before the store is created
    st = open_store(store, create=True)
    with _run_progress() as progress:
        summary = new_session(st, request, progress=progress)
    _end_run(
        summary,
        f"{summary.exit_status}: {summary.valid} valid, {summary.rejected} rejected, {summary.remaining} remaining",
        _resume_flags(store, robot_host, tracker_port),
    )


@app.command("list")
@user_errors
def list_(
    unit: str | None = typer.Option(
        None, "--unit", help="Only the sessions of this robot unit (the unit id recorded with the session)."
    ),
    as_json: bool = JsonOption,
    store: Path | None = StoreOption,
) -> None:
    """List the sessions of the store (oldest first).

    A store that does not exist is an error (exit 2): only `session new` and `session import` create one.

    Examples:

      labcal session list --store sessions/

      labcal session list --unit UR10-2019-0417 --json
    """
    st = open_store(store, create=False)
    rows = []
    for info in st.list_sessions():
        # The table needs no metadata; reading it again costs a second pass over each journal.
        meta = _meta(st, info.session_id) if unit is not None or as_json else {}
        if unit is not None and session_unit(meta) != unit:
            continue
        rows.append((info, meta))
    foreign = st.foreign_entries()  # copies, OS and editor files: listed, skipped, never fatal
    if as_json:
        print_json("labcal.session-list/1", {"store": str(st.root), "sessions": [_session_doc(i, m) for i, m in rows],
                                             "foreign": [{"name": n, "why": w} for n, w in foreign]})  # fmt: skip
        return
    from labcal.names import printable  # a stored name may predate the name checks: no raw escapes

    cells = [
        (info.session_id, printable(info.robot.get("name")), info.frame, info.status,
         ", ".join(v.name for v in info.versions) or "—", str(info.rows))
        for info, _ in rows
    ]  # fmt: skip
    out.print(table(("session", "robot", "frame", "status", "versions", "rows"), cells, f"sessions in {st.root}"))
    for name, why in foreign:
        out.print(f"foreign: {name!r} skipped ({why})")


def _meta(st, session_id: str) -> dict:
    """The session's metadata block, or {} for a damaged session (list and show say what they can; verify says why)."""
    try:
        return st.session_meta(session_id)
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def _session_doc(info, meta: dict) -> dict:
    """A session as JSON (labcal.session-list/1 and labcal.session-show/1; docs/cli-json.md)."""
    targets = meta.get("targets")
    return {
        "session": info.session_id,
        "robot": {
            **{k: info.robot.get(k) for k in ("name", "hash", "n_joints")},
            "file_stored": bool(info.robot.get("text")),
        },
        "unit": session_unit(meta),
        "identity": {
            "robot": (meta.get("robot_driver") or {}).get("identity"),
            "tracker": (meta.get("tracker") or {}).get("identity"),
        },
        "frame": info.frame,
        "n_targets": len(targets) if isinstance(targets, list) else None,
        "status": info.status,
        "measurements": info.measurements,
        "rows": info.rows,
        "versions": [_version_doc(v) for v in info.versions],
        "warnings": list(info.warnings),
    }


def _version_doc(v) -> dict:
    return {"version": v.name, **{k: getattr(v, k) for k in ("rows", "created", "source", "parent", "fits")}}


@app.command("show")
@user_errors
def show(
    session: str = typer.Argument(..., help="Session id."), as_json: bool = JsonOption, store: Path | None = StoreOption
) -> None:
    """Show a session: robot, frame, status, versions and their fits.

    Examples:

      labcal session show 20261122-031500-ur10-3f9a

      labcal session show 20261122-031500-ur10-3f9a --json
    """
    st = open_store(store, create=False)
    info = st.show(session)
    doc = _session_doc(info, _meta(st, session))
    if as_json:
        print_json("labcal.session-show/1", {"store": str(st.root), **doc})
        return
    stored = "robot file stored" if info.robot.get("text") else "robot file NOT stored (needs the built-in or --robot)"
    n_targets = doc["n_targets"]
    targets = "" if n_targets is None else f", {n_targets} target{'s' if n_targets != 1 else ''}"
    unit = "" if doc["unit"] is None else f", unit {doc['unit']}"
    from labcal.names import printable  # a stored name may predate the name checks: no raw escapes

    name = printable(info.robot.get("name"))
    out.print(f"session {info.session_id}: robot {name} ({info.robot.get('hash', '')[:12]}…, "
              f"{stored}){unit}, frame {info.frame}{targets}, status {info.status}")  # fmt: skip
    cells = [(v.name, str(v.rows), v.created, v.source, v.parent or "—", str(v.fits)) for v in info.versions]
    out.print(table(("version", "rows", "created", "source", "parent", "fits"), cells))
    for w in info.warnings:
        out.print(f"warning: {w}")


@app.command("resume")
@user_errors
def resume(
    session: str = typer.Argument(..., help="Session id."),
    robot: str | None = typer.Option(
        None, "--robot", help="Override the robot model stored with the session (must have the same hash)."
    ),
    allow: list[str] = typer.Option([], "--allow", help=ALLOW_HELP),
    profile: str | None = typer.Option(
        None, "--profile", help="Robot driver profile (hardware sessions; default: the one the session recorded)."
    ),
    tracker_profile: str | None = typer.Option(
        None, "--tracker-profile", help="Tracker profile (hardware sessions; default: the one the session recorded)."
    ),
    robot_host: str | None = typer.Option(
        None, "--robot-host", help=ROBOT_HOST_HELP + " Default: the host the session was started with."
    ),
    tracker_port: str | None = typer.Option(
        None, "--tracker-port", help=TRACKER_PORT_HELP + " Default: the port the session was started with."
    ),
    store: Path | None = StoreOption,
) -> None:
    """Continue an interrupted or paused session at its first unmeasured pose; prints the new version last.

    A sim session resumes on its simulated robot; a hardware session (paused by a protective stop, say) on the UR
    and tracker of the profiles it recorded, after the stop is cleared on the pendant. Before anything moves: the
    journal is checked (a corrupt line stops here: seal the valid prefix with `labcal session seal SESSION
    --valid-prefix`), and the arm must be the one recorded (serial number) and out of its protective stop. The
    robot model is the one stored with the session.

    Examples:

      labcal session resume 20261122-031500-ur10-3f9a

      labcal session resume S --profile drivers/ur10-lab.toml --tracker-profile drivers/ndi-polaris.toml   # files moved
    """
    from labcal.cli.ops.sessions import resume_session

    st = open_store(store, create=False, write=True)
    with _run_progress() as progress:
        summary = resume_session(
            st,
            session,
            robot=robot,
            progress=progress,
            allow=tuple(allow),
            profile=profile,
            tracker_profile=tracker_profile,
            robot_host=robot_host,
            tracker_port=tracker_port,
        )
    _end_run(
        summary, f"{summary.exit_status}: {summary.reason or 'done'}", _resume_flags(store, robot_host, tracker_port)
    )


@app.command("seal")
@user_errors
def seal(
    session: str = typer.Argument(..., help="Session id."),
    valid_prefix: bool = typer.Option(
        False, "--valid-prefix", help="If the journal has a corrupt line, seal the measurements before it."
    ),
    store: Path | None = StoreOption,
) -> None:
    """Seal a session's journal into a new version (the valid measurements not yet in one); prints it last.

    With --valid-prefix a journal with a corrupt line is sealed up to that line; every line left out is listed
    (line number and why) in the version's provenance. The journal itself is never changed.

    Example: labcal session seal 20261122-031500-ur10-3f9a --valid-prefix
    """
    from labcal.datasets import validate_id

    validate_id(session)
    st = open_store(store, create=False, write=True)
    result = st.seal(session, valid_prefix=valid_prefix)
    out.print(result.message)
    if result.created:
        m = st.manifest(result.ref)
        skipped = ((m.get("provenance") or {}).get("journal") or {}).get("valid_prefix", {}).get("skipped", [])
        for s in skipped:
            where = f"line {s['line']}" + (f" (seq {s['seq']}, pose {s['pose_index']})" if "seq" in s else "")
            out.print(f"  left out {where}: {s['reason']}")
    if result.ref is None:
        raise typer.Exit(1)
    print(result.ref)


@app.command("verify")
@user_errors
def verify(
    session: str = typer.Argument(..., help="SESSION or SESSION@vN."),
    as_json: bool = JsonOption,
    store: Path | None = StoreOption,
) -> None:
    """Check the file hashes of a version and of the fits stored under it (SESSION alone: every version, and what
    spans them: the journal against the part each version sealed, the start document, versions or journal gone).

    Each version stands on its own files: a damaged journal is reported once, for the session, and leaves intact
    versions usable. Foreign files (.DS_Store, editor backups) are noted and skipped. Exit 1 with one line per
    problem if anything is wrong (with --json: the same problems in the document, and exit 1 too).

    Examples:

      labcal session verify 20261122-031500-ur10-3f9a@v1

      labcal session verify 20261122-031500-ur10-3f9a --json
    """
    from labcal.datasets import Ref, parse_ref

    r = parse_ref(session)
    st = open_store(store, create=False)
    refs = [st.resolve(r)] if r.version is not None else [Ref(r.session_id, v) for v in st.versions(r.session_id)]
    whole = st.check_session(r.session_id) if r.version is None else None
    docs = []
    for ref in refs:
        report = st.verify(ref)
        fits = st.verify_fits(ref)
        problems = [*report.problems, *fits.problems]
        n_fits = len({c.split("/")[1] for c in fits.checked})
        docs.append({
            "ref": str(report.ref), "ok": not problems, "files_checked": len(report.checked), "fits_checked": n_fits,
            "fit_files_checked": len(fits.checked), "problems": problems, "notes": report.notes,
        })  # fmt: skip
        if not as_json:
            checked = f"{len(report.checked)} files checked, {n_fits} fit(s) with {len(fits.checked)} files checked"
            _print_findings(report.ref, checked, problems, [*report.notes, *fits.notes])
    bad = any(not d["ok"] for d in docs) or (whole is not None and not whole.ok)
    if whole is not None and not as_json:
        what = ", ".join(whole.checked) or "no journal (imported)"
        _print_findings(whole.ref, f"session: {len(refs)} version(s), {what} checked", whole.problems, whole.notes)
    if as_json:
        doc = {"session": r.session_id, "ok": not bad, "versions": docs}
        if whole is not None:
            doc["session_checks"] = {"ok": whole.ok, "checked": whole.checked, "problems": whole.problems,
                                     "notes": whole.notes}  # fmt: skip
        print_json("labcal.session-verify/1", doc)
    if bad:
        raise typer.Exit(VERIFY_FAILED)


def _print_findings(ref, checked: str, problems: list[str], notes: list[str]) -> None:
    """`REF: ok (what was checked)` when nothing is wrong, else one line per problem; then the notes."""
    if not problems:
        out.print(f"{ref}: ok ({checked})")
    for p in problems:
        out.print(f"{ref}: {p}")
    for n in notes:
        out.print(f"{ref}: note: {n}")


app.command("import")(import_)
