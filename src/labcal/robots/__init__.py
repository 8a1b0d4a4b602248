"""Robot model files (TOML) and the built-in robots.

A robot file (DESIGN.md section 4)::

    name = "ur10"
    kinematics = "dh"            # "dh" | "mdh" | "poe"
    [[joints]]                   # one table per joint, base to tool
    type = "revolute"            # or "prismatic"
    a = 0.0                      # dh/mdh: a, alpha, d, theta in m / rad
    alpha = 1.5707963267948966
    d = 0.1273
    theta = 0.0
    # poe instead: xyz = [..], rpy = [..] (pose of K_j in K_{j-1} at q = 0), axis = [0, 0, 1]
    limits = [-6.283, 6.283]     # rad (m for prismatic)
    mass = 7.1                   # optional, kg: the link moved by this joint
    com = [0.0, 0.0, 0.06]       # optional, m, base frame with all joints at 0 (default: link midpoint)
    [tool]                       # optional: flange → tool
    xyz = [0, 0, 0]
    rpy = [0, 0, 0]
    mass = 0.0                   # optional payload, kg

Units are SI everywhere: radians and metres. A file whose numbers look like degrees or millimetres is refused with
an error naming the field (``joints[2].alpha = 90 looks like degrees; robot files are in radians``): an angle
(alpha, theta, rpy, a revolute joint's offset) beyond 2π, a revolute limit beyond 4π (multi-turn joints stay
below two turns each way), a length (a, d, xyz, a prismatic limit) beyond 10 m. A file that really means such
values says so with a top-level ``units_checked = true``, which skips these checks and nothing else.

Controller joints vs model joints (optional, :mod:`labcal.robots.joint_map`): when the controller reports joints
that are not the model's joint angles, the file declares ``q_model = matrix · q_controller + offsets``::

    [joint_map]                  # e.g. a controller J3 measured from the horizontal: model elbow = J2 + J3
    matrix = [[1, 0, 0, 0, 0, 0],
              [0, 1, 0, 0, 0, 0],
              [0, 1, 1, 0, 0, 0],
              [0, 0, 0, 1, 0, 0],
              [0, 0, 0, 0, 1, 0],
              [0, 0, 0, 0, 0, 1]]
    offsets = [0, 0, 0, 0, 0, 0] # rad (m for prismatic joints), optional, default zeros

or, for a map that only flips directions, ``signs = [1, -1, 1, 1, 1, 1]`` instead of ``matrix`` (the diagonal
matrix; give one of the two). Both forms become the same :class:`JointMap` (matrix + offsets), the one form that
is stored and hashed. The joint tables (geometry, ``limits``) are always in *model* joints. The example robot
file ``coupled-elbow-6r`` (beside the built-ins, loadable by that name) is a 6R arm with a coupled elbow.

Identity: :attr:`RobotSpec.hash` is :func:`model_hash` of the model *and* its joint map, because the map changes
what recorded joint values mean; an identity map (or none) adds nothing, so files without a map keep their hashes.

Built-ins: ``ur5e``, ``ur10``, ``ur10e``, ``fanuc-m1000ia``, ``scara4``. A path ending in ``.urdf`` loads a URDF
(no joint map, no units check: a URDF is metres and radians by definition).

Example::

    >>> spec = load("ur10")
    >>> spec.model.n, spec.name, len(spec.hash)
    (6, 'ur10', 64)
"""

from __future__ import annotations

import dataclasses
import hashlib
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from labcal.kinematics import se3
from labcal.kinematics.conversions import from_dh, from_mdh, from_urdf
from labcal.kinematics.poe import PRISMATIC, REVOLUTE, LocalPOEModel
from labcal.robots.joint_map import JointMap

BUILTINS = ("ur5e", "ur10", "ur10e", "fanuc-m1000ia", "scara4")
# Example robot files shipped beside the built-ins and loadable by name, but not robots of their own: models to copy
# (coupled-elbow-6r: the fanuc-m1000ia geometry with a controller whose J3 is measured from the horizontal).
EXAMPLES = ("coupled-elbow-6r",)

