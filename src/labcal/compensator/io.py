"""Compensator export files: the payload (schema, models, network, ranges, golden vectors, per-field checksums),
JSON / NPZ save and load, and :class:`Compensator`, the deployable runtime that reads them. Numpy only.

:meth:`Compensator.load` reads a JSON or NPZ export written by :func:`save` (schema version, robot model and its
hash, identified frames, network, joint ranges, tracker pose, length scale, joint map, provenance, golden vectors,
and a checksum of each of those fields), refuses a file whose fields do not match their checksums (an edit naming
the field: a widened joint range would otherwise silently switch off the out-of-range guard), re-computes the
golden vectors and refuses a file that disagrees.

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
import json
from pathlib import Path

import numpy as np

from labcal.compensator.model import CalibratedRobot, Network
from labcal.kinematics import metric, se3
from labcal.kinematics.poe import LocalPOEModel
from labcal.robots import model_hash
from labcal.robots.joint_map import JointMap

SCHEMA = "labcal-compensator"
SCHEMA_VERSION = 2  # 2: joint map, and per-field checksums over everything that changes behaviour
GOLDEN_COUNT = 8
GOLDEN_TOL_Q = 1e-10  # rad (m): a loaded file must reproduce its golden q_cmd to this
GOLDEN_TOL_POSE = 1e-10  # m / rad-scaled entries of the predicted pose


class CompensatorFileError(ValueError):
    """A compensator export is unreadable, has the wrong schema, or fails its own golden vectors."""


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
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    rng = np.random.default_rng(seed)
    cand = lo + (hi - lo) * rng.uniform(0.1, 0.9, size=(32 * count, robot.n))
    J = robot.model.equivalent_jacobian(cand, length_scale=robot.length_scale)
    cond = metric.scaled_condition(J, robot.length_scale)
    keep = cand[np.argsort(cond, kind="stable")[:count]]
    return keep


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


def field_checksums(payload: dict) -> dict[str, str]:
    """sha256 of each checked field's canonical JSON (floats written exactly): {field: hex}."""
    out = {}
    for name in CHECKED_FIELDS:
        text = json.dumps(_canonical(payload.get(name)), sort_keys=True, separators=(",", ":"))
        out[name] = hashlib.sha256(text.encode()).hexdigest()
    return out


def _check_checksums(data: dict, source: str) -> None:
    stored = data.get("checksums")
    if not isinstance(stored, dict):
        raise CompensatorFileError(
            f"{source}: no checksums field: the file was damaged or edited — refusing to load it"
        )
    got = field_checksums(data)
    for name in CHECKED_FIELDS:
        if stored.get(name) != got[name]:
            raise CompensatorFileError(
                f"{source}: {name} does not match its checksum: the file was edited or damaged — refusing to load it "
                "(export the fit again rather than editing a compensator file)"
            )


def to_payload(robot: CalibratedRobot, provenance: dict | None = None) -> dict:
    """Everything an export holds, as JSON-ready Python data (lists and numbers), with its field checksums."""
    q = golden_configurations(robot)
    net = robot.network
    jm = robot.joint_map
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
            "in_mean": np.asarray(net.in_mean, float).tolist(),
            "in_scale": np.asarray(net.in_scale, float).tolist(),
            "out_mean": np.asarray(net.out_mean, float).tolist(),
            "out_scale": np.asarray(net.out_scale, float).tolist(),
        },
        "length_scale": float(robot.length_scale),
        "joint_ranges": np.asarray(robot.joint_ranges, float).tolist(),
        "T_tracker_base": np.asarray(robot.T_tracker_base, float).tolist(),
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
    payload["checksums"] = field_checksums(payload)
    return payload


def from_payload(data: dict, source: str = "<payload>", *, stored: bool = False) -> tuple[CalibratedRobot, dict]:
    """Rebuild (robot, payload) from export data; checks schema, model hash, field checksums and golden vectors.

    stored: the payload is a fit's file inside a session store, whose own sha256 list already guards it. Such a
    file may still be schema 1 (fits stored before joint maps and field checksums): it is read without a joint
    map, so old sessions' fits can still be reported and exported. An export file on its own must be schema 2.
    """
    legacy = _check_schema(data, source, stored)
    if not legacy:
        _check_checksums(data, source)
    try:
        robot = _robot_from(data, source, legacy)
        golden = data["golden"]
        if np.size(golden["q"]) == 0:
            raise CompensatorFileError(f"{source}: no golden vectors to verify the file against")
        q = np.asarray(golden["q"], dtype=float).reshape(-1, robot.n)
        q_cmd = np.asarray(golden["q_cmd"], dtype=float).reshape(q.shape)
        pose = np.asarray(golden["pose"], dtype=float).reshape(q.shape[0], 4, 4)
    except CompensatorFileError:
        raise
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise CompensatorFileError(f"{source}: missing or malformed field: {err!r}") from err
    if q.shape[0] == 0:
        raise CompensatorFileError(f"{source}: no golden vectors to verify the file against")
    _check_golden(robot, q, q_cmd, pose, golden.get("correct_method", "newton"), source)
    return robot, data


def _check_schema(data: dict, source: str, stored: bool) -> bool:
    """Raise unless ``data`` is a compensator payload this labcal reads; True for a stored schema-1 (legacy) fit."""
    if not isinstance(data, dict) or data.get("format") != SCHEMA:
        raise CompensatorFileError(f"{source}: not a labcal compensator export (format field is not {SCHEMA!r})")
    version = data.get("schema_version")
    legacy = stored and version == 1
    if version != SCHEMA_VERSION and not legacy:
        hint = "; export the fit again with this labcal" if version == 1 else ""
        raise CompensatorFileError(
            f"{source}: schema_version {version!r} is not supported (this labcal reads {SCHEMA_VERSION}){hint}"
        )
    return legacy


