"""The session runner: execute a :class:`~labcal.sessions.plans.Plan` on a Robot and a Tracker, journaling
every measurement durably before the robot moves again.

Per pose: move → settle → read the joints → measure (N samples averaged, spread kept) → validate → append the
measurement document to the session journal (written and fsynced by :class:`labcal.datasets.Journal`) →
next pose. Validation (:class:`Validation`): at least ``min_targets`` targets seen (a target not seen is a NaN
row of ``Measurement.points``; one seen is finite); the distances between the targets seen together agree with
those of the nominal targets within ``absolute_tolerance + spread_factor · spread`` (spread: the largest spread
of the targets seen; with one target seen there is no distance to check); the robot reports the commanded joints
within ``joint_tolerance``. A failed attempt is retried (:class:`RetryPolicy`: re-measure, optionally re-move) up to
``max_attempts`` times; then the pose is recorded as *rejected* with every attempt's reason and the run moves
on. Only final outcomes are journaled, so each plan pose has at most one measurement document per session.

Exits (``RunSummary.exit_status``, also the journal's stop document):

- ``"success"``: every pose has a valid or rejected measurement, and at least one is valid;
- ``"failed"`` also when the run ends without any valid measurement (every pose rejected), or when the tracker
  did not answer at all on ``RetryPolicy.max_silent_poses`` consecutive poses (a dead tracker: the run stops
  instead of moving the robot through the rest of the plan for nothing);
- ``"paused"``: the robot entered a protective stop (pause document, then stop document "paused"). Clear the
  stop on the robot and call :func:`resume`;
- ``"aborted"``: Ctrl-C (KeyboardInterrupt): the robot is stopped, the stop document written, and the
  function returns normally (nothing recorded is lost); :func:`resume` continues;
- ``"failed"``: a driver error the runner cannot retry (connection lost, stale data …); also resumable.

:func:`resume` continues at the first plan pose without a measurement document. Because a document is fsynced
before the next move, a crash (even kill -9) loses at most the pose being measured, which is then measured
again; nothing recorded is lost and nothing recorded is measured twice. After every run except a paused one
the journal is sealed into a new immutable version (when it has new valid measurements).

Joints: a plan is in *model* joints (what the planner and the kinematic model use). The runner commands the robot,
compares and records in *controller* joints, through the robot file's joint map
(``spec.joints.to_controller``; the identity for every built-in). The driver checks each command against its
joint limits and speed caps before it moves. :func:`resume` checks the whole journal before anything moves: a
corrupt line stops it with the line named (seal the valid prefix with ``SessionStore.seal(…, valid_prefix=True)``).

The runner never draws anything: pass ``progress`` (a callable taking :class:`Progress`) to show it (the CLI
renders it with rich).

How a run records (frame, validation, retries, overrides, driver identities, metadata, progress …) is one
:class:`RunOptions`; its fields may also be given as keywords of :func:`run` and :func:`resume`. The runner turns
them, the robot model, the targets and the plan into the session's :class:`~labcal.datasets.SessionHeader`.

Example::

    rig = SimRig(actual, targets, seed=0)
    plan = make_plan(random_configurations(spec.model, 20, seed=1), samples=5, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(SessionStore(root), spec, targets, plan, robot, tracker, RunOptions(frame="base"))
    summary.exit_status, summary.ref          # ("success", "20261122-031500-ur10-3f9a@v001")
"""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from labcal.datasets import Journal, JournalError, MeasurementDoc, SessionHeader, SessionStore, StartDoc
from labcal.datasets.sanity import Hints, check_measurements, check_names
from labcal.datasets.targets import pair_distances, target_pairs
from labcal.drivers.base import (
    DriverError,
    DriverTimeout,
    Measurement,
    MeasurementRejected,
    MotionFailed,
    MotionRejected,
    ProtectiveStop,
    ProtocolError,
    Robot,
    Tracker,
)
from labcal.robots import RobotSpec, from_record
from labcal.robots.joint_map import JointMap
from labcal.sessions.plans import Plan, PoseStep, checked_number

# triangle_error: the largest distance error between targets seen together (None with fewer than two seen); the name
# is older than 1..k targets and stays, as it is a column (x_triangle_error) of every recorded version.
EXTRA_UNITS = {"attempts": "1", "triangle_error": "m", "quality": ""}
# The record-time sanity check (labcal.datasets.sanity) runs once the session has max(this, 2 n) valid poses.
SANITY_MIN_ROWS = 3


