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
    velocity = 2.0944            # optional, rad/s (m/s): speed limit, for exports (not part of the model)
    effort = 330.0               # optional, N·m (N): torque limit, for exports
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

Built-ins: ``ur5e``, ``ur10``, ``ur10e``, ``fanuc-m1000ia``, ``scara4`` and the 7-joint ``franka-panda`` and
``kuka-iiwa14-r820``. A path ending in ``.urdf`` loads a URDF
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
from labcal.names import duplicate, label_problem, name_problem, printable
from labcal.robots.joint_map import JointMap
from labcal.tomlschema import Key, SchemaError, Table, non_negative, positive, validate

BUILTINS = ("ur5e", "ur10", "ur10e", "fanuc-m1000ia", "scara4", "franka-panda", "kuka-iiwa14-r820")
# Example robot files shipped beside the built-ins and loadable by name, but not robots of their own: models to copy
# (coupled-elbow-6r: the fanuc-m1000ia geometry with a controller whose J3 is measured from the horizontal).
EXAMPLES = ("coupled-elbow-6r",)

TWO_PI = 2.0 * np.pi
MAX_ANGLE = TWO_PI + 1e-9  # rad: alpha, theta, rpy, revolute offsets; a larger value is almost surely degrees
MAX_REVOLUTE_LIMIT = 2.0 * TWO_PI + 1e-9  # rad: two turns each way covers multi-turn wrists; 170 or 360 is degrees
MAX_LENGTH = 10.0  # m: no arm has a 10 m link or tool offset, while millimetre values are hundreds
_DH_KEYS = {"a": "m", "alpha": "rad", "d": "m", "theta": "rad"}  # dh and mdh joints, all required


class RobotFileError(SchemaError):
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


def from_record(record: dict, source: str) -> RobotSpec | None:
    """The robot a :meth:`RobotSpec.record` stored, read back with :func:`loads` (None: recorded without its file text,
    before labcal stored it). A record without a format is TOML."""
    text = record.get("text")
    return loads(text, record.get("format") or "toml", source=source) if text else None


def loads(text: str, format: str = "toml", source: str = "<text>") -> RobotSpec:
    """A robot from the text of a robot file (``format`` "toml" or "urdf"), e.g. the copy a session stored."""
    source = printable(source)  # it names the file in every message: a stored name may hold anything
    if format == "urdf":
        _check_urdf_joint_names(text, source)
        model = from_urdf(text)
        _check_urdf_names(model, source)
        spec = _spec(model.name or Path(source).stem, model, {}, [], source)
    elif format == "toml":
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise RobotFileError(f"{source}: not valid TOML: {err}") from err
        spec = parse(data, source=source)
    else:
        raise RobotFileError(f"{source}: robot file format must be 'toml' or 'urdf', got {format!r}")
    return dataclasses.replace(spec, text=text, format=format)


def _check_urdf_joint_names(text: str, source: str) -> None:
    """Refuse repeated <joint name>s before the chain is built (it would silently keep one of them)."""
    import xml.etree.ElementTree as ET

    try:
        names = [j.get("name") for j in ET.fromstring(text).iter("joint")]
    except ET.ParseError:
        return  # from_urdf says what is wrong with the XML
    twice = duplicate(names)
    if twice is not None:
        raise RobotFileError(
            f"{source}: joint {twice[1] + 1} name {printable(names[twice[1]])!r} repeats joint {twice[0] + 1}'s: "
            "joint names must be unique",
            source,
        )


def _check_urdf_names(model: LocalPOEModel, source: str) -> None:
    """The checks a TOML file's names get, for a URDF's robot and joint names."""
    if model.name and (problem := name_problem(model.name)):
        raise RobotFileError(f"{source}: robot name {problem}", source)
    for j, name in enumerate(model.joint_names):
        if problem := name_problem(name):
            raise RobotFileError(f"{source}: joint {j + 1} name {problem}", source)
    # Repeated names cannot reach here: the chain's joints are <joint>s, refused when repeated before it was built.


def _lo_below_hi(lim: list[float]) -> str | None:
    return f"has lo {lim[0]} greater than hi {lim[1]}" if lim[0] > lim[1] else None


def _non_zero(axis: list[float]) -> str | None:
    return "must not be zero" if np.linalg.norm(axis) < 1e-12 else None


def _unit_signs(signs: list[float]) -> str | None:
    return f"must be {len(signs)} values of 1 or -1, got {signs}" if any(abs(x) != 1 for x in signs) else None


