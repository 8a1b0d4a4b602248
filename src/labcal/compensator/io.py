"""Compensator export files: the payload (schema, models, network, ranges, golden vectors, per-field checksums),
JSON / NPZ save and load, and :class:`Compensator`, the deployable runtime that reads them. Numpy only.

:meth:`Compensator.load` reads a JSON or NPZ export written by :func:`save` (schema version, robot model and its
hash, identified frames, network, joint ranges, tracker pose, length scale, joint map, provenance, golden vectors,
and a checksum of each of those fields), checks sizes, shapes, finite values, plausible joint ranges, names and
provenance before anything large is read or computed (:func:`check_payload`; an NPZ member by its ``.npy`` header
first), refuses a file whose fields do not match their checksums (an edit naming the field: a widened joint range
would otherwise silently switch off the out-of-range guard), re-computes the golden vectors and refuses a file
that disagrees. :func:`save` writes through :mod:`labcal.atomicio` and refuses what load would refuse.

Example::

    >>> import tempfile, pathlib
    >>> from labcal.robots import load as load_robot
    >>> nominal = load_robot("ur10").model
    >>> path = save(CalibratedRobot(nominal, nominal), pathlib.Path(tempfile.mkdtemp()) / "c.json")
    >>> Compensator.load(path).correct(np.array([0.1, -1.2, 1.0, -1.4, -1.5, 0.2])).shape
    (6,)
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import zipfile
from pathlib import Path
from typing import NoReturn

import numpy as np

from labcal import features as feature_lib
from labcal.atomicio import write_bytes, write_text
from labcal.compensator.model import CalibratedRobot, Network
from labcal.compensator.validity import ValidityRegion
from labcal.kinematics import metric, se3
from labcal.kinematics.poe import PRISMATIC, REVOLUTE, LocalPOEModel
from labcal.names import duplicate, label_problem, name_problem, printable
from labcal.robots import MAX_LENGTH, MAX_REVOLUTE_LIMIT, model_hash
from labcal.robots.joint_map import JointMap

SCHEMA = "labcal-compensator"
SCHEMA_VERSION = 3  # 2: joint map, and per-field checksums over everything that changes behaviour
# 3: robot and tool apart: "model" ends at tool0 and "measurement_tool" holds the identified fixture (null: none).
# Version 2 files still load: their model ends at whatever the fit identified last (the fixture), as before.
READS = (2, 3)
GOLDEN_COUNT = 8
GOLDEN_TOL_Q = 1e-10  # rad (m): a loaded file must reproduce its golden q_cmd to this
GOLDEN_TOL_POSE = 1e-10  # m / rad-scaled entries of the predicted pose


class CompensatorFileError(ValueError):
    """A compensator export is unreadable, has the wrong schema, or fails its own golden vectors."""


# What a compensator file may hold, checked before its checksums, models or network are computed
# (:func:`check_payload`; an NPZ file's unpacked size and members' headers first, in :func:`_read_npz`). Generous
# for any arm labcal fits (6-7 joints, a network of a few hundred parameters, 8 golden vectors), tight enough that
# a crafted file cannot ask for gigabytes.
MAX_JOINTS = 32
MAX_GOLDEN = 256
MAX_LAYERS = 16
MAX_WIDTH = 4096  # inputs or nodes of one network layer
MAX_NETWORK_VALUES = 1_000_000  # weights + biases: 8 MB of float64 (the paper's networks hold hundreds)
MAX_FILE_BYTES = 48 * 1024**2  # a JSON file, or an NPZ file's unpacked arrays (1M numbers as JSON text)
MAX_META_CHARS = 4 * 1024**2  # the NPZ metadata (JSON text without the arrays)
MAX_PROVENANCE_DEPTH = 4  # provenance: {key: text | number | [{key: text}]}
MAX_PROVENANCE_TEXT = 65536  # one provenance string: a pooled fit lists every input ref and data hash
# Joint ranges are the data's covered range, which switches the out-of-range guard: a range beyond what any
# robot file may declare (two turns each way for a revolute joint, 10 m for a prismatic one: labcal.robots) is
# no range at all (±1e300 would switch the guard off) or degrees/millimetres.
MAX_RANGE = {REVOLUTE: MAX_REVOLUTE_LIMIT, PRISMATIC: MAX_LENGTH}
MAX_LENGTH_SCALE = 100.0  # m/rad: the arm's reach, metres


def _model_dict(model: LocalPOEModel) -> dict:
    return {
        "name": model.name,
        "joint_names": list(model.joint_names),
        "joint_types": list(model.joint_types),
        "frames": model.frames.tolist(),
        "twists": model.twists.tolist(),
        "limits": model.limits.tolist(),
    }


def _model_from(d: dict, what: str) -> LocalPOEModel:
    try:
        return LocalPOEModel(
            np.asarray(d["frames"], dtype=float),
            tuple(d["joint_types"]),
            np.asarray(d["twists"], dtype=float),
            np.asarray(d["limits"], dtype=float),
            str(d.get("name", "")),
            tuple(d.get("joint_names", ())),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise CompensatorFileError(f"{what}: not a valid robot model: {err}") from err


def golden_configurations(robot: CalibratedRobot, count: int = GOLDEN_COUNT, seed: int = 0) -> np.ndarray:
    """(count, n) well-conditioned configurations inside the robot's joint ranges, deterministic for a seed."""
    # CalibratedRobot.__post_init__ fills both from the nominal model when they were not given
    assert robot.joint_ranges is not None and robot.length_scale is not None
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    rng = np.random.default_rng(seed)
    cand = lo + (hi - lo) * rng.uniform(0.1, 0.9, size=(32 * count, robot.n))
    J = robot.model.equivalent_jacobian(cand, length_scale=robot.length_scale)
    cond = metric.scaled_condition(J, robot.length_scale)
    return cand[np.argsort(cond, kind="stable")[:count]]


