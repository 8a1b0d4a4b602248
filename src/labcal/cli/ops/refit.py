"""`labcal refit` as functions: select stored sessions, refit each with one method and seed, serially or on Dask.

One task per selected version (the latest version of each session, or every version with ``every_version``).
A task runs :func:`labcal.cli.ops.fitting.run_fit` on that version alone, so its fit is stored exactly as
``labcal fit SESSION@vN --method M --seed S`` stores it: same files, same bytes, apart from the fit id and the
times in fit.json. Where the task runs changes nothing in the numbers.

Executors:

- ``jobs == 1`` and no scheduler: in this process, one task after the other;
- ``jobs > 1``: a ``distributed.LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True)``;
- ``scheduler="tcp://host:8786"``: ``distributed.Client(scheduler)``; its workers need labcal installed and the
  store at the same path.

Worker death. Each task's fit id is drawn here, before any task runs, so an attempt Dask repeats after a worker
died writes under the same id: a fit the dead attempt already published is found and reported, not stored twice.
``SessionStore.save_fit`` publishes a fit by renaming a finished hidden folder, so a dead attempt leaves at most a
hidden ``.tmp-<fit id>-*`` folder, which the store ignores and this module removes once no attempt can still be
running. A task Dask gives up on (``KilledWorker``) is reported as failed; the others go on.

Worked example::

    >>> store = open_store("sessions", write=True)
    >>> refs, skipped = select_versions(store, Selection(robot="ur10"))
    >>> report = run_refit(store, refs, "local-poe", seed=0, jobs=2)
    >>> [(row.ref, row.status, row.after.error) for row in report.rows]
    [('20261122-031500-ur10-3f9a@v002', 'fitted', 0.000153…), …]
"""

from __future__ import annotations

import datetime as _dt
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from labcal.cli.common import INTERRUPTED, UserError, session_unit
from labcal.datasets import DatasetError, SessionStore

FITTED, FAILED, NOT_RUN = "fitted", "failed", "not run"


# ------------------------------------------------------------------------------------------------- selection


@dataclass(frozen=True)
class Selection:
    """Which sessions to refit. Every given criterion must hold (they narrow each other).

    everything: select every session (``--all``) when no other criterion is given; robot: the robot name recorded
    with the session (case-insensitive); unit: the session metadata's ``"unit"`` (sessions without one never
    match); since: sessions created at or after this time (naive = UTC); refs: explicit ``SESSION[@vN]``;
    every_version: one task per version instead of the latest version of each session.
    """

    everything: bool = False
    robot: str | None = None
    unit: str | None = None
    since: _dt.datetime | None = None
    refs: tuple[str, ...] = ()
    every_version: bool = False

    def check(self) -> None:
        if not (self.everything or self.robot or self.unit or self.since or self.refs):
            raise UserError("say which sessions to refit: --all, --robot NAME, --unit ID, --since DATE or SESSION …")


def parse_since(text: str) -> _dt.datetime:
    """``2026-11-20`` or ``2026-11-20T18:30[:00][Z|+01:00]`` → aware datetime (no zone given = UTC)."""
    try:
        t = _dt.datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise UserError(
            f"--since: {text!r} is not a date; use YYYY-MM-DD or YYYY-MM-DDTHH:MM (UTC unless a zone is given)"
        ) from None
    return t if t.tzinfo else t.replace(tzinfo=_dt.UTC)


def session_created(store: SessionStore, session_id: str) -> _dt.datetime | None:
    """When a session was started: its journal's start document, else the creation of its first version."""
    try:
        start = store.read_journal(session_id).start
    except (DatasetError, OSError):
        start = None
    if start is not None and start.time:
        return _dt.datetime.fromtimestamp(float(start.time), _dt.UTC)
    versions = store.versions(session_id)
    if not versions:
        return None
    created = store.manifest(f"{session_id}@v{versions[0]:03d}").get("created")
    try:
        return parse_since(str(created))
    except UserError:
        return None


