"""The cell around a robot: where it may go (an allowed box, keep-out boxes) and where the tracker stands.

Described by the ``[workspace]`` table of a robot profile (drivers/ur10-lab.toml), in millimetres in the robot's
base frame; held here in metres. The driver cannot check it (it needs the kinematic model): the planner does, on
the target points, the tool origin and every link origin of each pose it keeps (:mod:`labcal.sessions.planning`).

    [workspace]
    allowed_min_mm = [-1400.0, -1400.0, -50.0]   # the box every checked point stays in
    allowed_max_mm = [1400.0, 1400.0, 1600.0]
    tracker_mm = [2600.0, 0.0, 600.0]            # the tracker's origin (line of sight of the targets' normals)

    [[workspace.keep_out]]                       # any number of boxes no checked point may enter
    name = "tracker stand"
    min_mm = [2300.0, -300.0, -1000.0]
    max_mm = [2900.0, 300.0, 700.0]

Example::

    >>> w = parse_workspace({"allowed_min_mm": [-1e3] * 3, "allowed_max_mm": [1e3] * 3,
    ...                      "keep_out": [{"name": "table", "min_mm": [-1e3, -1e3, -1e3], "max_mm": [1e3, 1e3, 0]}]})
    >>> w.admits(np.array([[[0.0, 0.0, 0.5]], [[0.0, 0.0, -0.1]], [[2.0, 0.0, 0.5]]])).tolist()
    [True, False, False]
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from labcal.tomlschema import Key, SchemaError, Table, fail

_VEC3 = {"shape": (3,), "unit": "mm, robot base frame"}

WORKSPACE_SCHEMA = Table(
    {
        "allowed_min_mm": Key("vector", doc="lower corner of the box every checked point stays in", **_VEC3),
        "allowed_max_mm": Key("vector", doc="upper corner of that box", **_VEC3),
        "tracker_mm": Key("vector", doc="the tracker's origin, for the targets' line of sight", **_VEC3),
        "keep_out": Key(
            "tables",
            default=[],
            table=Table(
                {
                    "name": Key("str", required=True, doc="what the box is (table, tracker stand, fixture …)"),
                    "min_mm": Key("vector", required=True, **_VEC3),
                    "max_mm": Key("vector", required=True, **_VEC3),
                }
            ),
        ),
    },
    name="workspace",
)


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in the robot base frame: lo (3,) and hi (3,) corners, m; ``name`` for messages."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    name: str = "box"

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, dtype=float), np.asarray(self.hi, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError(f"box {self.name!r}: corners must be 3 finite numbers each (m)")
        if np.any(lo >= hi):
            raise ValueError(f"box {self.name!r}: every lower corner coordinate must be below the upper one")
        object.__setattr__(self, "lo", tuple(float(x) for x in lo))
        object.__setattr__(self, "hi", tuple(float(x) for x in hi))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """points (..., 3) m → (...) bool: inside the box (boundary included)."""
        p = np.asarray(points, dtype=float)
        return np.all((p >= np.asarray(self.lo)) & (p <= np.asarray(self.hi)), axis=-1)


@dataclass(frozen=True)
class Workspace:
    """Where a robot may be: every checked point inside ``allowed`` (None: anywhere) and in no ``keep_out`` box.

    tracker: (3,) the tracker's origin in the base frame, m, or None when not known.
    """

    allowed: Box | None = None
    keep_out: tuple[Box, ...] = ()
    tracker: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "keep_out", tuple(self.keep_out))
        if self.tracker is not None:
            t = np.asarray(self.tracker, dtype=float)
            if t.shape != (3,) or not np.all(np.isfinite(t)):
                raise ValueError(f"workspace tracker position must be 3 finite numbers (m), got {self.tracker!r}")
            object.__setattr__(self, "tracker", tuple(float(x) for x in t))

    @property
    def bounds_motion(self) -> bool:
        """True when the workspace restricts where the robot may go (an allowed box or a keep-out box)."""
        return self.allowed is not None or bool(self.keep_out)

    def admits(self, points: np.ndarray) -> np.ndarray:
        """points (k, p, 3) m, the checked points of k poses → (k,) bool: every point allowed."""
        p = np.asarray(points, dtype=float)
        ok = np.ones(p.shape[:-2], dtype=bool)
        if self.allowed is not None:
            ok &= self.allowed.contains(p).all(axis=-1)
        for box in self.keep_out:
            ok &= ~box.contains(p).any(axis=-1)
        return ok

    def offenders(self, points: np.ndarray) -> list[str]:
        """Names of what a single pose's points (p, 3) violate ("outside the allowed box", keep-out names)."""
        p = np.asarray(points, dtype=float)
        out = []
        if self.allowed is not None and not self.allowed.contains(p).all():
            out.append("outside the allowed box")
        out += [box.name for box in self.keep_out if box.contains(p).any()]
        return out


def parse_workspace(doc: dict[str, Any], source: str = "<workspace>", error: type[SchemaError] = SchemaError):
    """A :class:`Workspace` from a ``[workspace]`` table already checked against :data:`WORKSPACE_SCHEMA` (mm)."""
    has_min, has_max = "allowed_min_mm" in doc, "allowed_max_mm" in doc
    if has_min != has_max:
        raise fail(source, "workspace", "needs both allowed_min_mm and allowed_max_mm (or neither)", error)

    def box(lo, hi, name: str, where: str) -> Box:
        try:
            return Box(tuple(np.asarray(lo) / 1000.0), tuple(np.asarray(hi) / 1000.0), name)
        except ValueError:
            raise fail(source, where, "min_mm must be below max_mm in every coordinate", error) from None

    allowed = box(doc["allowed_min_mm"], doc["allowed_max_mm"], "allowed", "workspace.allowed") if has_min else None
    keep = tuple(
        box(b["min_mm"], b["max_mm"], b["name"], f"workspace.keep_out[{i}]")
        for i, b in enumerate(doc.get("keep_out", []))
    )
    tracker = doc.get("tracker_mm")
    return Workspace(allowed, keep, None if tracker is None else tuple(np.asarray(tracker) / 1000.0))