# Every field that changes what a loaded compensator does (or what it says about itself) has a checksum in the file.
# The golden vectors only exercise the model and network at a few configurations: they cannot see a widened
# joint range (which silently switches off the out-of-range guard), a moved tracker frame, a changed length scale
# (a different metric for n < 6), a different joint map, or edited provenance (e.g. a forced export made to look
# unforced). A checksum is integrity against edits and damage, not a signature: whoever can rewrite the file can
# rewrite its checksums too.
CHECKED_FIELDS = (
    "robot",
    "model",
    "network",
    "joint_map",
    "length_scale",
    "joint_ranges",
    "T_tracker_base",
    "method",
    "provenance",
    "golden",
    "measurement_tool",
)


def _canonical(value):
    """JSON-ready data with every number as a float, so the JSON and NPZ forms of a payload read the same."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int | float | np.number):
        return float(value)
    return value


# Fields added after schema 2 was published: checked when the file has them (or their checksum), so files written
# before them still load (a compensator without a validity region falls back to the joint ranges).
OPTIONAL_CHECKED_FIELDS = ("validity",)


def field_checksums(payload: dict, also=()) -> dict[str, str]:
    """sha256 of each checked field's canonical JSON (floats written exactly): {field: hex}. The checked fields of
    the payload's schema version (version 2 had no measurement tool), then the optional ones it holds or ``also``
    names (a stored checksum of a field the file no longer holds)."""
    names = [name for name in CHECKED_FIELDS if payload.get("schema_version") != 2 or name != "measurement_tool"]
    names += [name for name in OPTIONAL_CHECKED_FIELDS if name in payload or name in also]
    out = {}
    for name in names:
        text = json.dumps(_canonical(payload.get(name)), sort_keys=True, separators=(",", ":"))
        out[name] = hashlib.sha256(text.encode()).hexdigest()
    return out


def _check_checksums(data: dict, source: str) -> None:
    stored = data.get("checksums")
    if not isinstance(stored, dict):
        raise CompensatorFileError(
            f"{source}: no checksums field: the file was damaged or edited — refusing to load it"
        )
    for name, digest in field_checksums(data, also=stored).items():
        if stored.get(name) != digest:
            raise CompensatorFileError(
                f"{source}: {name} does not match its checksum: the file was edited or damaged — refusing to load it "
                "(export the fit again rather than editing a compensator file)"
            )


_NETWORK_SCALES = ("in_mean", "in_scale", "out_mean", "out_scale")  # a network's standardisation of inputs and outputs


def to_payload(robot: CalibratedRobot, provenance: dict | None = None) -> dict:
    """Everything an export holds, as JSON-ready Python data (lists and numbers), with its field checksums."""
    q = golden_configurations(robot)
    net = robot.network
    jm = robot.joint_map
    assert robot.length_scale is not None  # CalibratedRobot.__post_init__ fills it from the nominal model
    payload = {
        "format": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "robot": {**_model_dict(robot.nominal), "hash": model_hash(robot.nominal, jm)},
        "model": {**_model_dict(robot.model), "hash": model_hash(robot.model)},
        "network": None
        if net is None
        else {
            "features": list(net.features),
            "weights": [np.asarray(W, float).tolist() for W in net.weights],
            "biases": [np.asarray(b, float).tolist() for b in net.biases],
            **{key: np.asarray(getattr(net, key), float).tolist() for key in _NETWORK_SCALES},
        },
        "length_scale": float(robot.length_scale),
        "joint_ranges": np.asarray(robot.joint_ranges, float).tolist(),
        "T_tracker_base": np.asarray(robot.T_tracker_base, float).tolist(),
        # the identified measurement fixture in tool0 (the model ends at tool0: robot and tool apart)
        "measurement_tool": None if robot.measurement_tool is None else np.asarray(robot.measurement_tool).tolist(),
        "method": robot.method,
        # controller → model joints (q_model = matrix q_controller + offsets); None: the controller's joints are the
        # model's. Golden vectors, joint ranges and the models are in model joints.
        "joint_map": None if jm is None else jm.as_dict(),
        "provenance": dict(provenance or {}),
        "golden": {
            "correct_method": "newton",
            "q": q.tolist(),
            "q_cmd": robot.correct(q, extrapolate=True).tolist(),
            "pose": robot.predict_pose(q).tolist(),
        },
    }
    if robot.validity is not None:
        payload["validity"] = robot.validity.as_dict()
    payload["checksums"] = field_checksums(payload)
    return payload


def from_payload(data: dict, source: str = "<payload>", *, stored: bool = False) -> tuple[CalibratedRobot, dict]:
    """Rebuild (robot, payload) from export data; checks schema, model hash, field checksums and golden vectors.

    stored: the payload is a fit's file inside a session store, whose own sha256 list already guards it. Such a
    file may still be schema 1 (fits stored before joint maps and field checksums): it is read without a joint
    map, so old sessions' fits can still be reported and exported. An export file on its own must be schema 2.
    """
    legacy = _check_schema(data, source, stored)
    try:
        check_payload(data, source)
        if not legacy:
            _check_checksums(data, source)
    except RecursionError:  # a field nested deeper than Python recurses (json.loads read it): not an export
        raise CompensatorFileError(f"{source}: a field is nested too deeply to be a compensator export") from None
    try:
        robot = _robot_from(data, source, legacy)
        golden = data["golden"]  # check_payload saw 1..MAX_GOLDEN of them
        q = np.asarray(golden["q"], dtype=float).reshape(-1, robot.n)
        q_cmd = np.asarray(golden["q_cmd"], dtype=float).reshape(q.shape)
        pose = np.asarray(golden["pose"], dtype=float).reshape(q.shape[0], 4, 4)
    except CompensatorFileError:
        raise
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise CompensatorFileError(f"{source}: missing or malformed field: {err!r}") from err
    _check_golden(robot, q, q_cmd, pose, golden.get("correct_method", "newton"), source)
    return robot, data


def check_payload(data: dict, source: str, *, error: type[Exception] = CompensatorFileError) -> None:
    """Refuse a payload whose fields are not what an export holds, before its checksums, models or network are
    computed: sizes and shapes (bounded by :data:`MAX_JOINTS`, :data:`MAX_GOLDEN`, :data:`MAX_LAYERS`,
    :data:`MAX_WIDTH`, :data:`MAX_NETWORK_VALUES`), finite numbers, joint ranges within :data:`MAX_RANGE`, names
    (:mod:`labcal.names`: a name reaches URScript, YAML and URDF exports), unique joint names, and
    provenance as short printable text nested at most :data:`MAX_PROVENANCE_DEPTH` deep. Checksums cannot stand in
    for this: whoever writes a file can recompute them. One line naming ``source`` and the field.
    """
    check = _FieldCheck(source, error)
    types = _check_models(check, data)
    n = len(types)
    _check_ranges(check, data, types)
    _check_frames(check, data)
    jm = data.get("joint_map")
    if jm is not None:
        jm = check.table("joint_map", jm)
        for key, shape in (("matrix", (n, n)), ("offsets", (n,))):
            try:
                check.numbers(key, jm.get(key), shape)
            except error as err:
                check.fail("joint_map", f"is not a valid joint map for {n} joints: {str(err).split(': ', 1)[1]}")
    if data.get("network") is not None:
        _check_network(check, check.table("network", data["network"]), max(n, 6))
    _check_golden_fields(check, check.table("golden", data.get("golden")), n)
    _check_provenance(data.get("provenance", {}), "provenance", 0, check.fail)
    checksums = data.get("checksums")
    if checksums is not None and not (
        isinstance(checksums, dict) and all(isinstance(v, str) and len(v) <= 128 for v in checksums.values())
    ):
        check.fail("checksums", "must map each field to a hex digest")


class _FieldCheck:
    """:func:`check_payload`'s refusals: one error line naming the source and the field."""

    def __init__(self, source: str, error: type[Exception]) -> None:
        self.source, self.error = source, error

    def fail(self, field: str, problem: str) -> NoReturn:
        raise self.error(f"{self.source}: {field} {problem}")

    def table(self, field: str, value) -> dict:
        if not isinstance(value, dict):
            self.fail(field, f"must be a table, got {type(value).__name__}")
        return value

    def numbers(self, field: str, value, shape: tuple) -> np.ndarray:
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError, RecursionError):
            a = None
        if a is None or a.shape != shape:
            got = "ragged or not numbers" if a is None else f"shape {a.shape}"
            self.fail(field, f"must be numbers of shape {shape}, got {got}")
        if not np.isfinite(a).all():
            self.fail(field, "must be finite numbers (it holds NaN or infinity)")
        return a