def select_versions(store: SessionStore, selection: Selection) -> tuple[list[str], list[tuple[str, str]]]:
    """(refs to refit, [(session or ref, why it was left out)]) for a selection, sessions in the order they were
    started (versions in order within a session).

    Sessions that fail a criterion are simply not selected; those that pass but cannot be fitted (no version
    sealed yet, unreadable metadata) are listed as left out, with the reason.
    """
    selection.check()
    store.require_root()
    skipped: list[tuple[str, str]] = []
    found: list[tuple[tuple, str]] = []
    explicit: dict[str, list[str]] = {}
    for text in selection.refs:
        r = store.resolve(text)  # an unknown session or version is a usage error, named by the store
        explicit.setdefault(r.session_id, []).append(str(r))
    candidates = list(explicit) if selection.refs else store.session_ids()
    for sid in candidates:
        try:
            meta = store.session_meta(sid)
        except (DatasetError, OSError, ValueError, KeyError) as e:
            skipped.append((sid, f"unreadable session metadata ({e})"))
            continue
        if selection.robot and str((meta.get("robot") or {}).get("name", "")).casefold() != selection.robot.casefold():
            continue
        if selection.unit and session_unit(meta) != selection.unit:
            continue
        created = session_created(store, sid)
        if selection.since is not None and (created is None or created < selection.since):
            continue
        versions = store.versions(sid)
        if not versions:
            skipped.append((sid, "no version sealed yet (`labcal session seal` it first)"))
            continue
        if sid in explicit:
            chosen = list(dict.fromkeys(explicit[sid]))
        else:  # every version, or the latest
            chosen = [f"{sid}@v{v:03d}" for v in (versions if selection.every_version else versions[-1:])]
        # Ids sort by the second a session was started; the start time itself orders sessions of the same second.
        order = created.timestamp() if created is not None else float("inf")
        found += [((order, sid, i), r) for i, r in enumerate(chosen)]
    return [r for _, r in sorted(found)], skipped


# ------------------------------------------------------------------------------------------------- one task


@dataclass(frozen=True)
class FitSummary:
    """A fit in one line: its method, its held-out error (m) and where that error comes from."""

    fit_id: str | None = None
    method: str | None = None  # the chosen model (auto's winner)
    error: float | None = None  # mean target-point distance, m
    source: str | None = None  # "test" | "val" (a held-out split) | "cv" (mean over the folds)
    warnings: tuple[str, ...] = ()  # warning codes

    @classmethod
    def of(cls, fit_id: str, meta: dict) -> FitSummary:
        """From a fit's stored metadata (fit.json's ``metadata``, as ``run_fit`` writes it)."""
        error, source = held_out_error(meta)
        codes = tuple(str(w.get("code")) for w in meta.get("warnings") or [] if isinstance(w, dict))
        return cls(fit_id, meta.get("chosen") or meta.get("method"), error, source, codes)


def held_out_error(meta: dict) -> tuple[float | None, str | None]:
    """The fit's held-out mean point error (m): a test or validation split's if it has one, else the mean
    cross-validation error of the model it chose; (None, None) when neither was stored."""
    metrics = meta.get("metrics") or {}
    for split in ("test", "val"):
        after = ((metrics.get(split) or {}).get("points") or {}).get("after") or {}
        if after.get("mean") is not None:
            return float(after["mean"]), split
    cv = meta.get("cv") or {}
    mean = (cv.get("mean") or {}).get(cv.get("chosen"))
    if mean is not None:
        return float(mean), "cv"
    return None, None


@dataclass(frozen=True)
class RefitTask:
    """Everything one refit needs, picklable for a Dask worker. ``fit_id`` is fixed before the run (see the module
    docstring); ``hook``, if given, is called as ``hook(task)`` in the worker before the fit (tests inject faults)."""

    store_root: str
    ref: str
    method: str
    fit_id: str
    seed: int = 0
    hidden: int | None = None
    val_fraction: float = 0.0
    robot_file: str | None = None
    before: FitSummary = field(default_factory=FitSummary)
    hook: Callable | None = None


@dataclass(frozen=True)
class RefitRow:
    """The outcome of one task: before (the version's latest earlier fit) and after (the new one)."""

    ref: str
    status: str  # FITTED | FAILED | NOT_RUN
    before: FitSummary
    after: FitSummary = field(default_factory=FitSummary)
    message: str = ""  # why it failed, or a note (e.g. stored by an earlier attempt of a task whose worker died)