_JOINT = {
    # Names reach URScript, YAML and URDF exports and the terminal: a line break or an escape character in one would
    # become a statement, a key or a cursor move there (labcal.names).
    "name": Key("str", check=name_problem, doc="joint name (default joint1, joint2, …): letters, digits, _ - . + /"),
    "type": Key("str", default=REVOLUTE, choices=(REVOLUTE, PRISMATIC)),
    "limits": Key("vector", shape=(2,), unit="rad, m for prismatic", expect="[lo, hi] numbers", check=_lo_below_hi),
    "mass": Key("number", unit="kg", check=non_negative, doc="mass of the link this joint moves"),
    "com": Key("vector", shape=(3,), unit="m", doc="centre of mass, base frame, all joints at 0"),
    # Not part of the kinematic model (nor of its hash): for exports that describe the joints (URDF).
    "velocity": Key("number", unit="rad/s, m/s for prismatic", check=positive, doc="joint speed limit"),
    "effort": Key("number", unit="N·m, N for prismatic", check=positive, doc="joint torque/force limit"),
}
_DH_JOINT = Table({**_JOINT, **{k: Key("number", required=True, unit=u) for k, u in _DH_KEYS.items()}})
_POE_JOINT = Table(
    {
        **_JOINT,
        "xyz": Key("vector", shape=(3,), unit="m", required=True, doc="origin of K_j in K_{j-1} at q = 0"),
        "rpy": Key("vector", shape=(3,), unit="rad", default=[0.0, 0.0, 0.0]),
        "axis": Key("vector", shape=(3,), default=[0.0, 0.0, 1.0], check=_non_zero),
    }
)
_TOOL = Table(
    {
        "xyz": Key("vector", shape=(3,), unit="m", default=[0.0, 0.0, 0.0]),
        "rpy": Key("vector", shape=(3,), unit="rad", default=[0.0, 0.0, 0.0]),
        "mass": Key("number", unit="kg", check=non_negative, doc="payload"),
        "com": Key("vector", shape=(3,), unit="m"),
    }
)
_JOINT_MAP = Table(
    {
        "matrix": Key(
            "vectors", shape=("n", "n"), doc="q_model = matrix · q_controller + offsets, one row per model joint"
        ),
        "signs": Key("vector", shape=("n",), check=_unit_signs, doc="instead of matrix: its diagonal of ±1"),
        "offsets": Key("vector", shape=("n",), unit="rad, m for prismatic joints"),
    }
)


def _robot_name_problem(value: str) -> str | None:
    return "must not be empty" if not value else name_problem(value)


def _robot_schema(joint: Table) -> Table:
    return Table(
        {
            "name": Key("str", required=True, check=_robot_name_problem, doc="letters, digits, _ - . + /"),
            "description": Key("str", check=label_problem, doc="free text on one line"),
            "kinematics": Key("str", required=True, choices=("dh", "mdh", "poe")),
            "units_checked": Key("bool", default=False, doc="true: the numbers are not degrees/mm, skip that check"),
            "joints": Key("tables", table=joint, required=True, min_items=1),
            "tool": Key("table", table=_TOOL, default={}),
            "joint_map": Key("table", table=_JOINT_MAP),
        },
        name="robot file",
    )


#: The schemas of a robot file, by ``kinematics``.
ROBOT_SCHEMAS = {"dh": _robot_schema(_DH_JOINT), "mdh": _robot_schema(_DH_JOINT), "poe": _robot_schema(_POE_JOINT)}


def parse(data: dict, source: str = "<dict>") -> RobotSpec:
    """Build a RobotSpec from the parsed TOML of a robot file; errors name the file and field."""

    def fail(msg: str) -> RobotFileError:
        return RobotFileError(f"{source}: {msg}", source)

    raw_joints = data.get("joints") if isinstance(data, dict) else None
    n = len(raw_joints) if isinstance(raw_joints, list) else 0
    kind = data.get("kinematics") if isinstance(data, dict) else None
    schema = ROBOT_SCHEMAS.get(kind if isinstance(kind, str) else "", ROBOT_SCHEMAS["dh"])
    doc = validate(data, schema, source=source, error=RobotFileError, dims={"n": n})
    name, kind, joints, tool = doc["name"], doc["kinematics"], doc["joints"], doc["tool"]
    if not doc["units_checked"]:
        _check_units(kind, joints, tool, fail)

    T_tool = se3.pose(np.asarray(tool["xyz"]), np.asarray(tool["rpy"]))
    names = tuple(row.get("name", f"joint{j + 1}") for j, row in enumerate(joints))
    twice = duplicate(names)
    if twice is not None:
        i, j = twice
        raise fail(
            f"joints[{j + 1}].name {names[j]!r} repeats joints[{i + 1}].name: joint names must be unique (a URDF or a "
            "controller addresses joints by name)"
        )
    if kind in ("dh", "mdh"):
        model = (from_dh if kind == "dh" else from_mdh)(joints, T_tool, name=name, joint_names=names)
    else:
        frames = [se3.pose(np.asarray(r["xyz"]), np.asarray(r["rpy"])) for r in joints] + [T_tool]
        twists = []
        for r in joints:
            axis = np.asarray(r["axis"]) / np.linalg.norm(r["axis"])
            twists.append(np.concatenate([np.zeros(3), axis] if r["type"] == REVOLUTE else [axis, np.zeros(3)]))
        limits = [r.get("limits", [-np.pi, np.pi] if r["type"] == REVOLUTE else [-1.0, 1.0]) for r in joints]
        model = LocalPOEModel(
            np.array(frames), tuple(r["type"] for r in joints), np.array(twists), np.array(limits), name, names
        )
    spec = _spec(name, model, tool, joints, source)
    if "joint_map" not in doc:
        return spec
    joint_map = _joint_map(doc["joint_map"], model, doc["units_checked"], fail)
    return dataclasses.replace(spec, joint_map=joint_map, hash=model_hash(model, joint_map))