def _check_models(check: _FieldCheck, data: dict) -> list:
    """The robot's and the model's joint types (the same for both), names, frames, twists and limits; the types."""
    types = check.table("robot", data.get("robot")).get("joint_types")
    if not isinstance(types, list) or not 1 <= len(types) <= MAX_JOINTS:
        check.fail("robot.joint_types", f"must list 1 to {MAX_JOINTS} joints")
    n = len(types)
    for part in ("robot", "model"):
        d = check.table(part, data.get(part))
        if d.get("joint_types") != types or any(t not in (REVOLUTE, PRISMATIC) for t in types):
            check.fail(
                f"{part}.joint_types", f"must be {n} of {REVOLUTE!r} / {PRISMATIC!r}, the same for robot and model"
            )
        name = d.get("name", "")
        if name != "" and (problem := name_problem(name)):
            check.fail(f"{part}.name", problem)
        names = d.get("joint_names", [])
        if not isinstance(names, list) or len(names) not in (0, n):
            check.fail(f"{part}.joint_names", f"must list the {n} joints' names")
        for j, joint in enumerate(names):
            if problem := name_problem(joint):
                check.fail(f"{part}.joint_names[{j + 1}]", problem)
        if (twice := duplicate(names)) is not None:
            check.fail(f"{part}.joint_names", f"repeats {names[twice[1]]!r} (joints {twice[0] + 1} and {twice[1] + 1})")
        check.numbers(f"{part}.frames", d.get("frames"), (n + 1, 4, 4))
        check.numbers(f"{part}.twists", d.get("twists"), (n, 6))
        check.numbers(f"{part}.limits", d.get("limits"), (n, 2))
    return types


