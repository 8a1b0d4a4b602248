"""Typed run documents: the session header, and the start, measurement and stop documents of a journal.

A run is a start document (what is measured, with which robot model, targets, tracker and plan: the provenance),
numbered measurement documents (SI units named in each), and a stop document (exit status and why). On disk each
is one JSON object on one line of ``journal.jsonl`` (see :mod:`labcal.datasets.journal`); these classes are what
labcal reads and writes in between. ``to_json()`` gives exactly the JSON labcal has always written, and
``from_json()`` reads every journal written before the classes existed (missing optional keys get their old
defaults), so stored journals and versions read unchanged.

A :class:`SessionHeader` is the part of the start document a caller chooses (robot record, targets, frame, tracker
and robot identity, plan, units of the extra fields, metadata); it travels as one object from the CLI through the
runner to :meth:`SessionStore.create_session` instead of a dozen keyword arguments.

Unit identity: which physical arm (and tracker) the data come from, as opposed to the robot *model*. The header's
``unit`` (the robot's serial number when the controller tells it, else the id the operator gives with ``--unit``)
is written to ``metadata["unit"]``, so every manifest carries it and ``session list --unit`` / ``refit --unit`` /
``fit`` read it from one place; what the devices told about themselves (serial, model, firmware …) goes to
``robot_driver["identity"]`` and ``tracker["identity"]``. Sessions recorded before have neither and read as
"unit unknown"::

    {"type": "start", ..., "robot_driver": {"class": "...URRobot", "identity": {"serial": "20185500001",
     "model": "UR10", "software": "5.11.0.108249"}}, "metadata": {"unit": "20185500001", ...}}

Targets not seen: a measurement's ``points`` is a list of m entries, each ``[x, y, z]`` (m) or ``null`` for a
target the tracker did not see in that pose; ``spread`` likewise has ``null`` for it. Example (m = 2, t2 lost)::

    {"type": "measurement", "seq": 4, "pose_index": 3, "points": [[0.81, 0.12, 0.40], null],
     "spread": [2e-05, null], "status": "valid", "units": {"points": "m", ...}, ...}

    >>> MeasurementDoc.from_json(doc).points_array()       # (m, 3), NaN row for the target not seen
"""

from __future__ import annotations

import math
import time as _time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass, field, fields
from typing import TYPE_CHECKING, Any, ClassVar, Self

from ._util import jsonable, software_versions
from .errors import JournalError
from .schema import FRAMES, SCHEMA_VERSION
from .targets import validate_targets

# numpy is imported by the functions that check measurements: reading a journal (listing a store) needs none of them.
if TYPE_CHECKING:
    import numpy as np

EXIT_STATUSES = ("success", "aborted", "paused", "failed")
# A unit id is typed on command lines and matched exactly: printable, no blanks at the ends, and bounded so a
# confused device's whole reply cannot become one.
MAX_UNIT_LENGTH = 64
STATUSES = ("valid", "rejected")
MEASUREMENT_UNITS = {"q_commanded": "rad", "q_actual": "rad", "points": "m", "spread": "m", "time": "s"}


def _new_uid() -> str:
    return str(uuid.uuid4())