class SessionError(RuntimeError):
    """The runner cannot start or resume (robot still stopped, wrong robot model, nothing to resume …)."""


@dataclass(frozen=True)
class Validation:
    """Acceptance of one measurement.

    absolute_tolerance: m, allowed |measured − nominal| distance between two targets seen together (the sides of
    the target triangle for three), plus spread_factor × the largest per-target spread (m) of the averaged frames;
    joint_tolerance: rad (m), largest allowed |q_actual − q_commanded| after a move; min_targets: fewest targets
    seen for a valid measurement (1: any pose where the tracker saw something; the session's target count: every
    target in every row, retrying a pose where one was lost).
    """

    absolute_tolerance: float = 0.5e-3
    spread_factor: float = 5.0
    joint_tolerance: float = 1e-3
    min_targets: int = 1

    def __post_init__(self) -> None:
        # checked, not converted: the start document records the values as given
        for name in ("absolute_tolerance", "spread_factor", "joint_tolerance"):
            checked_number(getattr(self, name), f"Validation.{name}", error=ValueError)
        checked_number(self.min_targets, "Validation.min_targets", least=1, integer=True, error=ValueError)


@dataclass(frozen=True)
class RetryPolicy:
    """max_attempts: measurement attempts per pose (>= 1); remove: move to the pose again before each retry;
    max_silent_poses: stop the run as "failed" after this many consecutive poses on which the tracker timed out on
    every attempt (0 = never): a tracker that does not answer would otherwise walk the robot through the whole plan
    and record nothing; max_failed_poses: stop the run as "failed" after this many consecutive rejected poses,
    whatever the reason (garbled frames, targets not seen, distances off; 0 = never): a tracker sending garbage
    would otherwise walk the robot through the whole plan too. A pose the driver refuses to move to (limits, caps)
    is the plan's fault, not the measurement's, and neither counts nor resets the count."""

    max_attempts: int = 3
    remove: bool = False
    max_silent_poses: int = 3
    max_failed_poses: int = 5

    def __post_init__(self) -> None:
        for name, least in (("max_attempts", 1), ("max_silent_poses", 0), ("max_failed_poses", 0)):
            checked_number(getattr(self, name), f"RetryPolicy.{name}", least=least, integer=True, error=ValueError)


@dataclass(frozen=True)
class Progress:
    """A progress event. pose: plan index (or None for run-level events); done/total: poses with a recorded
    outcome / in the plan; status: "moving" | "retry" | "valid" | "rejected" | "success" | "paused" |
    "aborted" | "failed"; residual: the last triangle error, m (None if unknown); message: human text."""

    pose: int | None
    done: int
    total: int
    status: str
    residual: float | None = None
    message: str = ""


@dataclass(frozen=True)
class RunSummary:
    """Outcome of :func:`run` / :func:`resume`. valid/rejected count the whole session (all runs); measured:
    documents written by this run; remaining: plan poses still without a measurement; ref: the version sealed
    at the end (or the latest one, or None)."""

    session_id: str
    exit_status: str
    reason: str
    valid: int
    rejected: int
    remaining: int
    measured: int
    ref: str | None
    messages: list[str] = field(default_factory=list)


ProgressCallback = Callable[[Progress], None]


def describe(device: object) -> dict:
    """Identity of a driver for the start document: its class and what its ``identity()`` method (if any) says."""
    ident = getattr(device, "identity", None)
    info = {"class": f"{type(device).__module__}.{type(device).__qualname__}"}
    if callable(ident):
        info.update(dict(ident()))
    return info


def device_identity(device: object) -> dict:
    """What a device reported about itself: its ``device_identity()`` dict (``serial``, ``model``, ``firmware`` …,
    ``notes`` for what it would not tell), {} for a driver without one. A driver that fails to answer is recorded
    as a note, never a failed session: knowing the unit is worth having, not worth losing a measurement run for.
    """
    ask = getattr(device, "device_identity", None)
    if not callable(ask):
        return {}
    try:
        return {str(k): v for k, v in dict(ask() or {}).items()}
    except Exception as e:  # a driver's bug or a device's silence must not stop the run here
        return {"notes": [f"{type(device).__name__} did not report its identity: {e}"]}