def _joint_map(table: dict, model: LocalPOEModel, units_checked: bool, fail) -> JointMap:
    """The validated [joint_map] table → JointMap; the checks the schema cannot make name the field too."""
    n = model.n
    if ("matrix" in table) == ("signs" in table):
        raise fail("joint_map needs exactly one of 'matrix' (n×n coupling) or 'signs' (n values of +1/-1)")
    matrix = np.array(table["matrix"]) if "matrix" in table else np.diag(np.array(table["signs"]))
    offsets = np.array(table.get("offsets", [0.0] * n))
    if not units_checked:
        for j, (value, jtype) in enumerate(zip(offsets, model.joint_types, strict=True)):
            revolute = jtype == REVOLUTE
            if abs(value) > (MAX_ANGLE if revolute else MAX_LENGTH):
                raise fail(_unit_message(f"joint_map.offsets[{j + 1}]", value, angle=revolute))
    if abs(np.linalg.det(matrix)) < 1e-9:
        raise fail(
            "joint_map.matrix is singular: every model joint must follow from the controller joints and back "
            "(check for a row of zeros or two equal rows)"
        )
    return JointMap(matrix, offsets)


def _unit_message(field: str, value: float, angle: bool) -> str:
    """Why ``field = value`` is refused: it looks like degrees (an ``angle``) or millimetres (a length)."""
    if angle:
        looks, unit, converted = "degrees", "radians", f"{value:g}° = {np.radians(value):.6g} rad"
    else:
        looks, unit, converted = "millimetres", "metres", f"{value:g} mm = {value / 1000:.6g} m"
    return (
        f"{field} = {value:g} looks like {looks}; robot files are in {unit} ({converted}). If the value is right, "
        "add units_checked = true at the top of the file"
    )


def _check_units(kind: str, joints: list[dict], tool: dict, fail) -> None:
    """Refuse numbers that look like degrees or millimetres (in ``joints`` and ``tool`` as the schema validated them:
    numbers are floats, vectors lists of floats, ``type`` filled in)."""
    dh = kind in ("dh", "mdh")
    angles, lengths = (("alpha", "theta", "rpy"), ("a", "d", "xyz", "com")) if dh else (("rpy",), ("xyz", "com"))
    rows = [(f"joints[{j}]", row, angles, lengths, row["type"] == REVOLUTE) for j, row in enumerate(joints, start=1)]
    for where, row, angle_keys, length_keys, revolute in [*rows, ("tool", tool, ("rpy",), ("xyz", "com"), True)]:
        # (key, is an angle, largest plausible |value|): the angles, the lengths, then the limits
        bounds = [(key, True, MAX_ANGLE) for key in angle_keys] + [(key, False, MAX_LENGTH) for key in length_keys]
        bounds.append(("limits", revolute, MAX_REVOLUTE_LIMIT if revolute else MAX_LENGTH))
        for key, angle, bound in bounds:
            value = row.get(key)
            items = [(f"[{i + 1}]", x) for i, x in enumerate(value)] if isinstance(value, list) else [("", value)]
            for suffix, x in items:
                if x is not None and abs(x) > bound:
                    raise fail(_unit_message(f"{where}.{key}{suffix}", x, angle))


def _spec(name, model, tool, joints, source) -> RobotSpec:
    """The spec with its mass model; ``tool`` and ``joints`` are validated tables (URDF: empty)."""
    origins = model.link_frames(np.zeros(model.n))[0][:, :3, 3]  # (n+1, 3) at q = 0
    rows = [*(joints or [{}] * model.n), tool]  # links 1..n, then the payload
    defaults = [*(0.5 * (origins[:-1] + origins[1:])), origins[-1]]  # link midpoints, the tool origin
    masses = np.array([row.get("mass", 0.0) for row in rows], dtype=float)
    coms = np.array([row.get("com", default) for row, default in zip(rows, defaults, strict=True)], dtype=float)
    return RobotSpec(name=name, model=model, masses=masses, coms=coms, source=source, hash=model_hash(model))