@dataclass(frozen=True)
class SessionHeader:
    """What a new session is about; becomes its start document.

    robot: the model's record, at least ``name``, ``hash``, ``n_joints`` (``RobotSpec.record()`` adds the robot
    file's ``text`` and ``format``, which makes the session refittable without the file); targets: (m, 3) m in the
    tool frame; frame: "base" | "tracker", the frame of the measured points; tracker / robot_driver: identity
    dicts of the drivers; plan: one JSON-able entry per pose; extra_units: unit of each ``extra`` measurement
    field; metadata: the caller's (runner settings, sim seeds …); session_id: None = a new id from the robot name;
    unit: the robot unit's id (serial number, or the operator's id), None = unknown; robot_identity /
    tracker_identity: what the devices reported about themselves (``serial``, ``model``, ``firmware`` …, plus
    ``notes`` for what could not be read), stored under ``robot_driver["identity"]`` / ``tracker["identity"]``.
    """

    robot: Mapping[str, Any]
    targets: Any
    frame: str
    tracker: Mapping[str, Any] = field(default_factory=dict)
    robot_driver: Mapping[str, Any] = field(default_factory=dict)
    plan: Sequence[Any] = ()
    extra_units: Mapping[str, str] = field(default_factory=dict)
    metadata: Mapping[str, Any] = field(default_factory=dict)
    session_id: str | None = None
    unit: str | None = None
    robot_identity: Mapping[str, Any] = field(default_factory=dict)
    tracker_identity: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def of(
        cls, robot_name: str, robot_hash: str, n_joints: int, record: Mapping[str, Any] | None = None, **fields: Any
    ) -> SessionHeader:
        """A header for the model (name, hash, n_joints), with its full ``record`` if there is one (the record must
        describe the same model)."""
        return cls(robot=robot_document(robot_name, robot_hash, n_joints, record), **fields)

    def start_document(self, session_id: str, *, time: float | None = None) -> StartDoc:
        """The start document of a session with this header (checked: frame, joint count, targets, unit keys)."""
        if self.frame not in FRAMES:
            raise JournalError(f"frame must be one of {FRAMES}, got {self.frame!r}")
        n = self.robot.get("n_joints")
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise JournalError(f"n_joints must be a positive integer, got {n!r}")
        for k in self.extra_units:
            if not is_extra_key(k):
                raise JournalError(f"extra field name {k!r} must match [A-Za-z0-9_]+")
        metadata = metadata_with_unit(self.metadata, self.unit)
        # Only sessions whose devices said something carry the key: the others' documents read as before.
        tracker, robot_driver = dict(self.tracker), dict(self.robot_driver)
        if self.tracker_identity:
            tracker["identity"] = dict(self.tracker_identity)
        if self.robot_identity:
            robot_driver["identity"] = dict(self.robot_identity)
        return StartDoc(
            session_id=session_id,
            robot=robot_document(self.robot["name"], self.robot["hash"], n, self.robot),
            targets=validate_targets(self.targets).tolist(),
            frame=self.frame,
            tracker=jsonable(tracker),
            robot_driver=jsonable(robot_driver),
            plan=jsonable(list(self.plan)),
            extra_units=dict(self.extra_units),
            metadata=jsonable(metadata),
            software=software_versions(),
            time=float(_time.time() if time is None else time),
        )


def check_unit(value: object, what: str = "unit") -> str:
    """A robot unit id as stored: a non-empty printable string of at most 64 characters, no blanks at the ends.

    >>> check_unit("UR10-2019-0417")
    'UR10-2019-0417'
    """
    if not isinstance(value, str):
        raise JournalError(f"{what} must be a string (the robot unit's id, e.g. its serial number), got {value!r}")
    if not value or value != value.strip() or not value.isprintable() or len(value) > MAX_UNIT_LENGTH:
        raise JournalError(
            f"{what} {value!r} is not a unit id: give 1 to {MAX_UNIT_LENGTH} printable characters without leading or "
            "trailing blanks (e.g. the serial number on the controller's label)"
        )
    return value


def metadata_with_unit(metadata: Mapping[str, Any] | None, unit: str | None, what: str = "unit") -> dict:
    """The caller's metadata with ``"unit"`` set: ``unit`` wins over a ``unit`` key of the metadata, and either is
    checked (:func:`check_unit`; ``what`` names the given one in the error)."""
    out = dict(metadata or {})
    if unit is not None:
        out["unit"] = check_unit(unit, what)
    elif "unit" in out:
        out["unit"] = check_unit(out["unit"], "metadata unit")
    return out


def is_extra_key(k: object) -> bool:
    """A name for an ``extra`` field: 1 to 64 ASCII letters, digits or ``_``."""
    return isinstance(k, str) and 1 <= len(k) <= 64 and all(c.isascii() and (c.isalnum() or c == "_") for c in k)