# Decides the unit when recording; labcal.cli.common.session_unit reads back the one a stored version recorded.
def session_unit(unit: str | None, robot_identity: Mapping[str, Any]) -> tuple[str | None, list[str]]:
    """(the session's unit id, notes): the operator's ``unit`` when given, else the robot's serial number, else None.

    A given unit that differs from the serial the controller reports is kept (the operator names the unit) with a
    note, so the disagreement is on record in the start document.
    """
    serial = robot_identity.get("serial")
    serial = str(serial) if serial not in (None, "") else None
    if unit is None:
        return serial, []
    if serial is not None and serial != unit:
        return unit, [f"unit {unit!r} was given, the controller reports serial number {serial!r}"]
    return unit, []


# --------------------------------------------------------------------------------------------------------------


@dataclass
class _Outcome:
    status: str
    q_actual: np.ndarray | None
    measurement: Measurement | None
    reason: str
    attempts: int
    residual: float | None
    silent: bool = False  # the tracker timed out on every attempt
    refused: bool = False  # the driver refused the motion (the plan's fault, not the measurement's)


def check_measurement(m: Measurement, nominal: np.ndarray, validation: Validation) -> tuple[str, float | None]:
    """("" if acceptable else the reason, largest distance error in m, or None when fewer than two targets were
    seen). ``nominal``: the targets (m, 3) in the tool frame; the distances of every pair of them
    (:func:`~labcal.datasets.targets.pair_distances`) are checked. See :class:`Validation`."""
    nominal = np.asarray(nominal, dtype=float)
    n_targets, sides = len(nominal), pair_distances(nominal)
    points = np.asarray(m.points, dtype=float)
    if points.shape != (n_targets, 3):
        return f"tracker returned points of shape {points.shape}, expected ({n_targets}, 3)", None
    finite = np.isfinite(points)
    seen = finite.all(axis=1)
    partly = finite.any(axis=1) & ~seen
    if partly.any():
        bad = ", ".join(f"t{i + 1}" for i in np.flatnonzero(partly))
        return f"target(s) {bad} partly non-finite (a target is either seen, finite, or not seen, all NaN)", None
    missing = [f"t{i + 1}" for i in np.flatnonzero(~seen)]
    if int(seen.sum()) < validation.min_targets:
        if not seen.any():
            return "no target seen", None
        return f"missing target(s) {', '.join(missing)} ({int(seen.sum())} seen, {validation.min_targets} needed)", None
    together = np.array([seen[a] and seen[b] for a, b in target_pairs(n_targets)], dtype=bool)
    if not together.any():
        return "", None
    measured = pair_distances(points)
    error = float(np.max(np.abs(measured[together] - sides[together])))
    spread = np.asarray(m.spread, dtype=float)
    spread_seen = spread[seen] if spread.shape == (n_targets,) else spread
    worst = float(np.max(spread_seen)) if spread_seen.size and np.all(np.isfinite(spread_seen)) else 0.0
    tol = validation.absolute_tolerance + validation.spread_factor * worst
    if error > tol:
        what = "target triangle" if n_targets == 3 and together.all() else "distances between the targets seen"
        return (
            f"{what} differs from the nominal targets by {error * 1e3:.3f} mm (tolerance {tol * 1e3:.3f} mm)"
        ), error
    return "", error


