"""``--format ur-kinematics``: the calibration YAML that ur_description reads (what ur_calibration writes).

The file is ur_description's ``kinematics_params`` / ``default_kinematics.yaml`` format::

    kinematics:
      shoulder:  {x, y, z, roll, pitch, yaw}     # origin of shoulder_pan_joint
      upper_arm: {…}                             # shoulder_lift_joint
      forearm:   {…}                             # elbow_joint
      wrist_1:   {…}
      wrist_2:   {…}
      wrist_3:   {…}
      hash: "labcal_<16 hex digits>"

Each entry is a URDF joint origin (metres; roll-pitch-yaw in radians about fixed x, y, z:
``R = Rz(yaw) Ry(pitch) Rx(roll)``) of the joint that turns about its local z axis, parent link to child link.

Frames. labcal's base frame K0 of a UR robot is the controller's base frame (the DH base, the frame of the
pendant's TCP poses). ur_description's ``base_link`` is that frame turned by π about z; its ``base_link_inertia``
(and ``base``) is K0 again, and the shoulder origin is given in ``base_link_inertia``. So the YAML chain starts in
K0, and poses of labcal (``predict_pose``) equal ``base_link_inertia → tool0`` of the URDF ur_description builds
from this file. At the other end ur_description fixes ``wrist_3_link → flange → tool0`` (flange turned by
(0, −π/2, −π/2), tool0 back by (π/2, 0, π/2), so tool0 is the wrist_3_link frame) and has no calibration entry
for it.

Robot and tool apart. ``robot.model`` ends at tool0 (the robot file's tool: the flange for the built-in UR
files), so ``tool0``/``flange`` of the description sit on the real flange, off by the robot's own errors only;
the identified measurement fixture (``robot.measurement_tool``) is written beside it as a comment,
``# measurement_tool_in_tool0: x y z rx ry rz``.

What is exact. The joint frames of the identified local-POE model, rewritten with every joint axis along local z
through the frame origin (:class:`~labcal.export.zform.ZAxisForm`), are written to 17 significant digits, and a
rotation about / shift along the last joint's axis in the identified tool frame moves exactly into ``wrist_3``.
The rest of the identified tool0 frame (a shift across the last axis and a tilt: 4 numbers) has no place in
ur_description: it is written as ``# tcp_in_tool0: x y z rx ry rz`` (m, rotation vector, the pendant's TCP form)
in a comment and returned, to be set as the TCP; with it, the YAML reproduces the geometric model exactly. A
learned term (hybrid/ann) is not representable either: the export is refused, saying how large it is, unless
``geometry_only`` (then noted in the file). Refused: robots that are not 6-joint revolute UR arms, joint maps,
screw joints.

The ``hash`` key. ur_calibration writes ``calib_<n>``, where n is the C++ ``std::hash`` of the controller's own
DH parameters (the factory calibration it reads from the primary interface, ``KinematicsInfo::toHash`` in
ur_client_library); ur_robot_driver reads ``kinematics/hash`` from the description and, at every start, compares
it with the connected controller's value. On a mismatch it logs "The calibration parameters of the connected
robot don't match the ones from the given kinematics config file" as an ERROR and starts anyway. This file
describes labcal's identified kinematics, which are *not* the controller's factory calibration, so no honest
value can match: the key identifies these numbers (``labcal_`` + sha256 of the ``kinematics`` entries) and the
message is expected. What it means is true: the controller's own Cartesian motions (``movel``, the pendant's TCP
readout, the driver's pass-through Cartesian controllers) follow the controller's model, while joint targets
planned on this description (MoveIt, …) reach the calibrated poses. The file says so in a comment.

Strings. The robot's name and the provenance are comments: each is one printable line (control characters
escaped, :func:`labcal.names.printable`), so nothing in them can start a key; the hash is a double-quoted
YAML scalar (JSON string syntax, which YAML reads the same way). The file is written atomically
(:mod:`labcal.atomicio`).

Example::

    >>> from labcal.compensator import CalibratedRobot
    >>> from labcal.robots import load
    >>> nominal = load("ur10").model
    >>> text = ur_kinematics_text(CalibratedRobot(nominal, nominal))
    >>> [line for line in text.splitlines() if line.startswith("    z:")][0]     # shoulder z = the UR10's d1
    '    z: 0.1273'
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

from labcal.compensator import CalibratedRobot
from labcal.export.learned import refuse_or_note
from labcal.export.zform import without_pitch
from labcal.kinematics import se3
from labcal.kinematics.poe import REVOLUTE
from labcal.names import printable
from labcal.robots import model_hash

UR_SEGMENTS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
UR_JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def check_ur(robot: CalibratedRobot, fmt: str) -> None:
    """Refuse anything but a 6-joint revolute UR arm without a joint map (ValueError saying why)."""
    model = robot.nominal
    name = (model.name or "").lower()
    is_ur = name.startswith("ur") or tuple(model.joint_names) == UR_JOINT_NAMES
    if not is_ur or model.n != 6 or any(t != REVOLUTE for t in model.joint_types):
        raise ValueError(
            f"{fmt} is ur_description's format for Universal Robots arms (6 revolute joints named like "
            f"{UR_JOINT_NAMES[0]}, or a robot file named ur*); this robot is {printable(model.name or '?')} with "
            f"{model.n} joints ({', '.join(model.joint_types)}). Use --format urdf or the json/npz compensator"
        )
    if robot.joint_map is not None:
        raise ValueError(f"{fmt}: this robot file declares a joint map, which a UR controller does not have")


def ur_frames(robot: CalibratedRobot) -> tuple[np.ndarray, np.ndarray]:
    """(6, 4, 4) joint origins (parent → joint frame, z = the joint axis) and the (4, 4) tool0 → identified tool."""
    kin = without_pitch(robot.model)
    frames = np.concatenate([kin.A0[None], kin.A_rest])  # (7, 4, 4): six joint origins, then the tool
    # A shift along joint j's axis commutes with its rotation, so it may sit before or after it: move each next
    # frame's shift along z into joint j's origin, which gives ur_description's own layout (shoulder z = d1 …).
    for j in range(6):
        shift = np.eye(4)
        shift[2, 3] = frames[j + 1][2, 3]
        frames[j] = frames[j] @ shift
        frames[j + 1] = se3.inv(shift) @ frames[j + 1]
    # Likewise the tool frame's rotation about the last axis joins wrist_3 (the closest rotation about z).
    R = frames[6][:3, :3]
    turn = np.eye(4)
    turn[:3, :3] = se3.rpy_to_matrix(np.array([0.0, 0.0, float(np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]))]))
    frames[5] = frames[5] @ turn
    frames[6] = se3.inv(turn) @ frames[6]
    return frames[:6], frames[6]


def fmt(values) -> str:
    """Numbers (a scalar or an array) as their shortest round-trip reprs, space-separated (+ 0.0: no "-0.0")."""
    return " ".join(repr(float(x) + 0.0) for x in np.atleast_1d(values))


def ur_kinematics_text(robot: CalibratedRobot, provenance: dict | None = None, geometry_only: bool = False) -> str:
    """The ur_description calibration YAML of robot (see the module docstring)."""
    check_ur(robot, "ur-kinematics")
    origins, rest = ur_frames(robot)
    note = refuse_or_note(robot, "ur_description kinematics YAML", geometry_only)
    lines = [
        f"# labcal calibration of {printable(robot.nominal.name or 'robot')} for ur_description (kinematics_params), "
        f"method {printable(robot.method)}",
        f"# nominal robot sha256 {model_hash(robot.nominal)}; identified model sha256 {model_hash(robot.model)}",
        "# frames: shoulder is given in base_link_inertia (= the controller's base frame, base_link turned by pi "
        "about z); tool0 = wrist_3_link",
        "# tcp_in_tool0 (m, rotation vector): the part of the identified tool frame ur_description cannot hold; set it "
        "as the TCP",
        "# tcp_in_tool0: " + fmt(_pose6(rest)),
    ]
    if robot.measurement_tool is not None:
        # Robot and tool apart: the fixture the calibration measured through is not the robot (ur_description ignores
        # comments), so tool0 stays on the real flange and the fixture is written beside it.
        lines += [
            "# measurement_tool_in_tool0 (m, rotation vector): the identified measurement fixture (probe, SMR nest) "
            "the calibration saw the robot through; not part of the robot: set it as the TCP only to work with it",
            "# measurement_tool_in_tool0: " + fmt(_pose6(rest @ robot.measurement_tool)),
        ]
    if note:
        lines.append(f"# {printable(note)}")
    lines += [
        "# hash: identifies these numbers, not the controller's factory calibration, so ur_robot_driver logs "
        "\"calibration parameters ... don't match\" at start: expected (its movel/TCP use the controller's model)",
    ]
    lines += [f"# {printable(k)}: {printable(v)}" for k, v in sorted((provenance or {}).items())]
    body = ["kinematics:"]
    for name, T in zip(UR_SEGMENTS, origins, strict=True):
        xyz, rpy = T[:3, 3], se3.matrix_to_rpy(T[:3, :3])
        body.append(f"  {name}:")
        body += [f"    {key}: {fmt(v)}" for key, v in zip(("x", "y", "z"), xyz, strict=True)]
        body += [f"    {key}: {fmt(v)}" for key, v in zip(("roll", "pitch", "yaw"), rpy, strict=True)]
    # ur_calibration writes a hash of the controller's calibration; ours identifies the numbers above (module doc).
    digest = hashlib.sha256(chr(10).join(body).encode()).hexdigest()[:16]
    body.append(f"  hash: {json.dumps(f'labcal_{digest}')}")
    lines += body
    return "\n".join(lines) + "\n"


def _pose6(T: np.ndarray) -> np.ndarray:
    """x, y, z, rx, ry, rz (rotation vector) of a pose, as a UR pendant writes a TCP."""
    return np.concatenate([T[:3, 3], se3.log_so3(T[:3, :3])])
