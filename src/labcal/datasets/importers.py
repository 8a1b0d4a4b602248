"""Import external measurement files into the session store (DESIGN.md section 4, "Import").

Three forms, all ending in one atomic step: a new session with ``v001`` (or, with ``session_id`` of an
existing session, a new version of it whose parent is the latest):

- :func:`import_targets_csv`: columns ``q1..qn`` and ``t1_x, t1_y, t1_z, t2_x … tm_z`` (the m measured target
  points, m = the number of points in the targets file), optional ``split`` column (train / val / test / empty).
  An empty target cell means the target was not seen in that row: all three cells of a target are empty or none
  is, and every row has at least one target (errors name the row, its line and the column).
- :func:`import_probe_csv`: columns ``q1..qn`` and ``x, y, z, rx, ry, rz``: the pose of a 6-DOF probe (the
  tool) in the base or tracker frame. The rotation is a rotation vector (UR style) or Euler angles with a scipy
  sequence (``"XYZ"`` = intrinsic, ``"xyz"`` = extrinsic). Each row becomes three *virtual* targets
  ``p_i = R · v_i + t`` for offsets ``v_i`` in the probe frame (default (0,0,0), (0.1,0,0), (0,0.1,0) m); the
  offsets are stored as the session's targets so a fit uses the same ones.
- :func:`import_mapped`: any CSV described by a column-mapping TOML file (separator, decimal mark, joint
  columns, target or probe columns, units, Euler convention, frame, passthrough columns). Shipped mappings
  live in ``labcal/datasets/mappings/`` (see :func:`list_mappings`), e.g. ``ipa-ur10`` for the public UR10
  laser-tracker data set.

How to read the file (units, frame, separator, probe convention …) and what to record with it (session, metadata,
robot model, allowed checks) is one :class:`ImportOptions`; keyword arguments of the same names are a shorthand::

    import_targets_csv(store, "data.csv", "ur10", h, 6, targets, ImportOptions(length_unit="mm", frame="tracker"))
    import_targets_csv(store, "data.csv", "ur10", h, 6, targets, length_unit="mm", frame="tracker")   # the same

Errors name the file, the 1-based data row (header not counted) with its line in the file, and the column.

Before anything is written the parsed rows pass :mod:`labcal.datasets.sanity` (unit slips, targets file vs data,
joint limits after the robot's joint map, nominal consistency, reach, duplicated poses …; the model checks need
``robot=RobotSpec``). A failed check raises :class:`~labcal.datasets.sanity.SanityError` naming the rows and the
fix; ``allow=[CHECK, …]`` overrides named checks and is recorded in the version's import provenance together with
the checks' notes and numbers (``provenance.import.checks``).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from labcal.tomlschema import Key, Table, decode_text, fail, input_file_problem, read_toml, validate

from ._util import sha256_file
from .documents import metadata_with_unit
from .errors import DatasetError, ImportFormatError, MappingError, TargetsError
from .ids import validate_id
from .sanity import Hints, SanityReport, check_measurements, check_names
from .schema import FRAMES, SPLITS, joint_columns, target_columns
from .store import SessionStore, _plan_summary
from .targets import LENGTH_UNITS, validate_targets

if TYPE_CHECKING:
    from labcal.robots import RobotSpec

ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
#: Default virtual target offsets of the probe form, in the probe frame (m).
DEFAULT_PROBE_OFFSETS = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
MAPPINGS_DIR = Path(__file__).parent / "mappings"
#: A scipy Euler sequence: three axes of one case (upper: intrinsic, lower: extrinsic), none twice in a row.
_EULER_SEQUENCE = re.compile(r"(?!.*(.)\1)(?:[XYZ]{3}|[xyz]{3})")
#: Units an extra (passthrough) column may be converted from, to SI.
_TO_SI = {"mm": ("m", 1e-3), "deg": ("rad", math.pi / 180.0)}


@dataclass(frozen=True)
class ExtraColumn:
    """A passthrough column: ``column`` in the file → ``x_<name>`` in the table. mm/deg are converted to
    m/rad; any other unit is stored as given and named in the manifest."""

    column: str
    name: str
    unit: str = ""
    kind: str = "float"  # "float" | "str"


@dataclass(frozen=True)
class ImportSpec:
    """Everything an import needs to turn a CSV into measurements (built from arguments or a mapping)."""

    form: str  # "targets" | "probe"
    joints: tuple[str, ...]
    frame: str
    joint_unit: str = "rad"
    separator: str = ","
    decimal: str = "."
    target_columns: tuple[tuple[str, str, str], ...] = ()
    length_unit: str = "m"
    position: tuple[str, str, str] = ("x", "y", "z")
    rotation: tuple[str, str, str] = ("rx", "ry", "rz")
    rotation_unit: str = "rad"
    convention: str = "rotvec"  # "rotvec" | "euler"
    euler_sequence: str | None = None
    split_column: str | None = "split"
    split_required: bool = False
    #: Refuse columns q{n+1}, q{n+2} … (the plain CSV form names its joints q1..qn).
    reject_extra_joints: bool = False
    timestamp_column: str | None = None
    extras: tuple[ExtraColumn, ...] = ()
    tracker: dict = field(default_factory=dict)
    description: str = ""

    def check(self) -> None:
        for value, allowed, rule in (
            (self.form, ("targets", "probe"), 'form must be "targets" or "probe"'),
            (self.frame, FRAMES, f"frame must be one of {FRAMES}"),
            (self.joint_unit, ANGLE_UNITS, 'joint angle unit must be "rad" or "deg"'),
            (self.length_unit, LENGTH_UNITS, 'length unit must be "m", "mm" or "in"'),
            (self.rotation_unit, ANGLE_UNITS, 'rotation angle unit must be "rad" or "deg"'),
            (self.convention, ("rotvec", "euler"), 'rotation convention must be "rotvec" or "euler"'),
        ):
            if value not in allowed:
                raise MappingError(f"{rule}, got {value!r}")
        if len(self.separator) != 1 or len(self.decimal) != 1 or self.separator == self.decimal:
            raise MappingError(
                f"separator {self.separator!r} and decimal mark {self.decimal!r} must be single, different characters"
            )
        if self.form == "probe" and self.convention == "euler":
            _check_sequence(self.euler_sequence)
        if self.form == "targets" and len(self.target_columns) < 1:
            raise MappingError("the targets form needs a target column triple [x, y, z] per target")
        names = [e.name for e in self.extras]
        if len(set(names)) != len(names):
            raise MappingError(f"duplicate extra column names {names}")
        for e in self.extras:
            validate_id(e.name, "extra column name")
            if not all(c.isalnum() or c == "_" for c in e.name):
                raise MappingError(f"extra column name {e.name!r} may hold letters, digits and '_' only")
            if e.kind not in ("float", "str"):
                raise MappingError(f'extra column {e.name!r}: type must be "float" or "str", got {e.kind!r}')


def _check_sequence(seq: object) -> str:
    if not (isinstance(seq, str) and _EULER_SEQUENCE.fullmatch(seq)):
        raise MappingError(
            f"Euler sequence must be 3 axes, all upper case (intrinsic, e.g. 'XYZ') or all lower case "
            f"(extrinsic, e.g. 'xyz'), no axis twice in a row; got {seq!r}"
        )
    return seq


# --------------------------------------------------------------------------------------------------------------
# CSV reading with row/column-precise errors


class _Csv:
    """A CSV read as text. ``rows`` are data rows (blank lines dropped); ``lines[i]`` is row i's file line."""

    def __init__(self, path: Path, separator: str) -> None:
        self.path, self.separator = path, separator
        why = input_file_problem(path)
        if why is not None:
            raise ImportFormatError(f"{path} {why}")
        try:
            data = path.read_bytes()
        except OSError as e:
            raise ImportFormatError(f"cannot be read ({e.strerror or e})", path=str(path)) from None
        text = decode_text(data, path, ImportFormatError, "CSV file")  # the line and the fix of a non-UTF-8 byte
        _refuse_comments(text, path, separator)
        # strict: a quote left open (or text after a closing quote) is refused with its line instead of swallowing
        # the rest of the file into one field.
        rows: list[list[str]] = []
        try:
            rows.extend(csv.reader(io.StringIO(text, newline=""), delimiter=separator, strict=True))
        except csv.Error as e:  # the rows before the bad one are read: it starts on the next line
            raise ImportFormatError(f"malformed CSV: {e}", path=str(path), line=len(rows) + 1) from None
        if not rows or not any(h.strip() for h in rows[0]):
            raise ImportFormatError("empty file (no header line)", path=str(path))
        names = [h.strip() for h in rows[0]]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ImportFormatError(f"duplicate column name(s) {dupes} in the header", path=str(path), line=1)
        long = next((i for i, row in enumerate(rows, start=1) if len(row) > len(names)), None)
        if long is not None:  # a longer row would be cut to the header or shift every field after it
            raise ImportFormatError(
                f"a row has more fields than the {len(names)} columns of the header{_separator_hint(names, separator)}",
                path=str(path), line=long,
            )  # fmt: skip
        # A short row is padded with empty cells (named as missing values where a value is needed).
        df = pd.DataFrame([row + [""] * (len(names) - len(row)) for row in rows[1:]], columns=names, dtype=str)
        blank = (df.apply(lambda s: s.str.strip()) == "").all(axis=1).to_numpy()
        self.lines = np.flatnonzero(~blank) + 2  # header is line 1
        self.frame = df.loc[~blank].reset_index(drop=True)
        self.columns = names
        if len(self.frame) == 0:
            raise ImportFormatError("no data rows after the header", path=str(path))

    def __len__(self) -> int:
        return len(self.frame)

    def require(self, columns: Sequence[str], what: str) -> None:
        missing = [c for c in columns if c not in self.columns]
        if missing:
            hint = _separator_hint(self.columns, self.separator)
            raise ImportFormatError(
                f"missing {what} column(s) {missing}; the file has columns {self.columns}{hint}", path=str(self.path)
            )

    def error(self, message: str, index: int, column: str | None = None) -> ImportFormatError:
        return ImportFormatError(
            message, path=str(self.path), row=index + 1, line=int(self.lines[index]), column=column
        )

    def numbers(self, column: str, decimal: str, *, allow_missing: bool = False, empty_ok: bool = False) -> np.ndarray:
        """Column ``column`` as float64; raises naming the first bad row (missing, non-numeric, NaN, inf).

        ``allow_missing``: empty cells and NaN/inf become NaN; ``empty_ok``: empty cells only (a target not seen)."""
        text = self.frame[column].str.strip()
        if decimal != ".":
            if (bad := text.str.contains(".", regex=False)).any():
                at = int(np.flatnonzero(bad.to_numpy())[0])
                raise self.error(f"value {text[at]!r} has '.' but the decimal mark is {decimal!r}", at, column)
            text = text.str.replace(decimal, ".", regex=False)
        values = pd.to_numeric(text, errors="coerce").to_numpy(dtype=np.float64, copy=True)
        for i in map(int, np.flatnonzero(~np.isfinite(values))):
            raw, word = text[i], text[i].lower().lstrip("+-") in ("nan", "inf", "infinity")
            if raw == "" and not (allow_missing or empty_ok):
                raise self.error("missing value", i, column)
            if word and not allow_missing:
                empty = "; leave the cell empty for a target not seen" if empty_ok else ""
                raise self.error(f"non-finite value {raw!r} (NaN/inf are not measurements{empty})", i, column)
            if raw and not word:
                raise self.error(f"non-numeric value {self.frame[column][i]!r}", i, column)
        if allow_missing or empty_ok:
            values[~np.isfinite(values)] = np.nan
        return values

    def check_seen(self, columns: Sequence[str], points: np.ndarray) -> None:
        """Refuse a target partly empty and a row with no target seen (points (k, m, 3), NaN = empty cell)."""
        nan = np.isnan(points)
        partly = nan.any(axis=2) & ~nan.all(axis=2)
        if partly.any():
            i, t = (int(v) for v in np.argwhere(partly)[0])
            cols = columns[3 * t : 3 * t + 3]
            empty = [c for c, e in zip(cols, nan[i, t], strict=True) if e]
            given = [c for c, e in zip(cols, nan[i, t], strict=True) if not e]
            raise self.error(
                f"target t{t + 1} is partly empty ({', '.join(given)} given, {', '.join(empty)} empty): give all "
                "three coordinates, or leave all three empty if the target was not seen",
                i,
                empty[0],
            )
        blind = np.flatnonzero(nan.all(axis=(1, 2)))
        if blind.size:
            more = f" ({blind.size - 1} more row(s) like it)" if blind.size > 1 else ""
            raise self.error(
                f"no target seen: every target column ({columns[0]} … {columns[-1]}) is empty; a row needs at least "
                f"one measured target: remove the row{more}",
                int(blind[0]),
            )


