"""The append-only session journal (``journal.jsonl``): one JSON document per line, fsynced as it arrives.

Documents (each has ``type``, ``uid`` and ``time`` in UNIX seconds):

- ``start`` (first line): ``session_id``, ``schema_version``, ``robot`` {name, hash, n_joints, and, since the
  self-contained versions, ``text``/``format``: the robot file itself, so a session can be refitted or resumed
  from the store alone}, ``targets``
  (m×3, m, tool frame; m ≥ 1 targets), ``frame`` ("base" | "tracker": the frame of the measured points), ``tracker`` and
  ``robot_driver`` identity dicts, ``plan`` (list of JSON-able commands), ``extra_units`` (unit of each
  ``extra`` measurement field), ``software`` versions, ``metadata`` (user's).
- ``measurement``: ``seq`` (1, 2, … in order of arrival), ``pose_index`` (position in the plan),
  ``q_commanded``/``q_actual`` (n, rad; *controller* joints, as sent to and read from the robot — the plan in the
  start document is in model joints, converted through the robot file's joint map), ``points`` (m entries, m, entry
  i = target t(i+1) as [x, y, z], or null when it was not seen), ``spread`` (m, m; null where not seen),
  ``samples``, ``status`` ("valid" | "rejected"), ``reason``, ``split`` ("train" | "val" | "test" | "" or null),
  ``extra`` {name: value}, ``units``.
- ``pause`` / ``resume`` (``reason``: protective stop, Ctrl-C, restart after a crash …).
- ``stop``: ``exit_status`` ("success" | "aborted" | "paused" | "failed") and ``reason``.
- ``repair``: written by labcal itself when it reopens a journal whose last write was torn (``torn_lines``).

Crash safety: every document is written with one ``write`` and fsynced before ``append_*`` returns; the
file and, on creation, its directory are fsynced. A kill -9 can leave at most an unfinished last line; the
reader ignores it (with a warning in :attr:`JournalContents.warnings`) and :meth:`Journal.open` starts the
next document on a fresh line (it writes a newline and a ``repair`` document; earlier bytes are never
rewritten). Only one process may hold a journal open for appending (an exclusive ``flock``).

The start, measurement and stop documents are read and written as the typed documents of
:mod:`labcal.datasets.documents` (:class:`StartDoc`, :class:`MeasurementDoc`, :class:`StopDoc`); their JSON is the
JSON above, so journals written before the types existed read unchanged.

Lifecycle: measurements are accepted while the run is *running*; ``pause`` → paused, ``stop`` → stopped,
``resume`` (also after a crash) → running again. A session may therefore hold several runs.
"""

from __future__ import annotations

import contextlib
import functools
import os
import time as _time
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ._util import canonical_json, fsync_dir, json_lines, jsonable, write_all
from .documents import (
    EXIT_STATUSES,
    STATUSES,
    MeasurementDoc,
    SessionHeader,
    StartDoc,
    StopDoc,
    is_extra_key,
    measured_points,
    measured_spread,
)
from .errors import JournalCorrupted, JournalError
from .ids import validate_id
from .schema import SPLITS

# numpy is imported where measurements are checked before an append: reading a journal (listing a store) needs
# none of it.

try:  # POSIX only; without it we simply do not lock.
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

JOURNAL_NAME = "journal.jsonl"
DOC_TYPES = ("start", "measurement", "pause", "resume", "stop", "repair")
# The state of the run after each lifecycle document (JournalContents.state).
_STATES = {"start": "running", "resume": "running", "pause": "paused", "stop": "stopped"}


