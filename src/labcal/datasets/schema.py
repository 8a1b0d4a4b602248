"""The measurements table: column names, units, dtypes and validation.

One row per valid measurement. Columns, in this order:

==================  ======  =============================================================================
``pose``            int     index of the configuration in the plan (or the row number of an import)
``q1`` … ``qn``     rad     joint positions reported by the robot (m for a prismatic joint)
``t1_x`` … ``tm_z`` m       the m target points, in the frame named by the manifest (base | tracker); NaN = not seen
``split``           str     ``"train"``, ``"val"``, ``"test"`` or ``""`` (unassigned)
``spread_t1..tm``   m       optional: tracker spread of each target over the averaged samples (NaN = not seen)
``timestamp``       s       optional: UNIX time of the measurement
``x_<name>``        any     optional passthrough columns (temperature, tracker std…); unit in the manifest
==================  ======  =============================================================================

m (the number of targets, 1 or more) is the length of the manifest's targets list; three-target tables predate it
and look exactly as before. A target that was not seen in a row has all three of its cells NaN; a target with some
cells NaN and others not, or a row where no target was seen, is an error naming the row and the column. Example,
m = 2, the second target lost in row 1::

    pose  q1 … q6  t1_x  t1_y  t1_z  t2_x  t2_y  t2_z  split
    0     …        0.81  0.12  0.40  0.90  0.12  0.41  train
    1     …        0.75  0.30  0.38  NaN   NaN   NaN   train
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import TYPE_CHECKING

from .errors import DatasetError

if TYPE_CHECKING:
    import numpy as np
    import pandas as pd

# numpy and pandas are imported by the functions that check and build tables: journals and documents import this
# module for its constants, and listing or showing sessions (reading journals and manifests) must not pay for them.

SCHEMA_VERSION = 1
SPLITS = ("train", "val", "test", "")
FRAMES = ("base", "tracker")
_EXTRA_RE = re.compile(r"^x_[A-Za-z0-9_]+$")
_TARGET_RE = re.compile(r"^t\d+_[xyz]$")
_SPREAD_RE = re.compile(r"^spread_t(\d+)$")
# The unit of each kind of core column (column_units).
_UNITS = (
    (re.compile("pose"), "1"),
    (re.compile(r"q\d+"), "rad"),
    (re.compile(r"t\d+_[xyz]|spread_t\d+"), "m"),
    (re.compile("split"), ""),
    (re.compile("timestamp"), "s"),
)


def target_columns(m: int = 3) -> tuple[str, ...]:
    """``("t1_x", "t1_y", "t1_z", …, "tm_z")``: the 3·m point columns of m targets."""
    return tuple(f"t{i}_{a}" for i in range(1, m + 1) for a in "xyz")


def spread_columns(m: int = 3) -> tuple[str, ...]:
    """``("spread_t1", …, "spread_tm")``."""
    return tuple(f"spread_t{i}" for i in range(1, m + 1))


def joint_columns(n_joints: int) -> list[str]:
    return [f"q{j}" for j in range(1, n_joints + 1)]


def core_columns(n_joints: int, n_targets: int = 3) -> list[str]:
    return ["pose", *joint_columns(n_joints), *target_columns(n_targets), "split"]


def column_units(columns: list[str], extra_units: Mapping[str, str] | None = None) -> dict[str, str]:
    """Unit of every column (``"1"`` for dimensionless/int, ``""`` for text); ``x_*`` columns from ``extra_units``."""
    extra_units = dict(extra_units or {})
    return {c: next((u for rx, u in _UNITS if rx.fullmatch(c)), extra_units.get(c, "")) for c in columns}


def validate_split(value: object, row: int | None = None) -> str:
    s = "" if value is None else str(value).strip()
    if s not in SPLITS:
        where = f" at row {row}" if row is not None else ""
        raise DatasetError(f"unknown split value {value!r}{where}; allowed: train, val, test or empty")
    return s


def _check_points(p: np.ndarray) -> None:
    """Check (k, m ≥ 1, 3) points, a NaN row for each target not seen, against the rule of the table.

    Raises :class:`DatasetError` for a target with some coordinates NaN and others not (naming the row, 0-based as
    the table's index, the first empty coordinate and the fix), for a row with no target seen, and for ±inf anywhere.
    """
    import numpy as np

    if np.isinf(p).any():
        i, t, a = (int(v) for v in np.argwhere(np.isinf(p))[0])
        raise DatasetError(f"row {i}, column 't{t + 1}_{'xyz'[a]}': infinite value (an empty cell means not seen)")
    nan = np.isnan(p)
    partly = nan.any(axis=2) & ~nan.all(axis=2)
    if partly.any():
        i, t = (int(v) for v in np.argwhere(partly)[0])
        empty = [f"t{t + 1}_{a}" for a, e in zip("xyz", nan[i, t], strict=True) if e]
        given = [f"t{t + 1}_{a}" for a, e in zip("xyz", nan[i, t], strict=True) if not e]
        raise DatasetError(
            f"row {i}, column {empty[0]!r}: target t{t + 1} is partly empty ({', '.join(given)} given, "
            f"{', '.join(empty)} empty): give all three coordinates, or leave all three empty if it was not seen"
        )
    if (blind := np.flatnonzero(np.all(nan, axis=(1, 2)))).size:
        raise DatasetError(
            f"row {int(blind[0])}: no target seen (every target column empty): a row needs at least one measured "
            f"target; remove the row{f' (and {blind.size - 1} more like it)' if blind.size > 1 else ''}"
        )


def normalize_table(table: pd.DataFrame, n_joints: int, m: int) -> pd.DataFrame:
    """Check a measurements table and return it with canonical column order and dtypes.

    ``m``: the number of targets (the session's, at least 1). NaN in a target's three columns means the target was
    not seen (see the module docstring). Raises :class:`DatasetError` naming the column (and row) at fault.
    """
    cols = list(table.columns)
    need = core_columns(n_joints, m)
    missing = [c for c in need if c not in cols]
    if missing:
        raise DatasetError(f"measurements table lacks column(s) {missing}")
    extra_q = [c for c in cols if re.fullmatch(r"q\d+", c) and c not in need]
    if extra_q:
        raise DatasetError(f"measurements table has joint column(s) {extra_q} but the robot has n={n_joints}")
    extra_t = [c for c in cols if (_TARGET_RE.match(c) or _SPREAD_RE.match(c)) and c not in need]
    extra_t = [c for c in extra_t if not (_SPREAD_RE.match(c) and int(c[8:]) <= m)]
    if extra_t:
        raise DatasetError(f"measurements table has target column(s) {extra_t} but the session has {m} target(s)")
    optional = [c for c in (*spread_columns(m), "timestamp") if c in cols]
    extras = [c for c in cols if c not in need and c not in optional]
    bad = [c for c in extras if not _EXTRA_RE.match(c)]
    if bad:
        raise DatasetError(f"unknown column(s) {bad}; passthrough columns must be named x_<name>")
    import numpy as np
    import pandas as pd

    out = pd.DataFrame(index=pd.RangeIndex(len(table)))
    pose = table["pose"].to_numpy()
    if len(pose) and (not np.issubdtype(pose.dtype, np.integer) or pose.min() < 0):
        raise DatasetError("column 'pose' must hold integers >= 0")
    out["pose"] = pose.astype(np.int64)
    for c in joint_columns(n_joints):
        v = np.asarray(table[c].to_numpy(), dtype=np.float64)
        nonfinite = np.flatnonzero(~np.isfinite(v))
        if len(nonfinite):
            raise DatasetError(f"column {c!r} has a non-finite value at row {int(nonfinite[0])}")
        out[c] = v
    tcols = list(target_columns(m))
    points = np.stack([np.asarray(table[c].to_numpy(), dtype=np.float64) for c in tcols], axis=1)
    _check_points(points.reshape(len(table), m, 3))
    for j, c in enumerate(tcols):
        out[c] = points[:, j]
    out["split"] = [validate_split(s, i) for i, s in enumerate(table["split"].tolist())]
    out["split"] = out["split"].astype("str")
    for c in optional:
        out[c] = np.asarray(table[c].to_numpy(), dtype=np.float64)
    for c in extras:
        out[c] = _extra_column(table[c])
    return out


def _extra_column(s: pd.Series) -> pd.Series:
    """Passthrough values as float64 if all are numbers (missing → NaN), else as text (missing → "").

    One fixed rule keeps a column's dtype stable when later versions add rows that lack the value.
    """
    import numpy as np
    import pandas as pd

    values = s.tolist()
    present = [v for v in values if v is not None and not (isinstance(v, float) and np.isnan(v))]
    if all(isinstance(v, int | float | np.integer | np.floating) for v in present):
        return pd.Series(np.array([np.nan if v is None else v for v in values], dtype=np.float64))
    missing = [v is None or (isinstance(v, float) and np.isnan(v)) for v in values]
    return pd.Series(["" if m else str(v) for v, m in zip(values, missing, strict=True)], dtype="str")