def _separator_hint(names: Sequence[str], separator: str) -> str:
    """The fix when the header is one column that holds the others: the file uses another separator (and, with ';',
    usually decimal commas, which is why the data rows split on the ',' the header lacks)."""
    joined = next((sep for sep in (";", "\t", "|") if sep != separator and len(names) == 1 and sep in names[0]), None)
    if joined is None:
        return ""
    shown = "\\t" if joined == "\t" else joined
    return (
        f"; the header looks {joined!r}-separated: describe the file with a --mapping TOML that says "
        f'separator = "{shown}" (and decimal = "," if its numbers have decimal commas; see labcal\'s mappings/'
        "ipa-ur10.toml)"
    )


def _refuse_comments(text: str, path: Path, separator: str) -> None:
    """A line starting with '#' (a comment some exporters write above the header) names its line and the fix,
    instead of becoming the header or a row with more fields than it."""
    for i, line in enumerate(text.splitlines(), start=1):
        if line.lstrip().startswith("#"):
            raise ImportFormatError(
                f"a comment line ({line.strip()[:40]!r}): labcal reads the first line as the column header and every "
                "other line as a row; delete the comment lines (e.g. `grep -v '^#' in.csv > out.csv`)",
                path=str(path),
                line=i,
            )


def _rotations(angles: np.ndarray, spec: ImportSpec) -> np.ndarray:
    """(k, 3) angles in ``spec.rotation_unit`` → (k, 3, 3) rotation matrices."""
    from scipy.spatial.transform import Rotation

    a = angles * ANGLE_UNITS[spec.rotation_unit]
    if spec.convention == "rotvec":
        return Rotation.from_rotvec(a).as_matrix()
    return Rotation.from_euler(_check_sequence(spec.euler_sequence), a).as_matrix()