@dataclass(frozen=True)
class JournalContents:
    """What :func:`read_journal` found. ``documents`` are the parsed, well-formed documents in file order."""

    path: Path
    documents: list[dict]
    warnings: list[str] = field(default_factory=list)
    #: 1-based line numbers of unfinished lines at the end of the file (a torn last write).
    torn_lines: list[int] = field(default_factory=list)
    #: 1-based line numbers of unreadable lines that are *not* an explained torn write.
    corrupt_lines: list[int] = field(default_factory=list)
    #: True when the file does not end with a newline (the next append must start a fresh line).
    needs_newline: bool = False
    size: int = 0
    #: 1-based line number of each entry of ``documents``.
    document_lines: list[int] = field(default_factory=list)
    #: why each line in ``corrupt_lines`` was not accepted (line number → reason).
    corrupt_reasons: dict[int, str] = field(default_factory=dict)

    @functools.cached_property
    def start(self) -> StartDoc | None:
        """The start document (None if the first document is not one, or is damaged beyond reading)."""
        first = self.documents[0] if self.documents else None
        if first is None or first["type"] != "start":
            return None
        try:
            return StartDoc.from_json(first)
        except (KeyError, TypeError, ValueError):  # damaged into other valid JSON: read as damaged, never a crash
            return None

    @functools.cached_property
    def measurements(self) -> list[MeasurementDoc]:
        """Every measurement document, valid and rejected, in order of ``seq``."""
        return [MeasurementDoc.from_json(d) for d in self.documents if d["type"] == "measurement"]

    @property
    def state(self) -> str:
        """ "running", "paused" or "stopped", from the last lifecycle document."""
        return next((_STATES[d["type"]] for d in reversed(self.documents) if d["type"] in _STATES), "running")

    @property
    def stop(self) -> StopDoc | None:
        """The last ``stop`` document if the journal is stopped, else None."""
        if self.state != "stopped":
            return None
        return StopDoc.from_json(next(d for d in reversed(self.documents) if d["type"] == "stop"))

    @property
    def status(self) -> str:
        """The session's status for listings: the stop document's exit_status, "paused", or "open"."""
        stop = self.stop
        return stop.exit_status if stop is not None else "paused" if self.state == "paused" else "open"

    def valid_pose_indices(self) -> set[int]:
        """Plan positions that already have a valid measurement (skip them when resuming)."""
        return {d.pose_index for d in self.measurements if d.valid}


def _check_doc(doc: Any) -> str | None:
    """Return why ``doc`` is not a well-formed journal document, or None."""
    if not isinstance(doc, dict):
        return "not a JSON object"
    t = doc.get("type")
    if t not in DOC_TYPES:
        return f"unknown document type {t!r}"
    if t == "start":
        # a start document damaged into other valid JSON must read as damaged, not crash whoever reads the journal
        if not isinstance(doc.get("session_id"), str) or not isinstance(doc.get("robot"), dict):
            return "start document without a session_id or robot"
        if not isinstance(doc.get("targets"), list) or not isinstance(doc["robot"].get("n_joints"), int):
            return "start document without targets or robot.n_joints"
    if t == "measurement":
        if not isinstance(doc.get("seq"), int) or not isinstance(doc.get("pose_index"), int):
            return "measurement without integer seq/pose_index"
        if doc.get("status") not in STATUSES:
            return f"measurement with unknown status {doc.get('status')!r}"
    return None