TWO_PI = 2.0 * np.pi
MAX_ANGLE = TWO_PI + 1e-9  # rad: alpha, theta, rpy, revolute offsets; a larger value is almost surely degrees
MAX_REVOLUTE_LIMIT = 2.0 * TWO_PI + 1e-9  # rad: two turns each way covers multi-turn wrists; 170 or 360 is degrees
MAX_LENGTH = 10.0  # m: no arm has a 10 m link or tool offset, while millimetre values are hundreds


class RobotFileError(ValueError):
    """A robot model file is missing, unreadable or has a bad field (the message names it)."""


@dataclass(frozen=True, eq=False)
class RobotSpec:
    """A loaded robot: its nominal model, mass model and identity.

    masses: (n+1,) kg for links 1..n and the tool payload; coms: (n+1, 3) m in the base frame at q = 0.
    hash: sha256 of the model's numbers (:func:`model_hash`), so reformatting a file keeps its identity.
    text: the robot file's full text and format ("toml" | "urdf"), so a session can store the model itself and be
    refitted on a machine that has neither the file nor the same built-ins (:func:`loads` reads it back).
    """

    name: str
    model: LocalPOEModel
    masses: np.ndarray
    coms: np.ndarray
    source: str
    hash: str
    text: str = ""
    format: str = "toml"
    joint_map: JointMap | None = None  # controller → model joints; None: they are the same

    @property
    def joints(self) -> JointMap:
        """The controller → model joint map (identity when the robot file declares none)."""
        return self.joint_map if self.joint_map is not None else JointMap.identity(self.model.n)

    def record(self) -> dict:
        """The robot as run documents and manifests store it: name, hash, joint count, file text and format."""
        return {
            "name": self.name,
            "hash": self.hash,
            "n_joints": self.model.n,
            "text": self.text,
            "format": self.format,
        }


def model_hash(model: LocalPOEModel, joint_map: JointMap | None = None) -> str:
    """sha256 over joint types, frames, twists and limits (float64 bytes), and the joint map unless it is the identity:
    the identity of a robot model.

    The map is part of the identity because it decides what a recorded joint value means: the same numbers from a
    coupled-elbow controller and from an uncoupled one are different configurations. An identity map adds nothing,
    so a file without a ``[joint_map]`` keeps the hash it always had.
    """
    h = hashlib.sha256()
    h.update(",".join(model.joint_types).encode())
    for array in (model.frames, model.twists, model.limits):
        h.update(np.ascontiguousarray(array, dtype="<f8").tobytes())
    if joint_map is not None and not joint_map.is_identity:
        h.update(b"joint_map")
        for array in (joint_map.matrix, joint_map.offsets):
            h.update(np.ascontiguousarray(array, dtype="<f8").tobytes())
    return h.hexdigest()


def builtin_path(name: str) -> Path:
    return Path(str(resources.files("labcal.robots").joinpath(f"{name}.toml")))


def load(name_or_path: str | Path) -> RobotSpec:
    """Load a built-in robot by name, or a TOML / URDF robot file by path."""
    text = str(name_or_path)
    if text in BUILTINS or text in EXAMPLES:
        path = builtin_path(text)
    else:
        path = Path(text)
        if not path.is_file():
            raise RobotFileError(
                f"robot {text!r} is neither a built-in ({', '.join(BUILTINS)}), an example "
                f"({', '.join(EXAMPLES)}) nor an existing file"
            )
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise RobotFileError(f"{path}: cannot read the robot file: {err}") from err
    return loads(text, "urdf" if path.suffix.lower() == ".urdf" else "toml", source=str(path))


