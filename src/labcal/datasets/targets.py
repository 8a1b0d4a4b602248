"""The target points on the end effector (1 to k of them): validation and the targets TOML file.

File format (DESIGN.md section 4)::

    unit = "mm"            # "m", "mm" or "in"
    points = [[0, 0, 0], [100, 0, 0], [0, 100, 0]]   # t1, t2, t3 in the tool frame

    points = [[0, 0, 45]]  # a single reflector (SMR) 45 mm in front of the flange: one target

Inside labcal targets are an (m, 3) float array in metres, row i = target t(i+1). Any number of targets is
accepted as long as no two coincide (the same point listed twice is a typo). Targets on one line (two of them, or
a bar of reflectors) cannot show the rotation about that line, and a single target no rotation at all: that is
not an error but a limit of the set-up, which :func:`target_layout` names, the import checks note and the fit
reports.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.tomlschema import Key, Table, input_file_problem, is_number, read_toml, validate

from .errors import TargetsError

if TYPE_CHECKING:
    import numpy as np

# numpy is imported where targets are checked or measured: reading a session's journal (listing a store) imports
# this module without needing it.

#: Two targets closer than this (m) are the same point listed twice; targets within this of one line (or point)
#: are reported as lying on it by :func:`target_layout`.
MIN_TARGET_HEIGHT = 1e-3

#: Length units of targets files and imported measurements, to metres (inches for US-made tools and fixtures).
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "in": 0.0254}


def validate_targets(
    points: object,
    *,
    min_height: float = MIN_TARGET_HEIGHT,
    source: str = "targets",
) -> np.ndarray:
    """Return the targets as an (m, 3) float64 array in metres (m >= 1), or raise :class:`TargetsError`.

    ``points`` must already be in metres. Rejects no points, non-numeric or non-finite values and two targets
    closer than ``min_height`` m (the same point twice). Collinear targets are accepted (see :func:`target_layout`).
    """
    import numpy as np

    rows = points.tolist() if isinstance(points, np.ndarray) else points
    if (why := _points_problem(rows)) is not None:
        raise TargetsError(f"{source}: {why}")
    out = np.asarray(rows, dtype=np.float64)
    for i in range(len(out)):
        for j in range(i):
            gap = float(np.linalg.norm(out[i] - out[j]))
            if gap < min_height:
                raise TargetsError(
                    f"{source}: targets t{j + 1} and t{i + 1} coincide ({gap * 1e3:.3g} mm apart, minimum "
                    f"{min_height * 1e3:g} mm): list each target once"
                )
    return out


def target_layout(targets: np.ndarray, tol: float = MIN_TARGET_HEIGHT) -> str:
    """ "point" (one target), "line" (all within ``tol`` m of one line), "plane" or "solid": what the targets span.

    A point measures no rotation of the tool; a line no rotation about itself; a plane or solid every rotation.

    >>> import numpy as np
    >>> target_layout(np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]]))
    'line'
    """
    import numpy as np

    t = np.asarray(targets, dtype=float).reshape(-1, 3)
    if len(t) == 1:
        return "point"
    s = np.linalg.svd(t - t.mean(axis=0), compute_uv=False)
    # The spread of the targets off their best line (plane) is the second (third) singular value over √m.
    spread = s / math.sqrt(len(t))
    if spread[1] < tol:
        return "line"
    return "plane" if len(s) < 3 or spread[2] < tol else "solid"


def target_pairs(m: int) -> tuple[tuple[int, int], ...]:
    """Every pair (a, b), a < b, of m targets (0-based) in the order t1t2, t1t3, …, t2t3, …: the pairs whose
    distances :func:`pair_distances` gives by default. ``target_pairs(3) == ((0, 1), (0, 2), (1, 2))``."""
    return tuple(itertools.combinations(range(m), 2))


def pair_distances(points: np.ndarray, pairs: Sequence[tuple[int, int]] | None = None) -> np.ndarray:
    """(..., P) distances between the target points of ``points`` (..., m, 3) for each pair (a, b) of ``pairs``
    (default :func:`target_pairs`), in the points' unit; NaN where either point is NaN (a target not seen).

    Leading axes (rows of a session) are kept. For three points: |t1t2|, |t1t3|, |t2t3|.

    >>> import numpy as np
    >>> pair_distances(np.array([[0.0, 0, 0], [3, 0, 0], [0, 4, 0]])).tolist()
    [3.0, 4.0, 5.0]
    """
    import numpy as np

    p = np.asarray(points, dtype=float)
    pairs = target_pairs(p.shape[-2]) if pairs is None else pairs
    a, b = [i for i, _ in pairs], [j for _, j in pairs]
    return np.linalg.norm(p[..., a, :] - p[..., b, :], axis=-1)


def _points_problem(points: object) -> str | None:
    """Why ``points`` is not a list of [x, y, z] finite numbers (naming the target), or None: the targets file's
    rule and :func:`validate_targets`'."""
    if not isinstance(points, list | tuple) or not points:
        return f"must list at least 1 target point ([x, y, z] each), got {points!r}"
    for i, p in enumerate(points):
        if not isinstance(p, list | tuple) or len(p) != 3:
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
        # Optional: which way each reflector faces, for the planner's line of sight (labcal.sessions.planning).
        "normals": Key("vectors", shape=(None, 3), doc="one [x, y, z] direction per target, tool frame"),
        "acceptance_deg": Key("any", unit="deg", doc="half-angle a reflector answers within: one, or one per target"),
    },
    name="targets file",
)