class _Document:
    """A journal document. Its JSON is ``type`` and every field under the field's name, exactly as labcal has always
    written it (the journal writes it with sorted keys)."""

    type: ClassVar[str]

    def to_json(self) -> dict:
        return {"type": self.type, **{f.name: getattr(self, f.name) for f in fields(self)}}  # type: ignore[arg-type]

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> Self:
        """The document of a journal line written at any time: a key that older journals lack takes the field's
        default (``uid`` "": they had none), so does an empty or null table or list of a field that has one; numbers,
        text, tables and lists are read as their field's type."""
        values: dict[str, Any] = {"uid": ""}
        for f in fields(cls):  # type: ignore[arg-type]
            has_default = f.default is not MISSING or f.default_factory is not MISSING
            if f.name not in doc or (has_default and f.type in ("dict", "list") and not doc[f.name]):
                continue
            values[f.name] = _READ_AS.get(f.type, lambda v: v)(doc[f.name])  # type: ignore[arg-type]
        return cls(**values)


# How from_json reads a field of each declared type (the others as they are: lists or None, text or None …).
_READ_AS = {"dict": dict, "list": list, "float": float, "int": int, "str": str}


@dataclass(frozen=True)
class StartDoc(_Document):
    """The first document of a journal. ``targets``: m lists [x, y, z] in m, tool frame; ``robot``: name, hash,
    n_joints (+ text, format); ``plan``: one entry per pose (model joints)."""

    type: ClassVar[str] = "start"
    session_id: str
    robot: dict
    targets: list
    frame: str = "base"  # the frame of journals written before it was recorded
    tracker: dict = field(default_factory=dict)
    robot_driver: dict = field(default_factory=dict)
    plan: list = field(default_factory=list)
    extra_units: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    software: dict = field(default_factory=dict)
    uid: str = field(default_factory=_new_uid)
    time: float = 0.0
    schema_version: int = SCHEMA_VERSION
    targets_unit: str = "m"

    @property
    def n_joints(self) -> int:
        return int(self.robot["n_joints"])

    @property
    def robot_hash(self) -> str:
        return str(self.robot["hash"])

    @property
    def n_targets(self) -> int:
        return len(self.targets)

    @property
    def robot_identity(self) -> dict:
        """What the robot controller reported about itself (serial, model, software …); {} if nothing."""
        return dict(self.robot_driver.get("identity") or {})

    def targets_array(self) -> np.ndarray:
        """(m, 3) m."""
        import numpy as np

        return np.asarray(self.targets, dtype=np.float64).reshape(-1, 3)


@dataclass(frozen=True)
class MeasurementDoc(_Document):
    """One pose's final outcome. q_*: (n,) rad, controller joints; points: m entries ``[x, y, z]`` (m, session
    frame) or None for a target not seen (the whole ``points`` is None when a rejected pose has none); spread: m
    entries, m, None where unknown; status "valid" | "rejected" with ``reason``; extra: the runner's fields."""

    type: ClassVar[str] = "measurement"
    seq: int
    pose_index: int
    q_commanded: list | None
    q_actual: list | None
    points: list | None
    spread: list | None = None
    samples: int = 1
    status: str = "valid"
    reason: str = ""
    split: str | None = None
    extra: dict = field(default_factory=dict)
    units: dict = field(default_factory=lambda: dict(MEASUREMENT_UNITS))
    uid: str = field(default_factory=_new_uid)
    time: float = 0.0

    @property
    def valid(self) -> bool:
        return self.status == "valid"

    @property
    def q(self) -> list:
        """The joints the row is stored with: q_actual, else (a row recorded without a read-back) q_commanded."""
        return self.q_actual if self.q_actual is not None else self.q_commanded  # type: ignore[return-value]

    def points_array(self, m: int | None = None) -> np.ndarray | None:
        """(m, 3) m with NaN rows for targets not seen, or None if the document has no points."""
        if self.points is None:
            return None
        import numpy as np

        rows = [[math.nan] * 3 if p is None else p for p in self.points]
        out = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
        if m is not None and out.shape[0] != m:
            raise JournalError(f"measurement seq {self.seq} has {out.shape[0]} target(s), the session {m}")
        return out