def _check_ranges(check: _FieldCheck, data: dict, types: list) -> None:
    """The calibrated joint ranges: within what a robot file may declare for each joint's type."""
    ranges = check.numbers("joint_ranges", data.get("joint_ranges"), (len(types), 2))
    for j, (lo, hi) in enumerate(ranges):
        bound = MAX_RANGE[types[j]]
        if lo > hi or max(abs(lo), abs(hi)) > bound:
            unit = "rad" if types[j] == REVOLUTE else "m"
            check.fail(
                f"joint_ranges[{j + 1}]",
                f"= [{lo:.6g}, {hi:.6g}] is not a range of a {types[j]} joint (lo <= hi, within ±{bound:.4g} {unit}, "
                "what a robot file may declare): a wider range would switch off the out-of-range guard",
            )


def _check_frames(check: _FieldCheck, data: dict) -> None:
    """The tracker frame, the measurement tool (rigid), the length scale and the method's name."""
    check.numbers("T_tracker_base", data.get("T_tracker_base"), (4, 4))
    if data.get("measurement_tool") is not None:
        X = check.numbers("measurement_tool", data["measurement_tool"], (4, 4))
        if not (np.allclose(X[3], [0, 0, 0, 1]) and np.allclose(X[:3, :3].T @ X[:3, :3], np.eye(3), atol=1e-9)):
            check.fail("measurement_tool", "must be a rigid transform (rotation + translation, last row 0 0 0 1)")
    scale = data.get("length_scale")
    if not (isinstance(scale, int | float) and not isinstance(scale, bool) and 0 < scale <= MAX_LENGTH_SCALE):
        check.fail("length_scale", f"must be a number of metres per radian in (0, {MAX_LENGTH_SCALE:g}], got {scale!r}")
    if problem := name_problem(data.get("method")):
        check.fail("method", problem)


def _length(value) -> int:
    """The length of a list or of an array's first axis (an NPZ field); 0 for anything else."""
    return len(value) if isinstance(value, list) or (isinstance(value, np.ndarray) and value.ndim) else 0


def _check_golden_fields(check: _FieldCheck, golden: dict, n: int) -> None:
    """The golden vectors' count and shapes and the correction method they were made with."""
    q = golden.get("q")
    k = _length(q)
    if not 1 <= k <= MAX_GOLDEN:
        check.fail(
            "golden.q",
            f"holds {k} configurations: no golden vectors to verify the file against, or more than {MAX_GOLDEN}",
        )
    check.numbers("golden.q", q, (k, n))
    check.numbers("golden.q_cmd", golden.get("q_cmd"), (k, n))
    check.numbers("golden.pose", golden.get("pose"), (k, 4, 4))
    if problem := name_problem(golden.get("correct_method", "newton")):
        check.fail("golden.correct_method", problem)