def loads(text: str, format: str = "toml", source: str = "<text>") -> RobotSpec:
    """A robot from the text of a robot file (``format`` "toml" or "urdf"), e.g. the copy a session stored."""
    if format == "urdf":
        model = from_urdf(text)
        spec = _spec(model.name or Path(source).stem, model, {}, [], {}, source)
    elif format == "toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise RobotFileError(f"{source}: not valid TOML: {err}") from err
        spec = parse(data, source=source)
    else:
        raise RobotFileError(f"{source}: robot file format must be 'toml' or 'urdf', got {format!r}")
    return dataclasses.replace(spec, text=text, format=format)


def parse(data: dict, source: str = "<dict>") -> RobotSpec:
    """Build a RobotSpec from the parsed TOML of a robot file; errors name the file and field."""

    def fail(msg: str) -> RobotFileError:
        return RobotFileError(f"{source}: {msg}")

    name = data.get("name")
    if not isinstance(name, str) or not name:
        raise fail("'name' must be a non-empty string")
    kind = data.get("kinematics")
    if kind not in ("dh", "mdh", "poe"):
        raise fail(f'\'kinematics\' must be "dh", "mdh" or "poe", got {kind!r}')
    joints = data.get("joints")
    if not isinstance(joints, list) or not joints:
        raise fail("needs at least one [[joints]] table")
    tool = data.get("tool", {})
    if not isinstance(tool, dict):
        raise fail("[tool] must be a table")
    units_checked = data.get("units_checked", False)
    if not isinstance(units_checked, bool):
        raise fail(f"'units_checked' must be true or false, got {units_checked!r}")
    if not units_checked:
        _check_units(kind, joints, tool, fail)

    rows = []
    for j, row in enumerate(joints, start=1):
        where = f"joints[{j}]"
        if not isinstance(row, dict):
            raise fail(f"{where} must be a table, got {row!r}")
        jtype = row.get("type", REVOLUTE)
        if jtype not in (REVOLUTE, PRISMATIC):
            raise fail(f'{where}.type must be "revolute" or "prismatic", got {jtype!r}')
        keys = ("a", "alpha", "d", "theta") if kind in ("dh", "mdh") else ()
        clean = {"type": jtype}
        for key in keys:
            clean[key] = _number(row, key, where, fail)
        if kind == "poe":
            clean["xyz"] = _vector(row, "xyz", where, fail, default=None)
            clean["rpy"] = _vector(row, "rpy", where, fail, default=[0.0, 0.0, 0.0])
            clean["axis"] = _vector(row, "axis", where, fail, default=[0.0, 0.0, 1.0])
            if np.linalg.norm(clean["axis"]) < 1e-12:
                raise fail(f"{where}.axis must not be zero")
        if "limits" in row:
            lim = row["limits"]
            if not (isinstance(lim, list) and len(lim) == 2 and all(_is_number(x) for x in lim)):
                raise fail(f"{where}.limits must be [lo, hi] numbers, got {lim!r}")
            if lim[0] > lim[1]:
                raise fail(f"{where}.limits: lo {lim[0]} is greater than hi {lim[1]}")
            clean["limits"] = [float(lim[0]), float(lim[1])]
        rows.append(clean)

    T_tool = se3.pose(
        _vector(tool, "xyz", "tool", fail, [0.0, 0.0, 0.0]), _vector(tool, "rpy", "tool", fail, [0.0] * 3)
    )
    names = tuple(str(row.get("name", f"joint{j + 1}")) for j, row in enumerate(joints))
    if kind == "dh":
        model = from_dh(rows, T_tool, name=name, joint_names=names)
    elif kind == "mdh":
        model = from_mdh(rows, T_tool, name=name, joint_names=names)
    else:
        frames = [se3.pose(r["xyz"], r["rpy"]) for r in rows] + [T_tool]
        twists = [
            np.concatenate([np.zeros(3), r["axis"] / np.linalg.norm(r["axis"])])
            if r["type"] == REVOLUTE
            else np.concatenate([r["axis"] / np.linalg.norm(r["axis"]), np.zeros(3)])
            for r in rows
        ]
        limits = [r.get("limits") for r in rows]
        limits = [
            lim if lim is not None else ([-np.pi, np.pi] if r["type"] == REVOLUTE else [-1.0, 1.0])
            for lim, r in zip(limits, rows, strict=True)
        ]
        model = LocalPOEModel(
            np.array(frames), tuple(r["type"] for r in rows), np.array(twists), np.array(limits), name, names
        )
    spec = _spec(name, model, tool, joints, {}, source, fail)
    if "joint_map" not in data:
        return spec
    joint_map = _joint_map(data["joint_map"], model, units_checked, fail)
    return dataclasses.replace(spec, joint_map=joint_map, hash=model_hash(model, joint_map))