def _robot_from(data: dict, source: str, legacy: bool) -> CalibratedRobot:
    """The CalibratedRobot a payload describes (models, joint map checked against the stored hash, network)."""
    nominal = _model_from(data["robot"], f"{source}: robot")
    model = _model_from(data["model"], f"{source}: model")
    jd = None if legacy else data["joint_map"]
    try:
        joint_map = None if jd is None else JointMap(np.asarray(jd["matrix"]), np.asarray(jd["offsets"]))
    except (KeyError, TypeError, ValueError) as err:
        raise CompensatorFileError(f"{source}: joint_map is not a valid joint map: {err}") from err
    if joint_map is not None and joint_map.n != nominal.n:
        raise CompensatorFileError(
            f"{source}: joint_map is not a valid joint map: it maps {joint_map.n} joints, the robot has {nominal.n}"
        )
    if model_hash(nominal, joint_map) != data["robot"].get("hash"):
        raise CompensatorFileError(f"{source}: robot model does not match its hash (file edited or damaged)")
    nd = data.get("network")
    net = None
    if nd is not None:
        arrays = {key: np.asarray(nd[key], dtype=float) for key in ("in_mean", "in_scale", "out_mean", "out_scale")}
        net = Network(
            features=tuple(nd["features"]),
            weights=tuple(np.asarray(W, dtype=float) for W in nd["weights"]),
            biases=tuple(np.asarray(b, dtype=float) for b in nd["biases"]),
            **arrays,
        )
    return CalibratedRobot(
        nominal=nominal,
        model=model,
        network=net,
        T_tracker_base=np.asarray(data["T_tracker_base"], dtype=float).reshape(4, 4),
        joint_ranges=np.asarray(data["joint_ranges"], dtype=float).reshape(nominal.n, 2),
        length_scale=float(data["length_scale"]),
        method=str(data.get("method", "")),
        joint_map=joint_map,
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
    payload = to_payload(robot, provenance)
    suffix = path.suffix.lower()
    if suffix == ".json":
        path.write_text(json.dumps(payload, indent=1) + "\n")
    elif suffix == ".npz":
        arrays: dict[str, np.ndarray] = {}
        meta = _split_arrays(payload, "", arrays)
        arrays["__meta__"] = np.array(json.dumps(meta))
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)
    else:
        raise ValueError(f"compensator export path must end in .json or .npz, got {path.name!r}")
    return path


_ARRAY_KEYS = {"frames", "twists", "limits", "in_mean", "in_scale", "out_mean", "out_scale", "joint_ranges"}
_ARRAY_KEYS |= {"T_tracker_base", "q", "q_cmd", "pose", "matrix", "offsets"}


def _split_arrays(obj, prefix: str, arrays: dict):
    """Move numeric arrays out of the payload into ``arrays`` (referenced as {"$array": key})."""
    if isinstance(obj, dict):
        out = {}
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


def _join_arrays(obj, arrays):
    if isinstance(obj, dict):
        if set(obj) == {"$array"}:
            name = obj["$array"]
            if name not in arrays:
                raise CompensatorFileError(f"array {name!r} referenced by the metadata is missing")
            return arrays[name]
        return {k: _join_arrays(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_join_arrays(v, arrays) for v in obj]
    return obj


def read_payload(path) -> dict:
    """The raw payload of a JSON or NPZ export (arrays as numpy arrays for NPZ), unverified."""
    path = Path(path)
    if not path.is_file():
        raise CompensatorFileError(f"{path}: no such compensator file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            return json.loads(path.read_text())
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                arrays = {name: z[name] for name in z.files}
            if "__meta__" not in arrays:
                raise CompensatorFileError(f"{path}: NPZ file has no __meta__ entry (not a labcal export)")
            meta = json.loads(str(arrays.pop("__meta__")))
            return _join_arrays(meta, arrays)
    except CompensatorFileError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as err:
        raise CompensatorFileError(f"{path}: cannot read the export: {err}") from err
    raise CompensatorFileError(f"{path}: a compensator export ends in .json or .npz")


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
        return self.robot.joint_ranges

    @property
    def T_tracker_base(self) -> np.ndarray:
        """(4, 4) the pose of the robot base in the tracker frame (identity for base-frame data)."""
        return self.robot.T_tracker_base

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
    ) -> np.ndarray:
        """Commanded controller joints (n,) or (k, n) that make the real robot reach the nominal pose of the
        controller joints q (an empty (0, n) q gives an empty answer). method, tol and damped_iterations: as
        :meth:`CalibratedRobot.correct` (a control loop that must bound its worst case lowers damped_iterations)."""
        correct = self.robot.correct
        if self._map is None:  # a control loop's call: keywords, not a dict unpacked, cost least
            return correct(q, extrapolate=extrapolate, method=method, tol=tol, damped_iterations=damped_iterations)
        q_model = self.to_model(q)
        if not extrapolate:
            self._check_model_range(q_model)
        q_cmd = correct(q_model, extrapolate=True, method=method, tol=tol, damped_iterations=damped_iterations)
        return self._map.to_controller(q_cmd)

    def predict_pose(self, q, *, extrapolate: bool = False) -> np.ndarray:
        """Pose (4, 4) or (k, 4, 4) in the base frame that the real robot reaches when commanded the controller
        joints q (an empty (0, n) q gives (0, 4, 4))."""
        if self._map is None:
            self.robot.check_range(q, extrapolate)
            return self.robot.predict_pose(q)
        q_model = self.to_model(q)
        if not extrapolate:
            self._check_model_range(q_model)
        return self.robot.predict_pose(q_model)


def load(path) -> Compensator:
    """Shorthand for :meth:`Compensator.load`."""
    return Compensator.load(path)