def _check_network(check: _FieldCheck, net: dict, outputs: int) -> None:
    """Features known to the registry, layer shapes that chain, sizes within the bounds, finite numbers; outputs:
    the equivalent robot's joint motion errors, max(n, 6) for an n-joint robot."""
    features = net.get("features")
    if not isinstance(features, list) or not features:
        check.fail("network.features", "must list the network's input features")
    for i, name in enumerate(features):
        if label_problem(name, 64) or not feature_lib.is_feature(name):
            known = ", ".join(feature_lib.NAMES)
            check.fail(f"network.features[{i + 1}]", f"must be one of {known}, got {printable(name, 80)!r}")
    weights, biases = net.get("weights"), net.get("biases")
    if not (isinstance(weights, list) and isinstance(biases, list) and 1 <= len(weights) == len(biases) <= MAX_LAYERS):
        check.fail("network.weights", f"must be 1 to {MAX_LAYERS} layers, each with its biases")
    in_mean = net.get("in_mean")
    width = _length(in_mean)
    if not 1 <= width <= MAX_WIDTH:
        check.fail("network.in_mean", f"must hold 1 to {MAX_WIDTH} numbers (one per network input)")
    check.numbers("network.in_mean", in_mean, (width,))
    check.numbers("network.in_scale", net.get("in_scale"), (width,))
    check.numbers("network.out_mean", net.get("out_mean"), (outputs,))
    check.numbers("network.out_scale", net.get("out_scale"), (outputs,))
    total = 0
    for i, (W, b) in enumerate(zip(weights, biases, strict=True)):
        rows = outputs if i == len(weights) - 1 else _length(W)
        if not 1 <= rows <= MAX_WIDTH:
            check.fail(f"network.weights.{i}", f"must have 1 to {MAX_WIDTH} rows")
        total += rows * (width + 1)
        if total > MAX_NETWORK_VALUES:
            check.fail("network.weights", f"hold more than {MAX_NETWORK_VALUES} numbers: more than a compensator holds")
        check.numbers(f"network.weights.{i}", W, (rows, width))
        check.numbers(f"network.biases.{i}", b, (rows,))
        width = rows


def _check_provenance(value, field: str, depth: int, fail) -> None:
    """Provenance: text, numbers, true/false, null, and lists / tables of them, shallow and printable."""
    if value is None or isinstance(value, bool):
        return
    if isinstance(value, int | float):
        if not math.isfinite(value):
            fail(field, "must be a finite number")
        return
    if isinstance(value, str):
        if problem := label_problem(value, MAX_PROVENANCE_TEXT):
            fail(field, problem)
        return
    if depth >= MAX_PROVENANCE_DEPTH or not isinstance(value, list | dict):
        fail(field, f"must be text, numbers, or lists and tables of them nested at most {MAX_PROVENANCE_DEPTH} deep")
    if isinstance(value, list):
        for i, item in enumerate(value[:10_000]):
            _check_provenance(item, f"{field}[{i + 1}]", depth + 1, fail)
        if len(value) > 10_000:
            fail(field, "must hold at most 10000 entries")
        return
    for key, item in value.items():
        if problem := name_problem(key):
            fail(f"{field} key", problem)
        _check_provenance(item, f"{field}.{key}", depth + 1, fail)


def _check_schema(data: dict, source: str, stored: bool) -> bool:
    """Raise unless ``data`` is a compensator payload this labcal reads; True for a stored schema-1 (legacy) fit."""
    if not isinstance(data, dict) or data.get("format") != SCHEMA:
        raise CompensatorFileError(f"{source}: not a labcal compensator export (format field is not {SCHEMA!r})")
    version = data.get("schema_version")
    legacy = stored and version == 1
    if version not in READS and not legacy:
        hint = "; export the fit again with this labcal" if version == 1 else ""
        reads = ", ".join(map(str, READS))
        raise CompensatorFileError(
            f"{source}: schema_version {version!r} is not supported (this labcal reads {reads}){hint}"
        )
    return legacy


def _robot_from(data: dict, source: str, legacy: bool) -> CalibratedRobot:
    """The CalibratedRobot a payload describes (models, joint map checked against the stored hash, network)."""
    nominal = _model_from(data["robot"], f"{source}: robot")
    model, n = _model_from(data["model"], f"{source}: model"), nominal.n
    jd = None if legacy else data["joint_map"]
    try:
        # check_payload saw an (n, n) matrix and (n,) offsets for the robot's n joints
        joint_map = None if jd is None else JointMap(np.asarray(jd["matrix"]), np.asarray(jd["offsets"]))
    except (KeyError, TypeError, ValueError) as err:
        raise CompensatorFileError(f"{source}: joint_map is not a valid joint map: {err}") from err
    if model_hash(nominal, joint_map) != data["robot"].get("hash"):
        raise CompensatorFileError(f"{source}: robot model does not match its hash (file edited or damaged)")
    nd = data.get("network")
    net = None
    if nd is not None:
        net = Network(
            features=tuple(nd["features"]),
            weights=tuple(np.asarray(W, dtype=float) for W in nd["weights"]),
            biases=tuple(np.asarray(b, dtype=float) for b in nd["biases"]),
            **{key: np.asarray(nd[key], dtype=float) for key in _NETWORK_SCALES},
        )
    try:  # a file written without a validity region has the joint ranges alone
        validity = None if data.get("validity") is None else ValidityRegion.from_dict(data["validity"], n)
    except (KeyError, TypeError, ValueError) as err:
        raise CompensatorFileError(f"{source}: validity is not a validity region of {n} joints: {err}") from None
    return CalibratedRobot(
        nominal=nominal,
        model=model,
        network=net,
        T_tracker_base=np.asarray(data["T_tracker_base"], dtype=float).reshape(4, 4),
        joint_ranges=np.asarray(data["joint_ranges"], dtype=float).reshape(n, 2),
        length_scale=float(data["length_scale"]),
        method=str(data.get("method", "")),
        joint_map=joint_map,
        measurement_tool=None if data.get("measurement_tool") is None else np.asarray(data["measurement_tool"], float),
        validity=validity,
    )