def read_journal(path: str | Path) -> JournalContents:
    """Read a journal, tolerating a torn last write (never raises for one; see ``warnings``).

    Unreadable lines in the middle are skipped with a warning and listed in ``corrupt_lines`` unless a
    later ``repair`` document explains them as a torn write. Raises :class:`JournalError` only if the file
    cannot be read at all.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise JournalError(f"cannot read journal {path}: {e}") from None
    needs_newline = bool(data) and not data.endswith(b"\n")  # the last line is unterminated
    parsed: list[tuple[int, dict]] = []
    bad: list[tuple[int, str]] = []
    for i, doc, unreadable in json_lines(data):
        why = unreadable or _check_doc(doc)
        if why:
            bad.append((i, why))
        else:
            parsed.append((i, doc))
    last_good = parsed[-1][0] if parsed else 0
    repaired = {ln for _, d in parsed if d["type"] == "repair" for ln in d.get("torn_lines", [])}
    warnings: list[str] = []
    torn: list[int] = []
    reasons: dict[int, str] = {}  # the corrupt lines, each with why

    def reject(ln: int, why: str, warning: str) -> None:
        reasons[ln] = why
        warnings.append(f"{path}: line {ln} ignored: {warning}")

    for ln, why in bad:
        if ln > last_good:
            torn.append(ln)
            warnings.append(f"{path}: line {ln} ignored: torn last write ({why})")
        elif ln in repaired:
            warnings.append(f"{path}: line {ln} ignored: torn write, repaired later ({why})")
        else:
            reject(ln, why, f"CORRUPT ({why})")
    docs: list[dict] = []
    doc_lines: list[int] = []
    last_seq = 0
    for ln, d in parsed:
        if d["type"] == "start" and docs:
            reject(ln, "a second start document", "a second start document")
            continue
        if d["type"] == "measurement":
            if d["seq"] <= last_seq:
                why = f"seq {d['seq']} does not follow {last_seq}"
                reject(ln, why, why)
                continue
            last_seq = d["seq"]
        docs.append(d)
        doc_lines.append(ln)
    if docs and docs[0]["type"] != "start":
        warnings.append(f"{path}: the first document is not a start document")
    return JournalContents(
        path=path,
        documents=docs,
        warnings=warnings,
        torn_lines=torn,
        corrupt_lines=sorted(reasons),
        needs_newline=needs_newline,
        size=len(data),
        document_lines=doc_lines,
        corrupt_reasons=reasons,
    )


def _vector(value: Any, n: int, name: str, *, allow_none: bool) -> list[float] | None:
    if value is None:
        if allow_none:
            return None
        raise JournalError(f"{name} is required")
    import numpy as np

    a = np.asarray(value, dtype=np.float64)
    if a.shape != (n,):
        raise JournalError(f"{name} must have shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise JournalError(f"{name} has a non-finite value: {a.tolist()}")
    return a.tolist()


class Journal:
    """An open, append-only journal of one session. Use :meth:`create` or :meth:`open`; close it (or use
    ``with``) to release the file lock.

    Example::

        header = SessionHeader.of("ur10", h, 6, targets=targets, frame="tracker", plan=plan)
        with Journal.create(path, header, session_id="s1") as j:
            done = j.valid_pose_indices()
            j.append_measurement(pose_index=0, q_commanded=q, q_actual=q_meas, points=p, spread=s, samples=5)
            j.stop("success")
    """

    def __init__(self, path: Path, fd: int, contents: JournalContents) -> None:
        self.path = path
        self._fd: int | None = fd
        self._broken = False
        start = contents.start
        if start is None:
            raise JournalError(f"{path}: journal has no start document")
        self.start: StartDoc = start
        self.session_id: str = start.session_id
        self.n_joints: int = start.n_joints
        self.n_targets: int = start.n_targets
        self.plan_length: int = len(start.plan)
        self.state: str = contents.state  # "running", "paused" or "stopped"
        self.next_seq = max((m.seq for m in contents.measurements), default=0) + 1  # read_journal keeps seqs rising
        self._valid = contents.valid_pose_indices()
        self.warnings: list[str] = list(contents.warnings)

    # ---------------------------------------------------------------------------------------------- opening
    @classmethod
    def create(cls, path: str | Path, header: SessionHeader, *, session_id: str, time: float | None = None) -> Journal:
        """Create a new journal at ``path`` (must not exist) and write the start document of ``header``.

        ``header.targets``: (m, 3) in metres, tool frame; ``header.frame``: frame of the measured points;
        ``header.robot``: the robot model's record (``RobotSpec.record()``: name, hash, n_joints, text, format).
        """
        path = Path(path)
        validate_id(session_id)
        doc = header.start_document(session_id, time=time).to_json()
        line = _encode(doc)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o644)
        except FileExistsError:
            raise JournalError(f"journal {path} already exists; use Journal.open to append") from None
        try:
            _lock(fd, path)
            write_all(fd, line)
            os.fsync(fd)
            fsync_dir(path.parent)
            # Read back before anyone records: the robot must not move for a session whose start document (robot,
            # targets, plan) did not reach the disk as written.
            if path.read_bytes() != line:
                raise JournalCorrupted(
                    f"{path}: the start document read back differs from what was written (a failing disk or a second "
                    "writer?); nothing was recorded: start the session again, in another store if it repeats"
                )
        except BaseException:
            os.close(fd)
            raise
        return cls(path, fd, read_journal(path))

    @classmethod
    def open(cls, path: str | Path) -> Journal:
        """Open an existing journal for appending (e.g. to resume). Repairs a torn last line first."""
        path = Path(path)
        try:
            fd = os.open(path, os.O_RDWR | os.O_APPEND)
        except FileNotFoundError:
            raise JournalError(f"journal {path} not found") from None
        try:
            _lock(fd, path)
            contents = read_journal(path)
            if contents.start is None:
                raise JournalCorrupted(f"{path}: no start document on the first line")
            if contents.needs_newline or contents.torn_lines:
                why = "the previous writer stopped in the middle of a line (crash or kill)"
                repair = _document("repair", torn_lines=contents.torn_lines, reason=why)
                write_all(fd, (b"\n" if contents.needs_newline else b"") + _encode(repair))
                os.fsync(fd)
                contents = read_journal(path)
        except BaseException:
            os.close(fd)
            raise
        return cls(path, fd, contents)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing releases the flock
            self._fd = None

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - safety net only
        with contextlib.suppress(Exception):
            self.close()

    # ---------------------------------------------------------------------------------------------- queries
    def valid_pose_indices(self) -> set[int]:
        """Plan positions that already have a valid measurement (a resumed run skips them)."""
        return set(self._valid)

    def read(self) -> JournalContents:
        return read_journal(self.path)

    # ---------------------------------------------------------------------------------------------- appends
    def append_measurement(
        self,
        *,
        pose_index: int,
        q_commanded: Any,
        q_actual: Any,
        points: Any,
        spread: Any = None,
        samples: int = 1,
        status: str = "valid",
        reason: str = "",
        split: str | None = None,
        extra: Mapping[str, Any] | None = None,
        time: float | None = None,
    ) -> MeasurementDoc:
        """Append and fsync one measurement; return the document written (with its ``seq``).

        ``q_commanded``, ``q_actual``: (n,) rad. ``points``: (m, 3) m, row i = target t(i+1), in the
        session's frame, a NaN row for a target not seen (stored as null; at least one target must be seen).
        ``spread``: (m,) m, one per target. A rejected measurement needs a ``reason`` and may have
        ``points=None`` (or non-finite points, stored as null).
        """
        import numpy as np

        if self.state != "running":
            raise JournalError(f"cannot record a measurement while the run is {self.state}; call resume() first")
        if isinstance(pose_index, bool) or not isinstance(pose_index, int | np.integer) or pose_index < 0:
            raise JournalError(f"pose_index must be an integer >= 0, got {pose_index!r}")
        pose_index = int(pose_index)
        if self.plan_length and pose_index >= self.plan_length:
            raise JournalError(f"pose_index {pose_index} is outside the plan (length {self.plan_length})")
        if status not in STATUSES:
            raise JournalError(f"status must be one of {STATUSES}, got {status!r}")
        valid = status == "valid"
        if not valid and not reason:
            raise JournalError("a rejected measurement needs a reason")
        if split is not None and split not in SPLITS:
            raise JournalError(f"split must be one of train, val, test, '' or None, got {split!r}")
        if isinstance(samples, bool) or not isinstance(samples, int | np.integer) or samples < 0:
            raise JournalError(f"samples must be an integer >= 0, got {samples!r}")
        n = self.n_joints
        extra_doc: dict[str, Any] = {}
        for k, v in (extra or {}).items():
            if not is_extra_key(k):
                raise JournalError(f"extra field name {k!r} must match [A-Za-z0-9_]+")
            v = jsonable(v, finite=True)  # a NaN or infinite value is stored as null
            if v is not None and not isinstance(v, bool | int | float | str):
                raise JournalError(f"extra field {k!r} must be a number, string, bool or None, got {type(v)}")
            extra_doc[k] = v
        q_cmd = _vector(q_commanded, n, "q_commanded", allow_none=True)
        q_act = _vector(q_actual, n, "q_actual", allow_none=not valid)
        stored = measured_points(points, self.n_targets, allow_none=not valid)
        doc = MeasurementDoc(
            seq=self.next_seq,
            pose_index=pose_index,
            q_commanded=q_cmd,
            q_actual=q_act,
            points=stored,
            spread=measured_spread(spread, stored, self.n_targets),
            samples=int(samples),
            status=status,
            reason=str(reason),
            split=split,
            extra=extra_doc,
            time=float(_time.time() if time is None else time),
        )
        self._append(doc.to_json())
        self.next_seq += 1
        if valid:
            self._valid.add(pose_index)
        return doc

    def pause(self, reason: str) -> dict:
        """Record a pause (protective stop, Ctrl-C …); measurements need :meth:`resume` afterwards."""
        if self.state != "running":
            raise JournalError(f"cannot pause: the run is {self.state}")
        doc = self._append(_document("pause", reason=str(reason)))
        self.state = "paused"
        return doc

    def resume(self, reason: str = "") -> dict:
        """Record that measuring continues (after a pause, a stop with exit_status "paused", or a crash)."""
        doc = self._append(_document("resume", reason=str(reason)))
        self.state = "running"
        return doc

    def stop(self, exit_status: str, reason: str = "") -> StopDoc:
        """Record the end of a run: exit_status "success" | "aborted" | "paused" | "failed"."""
        if exit_status not in EXIT_STATUSES:
            raise JournalError(f"exit_status must be one of {EXIT_STATUSES}, got {exit_status!r}")
        if self.state == "stopped":
            raise JournalError("the run is already stopped")
        doc = StopDoc(exit_status, str(reason), self.next_seq - 1, time=_time.time())
        self._append(doc.to_json())
        self.state = "stopped"
        return doc

    def _append(self, doc: dict) -> dict:
        if self._fd is None:
            raise JournalError(f"journal {self.path} is closed")
        if self._broken:
            raise JournalError(f"a previous write to {self.path} failed; reopen the journal with Journal.open")
        line = _encode(doc)
        try:
            write_all(self._fd, line)
            os.fsync(self._fd)
        except OSError as e:
            self._broken = True
            import errno

            full = e.errno in (errno.ENOSPC, errno.EDQUOT)
            fix = "free space on its disk, then" if full else "fix the disk, then"
            raise JournalError(
                f"writing to journal {self.path} failed: {e.strerror or e}; every document before this one is on disk: "
                f"{fix} `labcal session resume {self.session_id}` continues after the last one"
            ) from e
        return doc


def _document(kind: str, **fields: Any) -> dict:
    """A pause, resume or repair document: its type, a new uid, the time and ``fields``."""
    return {"type": kind, "uid": str(uuid.uuid4()), "time": _time.time(), **fields}


def _encode(doc: dict) -> bytes:
    try:
        return (canonical_json(doc) + "\n").encode("utf-8")
    except (TypeError, ValueError) as e:
        raise JournalError(f"document is not JSON-serialisable (no NaN/inf, plain types only): {e}") from None


def _lock(fd: int, path: Path) -> None:
    if fcntl is None:  # pragma: no cover
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise JournalError(f"journal {path} is open for appending in another process") from None