@dataclass(frozen=True)
class RunOptions:
    """How :func:`run` records a session (and :func:`resume` continues it; resume reads validation, retry and the
    overrides from the start document).

    frame: "tracker", or "base" if the tracker reports in the robot base frame; validation, retry: see
    :class:`Validation`, :class:`RetryPolicy`; allow: record-time sanity checks to override (names of
    :data:`labcal.datasets.sanity.CHECKS`); progress: callable taking :class:`Progress`; session_id: None = a new
    id; metadata: the caller's (sim seeds, profiles …); sleep: how to wait for settling (tests pass a no-op); seal:
    make a version at the end; unit: the robot unit's id (default: the serial number the robot driver reports in
    ``device_identity()``, see :func:`session_unit`).
    """

    frame: str = "tracker"
    validation: Validation = field(default_factory=Validation)
    retry: RetryPolicy = field(default_factory=RetryPolicy)
    allow: tuple[str, ...] = ()
    progress: ProgressCallback | None = None
    session_id: str | None = None
    metadata: Mapping[str, Any] | None = None
    sleep: Callable[[float], None] = time.sleep
    seal: bool = True
    unit: str | None = None

    def with_changes(self, **changes: Any) -> RunOptions:
        """These options with some fields replaced (None for validation/retry keeps the default)."""
        known = {f.name for f in dataclasses.fields(self)}
        if unknown := sorted(set(changes) - known):
            raise TypeError(f"unknown run option(s) {unknown}; the options are {sorted(known)}")
        changes = {k: v for k, v in changes.items() if not (k in ("validation", "retry") and v is None)}
        if "allow" in changes:
            changes["allow"] = tuple(changes["allow"])
        return dataclasses.replace(self, **changes) if changes else self