def _check_golden(robot: CalibratedRobot, q, q_cmd, pose, method: str, source: str) -> None:
    """Raise unless the rebuilt robot reproduces its golden vectors (q_cmd and predicted poses)."""
    try:
        got_pose = robot.predict_pose(q)
        if robot.n > 6:
            # A redundant arm reaches a pose along a whole self-motion, so which q_cmd the solver lands on depends on
            # its details: check that the stored commands still reach the nominal poses instead of re-finding them.
            miss = se3.log_se3(se3.inv(robot.predict_pose(q_cmd)) @ robot.nominal.fk(q))
            dq, what = float(np.max(np.abs(miss))), "pose error at the stored q_cmd (m, rad)"
        else:
            got_q = robot.correct(q, method=method, extrapolate=True)
            dq, what = float(np.max(np.abs(got_q - q_cmd))), "|Δq_cmd| (rad)"
    except (ValueError, np.linalg.LinAlgError) as err:
        raise CompensatorFileError(f"{source}: cannot evaluate the golden vectors: {err}") from err
    dT = float(np.max(np.abs(got_pose - pose)))
    if not (dq <= GOLDEN_TOL_Q and dT <= GOLDEN_TOL_POSE):
        raise CompensatorFileError(
            f"{source}: golden vectors disagree with the stored model (max {what} = {dq:.3g}, "
            f"max |Δpose| = {dT:.3g}); the file was edited or damaged — refusing to load it"
        )


def save(robot: CalibratedRobot, path, provenance: dict | None = None) -> Path:
    """Write a compensator export: ``.json`` (text) or ``.npz`` (arrays; metadata as a JSON string, no pickle)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".json", ".npz"):
        raise ValueError(f"compensator export path must end in .json or .npz, got {path.name!r}")
    payload = to_payload(robot, provenance)
    # What load would refuse is not written: a name or a provenance value that could inject into an export.
    check_payload(payload, "the compensator to save", error=ValueError)
    if suffix == ".json":
        write_text(path, json.dumps(payload, indent=1) + "\n")
    else:
        arrays: dict[str, np.ndarray] = {}
        meta = _split_arrays(payload, "", arrays)
        arrays["__meta__"] = np.array(json.dumps(meta))
        buffer = io.BytesIO()  # whole in memory first: the file is then replaced in one rename, never half written
        # numpy's stub types savez's **kwds as its allow_pickle: bool keyword; these are arrays by name
        np.savez(buffer, **arrays)  # type: ignore[arg-type]
        write_bytes(path, buffer.getvalue())
    return path


_ARRAY_KEYS = {"frames", "twists", "limits", "in_mean", "in_scale", "out_mean", "out_scale", "joint_ranges"}
_ARRAY_KEYS |= {"T_tracker_base", "q", "q_cmd", "pose", "matrix", "offsets", "measurement_tool"}
_ARRAY_KEYS |= {"centres", "joint_scale"}


def _split_arrays(obj, prefix: str, arrays: dict):
    """Move numeric arrays out of the payload into ``arrays`` (referenced as {"$array": key})."""
    if isinstance(obj, dict):
        out: dict[str, object] = {}
        for key, value in obj.items():
            name = f"{prefix}{key}"
            if key in _ARRAY_KEYS and value is not None:
                arrays[name] = np.asarray(value, dtype=float)
                out[key] = {"$array": name}
            elif key in ("weights", "biases") and isinstance(value, list):
                refs = []
                for i, item in enumerate(value):
                    arrays[f"{name}.{i}"] = np.asarray(item, dtype=float)
                    refs.append({"$array": f"{name}.{i}"})
                out[key] = refs
            elif key in ("provenance", "checksums"):
                out[key] = value  # JSON-able metadata (checksums are strings named like the array fields), kept as is
            else:
                out[key] = _split_arrays(value, f"{name}.", arrays)
        return out
    return obj


def _join_arrays(obj, arrays: dict, used: set, source: str, where: str = ""):
    """The NPZ metadata with each {"$array": name} reference replaced by its array (names in ``used``). A reference
    must sit where :func:`_split_arrays` puts one (a numeric field, or a network layer, named by its own path), so
    that no field :func:`check_payload` reads as text, a count or a table can be an array."""
    if isinstance(obj, dict):
        if set(obj) == {"$array"}:
            parent, _, key = where.rpartition(".")
            name = obj["$array"]
            if name != where or not (key in _ARRAY_KEYS or parent.rpartition(".")[2] in ("weights", "biases")):
                raise CompensatorFileError(f"{source}: {printable(where)} must not be an array reference")
            if name not in arrays:
                raise CompensatorFileError(f"{source}: array {name!r} referenced by the metadata is missing")
            used.add(name)
            return arrays[name]
        prefix = f"{where}." if where else ""
        kept = ("provenance", "checksums")  # metadata _split_arrays keeps as they are
        return {k: v if k in kept else _join_arrays(v, arrays, used, source, prefix + k) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_join_arrays(v, arrays, used, source, f"{where}.{i}") for i, v in enumerate(obj)]
    return obj


def read_payload(path) -> dict:
    """The raw payload of a JSON or NPZ export (arrays as numpy arrays for NPZ), not yet verified.

    Bounded before anything large is read: a JSON file by its size, an NPZ file by its members' unpacked sizes
    and each member's ``.npy`` header (:func:`_read_npz`). The fields' shapes and values are then
    :func:`check_payload`'s, for both forms alike. Every refusal is one line naming the file and the field.
    """
    path = Path(path)
    if not path.is_file():
        raise CompensatorFileError(f"{path}: no such compensator file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            size = path.stat().st_size
            if size > MAX_FILE_BYTES:
                raise CompensatorFileError(
                    f"{path}: {size} bytes is larger than any compensator export ({MAX_FILE_BYTES} bytes at most)"
                )
            return json.loads(path.read_bytes())
        if suffix == ".npz":
            return _read_npz(path)
    except CompensatorFileError:
        raise
    except RecursionError:
        raise CompensatorFileError(f"{path}: cannot read the export: nested too deeply to be a compensator") from None
    except (OSError, ValueError, UnicodeDecodeError, zipfile.BadZipFile, EOFError) as err:
        raise CompensatorFileError(f"{path}: cannot read the export: {printable(err, 200)}") from None
    raise CompensatorFileError(f"{path}: a compensator export ends in .json or .npz")


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of an NPZ member from its header alone (a few hundred bytes read)."""
    with zf.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in readers:
            raise ValueError(f"npy format version {version} is not one labcal writes")
        shape, _, dtype = readers[version](fh)
    return tuple(shape), dtype