def _joint_map(table, model: LocalPOEModel, units_checked: bool, fail) -> JointMap:
    """The [joint_map] table → JointMap; every error names the field and says what it should be."""
    n = model.n
    if not isinstance(table, dict):
        raise fail("[joint_map] must be a table with 'matrix' (or 'signs') and optional 'offsets'")
    unknown = sorted(set(table) - {"matrix", "signs", "offsets"})
    if unknown:
        raise fail(f"joint_map: unknown field(s) {', '.join(unknown)}; known: matrix, signs, offsets")
    if ("matrix" in table) == ("signs" in table):
        raise fail("joint_map needs exactly one of 'matrix' (n×n coupling) or 'signs' (n values of +1/-1)")
    if "matrix" in table:
        M = table["matrix"]
        if not (
            isinstance(M, list)
            and len(M) == n
            and all(isinstance(row, list) and len(row) == n and all(_is_number(x) for x in row) for row in M)
        ):
            raise fail(f"joint_map.matrix must be {n} rows of {n} numbers (one row per model joint), got {M!r}")
        matrix = np.array(M, dtype=float)
    else:
        signs = table["signs"]
        if not (isinstance(signs, list) and len(signs) == n and all(_is_number(x) and abs(x) == 1 for x in signs)):
            raise fail(f"joint_map.signs must be {n} values of 1 or -1, got {signs!r}")
        matrix = np.diag(np.array(signs, dtype=float))
    offsets = table.get("offsets", [0.0] * n)
    if not (isinstance(offsets, list) and len(offsets) == n and all(_is_number(x) for x in offsets)):
        raise fail(f"joint_map.offsets must be {n} numbers (rad, m for prismatic joints), got {offsets!r}")
    offsets = np.array(offsets, dtype=float)
    if not units_checked:
        for j, (value, jtype) in enumerate(zip(offsets, model.joint_types, strict=True)):
            if jtype == REVOLUTE and abs(value) > MAX_ANGLE:
                raise fail(_degrees_message(f"joint_map.offsets[{j + 1}]", value))
            if jtype != REVOLUTE and abs(value) > MAX_LENGTH:
                raise fail(_millimetres_message(f"joint_map.offsets[{j + 1}]", value))
    if abs(np.linalg.det(matrix)) < 1e-9:
        raise fail(
            "joint_map.matrix is singular: every model joint must follow from the controller joints and back "
            "(check for a row of zeros or two equal rows)"
        )
    return JointMap(matrix, offsets)


def _degrees_message(field: str, value: float) -> str:
    return (
        f"{field} = {value:g} looks like degrees; robot files are in radians ({value:g}° = {np.radians(value):.6g} "
        "rad). If the value is right, add units_checked = true at the top of the file"
    )


def _millimetres_message(field: str, value: float) -> str:
    return (
        f"{field} = {value:g} looks like millimetres; robot files are in metres ({value:g} mm = {value / 1000:.6g} "
        "m). If the value is right, add units_checked = true at the top of the file"
    )