class _Run:
    """State of one run over a journal (shared by :func:`run` and :func:`resume`)."""

    def __init__(
        self,
        journal: Journal,
        plan: Plan,
        robot: Robot,
        tracker: Tracker,
        options: RunOptions,
        spec: RobotSpec | None = None,
    ) -> None:
        self.journal, self.plan, self.robot, self.tracker = journal, plan, robot, tracker
        self.validation, self.retry = options.validation, options.retry
        self.joints = spec.joints if spec is not None else JointMap.identity(plan.n_joints)
        self.targets = journal.start.targets_array()
        self._progress = options.progress
        self.sleep = options.sleep
        self.measured = 0
        self.spec, self.allow = spec, check_names(options.allow)
        self.frame = journal.start.frame
        contents = journal.read()
        self.done = {d.pose_index for d in contents.measurements}
        # Valid rows so far (controller joints, points with NaN rows for targets not seen): the record-time sanity
        # check runs on them.
        self.rows = [(d.pose_index, d.q, d.points_array(len(self.targets))) for d in contents.measurements if d.valid]
        self.sanity_at = max(SANITY_MIN_ROWS, 2 * plan.n_joints)
        self.sanity_done = False

    def sanity(self, at_end: bool = False) -> str:
        """Run :func:`labcal.datasets.sanity.check_measurements` on the valid rows once there are enough of them
        (``2 n``, as the import's few-poses rule: the nominal-model check needs rows to register the tracker frame);
        return "" if they pass (or are too few yet), else why the run must stop. Overridden checks (``allow``) still
        run and are only noted. ``at_end``: the run is over with fewer rows than that; check what there is (from 3)."""
        needed = SANITY_MIN_ROWS if at_end else self.sanity_at
        if self.sanity_done or len(self.rows) < needed:
            return ""
        self.sanity_done = True
        poses = [r[0] for r in self.rows]
        hints = Hints(
            length="a tracker reporting in {unit} (check the tracker profile's unit)",
            angle="joint values in {unit} (check the robot driver and the robot file's [joint_map])",
            frame='frame "{frame}" (check which frame the tracker reports in)',
            row=lambda i: f"pose {poses[i]}",
        )
        report = check_measurements(
            np.array([r[1] for r in self.rows], dtype=float),
            np.array([r[2] for r in self.rows], dtype=float).reshape(len(self.rows), len(self.targets), 3),
            self.targets,
            robot=self.spec,
            frame=self.frame,
            allow=self.allow,
            hints=hints,
            final=False,
        )
        if report.ok:
            return ""
        found = "; ".join(f"[{f.check}] {f.message}" for f in report.failures)
        flags = " ".join(f"--allow {f.check}" for f in report.failures)
        stopped = "the run is over" if at_end else "so the run stopped before measuring more"
        return (
            f"sanity check failed on the first {len(self.rows)} valid poses, {stopped}: {found}. Fix the setup and "
            f"start a new session, or if the data are right resume with {flags}"
        )

    def emit(self, pose: int | None, status: str, residual: float | None = None, message: str = "") -> None:
        if self._progress is not None:
            self._progress(Progress(pose, len(self.done), self.plan.n_poses, status, residual, message))

    def execute(self) -> tuple[str, str]:
        """Run the remaining poses; return (exit_status, reason). Writes the stop document (not for a crash)."""
        robot, journal = self.robot, self.journal
        pose: int | None = None
        self.silent = 0  # consecutive poses without a single tracker answer
        self.failed = 0  # consecutive rejected poses (motion refusals aside)
        valid_now = 0
        try:
            for step in self.plan.poses():
                if step.index in self.done:
                    continue
                pose = step.index
                outcome = self.record(step)
                valid_now += outcome.status == "valid"
                why = self.stop_reason(outcome, pose)
                if why:
                    _safe_stop(robot)
                    return self.stopped("failed", why)
        except ProtectiveStop as e:
            _safe_stop(robot)
            reason = f"protective stop at pose {pose}: {e}"
            journal.pause(reason)
            return self.stopped("paused", reason)
        except KeyboardInterrupt as e:
            _safe_stop(robot)
            # counted in the journal, not a plan index: "at pose 92" read as 92 recorded or as the 92nd, depending on
            # the moment, and a count kept here can miss the pose journaled just before the interrupt
            valid = len(journal.valid_pose_indices())
            # labcal's entry point turns SIGTERM / SIGHUP into a KeyboardInterrupt carrying the signal's number
            signum = e.args[0] if e.args and isinstance(e.args[0], int) else None
            by = "by the operator (Ctrl-C)" if signum is None else f"by {signal.Signals(signum).name}"
            return self.stopped("aborted", f"interrupted {by} with {valid} of {self.plan.n_poses} poses recorded valid")
        except JournalError:
            # The journal cannot record any more: stop the robot and let the caller see why.
            _safe_stop(robot)
            raise
        except DriverError as e:
            _safe_stop(robot)
            return self.stopped("failed", f"{type(e).__name__} at pose {pose}: {e}")
        return self.finish(valid_now)

    def stopped(self, status: str, reason: str) -> tuple[str, str]:
        """Write the stop document and return (exit_status, reason) as :meth:`execute` does."""
        self.journal.stop(status, reason)
        return status, reason

    def record(self, step: PoseStep) -> _Outcome:
        """Measure one pose and journal it (whatever its status), then count it and report it."""
        q_command = self.joints.to_controller(step.q)
        outcome = self.measure_pose(step, q_command)
        m = outcome.measurement
        self.journal.append_measurement(
            pose_index=step.index,
            q_commanded=q_command,
            q_actual=outcome.q_actual,
            points=None if m is None else m.points,
            spread=_spread_of(m),
            samples=0 if m is None else int(m.samples),
            status=outcome.status,
            reason=outcome.reason,
            extra={
                "attempts": outcome.attempts,
                "triangle_error": outcome.residual,
                "quality": ",".join(m.quality) if m is not None else "",
            },
        )
        self.measured += 1
        self.done.add(step.index)
        self.emit(step.index, outcome.status, outcome.residual, outcome.reason)
        if outcome.status == "valid":
            self.rows.append((step.index, np.asarray(outcome.q_actual).tolist(), np.asarray(m.points)))
        return outcome

    def stop_reason(self, outcome: _Outcome, pose: int) -> str:
        """Why the run must stop after this journaled pose ("" to go on): the record-time sanity check, a silent
        tracker, too many rejected poses in a row."""
        self.silent = self.silent + 1 if outcome.silent else 0
        if not outcome.refused:
            self.failed = self.failed + 1 if outcome.status == "rejected" else 0
        if outcome.status == "valid":  # (both counts are 0 again)
            # Checked after the measurement is journaled (nothing recorded is lost) and before the next
            # motion: a wrong robot model, targets file, unit or frame stops the run early.
            return self.sanity()
        # a silent tracker is named as such first: its poses are rejected poses too
        if self.retry.max_silent_poses and self.silent >= self.retry.max_silent_poses:
            return (
                f"the tracker did not answer on {self.silent} consecutive poses (every attempt timed out, last "
                f"at pose {pose}): check its cable, power and profile, then resume"
            )
        if self.retry.max_failed_poses and self.failed >= self.retry.max_failed_poses:
            return (
                f"{self.failed} consecutive poses rejected (last at pose {pose}: {outcome.reason}): check the "
                "tracker (line of sight, targets, profile), then resume"
            )
        return ""

    def finish(self, valid_now: int) -> tuple[str, str]:
        """The end of a run that went through every pose: failed when it kept none or the data fail the sanity
        check, else success."""
        journal = self.journal
        if self.measured and not valid_now:
            # A run that measured poses and kept none is not a success, whatever the cause (dead tracker, wrong
            # targets file, robot never reaching the poses): say why instead of sealing nothing quietly.
            contents = journal.read()
            last = next((d.reason for d in reversed(contents.measurements) if not d.valid), "")
            reason = f"no valid measurement: all {self.measured} pose(s) measured in this run were rejected"
            return self.stopped("failed", reason + (f" (last reason: {last})" if last else ""))
        why = self.sanity(at_end=True)  # a short session still gets checked once
        if why:
            return self.stopped("failed", why)
        journal.stop("success", f"{self.plan.n_poses} poses done")
        return "success", ""

    def measure_pose(self, step: PoseStep, q_cmd: np.ndarray) -> _Outcome:
        """Move to ``q_cmd`` (the pose in controller joints), settle, measure and validate with bounded retries.
        ProtectiveStop propagates."""
        robot, tracker, v = self.robot, self.tracker, self.validation
        timeouts = 0
        reasons: list[str] = []
        moved = False
        q_actual: np.ndarray | None = None
        last: Measurement | None = None
        residual: float | None = None
        for attempt in range(1, self.retry.max_attempts + 1):
            if attempt > 1:
                self.emit(step.index, "retry", residual, reasons[-1])
            if not moved or self.retry.remove:
                self.emit(step.index, "moving")
                try:
                    robot.move_joints(q_cmd, step.move.speed, step.move.acceleration)
                except MotionRejected as e:
                    # The plan itself is at fault (limits, caps): retrying cannot help.
                    reasons.append(f"motion rejected: {e}")
                    return _Outcome("rejected", None, None, _join(reasons), attempt, None, refused=True)
                except MotionFailed as e:
                    reasons.append(f"motion failed: {e}")
                    continue
                moved = True
                if step.settle > 0:
                    self.sleep(step.settle)
            q_actual = np.asarray(robot.joint_positions(), dtype=float)
            deviation = float(np.max(np.abs(q_actual - q_cmd)))
            if deviation > v.joint_tolerance:
                reasons.append(f"robot is {deviation:.6f} rad from the commanded joints")
                moved = False
                continue
            try:
                m = tracker.measure(step.samples)
            except MeasurementRejected as e:
                reasons.append(f"tracker rejected the frame: {e.reason}")
                continue
            except (DriverTimeout, ProtocolError) as e:
                timeouts += isinstance(e, DriverTimeout)
                reasons.append(f"{type(e).__name__}: {e}")
                continue
            # A protective stop during the measurement makes the frame suspect; pause instead.
            if robot.state().protective_stop:
                raise ProtectiveStop("robot entered a protective stop while measuring")
            last = m
            why, residual = check_measurement(m, self.targets, v)
            if not why:
                return _Outcome("valid", q_actual, m, "", attempt, residual)
            reasons.append(why)
        silent = timeouts == self.retry.max_attempts
        return _Outcome("rejected", q_actual, last, _join(reasons), self.retry.max_attempts, residual, silent)