def _read_npz(path: Path) -> dict:
    """The payload of an NPZ export: its members (``.npy`` arrays, no pickle) joined into the ``__meta__`` JSON.

    Nothing is read beyond what the file holds: the members unpack to at most :data:`MAX_FILE_BYTES` together, and
    a member is read only when its header declares float64 numbers (the metadata: one string of at most
    :data:`MAX_META_CHARS` characters) that fit in its unpacked size (numpy allocates what a header declares, so a
    crafted header of a few bytes could otherwise ask for gigabytes).
    """
    with zipfile.ZipFile(path) as zf:
        infos = zf.infolist()
        for info in infos:
            if not info.filename.endswith(".npy"):
                raise CompensatorFileError(f"{path}: member {info.filename!r} is not an array: not a labcal export")
        total = sum(info.file_size for info in infos)
        if total > MAX_FILE_BYTES:
            raise CompensatorFileError(
                f"{path}: its arrays unpack to {total} bytes, more than any compensator export holds "
                f"({MAX_FILE_BYTES} bytes at most): refusing to read them"
            )
        arrays = {}
        for info in infos:
            name = info.filename[:-4]
            shape, dtype = _npy_header(zf, info)
            if name == "__meta__":
                if shape != () or dtype.kind != "U" or dtype.itemsize // 4 > MAX_META_CHARS:
                    raise CompensatorFileError(
                        f"{path}: __meta__ must be one string of at most {MAX_META_CHARS} characters"
                    )
            elif dtype != np.float64:
                raise CompensatorFileError(f"{path}: {name} must be float64 numbers, got dtype {dtype}")
            if math.prod(shape) * dtype.itemsize > info.file_size:
                raise CompensatorFileError(
                    f"{path}: {name} has shape {shape}, more numbers than its {info.file_size} bytes hold: "
                    "refusing to read it"
                )
            with zf.open(info) as fh:
                arrays[name] = np.lib.format.read_array(fh, allow_pickle=False)
    if "__meta__" not in arrays:
        raise CompensatorFileError(f"{path}: NPZ file has no __meta__ entry (not a labcal export)")
    used: set[str] = set()
    payload = _join_arrays(json.loads(str(arrays.pop("__meta__"))), arrays, used, str(path))
    if unused := sorted(set(arrays) - used):
        raise CompensatorFileError(f"{path}: array {unused[0]!r} is not referenced by the metadata")
    return payload