def load_targets(path: str | Path) -> np.ndarray:
    """Read a targets TOML file; return the (m, 3) targets in metres (row i = target t(i+1))."""
    path = Path(path)
    why = input_file_problem(path)
    if why is not None:
        raise TargetsError(f"targets file {path} {why}", str(path))
    doc = validate(read_toml(path, TargetsError, "targets file"), TARGETS_SCHEMA, source=str(path), error=TargetsError)
    # The numbers were checked before scaling so that a message shows what the user wrote.
    scale = LENGTH_UNITS[doc["unit"]]
    scaled = [[float(v) * scale for v in p] for p in doc["points"]]
    try:
        return validate_targets(scaled, source=f"targets file {path}")
    except TargetsError as e:
        hint = _unit_hint(doc["points"], doc["unit"])
        if hint is None:
            raise
        raise TargetsError(f"{e}; {hint}", str(path)) from None


def _unit_hint(points: list, unit: str) -> str | None:
    """When targets coincide only because of the unit (numbers of a file in metres declared "mm"), the fix.

    The spread of the numbers as written: a tool's targets lie millimetres to decimetres apart, so a set that spans
    less than one unit of "mm" (or "in") but is a sensible tool in metres is a unit mistake, not a repeated point.
    """
    import numpy as np

    raw = np.asarray(points, dtype=float).reshape(-1, 3)
    if unit == "m" or len(raw) < 2:
        return None
    span = float(pair_distances(raw).max())
    if 0.0 < span < 1.0 and span >= MIN_TARGET_HEIGHT:
        return (
            f'the points span {span:g} {unit} as written, which is a tool of {span:g} m: write unit = "m" at the top '
            "of the file if the numbers are metres"
        )
    return None


def load_target_normals(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The targets file's ``normals`` (m, 3), unit vectors in the tool frame, and ``acceptance_deg`` as (m,) rad;
    None when the file gives no normals. Raises :class:`TargetsError` naming the key.

    ``acceptance_deg`` is required with ``normals``: one number for all targets or one per target, in (0, 90]
    (a reflector (SMR) answers within about ±30° to ±60° of its normal).
    """
    import numpy as np

    path = Path(path)
    doc = validate(read_toml(path, TargetsError, "targets file"), TARGETS_SCHEMA, source=str(path), error=TargetsError)
    if "normals" not in doc:
        if "acceptance_deg" in doc:
            raise TargetsError(f"{path}: acceptance_deg needs normals (one [x, y, z] per target)", str(path))
        return None
    m = len(doc["points"])
    normals = np.asarray(doc["normals"], dtype=float)
    if normals.shape != (m, 3):
        raise TargetsError(f"{path}: normals lists {len(normals)} directions for {m} targets; give one per target")
    length = np.linalg.norm(normals, axis=1)
    for i in np.flatnonzero(length < 1e-9):
        raise TargetsError(f"{path}: normals entry t{i + 1} is zero; give the direction the reflector faces")
    if "acceptance_deg" not in doc:
        raise TargetsError(f"{path}: normals need acceptance_deg (the reflectors' half-angle, e.g. 30)", str(path))
    raw = doc["acceptance_deg"]
    values = [raw] if is_number(raw) else raw
    ok = isinstance(values, list) and len(values) in (1, m) and all(is_number(v) and 0 < v <= 90 for v in values)
    if not ok:
        raise TargetsError(
            f"{path}: acceptance_deg must be one angle in (0, 90] degrees or {m} of them (one per target), got {raw!r}"
        )
    acceptance = np.radians(np.broadcast_to(np.asarray(values, dtype=float), (m,)))
    return normals / length[:, None], np.array(acceptance)