def _spread_of(m: Measurement | None) -> np.ndarray | None:
    """The spread to journal: per target (NaN where not seen), or None when a seen target's spread is unknown."""
    if m is None:
        return None
    spread = np.asarray(m.spread, dtype=float)
    seen = np.isfinite(np.asarray(m.points, dtype=float)).all(axis=-1)
    if spread.shape != seen.shape or not np.isfinite(spread[seen]).all():
        return None
    return np.where(seen, spread, np.nan)


def _join(reasons: list[str]) -> str:
    return "; ".join(f"attempt {i + 1}: {r}" for i, r in enumerate(reasons))


def _spec_of_start(start: StartDoc) -> RobotSpec | None:
    """The robot model stored in a start document (None when the session predates stored robot files)."""
    try:
        return from_record(start.robot, f"<robot file of {start.session_id}>")
    except ValueError as e:
        raise SessionError(f"the robot file stored with session {start.session_id} cannot be read: {e}") from None


def _safe_stop(robot: Robot) -> None:
    with contextlib.suppress(Exception):  # stop() must never mask the reason we are stopping
        robot.stop()


def _finish(store: SessionStore, state: _Run, exit_status: str, reason: str, seal: bool) -> RunSummary:
    """Report the end of a run (progress), close its journal, seal a version (not when paused) and sum it up."""
    state.emit(None, exit_status, message=reason)
    journal = state.journal
    docs: list[MeasurementDoc] = journal.read().measurements
    valid = sum(d.valid for d in docs)
    rejected = len(docs) - valid
    remaining = state.plan.n_poses - len({d.pose_index for d in docs})
    journal.close()
    messages = []
    session_id = journal.session_id
    if seal and exit_status != "paused":
        result = store.seal(session_id)
        ref = result.ref
        messages.append(result.message)
    else:
        versions = store.versions(session_id)
        ref = f"{session_id}@v{versions[-1]:03d}" if versions else None
    return RunSummary(session_id, exit_status, reason, valid, rejected, remaining, state.measured, ref, messages)