class Compensator:
    """The deployable runtime of a calibration: correct joint commands, predict poses. Numpy only.

    It speaks the controller's joints: when the robot file declared a joint map (controller joints are not the
    model's, e.g. a coupled elbow), ``correct`` and ``predict_pose`` take controller joints, convert them to model
    joints (q_model = M q_controller + b), work on the calibrated model, and ``correct`` converts its answer back.
    Range checks apply to the model joints (the calibrated ranges are the data's model-joint ranges). Without a map
    (or an identity one) nothing is converted. :attr:`robot` (a :class:`CalibratedRobot`) works in model joints.

    Example::

        comp = Compensator.load("ur10-hybrid.json")   # verifies schema, checksums, model hash and golden vectors
        q_cmd = comp.correct(q)                        # (n,) or (k, n) rad; refuses q outside the trained ranges
        T = comp.predict_pose(q_cmd)                   # (4, 4) base frame: where the real robot goes
        comp.T_tracker_base                            # (4, 4) base pose in the tracker frame
    """

    def __init__(self, robot: CalibratedRobot, provenance: dict | None = None, source: str = "") -> None:
        self.robot = robot
        self.provenance = dict(provenance or {})
        self.source = source
        self._map = robot.joint_map  # None for the identity: the hot path then converts nothing

    @classmethod
    def load(cls, path) -> Compensator:
        """Read and verify a ``.json`` / ``.npz`` export; CompensatorFileError if it is damaged or edited."""
        data = read_payload(path)
        robot, data = from_payload(data, str(path))
        return cls(robot, data.get("provenance") or {}, str(path))

    def save(self, path) -> Path:
        return save(self.robot, path, self.provenance)

    @property
    def n(self) -> int:
        return self.robot.n

    @property
    def method(self) -> str:
        return self.robot.method

    @property
    def joint_ranges(self) -> np.ndarray:
        """(n, 2) the joint ranges the calibration covered (rad, m), in model joints (see :attr:`joint_map`)."""
        assert self.robot.joint_ranges is not None  # CalibratedRobot.__post_init__ fills it
        return self.robot.joint_ranges

    @property
    def T_tracker_base(self) -> np.ndarray:
        """(4, 4) the pose of the robot base in the tracker frame (identity for base-frame data)."""
        return self.robot.T_tracker_base

    @property
    def measurement_tool(self) -> np.ndarray | None:
        """(4, 4) the fixture the calibration measured through, in tool0 (None: tool0 itself); not corrected."""
        return self.robot.measurement_tool

    @property
    def joint_map(self) -> JointMap:
        """The controller → model joint map (identity when the robot file declared none)."""
        return self._map if self._map is not None else JointMap.identity(self.n)

    @property
    def robot_hash(self) -> str:
        """sha256 of the nominal robot model and its joint map (labcal.robots.model_hash, = RobotSpec.hash)."""
        return model_hash(self.robot.nominal, self._map)

    def to_model(self, q) -> np.ndarray:
        """Controller joints (n,) or (k, n) → model joints, checked for shape and finite values first."""
        q2, single = self.robot._batch(q)
        out = q2.copy() if self._map is None else self._map.to_model(q2)  # never the caller's own array
        return out[0] if single else out

    def check_range(self, q, extrapolate: bool = False) -> None:
        """Raise ValueError naming the first configuration and joint outside the calibrated ranges (q: controller
        joints; the ranges are the model joints', so a mapped joint is named as the model joint it becomes)."""
        if extrapolate:
            return
        if self._map is None:
            self.robot.check_range(q)
            return
        self._check_model_range(self.to_model(q))

    def _check_model_range(self, q_model: np.ndarray) -> None:
        try:
            self.robot._check_range(np.atleast_2d(q_model))
        except ValueError as err:
            raise ValueError(
                f"{err} (model joints: the robot file's joint map turns the controller joints into these)"
            ) from None

    def correct(
        self,
        q,
        *,
        extrapolate: bool = False,
        method: str = "newton",
        tol: float = 1e-11,
        damped_iterations: int | None = None,
        tcp=None,
    ) -> np.ndarray:
        """Commanded controller joints (n,) or (k, n) that make the real robot reach the nominal pose of the
        controller joints q (an empty (0, n) q gives an empty answer). method, tol, damped_iterations and tcp (the
        working TCP in tool0): as :meth:`CalibratedRobot.correct` (a control loop that must bound its worst case
        lowers damped_iterations)."""
        correct = self.robot.correct
        if self._map is None:  # a control loop's call: keywords, not a dict unpacked, cost least
            return correct(
                q, extrapolate=extrapolate, method=method, tol=tol, damped_iterations=damped_iterations, tcp=tcp
            )
        q_model = self.to_model(q)
        if not extrapolate:
            self._check_model_range(q_model)
        q_cmd = correct(q_model, extrapolate=True, method=method, tol=tol, damped_iterations=damped_iterations, tcp=tcp)
        return self._map.to_controller(q_cmd)

    def predict_pose(self, q, *, extrapolate: bool = False, tcp=None) -> np.ndarray:
        """Pose (4, 4) or (k, 4, 4) in the base frame of the TCP (``tcp`` in tool0; default tool0) that the real robot
        reaches when commanded the controller joints q (an empty (0, n) q gives (0, 4, 4))."""
        self.check_range(q, extrapolate)
        return self.robot.predict_pose(q if self._map is None else self.to_model(q), tcp=tcp)


def load(path) -> Compensator:
    """Shorthand for :meth:`Compensator.load`."""
    return Compensator.load(path)