def probe_points(position: np.ndarray, rotation: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Virtual targets of a 6-DOF probe: ``p_i = R · v_i + t``.

    position: (k, 3) m; rotation: (k, 3, 3); offsets: (m, 3) m, row i = v_i in the probe frame.
    Returns (k, m, 3) m, ``[:, i]`` = target t(i+1).
    """
    return np.einsum("kab,ib->kia", rotation, offsets) + position[:, None, :]


def _build_rows(csvf: _Csv, spec: ImportSpec, n_joints: int, targets: np.ndarray) -> pd.DataFrame:
    """Parse every needed column of ``csvf`` into a measurements table (SI units); ``targets``: the session's, for
    the probe form its virtual offsets."""
    if len(spec.joints) != n_joints:
        raise ImportFormatError(
            f"{len(spec.joints)} joint column(s) {list(spec.joints)} but the robot has n={n_joints} joints",
            path=str(csvf.path),
        )
    if spec.reject_extra_joints:
        extra_q = sorted(
            (c for c in csvf.columns if c[:1] == "q" and c[1:].isdigit() and int(c[1:]) > n_joints),
            key=lambda c: int(c[1:]),
        )
        if extra_q:
            raise ImportFormatError(
                f"joint column(s) {extra_q} present but the robot has n={n_joints} joints (q1..q{n_joints})",
                path=str(csvf.path),
            )
    csvf.require(spec.joints, "joint")
    d = spec.decimal
    rows: dict[str, Any] = {"pose": np.arange(len(csvf), dtype=np.int64)}
    for j, col in enumerate(spec.joints):
        rows[f"q{j + 1}"] = csvf.numbers(col, d) * ANGLE_UNITS[spec.joint_unit]
    scale = LENGTH_UNITS[spec.length_unit]
    if spec.form == "targets":
        cols = [c for triple in spec.target_columns for c in triple]
        csvf.require(cols, "target")
        m = len(spec.target_columns)
        if spec.reject_extra_joints:  # the plain form: a t(m+1) column means the targets file lacks targets
            more = [c for c in csvf.columns if c.startswith(f"t{m + 1}_")]
            if more:
                raise ImportFormatError(
                    f"target column(s) {more} present but the targets file has {m} target(s): add the missing "
                    "target(s) to the targets file (tool frame), in the order of the CSV",
                    path=str(csvf.path),
                )
        pts = np.stack([csvf.numbers(c, d, empty_ok=True) for c in cols], axis=1).reshape(len(csvf), m, 3)
        csvf.check_seen(cols, pts)
        pts = pts * scale
    else:
        csvf.require([*spec.position, *spec.rotation], "probe pose")
        t = np.stack([csvf.numbers(c, d) for c in spec.position], axis=1) * scale
        ang = np.stack([csvf.numbers(c, d) for c in spec.rotation], axis=1)
        pts = probe_points(t, _rotations(ang, spec), targets)
    rows |= dict(zip(target_columns(pts.shape[1]), pts.reshape(len(csvf), -1).T, strict=True))
    if spec.split_column and spec.split_column in csvf.columns:
        values = csvf.frame[spec.split_column].str.strip().tolist()
        for i, v in enumerate(values):
            if v not in SPLITS:
                raise csvf.error(f"unknown split value {v!r}; allowed: train, val, test or empty", i, spec.split_column)
        rows["split"] = values
    elif spec.split_required:
        csvf.require([spec.split_column or "split"], "split")
    else:
        rows["split"] = [""] * len(csvf)
    if spec.timestamp_column:
        csvf.require([spec.timestamp_column], "timestamp")
        rows["timestamp"] = csvf.numbers(spec.timestamp_column, d)
    csvf.require([e.column for e in spec.extras], "passthrough")
    for e in spec.extras:
        if e.kind == "str":
            rows[f"x_{e.name}"] = csvf.frame[e.column].str.strip().tolist()
        else:
            factor = _TO_SI.get(e.unit, (e.unit, 1.0))[1]
            rows[f"x_{e.name}"] = csvf.numbers(e.column, d, allow_missing=True) * factor
    table = pd.DataFrame(rows)
    table["split"] = table["split"].astype("str")
    return table


def _sanity(
    csvf: _Csv,
    rows: pd.DataFrame,
    spec: ImportSpec,
    targets: np.ndarray,
    robot: RobotSpec | None,
    allow: frozenset[str],
    hints: Hints | None,
    existing_q: np.ndarray | None,
) -> SanityReport:
    """Run :mod:`labcal.datasets.sanity` on the parsed rows; fixes are phrased for CLI flags unless told otherwise."""
    q = rows[joint_columns(len(spec.joints))].to_numpy(dtype=float)
    m = len(targets)
    points = rows[list(target_columns(m))].to_numpy(dtype=float).reshape(-1, m, 3)
    base = hints or Hints()
    hints = dataclasses.replace(base, row=base.row or (lambda i: f"row {i + 1} (line {int(csvf.lines[i])})"))
    return check_measurements(
        q,
        points,
        targets,
        robot=robot,
        frame=spec.frame,
        form=spec.form,
        length_unit=spec.length_unit,
        angle_unit=spec.joint_unit,
        allow=allow,
        hints=hints,
        existing_q=existing_q,
    )


@dataclass(frozen=True)
class ImportOptions:
    """How to read an import file and what to record with it: one object for every import form.

    Reading: ``length_unit`` ("m" | "mm" | "in": target / probe position columns), ``angle_unit`` ("rad" | "deg":
    joints), ``frame`` ("base" | "tracker": frame of the measured points), ``separator`` and ``decimal`` mark.
    Probe form only: ``rotation`` ("rotvec" | "euler"), ``euler_sequence`` (scipy: "XYZ" intrinsic, "xyz"
    extrinsic), ``rotation_unit`` (default ``angle_unit``), ``offsets`` ((m, 3) m virtual targets in the probe
    frame, default :data:`DEFAULT_PROBE_OFFSETS`), ``columns`` (the names of x, y, z, rx, ry, rz). (A mapping file
    sets the reading options itself.) Recording: ``session_id`` (an existing session gets a new version),
    ``metadata`` (the user's), ``robot`` (a :class:`~labcal.robots.RobotSpec` matching name, hash and n: enables
    the model checks and stores the robot file with the data), ``allow`` (sanity checks to override, recorded in
    the provenance), ``hints`` (how the fixes are phrased; default: the CLI's flags), ``unit`` (the robot unit's
    id, e.g. its serial number: stored as the session metadata's ``"unit"``; None = unknown).
    """

    length_unit: str = "m"
    angle_unit: str = "rad"
    frame: str = "base"
    separator: str = ","
    decimal: str = "."
    rotation: str = "rotvec"
    euler_sequence: str | None = None
    rotation_unit: str | None = None
    offsets: Any = None
    columns: Sequence[str] = ("x", "y", "z", "rx", "ry", "rz")
    session_id: str | None = None
    metadata: Mapping[str, Any] | None = None
    robot: RobotSpec | None = None
    allow: Sequence[str] = ()
    hints: Hints | None = None
    unit: str | None = None

    def with_changes(self, **changes: Any) -> ImportOptions:
        """These options with some fields replaced (an unknown name is a :class:`DatasetError` listing the fields)."""
        known = {f.name for f in dataclasses.fields(self)}
        if unknown := sorted(set(changes) - known):
            raise DatasetError(f"unknown import option(s) {unknown}; the options are {sorted(known)}")
        return dataclasses.replace(self, **changes)


def _options(options: ImportOptions | None, changes: Mapping[str, Any]) -> ImportOptions:
    return (options or ImportOptions()).with_changes(**changes)


@dataclass(frozen=True)
class _Labels:
    """What the imported rows are labelled with: the robot model (name, hash, joints) and the session's targets
    (the probe form: its virtual offsets)."""

    robot_name: str
    robot_hash: str
    n_joints: int
    targets: np.ndarray


def _run_import(
    store: SessionStore | str | Path | None,
    path: str | Path,
    spec: ImportSpec,
    labels: _Labels,
    opts: ImportOptions,
    recorded_options: dict,
) -> str:
    spec.check()
    allowed = check_names(opts.allow)
    store = store if isinstance(store, SessionStore) else SessionStore(store)
    n_joints, robot, session_id = labels.n_joints, opts.robot, opts.session_id
    if isinstance(n_joints, bool) or not isinstance(n_joints, int) or n_joints < 1:
        raise DatasetError(f"n_joints must be a positive integer, got {n_joints!r}")
    record = {"name": str(labels.robot_name), "hash": str(labels.robot_hash), "n_joints": n_joints}
    if robot is not None:
        if (robot.name, robot.hash, robot.model.n) != (labels.robot_name, labels.robot_hash, n_joints):
            raise DatasetError(
                f"robot {robot.name!r} (hash {robot.hash[:12]}…, n={robot.model.n}) is not the model the data are "
                f"labelled with ({labels.robot_name!r}, hash {str(labels.robot_hash)[:12]}…, n={n_joints})"
            )
        # The model itself (file text) goes with the data, so a version can be refitted without the robot file.
        record = robot.record()
    path = Path(path)
    csvf = _Csv(path, spec.separator)
    rows = _build_rows(csvf, spec, n_joints, labels.targets)
    # the session to add a version to, when session_id names one that exists
    existing = session_id if session_id is not None and (store.root / validate_id(session_id)).is_dir() else None
    latest = store.load(existing) if existing is not None and store.versions(existing) else None
    existing_q = None if latest is None else latest.q
    report = _sanity(csvf, rows, spec, labels.targets, robot, allowed, opts.hints, existing_q)
    report.raise_if_failed()
    options = {**recorded_options, "allow": sorted(allowed)}
    file_sha = sha256_file(path)
    meta = {
        "robot": record,
        "targets": labels.targets.tolist(),
        "targets_unit": "m",
        "frame": spec.frame,
        "tracker": dict(spec.tracker),
        "robot_driver": {},
        "plan": _plan_summary([]),
        "extra_units": {e.name: _TO_SI.get(e.unit, (e.unit, 1.0))[0] for e in spec.extras},
        "metadata": metadata_with_unit(opts.metadata, opts.unit, "--unit"),
    }
    provenance = {
        "import": {
            "file": path.name,
            "sha256": file_sha,
            "bytes": path.stat().st_size,
            "rows": len(rows),
            "form": spec.form,
            "options": options,
            "checks": report.as_dict(),
        }
    }
    source = f"import:{file_sha}"
    if existing is not None:
        if latest is not None:  # continue the pose numbering of the rows already there
            rows["pose"] += int(latest.pose.max()) + 1 if len(latest) else 0
        meta["session_id"] = existing
        _check_unit_of_existing(store, existing, meta["metadata"].get("unit"))
        return store.append_rows(existing, rows, meta, source=source, provenance=provenance)
    return store.create_imported_session(rows, meta, source=source, provenance=provenance, session_id=session_id)


def _check_unit_of_existing(store: SessionStore, session_id: str, unit: str | None) -> None:
    """Rows added to a session must come from its unit: the session keeps its recorded unit, so a different one
    given now would label the new rows wrongly without a trace."""
    recorded = (store.session_meta(session_id).get("metadata") or {}).get("unit")
    if unit is not None and unit != recorded:
        had = f"unit {recorded!r}" if recorded is not None else "no unit"
        raise DatasetError(
            f"session {session_id} was recorded with {had}, the rows to add are of unit {unit!r}: import them into a "
            "new session (rows of one session come from one robot)"
        )


def _plain_spec(form: str, opts: ImportOptions, n_joints: int, **fields: Any) -> ImportSpec:
    """The spec of a plain CSV form (joints ``q1..qn``), read with the units, frame, separator and decimal mark of
    ``opts``; ``fields``: the form's own."""
    return ImportSpec(
        form=form,
        joints=tuple(joint_columns(n_joints)),
        frame=opts.frame,
        joint_unit=opts.angle_unit,
        separator=opts.separator,
        decimal=opts.decimal,
        length_unit=opts.length_unit,
        **fields,
    )


def _read_options(opts: ImportOptions, *more: str) -> dict[str, Any]:
    """The reading options of a plain CSV import (and the ``more`` of its form), as recorded in the version's
    provenance."""
    return {k: getattr(opts, k) for k in ("length_unit", "angle_unit", "frame", "separator", "decimal", *more)}


def import_targets_csv(
    store: SessionStore | str | Path | None,
    path: str | Path,
    robot_name: str,
    robot_hash: str,
    n_joints: int,
    targets: Any,
    options: ImportOptions | None = None,
    **changes: Any,
) -> str:
    """Import a targets CSV (``q1..qn``, ``t1_x … tm_z``, optional ``split``); return ``SESSION@vNNN``.

    ``targets``: (m, 3) m, the targets in the tool frame (e.g. from :func:`load_targets`); the CSV has their
    m column triples, and an empty triple where a target was not seen. ``options`` (:class:`ImportOptions`, or
    its fields as keywords): ``length_unit`` applies to the target columns, ``angle_unit`` to the joints,
    ``frame`` names the frame of the measured points; joint columns beyond ``q{n_joints}`` and target columns
    beyond ``t{m}`` are errors. With ``session_id`` of an existing session, the rows are appended as a new version.

    Before anything is written the rows pass :func:`labcal.datasets.sanity.check_measurements` (distances between
    targets seen together vs ``targets``, duplicates; with ``robot`` also joint limits, nominal consistency and
    reach, and the model's file text is stored with the session). A failed check raises
    :class:`~labcal.datasets.sanity.SanityError` naming the fix; ``allow`` lists the checks to override.
    """
    opts = _options(options, changes)
    t = validate_targets(targets)
    triples = tuple(tuple(target_columns(len(t))[3 * i : 3 * i + 3]) for i in range(len(t)))
    spec = _plain_spec("targets", opts, n_joints, target_columns=triples, reject_extra_joints=True)
    labels = _Labels(robot_name, robot_hash, n_joints, t)
    return _run_import(store, path, spec, labels, opts, _read_options(opts))


def import_probe_csv(
    store: SessionStore | str | Path | None,
    path: str | Path,
    robot_name: str,
    robot_hash: str,
    n_joints: int,
    options: ImportOptions | None = None,
    **changes: Any,
) -> str:
    """Import a 6-DOF probe CSV (``q1..qn``, ``x, y, z, rx, ry, rz``); return ``SESSION@vNNN``.

    ``options`` (:class:`ImportOptions`, or its fields as keywords): ``rotation`` "rotvec" (rotation vector, UR
    style) or "euler" with ``euler_sequence``; ``length_unit`` applies to x, y, z, ``angle_unit`` to the joints,
    ``rotation_unit`` (default ``angle_unit``) to rx, ry, rz; ``offsets``: (m, 3) m virtual target offsets in
    the probe frame (default :data:`DEFAULT_PROBE_OFFSETS`), which become the session's targets. ``robot``,
    ``allow``, ``hints``: sanity checks as for :func:`import_targets_csv` (the probe's mount on the flange is
    unknown, so the nominal check registers it).
    """
    opts = _options(options, changes)
    v = validate_targets(DEFAULT_PROBE_OFFSETS if opts.offsets is None else opts.offsets)
    columns = list(opts.columns)
    if len(columns) != 6:
        raise DatasetError(f"columns must name x, y, z, rx, ry, rz (6 names), got {columns}")
    spec = _plain_spec(
        "probe",
        opts,
        n_joints,
        position=tuple(columns[:3]),
        rotation=tuple(columns[3:]),
        rotation_unit=opts.rotation_unit or opts.angle_unit,
        convention=opts.rotation,
        euler_sequence=opts.euler_sequence,
    )
    recorded = {**_read_options(opts, "rotation", "euler_sequence"), "rotation_unit": spec.rotation_unit}
    recorded |= {"offsets_m": v.tolist(), "columns": columns}
    labels = _Labels(robot_name, robot_hash, n_joints, v)
    return _run_import(store, path, spec, labels, opts, recorded)


# --------------------------------------------------------------------------------------------------------------
# Mapping files


def _target_triples(value: object) -> str | None:
    """Why ``[targets] columns`` is not a list of [x, y, z] column-name triples, one per target, or None."""
    if not isinstance(value, list) or not value:
        return f"must be one [x, y, z] column-name list per target, got {value!r}"
    for i, triple in enumerate(value):
        if not isinstance(triple, list) or len(triple) != 3 or not all(isinstance(c, str) and c for c in triple):
            return f"entry {i + 1} (target t{i + 1}) must be three column names [x, y, z], got {triple!r}"
    return None


def _is_table(value: object) -> str | None:
    return None if isinstance(value, dict) else f"must be a table, got {value!r}"


def _named(value: list) -> str | None:
    return None if value and all(value) else f"must list the joint column names in order q1..qn, got {value!r}"


_MAPPING_TARGETS = Table(
    {
        "columns": Key("any", required=True, check=_target_triples, doc="[[x, y, z], …] column names, one per target"),
        "unit": Key("str", default="m", choices=tuple(LENGTH_UNITS)),
    }
)
_MAPPING_PROBE = Table(
    {
        "position": Key("strings", required=True, shape=(3,)),
        "rotation": Key("strings", required=True, shape=(3,)),
        "position_unit": Key("str", default="m", choices=tuple(LENGTH_UNITS)),
        "rotation_unit": Key("str", default="rad", choices=tuple(ANGLE_UNITS)),
        "convention": Key("str", default="rotvec", choices=("rotvec", "euler")),
        "euler_sequence": Key("str"),
        "offsets": Key("vectors", shape=(None, 3), unit="in offsets_unit"),
        "offsets_unit": Key("str", default="m", choices=tuple(LENGTH_UNITS)),
    }
)
_MAPPING_EXTRA = Table(
    {
        "column": Key("str", required=True),
        "name": Key("str"),
        "unit": Key("str", default=""),
        "type": Key("str", default="float", choices=("float", "str")),
    }
)
#: A column-mapping file, for the one TOML validator (:mod:`labcal.tomlschema`); ``mappings/ipa-ur10.toml`` shows
#: every key with comments.
MAPPING_SCHEMA = Table(
    {
        "description": Key("str", default=""),
        "source": Key("any"),
        "form": Key("str", required=True, choices=("targets", "probe")),
        "separator": Key("str", default=","),
        "decimal": Key("str", default="."),
        "frame": Key("str", default="base", choices=FRAMES),
        "joints": Key("strings", required=True, check=_named),
        "joint_unit": Key("str", default="rad", choices=tuple(ANGLE_UNITS)),
        "split_column": Key("str"),
        "timestamp_column": Key("str"),
        "targets": Key("table", table=_MAPPING_TARGETS),
        "probe": Key("table", table=_MAPPING_PROBE),
        "tracker": Key("any", default={}, check=_is_table),
        "extra": Key("tables", table=_MAPPING_EXTRA, default=[]),
    },
    name="mapping",
)


def list_mappings() -> list[str]:
    """Names of the mappings shipped with labcal (usable as ``import_mapped(..., "<name>", ...)``)."""
    return sorted(p.stem for p in MAPPINGS_DIR.glob("*.toml"))


def _resolve_mapping(mapping: str | Path) -> Path:
    p = Path(mapping)
    if p.is_file():
        return p
    name = p.name[:-5] if p.name.endswith(".toml") else p.name
    shipped = MAPPINGS_DIR / f"{name}.toml"
    if str(p) == p.name and shipped.is_file():
        return shipped
    raise MappingError(
        f"mapping {str(mapping)!r} is neither a file nor a shipped mapping ({', '.join(list_mappings())})"
    )


def load_mapping(mapping: str | Path) -> tuple[ImportSpec, np.ndarray | None, dict]:
    """Read a mapping TOML (path or shipped name) → (spec, probe offsets in m or None, raw document).

    See ``mappings/ipa-ur10.toml`` for a commented example of every key. The file is checked by
    :data:`MAPPING_SCHEMA` (unknown keys with a did-you-mean, types, allowed values), then for what one key alone
    cannot say (the table its form needs, the Euler sequence, the offsets' geometry).
    """
    path = _resolve_mapping(mapping)
    src = f"mapping {path}"
    doc = read_toml(path, MappingError, "mapping")
    d = validate(doc, MAPPING_SCHEMA, source=src, error=MappingError)
    form = d["form"]
    if form not in d:
        raise fail(src, "", f'form = "{form}" needs a [{form}] table', MappingError)
    kw: dict[str, Any] = {k: d[k] for k in ("form", "frame", "joint_unit", "separator", "decimal", "description")}
    kw |= {
        "joints": tuple(d["joints"]),
        "split_column": d.get("split_column", "split"),
        "split_required": "split_column" in d,
        "timestamp_column": d.get("timestamp_column"),
        "tracker": dict(d["tracker"]),
    }
    offsets = None
    if form == "targets":
        kw["target_columns"] = tuple(tuple(c) for c in d["targets"]["columns"])
        kw["length_unit"] = d["targets"]["unit"]
    else:
        p = d["probe"]
        kw["position"], kw["rotation"] = tuple(p["position"]), tuple(p["rotation"])
        kw["length_unit"], kw["rotation_unit"] = p["position_unit"], p["rotation_unit"]
        kw["convention"], kw["euler_sequence"] = p["convention"], p.get("euler_sequence")
        if "offsets" in p:
            try:
                raw = validate_targets(p["offsets"], min_height=0, source=f"{src} [probe] offsets")
                offsets = validate_targets(raw * LENGTH_UNITS[p["offsets_unit"]], source=f"{src} [probe] offsets")
            except TargetsError as e:
                raise MappingError(str(e)) from None
    kw["extras"] = tuple(ExtraColumn(e["column"], e.get("name", e["column"]), e["unit"], e["type"]) for e in d["extra"])
    try:
        spec = ImportSpec(**kw)
        spec.check()
    except MappingError as e:
        raise MappingError(f"{src}: {e}") from None
    return spec, offsets, doc


def import_mapped(
    store: SessionStore | str | Path | None,
    path: str | Path,
    mapping: str | Path,
    robot_name: str,
    robot_hash: str,
    n_joints: int,
    options: ImportOptions | None = None,
    *,
    targets: Any = None,
    **changes: Any,
) -> str:
    """Import ``path`` as described by a mapping TOML (a path, or a shipped name such as ``"ipa-ur10"``).

    ``targets`` (m, 3) m: required for a "targets" mapping (one point per ``[targets] columns`` triple); for a
    "probe" mapping it overrides the mapping's virtual offsets. Returns ``SESSION@vNNN``. ``options``
    (:class:`ImportOptions`, or its fields as keywords): the recording options ``session_id``, ``metadata``,
    ``robot``, ``allow``, ``hints`` as for :func:`import_targets_csv`; the mapping sets units, frame and form.
    """
    opts = _options(options, changes)
    spec, offsets, doc = load_mapping(mapping)
    mpath = _resolve_mapping(mapping)
    if spec.form == "targets":
        if targets is None:
            raise TargetsError(
                f"mapping {mpath.name} imports measured targets: pass targets ({len(spec.target_columns)}x3, tool "
                "frame)"
            )
        t = validate_targets(targets)
        if len(t) != len(spec.target_columns):
            raise TargetsError(
                f"mapping {mpath.name} has {len(spec.target_columns)} target column triple(s) but the targets file "
                f"{len(t)} point(s): give one point per measured target, in the order of the mapping's columns"
            )
    else:
        t = validate_targets(
            targets if targets is not None else (offsets if offsets is not None else DEFAULT_PROBE_OFFSETS)
        )
    hints = opts.hints
    if hints is None:  # the units and frame of a mapped import are keys of the mapping, not flags
        unit_key = "[targets] unit" if spec.form == "targets" else "[probe] position_unit"
        where = f"in the mapping {mpath.name}"
        hints = Hints(
            length=f'{unit_key} = "{{unit}}" {where}',
            angle=f'joint_unit = "{{unit}}" {where}',
            frame=f'frame = "{{frame}}" {where}',
        )
    recorded = {"mapping": mpath.stem, "mapping_sha256": sha256_file(mpath), "mapping_content": doc}
    labels = _Labels(robot_name, robot_hash, n_joints, t)
    return _run_import(store, path, spec, labels, opts.with_changes(hints=hints), recorded)
