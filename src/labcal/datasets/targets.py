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
import tomllib
from pathlib import Path

import numpy as np

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


def load_targets(path: str | Path) -> np.ndarray:
    """Read a targets TOML file; return the (m, 3) targets in metres (row i = target t(i+1))."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise TargetsError(f"targets file {path} not found") from None
    except tomllib.TOMLDecodeError as e:
        raise TargetsError(f"targets file {path}: not valid TOML: {e}") from None
    if "unit" not in doc:
        raise TargetsError(f'targets file {path}: missing key "unit" (use unit = "m", "mm" or "in")')
    unit = doc["unit"]
    if unit not in LENGTH_UNITS:
        raise TargetsError(f'targets file {path}: unit must be "m", "mm" or "in", got {unit!r}')
    if "points" not in doc:
        raise TargetsError(f'targets file {path}: missing key "points" (a list of [x, y, z] lists, one per target)')
    pts = doc["points"]
    # Check the numbers before scaling so that a message shows what the user wrote.
    if not isinstance(pts, list) or len(pts) < 1:
        n = len(pts) if isinstance(pts, list) else "no"
        raise TargetsError(f"targets file {path}: expected at least 1 point ([x, y, z] each), got {n}")
    scaled = []
    for i, p in enumerate(pts):
        if not isinstance(p, list) or len(p) != 3:
            raise TargetsError(f"targets file {path}: point t{i + 1} must be [x, y, z], got {p!r}")
        row = []
        for j, v in enumerate(p):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise TargetsError(
                    f"targets file {path}: point t{i + 1} coordinate {'xyz'[j]} is not a finite number: {v!r}"
                )
            row.append(float(v) * LENGTH_UNITS[unit])
        scaled.append(row)
    return validate_targets(scaled, source=f"targets file {path}")