def _published(task: RefitTask, note: str) -> RefitRow | None:
    """The FITTED row of a task whose fit an attempt already published (verified), with ``note`` saying how; None
    when no attempt did."""
    try:
        record = SessionStore(task.store_root).load_fit(task.ref, task.fit_id)
    except DatasetError:
        return None
    return RefitRow(task.ref, FITTED, task.before, FitSummary.of(task.fit_id, record.metadata), note)


def refit_one(task: RefitTask) -> RefitRow:
    """Run one refit (in a worker or here) and say how it went; never raises for a failed fit.

    The fit goes through ``run_fit`` exactly as ``labcal fit REF --method M --seed S`` runs it, so the stored
    files are the same bytes. A fit with warnings is stored like ``labcal fit`` stores it, and counts as fitted.
    """
    from labcal.cli.ops.fitting import run_fit

    if task.hook is not None:
        task.hook(task)
    earlier = _published(task, "stored by an earlier attempt whose worker died")
    if earlier is not None:
        return earlier
    store = SessionStore(task.store_root)
    try:
        outcome = run_fit(
            store, [task.ref], task.method, seed=task.seed, hidden=task.hidden, val_fraction=task.val_fraction,
            robot=task.robot_file, fit_id=task.fit_id,
        )  # fmt: skip
    except Exception as e:  # one session's bad data must not stop the others; the row names it
        # A concurrent attempt (a worker wrongly declared dead) may have won.
        concurrent = _published(task, "stored by a concurrent attempt")
        return concurrent or RefitRow(task.ref, FAILED, task.before, message=f"{type(e).__name__}: {e}")
    meta = store.load_fit(outcome.ref, outcome.fit_id, check_files=False).metadata
    return RefitRow(task.ref, FITTED, task.before, FitSummary.of(outcome.fit_id, meta))


# ------------------------------------------------------------------------------------------------- the run


@dataclass(frozen=True)
class RefitReport:
    """All rows in task order; ``skipped``: selected sessions that could not be fitted; ``interrupted``: Ctrl-C
    stopped the run (rows not reached are ``NOT_RUN``); ``executor``: where the tasks ran."""

    rows: list[RefitRow]
    skipped: list[tuple[str, str]] = field(default_factory=list)
    interrupted: bool = False
    executor: str = "serial"

    @property
    def failed(self) -> list[RefitRow]:
        return [r for r in self.rows if r.status != FITTED]

    @property
    def exit_code(self) -> int:
        """0 all fitted, 1 any failed, 130 interrupted."""
        if self.interrupted:
            return INTERRUPTED
        return 1 if self.failed else 0


def latest_fit(store: SessionStore, ref: str) -> FitSummary:
    """The version's newest stored fit, summarised (empty when it has none or its record is unreadable)."""
    try:
        fits = store.list_fits(ref)
    except (DatasetError, OSError, ValueError) as e:
        return FitSummary(method=f"unreadable ({type(e).__name__})")
    if not fits:
        return FitSummary()
    return FitSummary.of(fits[-1].fit_id, fits[-1].metadata)


def plan_tasks(
    store: SessionStore,
    refs: Sequence[str],
    method: str,
    *,
    seed: int = 0,
    hidden: int | None = None,
    val_fraction: float = 0.0,
    robot_file: str | None = None,
    hook: Callable | None = None,
) -> list[RefitTask]:
    """One task per ref, with its fit id drawn now and the version's latest earlier fit as "before"."""
    from labcal.cli.ops.fitting import check_fit_options
    from labcal.datasets.ids import new_fit_id

    # The checks run_fit makes, made once here: a bad option is a usage error, not a failure of every task.
    check_fit_options(method, seed, hidden, val_fraction)
    root = str(Path(store.root).resolve())
    resolved = [str(store.resolve(ref)) for ref in refs]
    return [
        RefitTask(root, r, method, new_fit_id(), seed, hidden, val_fraction, robot_file, latest_fit(store, r), hook)
        for r in resolved
    ]