def run(
    store: SessionStore,
    spec: RobotSpec,
    targets,
    plan: Plan,
    robot: Robot,
    tracker: Tracker,
    options: RunOptions | None = None,
    **changes: Any,
) -> RunSummary:
    """Create a session for ``spec`` (robot model) and ``targets`` ((m, 3) m, tool frame) and execute ``plan``.

    ``options`` (:class:`RunOptions`, or its fields as keywords): frame, validation, retry, allow (record-time sanity
    checks to override; the checks run once the session has ``2 n`` valid poses and a failure stops the run as
    "failed" before the next motion), progress, session id, driver identities, metadata. ``plan``: in model joints;
    the robot is commanded in controller joints (``spec.joints``). The start document records the robot model
    (name, hash and the robot file's text: ``spec.record()``), the targets, the tracker and robot identity, the plan
    (one entry per pose), the runner settings (so :func:`resume` validates the same way) and software versions.
    """
    opts = (options or RunOptions()).with_changes(**changes)
    targets = np.asarray(targets, dtype=float)
    if robot.n_joints != spec.model.n or plan.n_joints != spec.model.n:
        raise SessionError(
            f"robot model {spec.name!r} has {spec.model.n} joints, the robot driver {robot.n_joints}, "
            f"the plan {plan.n_joints}"
        )
    allowed = check_names(opts.allow)
    runner_settings = {
        "validation": asdict(opts.validation),
        "retry": asdict(opts.retry),
        "sanity_allow": sorted(allowed),
    }
    if opts.validation.min_targets == 1:  # sessions before 1..k targets have no such key: keep their documents
        del runner_settings["validation"]["min_targets"]
    robot_identity, tracker_identity = device_identity(robot), device_identity(tracker)
    unit, notes = session_unit(opts.unit, robot_identity)
    if notes:
        robot_identity["notes"] = [*robot_identity.get("notes", []), *notes]
    header = SessionHeader(
        robot=spec.record(),
        targets=targets,
        frame=opts.frame,
        tracker=describe(tracker),
        robot_driver=describe(robot),
        plan=plan.pose_documents(),
        extra_units=EXTRA_UNITS,
        metadata={"runner": runner_settings, "robot_source": spec.source, **dict(opts.metadata or {})},
        session_id=opts.session_id,
        unit=unit,
        robot_identity=robot_identity,
        tracker_identity=tracker_identity,
    )
    journal = store.create_session(header)
    state = _Run(journal, plan, robot, tracker, opts, spec)
    try:
        status, reason = state.execute()
    except BaseException:
        journal.close()
        raise
    return _finish(store, state, status, reason, opts.seal)


