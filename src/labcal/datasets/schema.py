"""The measurements table: column names, units, dtypes and validation.

One row per valid measurement. Columns, in this order:

==================  ======  =============================================================================
``pose``            int     index of the configuration in the plan (or the row number of an import)
``q1`` … ``qn``     rad     joint positions reported by the robot (m for a prismatic joint)
``t1_x`` … ``t3_z`` m       the three target points, in the frame named by the manifest (base | tracker)
``split``           str     ``"train"``, ``"val"``, ``"test"`` or ``""`` (unassigned)
``spread_t1..t3``   m       optional: tracker spread of each target over the averaged samples
``timestamp``       s       optional: UNIX time of the measurement
``x_<name>``        any     optional passthrough columns (temperature, tracker std…); unit in the manifest
==================  ======  =============================================================================
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import numpy as np
import pandas as pd

from .errors import DatasetError

SCHEMA_VERSION = 1
SPLITS = ("train", "val", "test", "")
FRAMES = ("base", "tracker")
TARGET_COLUMNS = tuple(f"t{i}_{a}" for i in (1, 2, 3) for a in "xyz")
SPREAD_COLUMNS = ("spread_t1", "spread_t2", "spread_t3")
_EXTRA_RE = re.compile(r"^x_[A-Za-z0-9_]+$")


def joint_columns(n_joints: int) -> list[str]:
    return [f"q{j}" for j in range(1, n_joints + 1)]


def core_columns(n_joints: int) -> list[str]:
    return ["pose", *joint_columns(n_joints), *TARGET_COLUMNS, "split"]


def column_units(columns: list[str], extra_units: Mapping[str, str] | None = None) -> dict[str, str]:
    """Unit of every column (``"1"`` for dimensionless/int, ``""`` for text)."""
    extra_units = dict(extra_units or {})
    out: dict[str, str] = {}
    for c in columns:
        if c == "pose":
            out[c] = "1"
        elif re.fullmatch(r"q\d+", c):
            out[c] = "rad"
        elif c in TARGET_COLUMNS or c in SPREAD_COLUMNS:
            out[c] = "m"
        elif c == "split":
            out[c] = ""
        elif c == "timestamp":
            out[c] = "s"
        else:
            out[c] = extra_units.get(c, "")
    return out


def validate_split(value: object, row: int | None = None) -> str:
    s = "" if value is None else str(value).strip()
    if s not in SPLITS:
        where = f" at row {row}" if row is not None else ""
        raise DatasetError(f"unknown split value {value!r}{where}; allowed: train, val, test or empty")
    return s


def normalize_table(table: pd.DataFrame, n_joints: int) -> pd.DataFrame:
    """Check a measurements table and return it with canonical column order and dtypes.

    Raises :class:`DatasetError` naming the column (and row) at fault.
    """
    cols = list(table.columns)
    need = core_columns(n_joints)
    missing = [c for c in need if c not in cols]
    if missing:
        raise DatasetError(f"measurements table lacks column(s) {missing}")
    extra_q = [c for c in cols if re.fullmatch(r"q\d+", c) and c not in need]
    if extra_q:
        raise DatasetError(f"measurements table has joint column(s) {extra_q} but the robot has n={n_joints}")
    optional = [c for c in (*SPREAD_COLUMNS, "timestamp") if c in cols]
    extras = [c for c in cols if c not in need and c not in optional]
    bad = [c for c in extras if not _EXTRA_RE.match(c)]
    if bad:
        raise DatasetError(f"unknown column(s) {bad}; passthrough columns must be named x_<name>")
    out = pd.DataFrame(index=pd.RangeIndex(len(table)))
    pose = table["pose"].to_numpy()
    if len(pose) and (not np.issubdtype(pose.dtype, np.integer) or pose.min() < 0):
        raise DatasetError("column 'pose' must hold integers >= 0")
    out["pose"] = pose.astype(np.int64)
    for c in [*joint_columns(n_joints), *TARGET_COLUMNS]:
        v = np.asarray(table[c].to_numpy(), dtype=np.float64)
        nonfinite = np.flatnonzero(~np.isfinite(v))
        if len(nonfinite):
            raise DatasetError(f"column {c!r} has a non-finite value at row {int(nonfinite[0])}")
        out[c] = v
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
    values = s.tolist()
    present = [v for v in values if v is not None and not (isinstance(v, float) and np.isnan(v))]
    if all(isinstance(v, int | float | np.integer | np.floating) for v in present):
        return pd.Series(np.array([np.nan if v is None else v for v in values], dtype=np.float64))
    missing = [v is None or (isinstance(v, float) and np.isnan(v)) for v in values]
    return pd.Series(["" if m else str(v) for v, m in zip(values, missing, strict=True)], dtype="str")