def run_refit(
    store: SessionStore,
    refs: Sequence[str],
    method: str,
    *,
    seed: int = 0,
    hidden: int | None = None,
    val_fraction: float = 0.0,
    robot_file: str | None = None,
    jobs: int = 1,
    scheduler: str | None = None,
    skipped: Sequence[tuple[str, str]] = (),
    progress: Callable[[RefitRow, int, int], None] | None = None,
    hook: Callable | None = None,
) -> RefitReport:
    """Refit every ref with one method and seed; see the module docstring for the executors.

    progress(row, done, total) is called as each task finishes. Ctrl-C returns the report so far with
    ``interrupted=True`` (every stored fit complete, no temporary folder of this run left behind locally).
    """
    if jobs < 1:
        raise UserError(f"--jobs must be at least 1, got {jobs}")
    if scheduler and jobs > 1:
        raise UserError("--jobs sets the size of the local cluster; with --scheduler the cluster's workers decide")
    tasks = plan_tasks(store, refs, method, seed=seed, hidden=hidden, val_fraction=val_fraction,
                       robot_file=robot_file, hook=hook)  # fmt: skip
    rows: dict[int, RefitRow] = {}

    def done(i: int, row: RefitRow) -> None:
        rows[i] = row
        if progress is not None:
            progress(row, len(rows), len(tasks))

    interrupted = False
    if not tasks:
        executor = "none"
    elif scheduler is None and jobs == 1:
        executor = "serial"
        try:
            for i, task in enumerate(tasks):
                done(i, refit_one(task))
        except KeyboardInterrupt:
            interrupted = True  # save_fit removes its own temporary folder on the way out
    else:
        executor = f"dask scheduler {scheduler}" if scheduler else f"dask LocalCluster ({jobs} processes)"
        interrupted = _run_dask(tasks, jobs, scheduler, done)
    if not interrupted or scheduler is None:  # a remote attempt may still be running after a Ctrl-C
        for task in tasks:
            _remove_temp_folders(store, task)
    # A task the interrupt caught: not run, unless its fit was published before the workers stopped.
    ordered = [
        rows.get(i)
        or _published(t, "stored just before the interrupt")
        or RefitRow(t.ref, NOT_RUN, t.before, message="interrupted")
        for i, t in enumerate(tasks)
    ]
    return RefitReport(ordered, list(skipped), interrupted, executor)


def _run_dask(tasks: list[RefitTask], jobs: int, scheduler: str | None, done) -> bool:
    """Run the tasks on a Dask client; True when Ctrl-C stopped it. A task whose workers kept dying (Dask's
    ``KilledWorker`` after its allowed failures) or that the cluster lost is a failed row, not an abort."""
    from distributed import Client, LocalCluster, as_completed

    cluster = None
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout="10s")
            except OSError as e:
                raise UserError(f"--scheduler {scheduler}: cannot connect ({e})") from None
        else:
            cluster = LocalCluster(
                # No fixed port (8787 may be another cluster's): a free one, on this machine only.
                n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
                silence_logs=logging.ERROR,
            )  # fmt: skip
            client = Client(cluster)
    except KeyboardInterrupt:
        if cluster is not None:
            cluster.close()
        return True
    futures: list = []
    try:
        # pure=False: the same task twice is two fits; the key names the fit id for the scheduler's logs.
        futures += [client.submit(refit_one, t, key=f"refit-{t.fit_id}", pure=False) for t in tasks]
        index = {f.key: i for i, f in enumerate(futures)}
        for fut in as_completed(futures):
            i = index[fut.key]
            try:
                row = fut.result()
            except Exception as e:  # KilledWorker, a lost worker, a deserialisation error
                # Failed, unless an attempt published its fit before its worker died.
                why = f"{type(e).__name__}: {e}"
                note = f"stored before its worker died; Dask then gave up ({why})"
                row = _published(tasks[i], note) or RefitRow(tasks[i].ref, FAILED, tasks[i].before, message=why)
            done(i, row)
        return False
    except KeyboardInterrupt:
        client.cancel(futures)
        return True
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _remove_temp_folders(store: SessionStore, task: RefitTask) -> None:
    """Remove hidden ``.tmp-<fit id>-*`` folders a dead attempt of this task left (never a published fit)."""
    from labcal.datasets._util import remove_tree

    try:
        fits = store.version_dir(task.ref) / "fits"
    except DatasetError:
        return
    if fits.is_dir():
        for p in fits.glob(f".tmp-{task.fit_id}-*"):
            remove_tree(p)