def _check_units(kind: str, joints: list, tool: dict, fail) -> None:
    """Refuse numbers that look like degrees or millimetres (the type checks come later, in parse)."""

    def numbers(row: dict, key: str) -> list[tuple[str, float]]:
        """(index suffix, value) of the numbers in a scalar or list field."""
        value = row.get(key)
        items = [(f"[{i + 1}]", x) for i, x in enumerate(value)] if isinstance(value, list) else [("", value)]
        return [(suffix, x) for suffix, x in items if _is_number(x)]

    def check(where: str, row: dict, angles: tuple, lengths: tuple, revolute: bool) -> None:
        for key in angles:
            for suffix, x in numbers(row, key):
                if abs(x) > MAX_ANGLE:
                    raise fail(_degrees_message(f"{where}.{key}{suffix}", x))
        for key in lengths:
            for suffix, x in numbers(row, key):
                if abs(x) > MAX_LENGTH:
                    raise fail(_millimetres_message(f"{where}.{key}{suffix}", x))
        for suffix, x in numbers(row, "limits"):
            if revolute and abs(x) > MAX_REVOLUTE_LIMIT:
                raise fail(_degrees_message(f"{where}.limits{suffix}", x))
            if not revolute and abs(x) > MAX_LENGTH:
                raise fail(_millimetres_message(f"{where}.limits{suffix}", x))

    dh = kind in ("dh", "mdh")
    for j, row in enumerate(joints, start=1):
        if isinstance(row, dict):  # parse names a row that is not a table
            angles = ("alpha", "theta", "rpy") if dh else ("rpy",)
            lengths = ("a", "d", "xyz", "com") if dh else ("xyz", "com")
            check(f"joints[{j}]", row, angles, lengths, row.get("type", REVOLUTE) == REVOLUTE)
    check("tool", tool if isinstance(tool, dict) else {}, ("rpy",), ("xyz", "com"), revolute=True)


def _spec(name, model, tool, joints, _unused, source, fail=None) -> RobotSpec:
    fail = fail or (lambda msg: RobotFileError(f"{source}: {msg}"))
    n = model.n
    frames0 = model.link_frames(np.zeros(n))[0]  # (n+1, 4, 4) at q = 0
    origins = frames0[:, :3, 3]
    masses = np.zeros(n + 1)
    coms = np.empty((n + 1, 3))
    for j in range(n + 1):
        row = joints[j] if j < n and j < len(joints) else (tool if j == n else {})
        if "mass" in row:
            m = row["mass"]
            if not _is_number(m) or m < 0:
                raise fail(f"{'tool' if j == n else f'joints[{j + 1}]'}.mass must be a number >= 0, got {m!r}")
            masses[j] = float(m)
        default = origins[j] if j == n else 0.5 * (origins[j] + origins[j + 1])
        coms[j] = _vector(row, "com", "tool" if j == n else f"joints[{j + 1}]", fail, default)
    return RobotSpec(name=name, model=model, masses=masses, coms=coms, source=source, hash=model_hash(model))


def _is_number(x) -> bool:
    """A finite int or float; TOML booleans are not numbers here, although Python's bool is an int."""
    return isinstance(x, int | float) and not isinstance(x, bool) and bool(np.isfinite(x))


def _number(row: dict, key: str, where: str, fail) -> float:
    if key not in row:
        raise fail(f"{where}.{key} is missing")
    value = row[key]
    if not _is_number(value):
        raise fail(f"{where}.{key} must be a finite number, got {value!r}")
    return float(value)


def _vector(row: dict, key: str, where: str, fail, default) -> np.ndarray:
    if key not in row:
        if default is None:
            raise fail(f"{where}.{key} is missing")
        return np.asarray(default, dtype=float)
    value = row[key]
    if not isinstance(value, list) or len(value) != 3 or not all(_is_number(x) for x in value):
        raise fail(f"{where}.{key} must be a list of 3 numbers, got {value!r}")
    return np.asarray(value, dtype=float)