def resume(
    store: SessionStore,
    session_id: str,
    robot: Robot,
    tracker: Tracker,
    *,
    spec: RobotSpec | None = None,
    reason: str = "resumed by the operator",
    options: RunOptions | None = None,
    **changes: Any,
) -> RunSummary:
    """Continue a session at the first plan pose without a measurement document (valid or finally rejected).

    Works after a pause (protective stop, cleared on the robot first), an abort, a failure or a crash (the
    journal is reopened, a torn last line repaired). ``spec``: if given, its hash must match the session's
    robot model; else the robot file stored in the start document is used (its joint map converts the plan to
    controller joints; a session recorded before robot files were stored uses the identity). Uses the plan,
    targets and runner settings stored in the start document; of ``options`` (or keywords) only progress, sleep,
    seal and allow (added to the session's overrides) apply.

    Raises :class:`SessionError` before anything moves when the journal has a corrupt line (naming it): the run
    could not be sealed afterwards, so measuring would only move the robot for nothing; likewise when the plan's
    moves are faster than the robot's speed or acceleration caps now (every pose would be refused and burnt).
    """
    opts = (options or RunOptions()).with_changes(**changes)
    journal = store.open_journal(session_id)
    try:
        start = journal.start
        contents = journal.read()
        if contents.corrupt_lines:
            lines = ", ".join(
                f"line {ln} ({contents.corrupt_reasons.get(ln, 'corrupt')})" for ln in contents.corrupt_lines
            )
            raise SessionError(
                f"the journal of session {session_id} is corrupt at {lines}; nothing was moved. Seal the "
                f"measurements before line {contents.corrupt_lines[0]} with `labcal session seal {session_id} "
                "--valid-prefix` (the skipped lines are recorded in the version), then record the remaining poses "
                "in a new session"
            )
        if spec is None:
            spec = _spec_of_start(start)
        if spec is not None and spec.hash != start.robot_hash:
            raise SessionError(
                f"session {session_id} was recorded with robot model {start.robot['name']!r} "
                f"(hash {start.robot_hash[:12]}…), not {spec.name!r} (hash {spec.hash[:12]}…)"
            )
        if robot.n_joints != journal.n_joints:
            raise SessionError(f"session {session_id} has {journal.n_joints} joints, the robot {robot.n_joints}")
        _check_same_unit(session_id, start, robot)
        plan = Plan.from_pose_documents(start.plan)
        settings = start.metadata.get("runner") or {}
        recorded = opts.with_changes(
            validation=Validation(**settings.get("validation", {})),
            retry=RetryPolicy(**settings.get("retry", {})),
            allow=tuple(check_names([*settings.get("sanity_allow", []), *opts.allow])),
        )
        state = _Run(journal, plan, robot, tracker, recorded, spec)
        why = state.sanity()  # the rows already recorded, checked before anything moves
        if why:
            raise SessionError(why)
        if len(state.done) < plan.n_poses:
            _check_motion_caps(plan, state.done, robot)
            if robot.state().protective_stop:
                raise SessionError("the robot is still in a protective stop: clear it on the robot, then resume")
            crashed = journal.state == "running"
            journal.resume(reason + (" (the previous run ended without a stop document)" if crashed else ""))
            status, why = state.execute()
        else:
            status, why = "success", "nothing left to measure"
            if journal.state != "stopped":
                journal.stop("success", why)
    except BaseException:
        journal.close()
        raise
    return _finish(store, state, status, why, opts.seal)


def _check_motion_caps(plan: Plan, done: set[int], robot: Robot) -> None:
    """Refuse to resume a plan whose moves are faster than the robot's caps now (before anything moves).

    The driver refuses such a move, and the runner journals a refused pose as rejected (the plan's fault): with a
    cap lowered since the session started, every remaining pose would be burnt that way and none measured. Joint
    limits stay per pose: a narrowed limit refuses only the poses outside it.
    """
    limits = robot.limits
    for step in plan.poses():
        for what, value, cap, unit in (
            ("moves at", step.move.speed, limits.max_speed, "rad/s"),
            ("accelerates at", step.move.acceleration, limits.max_acceleration, "rad/s²"),
        ):
            if step.index not in done and not value <= cap:
                raise SessionError(
                    f"pose {step.index} {what} {value:g} {unit}, above the robot's cap of {cap:g} {unit} (lowered "
                    "since the session started?); nothing was moved: resume with the cap the session was planned "
                    "for, or record the remaining poses in a new session"
                )


def _check_same_unit(session_id: str, start: StartDoc, robot: Robot) -> None:
    """Refuse to resume a session on another arm: both serial numbers known and different (nothing moved yet)."""
    recorded = start.robot_identity.get("serial")
    now = device_identity(robot).get("serial")
    if recorded not in (None, "") and now not in (None, "") and str(recorded) != str(now):
        raise SessionError(
            f"session {session_id} was recorded on the robot with serial number {recorded!r}, this controller "
            f"reports {now!r}: resume it on the same arm, or record a new session for this one"
        )