@dataclass(frozen=True)
class StopDoc(_Document):
    """The end of a run: ``exit_status`` "success" | "aborted" | "paused" | "failed", ``reason``, and the number of
    measurement documents in the journal at that point."""

    type: ClassVar[str] = "stop"
    exit_status: str
    reason: str = ""
    num_measurements: int | None = None
    uid: str = field(default_factory=_new_uid)
    time: float = 0.0

    def to_json(self) -> dict:
        doc = super().to_json()
        if self.num_measurements is None:  # stop documents written without the count have no key for it
            del doc["num_measurements"]
        return doc


def robot_document(name: str, robot_hash: str, n_joints: int, record: Mapping[str, Any] | None = None) -> dict:
    """The ``robot`` block of a start document / manifest: name, hash, n_joints plus the record's other keys.

    The record (``RobotSpec.record()``) carries the robot file's text so the data can be refitted without the
    file; it must describe the same model (same name, hash and joint count), else the session would be mislabelled.
    """
    doc: dict[str, Any] = {"name": str(name), "hash": str(robot_hash), "n_joints": n_joints}
    for key, value in dict(record or {}).items():
        if key in doc:
            if value is not None and value != doc[key]:
                raise JournalError(f"robot record {key} = {value!r} disagrees with the session's {doc[key]!r}")
            continue
        doc[str(key)] = jsonable(value)
    return doc


def measured_points(value: Any, m: int, *, allow_none: bool) -> list | None:
    """Points as the journal stores them: m entries ``[x, y, z]`` or None (not seen).

    ``value``: (m, 3) m with a NaN row for each target not seen. A target partly NaN, or (for a valid
    measurement, ``allow_none=False``) no target seen at all, is refused; a rejected measurement may have lost
    every target, or any coordinate: it keeps what JSON can hold (None)."""
    if value is None:
        if allow_none:
            return None
        raise JournalError("points are required for a valid measurement")
    import numpy as np

    a = np.asarray(value, dtype=np.float64)
    if a.shape != (m, 3):
        raise JournalError(f"points must have shape ({m}, 3) (targets × xyz, m), got {a.shape}")
    finite = np.isfinite(a)
    seen = np.all(finite, axis=1)  # np.all, not finite.all: numpy's stub types the method's as "a bool or an array"
    if allow_none:
        return None if not seen.any() else [row.tolist() if ok else None for row, ok in zip(a, seen, strict=True)]
    lost = ~finite.any(axis=1) & np.isnan(a).all(axis=1)
    bad = ~seen & ~lost
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise JournalError(
            f"points have a non-finite value in target t{i + 1} ({a[i].tolist()}): a target not seen is all NaN, "
            "one seen is finite"
        )
    if not seen.any():
        raise JournalError(f"points have no seen target (all non-finite: {a.tolist()}); a valid measurement needs one")
    return [row.tolist() if ok else None for row, ok in zip(a, seen, strict=True)]


def measured_spread(value: Any, points: list | None, m: int) -> list | None:
    """Spread per target (m,) m as stored: None for a target not seen or a non-finite value."""
    if value is None:
        return None
    import numpy as np

    a = np.asarray(value, dtype=np.float64)
    if a.shape != (m,):
        raise JournalError(f"spread must have shape ({m},), got {a.shape}")
    # Without points (a rejected pose) a NaN spread is simply unknown; with them, a seen target needs its spread.
    seen = [False] * m if points is None else [p is not None for p in points]
    if np.isinf(a).any() or any(ok and not math.isfinite(v) for ok, v in zip(seen, a.tolist(), strict=True)):
        raise JournalError(f"spread has a non-finite value: {a.tolist()}")
    if points is None:
        return [float(v) if math.isfinite(v) else None for v in a.tolist()]
    return [float(v) if ok and math.isfinite(v) else None for ok, v in zip(seen, a.tolist(), strict=True)]
