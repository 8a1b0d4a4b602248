"""The target points on the end effector (1 to k of them): validation and the targets TOML file.

File format (DESIGN.md section 4)::

    unit = "mm"            # "m", "mm" or "in"
    points = [[0, 0, 0], [100, 0, 0], [0, 100, 0]]   # t1, t2, t3 in the tool frame

    points = [[0, 0, 45]]  # a single reflector (SMR) 45 mm in front of the flange: one target

Inside labcal targets are an (m, 3) float array in metres, row i = target t(i+1). Three targets must span a
triangle (three in a row would leave the rotation about their line unmeasured, so the file is most likely wrong);
one or two targets, or more than three, are accepted as long as no two of them coincide. What a set of fewer than
three targets cannot identify is the fit's to report.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from labcal.tomlschema import Key, Table, is_number, read_toml, validate

from .errors import TargetsError

#: The three targets must span a triangle at least this large (m²) …
MIN_TARGET_AREA = 1e-6
#: … and each target must be at least this far (m) from the line through the other two, otherwise the
#: orientation about that line is unobservable and the fit ill-conditioned.
MIN_TARGET_HEIGHT = 1e-3

#: Length units of targets files and imported measurements, to metres (inches for US-made tools and fixtures).
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "in": 0.0254}


def validate_targets(
    points: object,
    *,
    min_area: float = MIN_TARGET_AREA,
    min_height: float = MIN_TARGET_HEIGHT,
    source: str = "targets",
) -> np.ndarray:
    """Return the targets as an (m, 3) float64 array in metres (m >= 1), or raise :class:`TargetsError`.

    ``points`` must already be in metres. Rejects no points, non-numeric or non-finite values, two targets closer
    than ``min_height`` m (the same point twice) and, for exactly three targets, (nearly) collinear ones: triangle
    area < ``min_area`` m² or a triangle height < ``min_height`` m.
    """
    rows = points.tolist() if isinstance(points, np.ndarray) else points
    if not isinstance(rows, list | tuple) or len(rows) < 1:
        n = len(rows) if isinstance(rows, list | tuple) else "no"
        raise TargetsError(f"{source}: expected at least 1 target point ([x, y, z] each), got {n}")
    out = np.empty((len(rows), 3))
    for i, p in enumerate(rows):
        if not isinstance(p, list | tuple) or len(p) != 3:
            raise TargetsError(f"{source}: target t{i + 1} must be [x, y, z], got {p!r}")
        for j, v in enumerate(p):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise TargetsError(f"{source}: target t{i + 1} coordinate {'xyz'[j]} is not a finite number: {v!r}")
            out[i, j] = float(v)
    if len(out) != 3:
        for i in range(len(out)):
            for j in range(i):
                gap = float(np.linalg.norm(out[i] - out[j]))
                if gap < min_height:
                    raise TargetsError(
                        f"{source}: targets t{j + 1} and t{i + 1} coincide ({gap * 1e3:.3g} mm apart, minimum "
                        f"{min_height * 1e3:g} mm): list each target once"
                    )
        return out
    a, b, c = out
    area = 0.5 * float(np.linalg.norm(np.cross(b - a, c - a)))
    sides = [np.linalg.norm(c - b), np.linalg.norm(a - c), np.linalg.norm(b - a)]
    longest = max(sides)
    height = 2 * area / longest if longest > 0 else 0.0
    if area < min_area or height < min_height:
        raise TargetsError(
            f"{source}: the three targets are (nearly) collinear or coincident: triangle area {area:.3g} m² "
            f"(minimum {min_area:g}), smallest height {height * 1e3:.3g} mm (minimum {min_height * 1e3:g} mm)"
        )
    return out


def _points_problem(points: object) -> str | None:
    """Why ``points`` is not a list of [x, y, z] numbers (naming the target), or None."""
    if not isinstance(points, list) or not points:
        return f"must list the targets as [x, y, z] points (at least 1 point), got {points!r}"
    for i, p in enumerate(points):
        if not isinstance(p, list) or len(p) != 3:
            return f"entry t{i + 1} must be [x, y, z], got {p!r}"
        for j, v in enumerate(p):
            if not is_number(v):
                return f"entry t{i + 1} coordinate {'xyz'[j]} is not a finite number: {v!r}"
    return None


#: The targets file, for the one TOML validator (:mod:`labcal.tomlschema`). The unit has no default on purpose: a
#: file of millimetres read as metres would pass every other check.
TARGETS_SCHEMA = Table(
    {
        "unit": Key("str", required=True, choices=tuple(LENGTH_UNITS), doc='"m", "mm" or "in"'),
        "points": Key("any", required=True, check=_points_problem, doc="one [x, y, z] per target, tool frame"),
    },
    name="targets file",
)


def load_targets(path: str | Path) -> np.ndarray:
    """Read a targets TOML file; return the (m, 3) targets in metres (row i = target t(i+1))."""
    path = Path(path)
    if not path.is_file():
        raise TargetsError(f"targets file {path} not found", str(path))
    doc = validate(read_toml(path, TargetsError, "targets file"), TARGETS_SCHEMA, source=str(path), error=TargetsError)
    # The numbers were checked before scaling so that a message shows what the user wrote.
    scaled = [[float(v) * LENGTH_UNITS[doc["unit"]] for v in p] for p in doc["points"]]
    return validate_targets(scaled, source=f"targets file {path}")
