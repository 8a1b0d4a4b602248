"""Calibrated URDF export, written with ``xml.etree`` (names and comments are escaped by the XML writer).

Strings. Names are checked where they enter labcal (:mod:`labcal.names`); here every name and comment is
also made printable (XML 1.0 has no form at all for most control characters, escaped or not, so one would make
the file ill-formed) and the XML library escapes ``<``, ``&`` and quotes. Repeated joint names are refused (a URDF
addresses joints by name). The file is written atomically (:mod:`labcal.atomicio`).

A URDF joint (origin xyz/rpy + axis) is exactly one local-POE frame A_j(0) and unit twist ξ_j, so the identified
geometric model is written without approximation (17 significant digits), with every joint frame moved onto its
axis line (:func:`urdf_model`). What the file holds:

- joints: origin and axis of the identified model; ``<limit lower upper>`` from the robot file's limits, and
  ``effort`` / ``velocity`` from the robot file's per-joint ``effort`` (N·m, N) and ``velocity`` (rad/s, m/s)
  keys. A URDF needs both; when the robot file has none, the export is refused (``ValueError`` naming the joint)
  unless ``unknown_dynamics="zero"``, which writes 0 and says so in the file;
- links: an ``<inertial>`` wherever the robot file gives a mass (link j carries the mass of ``joints[j].mass`` at
  its centre of mass ``com``; the tool payload on the tool link). Robot files give no inertia tensors, so the
  inertial is a point mass (zero inertia) and the file says so;
- names: generic (``base_link``, ``link_1`` … ``link_n``, ``tool0``) or, with ``ur_names=True`` for a UR arm,
  ur_description's (``base_link`` → ``base_link_inertia`` turned by π about z, so labcal's base frame K0 — the
  controller's base — is ``base_link_inertia`` and ``base``; ``shoulder_link`` … ``wrist_3_link``, ``flange`` and
  ``tool0``). With generic names ``base_link`` is K0 itself.

Robot and tool apart: the chain ends at ``tool0`` (the robot file's tool, the flange for the built-in robots) on
the identified robot; the calibration's identified measurement fixture, when it has one, is a separate link
``measurement_tool`` fixed to ``tool0``.

What a URDF cannot hold is left out and said: the tracker-to-base transform, and a learned joint-motion-error term
(hybrid / ann). Exporting a calibration with a learned term is refused, stating its size over the calibration's
joint ranges (:mod:`labcal.export.learned`), unless ``geometry_only=True``, which writes the frames alone and
the size in a comment.

Example::

    from labcal.export import export
    export(fit.robot, "urdf", "ur10-calibrated.urdf", velocity=[2.09] * 6, effort=[330, 330, 150, 56, 56, 56])
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from labcal.compensator import CalibratedRobot
from labcal.export.learned import refuse_or_note
from labcal.export.ros import UR_JOINT_NAMES, check_ur, fmt, ur_frames
from labcal.export.zform import without_pitch
from labcal.kinematics import se3
from labcal.kinematics.poe import PRISMATIC, REVOLUTE, LocalPOEModel, default_twist
from labcal.names import duplicate, printable
from labcal.robots import model_hash

UR_LINKS = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")
# ur_description's fixed frames after wrist_3_link: flange (x along the last axis), then tool0 turned back from it
# (= wrist_3_link's axes).
_UR_FLANGE_RPY = (0.0, -np.pi / 2, -np.pi / 2)


def urdf_model(model: LocalPOEModel) -> LocalPOEModel:
    """The same robot with every joint frame on its axis line and the axis along local z (URDF-representable).

    A URDF axis is a direction through the joint origin, while a local-POE twist may also carry an axis-line
    offset (v = r × ω); the frames are moved onto the axis line, which changes no forward kinematics. A revolute
    twist with a pitch (ω·v ≠ 0, a screw joint) has no URDF form and is refused.
    """
    kin = without_pitch(model)
    if kin.identity_C:
        return model
    frames = np.concatenate([kin.A0[None], kin.A_rest])
    twists = np.array([default_twist(t) for t in model.joint_types])
    return model.replace(frames=frames, twists=twists)


def _origin(parent: ET.Element, T: np.ndarray) -> None:
    ET.SubElement(parent, "origin", xyz=fmt(T[:3, 3]), rpy=fmt(se3.matrix_to_rpy(T[:3, :3])))


def _dynamics(values, n: int, what: str, unknown: str) -> tuple[list[float], bool]:
    """Per-joint values (n,) and whether they were unknown (written as 0)."""
    if values is None or any(v is None for v in values):
        if unknown == "zero":
            return [0.0] * n, True
        missing = [j + 1 for j in range(n)] if values is None else [j + 1 for j, v in enumerate(values) if v is None]
        raise ValueError(
            f"the robot file gives no joint {what} for joint(s) {', '.join(map(str, missing))}: a URDF needs "
            f"<limit {what}=…> on every joint. Add '{what} = …' to each [[joints]] table of the robot file "
            f"({'N·m' if what == 'effort' else 'rad/s'}; N and m/s for prismatic joints), or accept zeros explicitly "
            "(--unknown-dynamics zero)"
        )
    out = [float(v) for v in values]
    if len(out) != n or not all(np.isfinite(v) and v > 0 for v in out):
        raise ValueError(f"joint {what} must be {n} positive numbers, got {list(values)!r}")
    return out, False


def urdf_text(
    robot: CalibratedRobot,
    provenance: dict | None = None,
    *,
    velocity=None,
    effort=None,
    masses=None,
    coms=None,
    ur_names: bool = False,
    geometry_only: bool = False,
    unknown_dynamics: str = "refuse",
) -> str:
    """The URDF document of robot.model (the identified frames); see the module docstring.

    velocity, effort: (n,) per joint (None entries / None: unknown); masses (n+1,) kg for links 1..n and the tool
    payload, coms (n+1, 3) m in the base frame at q = 0 (None: no inertials). Refused for a robot with a joint map:
    a URDF's joint values are the model's, and whatever reads it would feed it the controller's joints.
    """
    if robot.joint_map is not None:
        raise ValueError(
            "URDF export of a robot with a joint map (controller joints are not the model's joints) is refused: a "
            "URDF has no way to say so, and a controller feeding it its own joints would get wrong poses; use the "
            "json/npz compensator, which converts controller joints"
        )
    if unknown_dynamics not in ("refuse", "zero"):
        raise ValueError(f"unknown_dynamics must be 'refuse' or 'zero', got {unknown_dynamics!r}")
    model = urdf_model(robot.model)
    if ur_names:  # ur_description's frame layout: wrist_3_link at the flange
        check_ur(robot, "URDF with UR link names")
        origins, tool = ur_frames(robot)
        model = model.replace(frames=np.concatenate([origins, tool[None]]))
    note = refuse_or_note(robot, "URDF", geometry_only)
    n = model.n
    vel, vel_unknown = _dynamics(velocity, n, "velocity", unknown_dynamics)
    eff, eff_unknown = _dynamics(effort, n, "effort", unknown_dynamics)
    notes = _notes(robot, model, note, vel_unknown or eff_unknown, masses is not None, provenance)

    root = ET.Element("robot", name=printable(f"{robot.nominal.name or 'robot'}_calibrated"))
    # An XML comment may not hold "--" (nor end in "-": the spaces around it see to that).
    root.append(ET.Comment(" " + printable("; ".join(map(str, notes))).replace("--", "- -") + " "))
    links, joint_names = _link_and_joint_names(model, ur_names)
    elements = {}
    for name in (["base_link"] if ur_names else []) + links + (["flange", "tool0", "base"] if ur_names else ["tool0"]):
        elements[name] = ET.SubElement(root, "link", name=name)
    if masses is not None and coms is not None:
        _inertials(model, elements, links, masses, coms)
    if ur_names:
        _fixed(
            root, "base_link-base_link_inertia", "base_link", "base_link_inertia", se3.pose([0, 0, 0], [0, 0, np.pi])
        )
    _joints(root, robot, model, links, joint_names, vel, eff)
    _tool_joints(root, robot, model, links, ur_names)
    ET.indent(root, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _notes(
    robot: CalibratedRobot,
    model: LocalPOEModel,
    note: str | None,
    dynamics_unknown: bool,
    inertials: bool,
    provenance: dict | None,
) -> list[str]:
    """The file's leading comment: what it is, what it leaves out, and the provenance."""
    notes = [
        f"labcal calibrated URDF: method {robot.method}",
        f"nominal robot {robot.nominal.name or '?'} sha256 {model_hash(robot.nominal)}",
        f"identified model sha256 {model_hash(robot.model)}",
        "NOT INCLUDED: the tracker-to-base transform",
    ]
    if note:
        notes.append(note)
    if dynamics_unknown:
        notes.append("joint effort/velocity UNKNOWN (the robot file gives none): written as 0, do not simulate with it")
    if inertials:
        notes.append("inertials: point masses from the robot file (no inertia tensors are known)")
    return notes + [f"{k}: {v}" for k, v in sorted((provenance or {}).items())]


def _link_and_joint_names(model: LocalPOEModel, ur_names: bool) -> tuple[list[str], list[str]]:
    """(links base..link n, joint names): ur_description's, or generic links and the model's (unique) joint names."""
    if ur_names:
        links = ["base_link_inertia", *UR_LINKS]
        return links, list(UR_JOINT_NAMES)
    links = ["base_link", *[f"link_{j + 1}" for j in range(model.n)]]
    joint_names = [printable(name) for name in model.joint_names]
    twice = duplicate(joint_names)
    if twice is not None:
        raise ValueError(
            f"joints {twice[0] + 1} and {twice[1] + 1} are both named {joint_names[twice[1]]!r}: a URDF addresses "
            "joints by name, so they must be unique (rename one in the robot file)"
        )
    return links, joint_names


def _inertials(model: LocalPOEModel, elements: dict, links: list[str], masses, coms) -> None:
    """Point-mass inertials: link j + 1 (the one joint j moves) carries mass j; the tool payload sits on tool0."""
    n = model.n
    frames0 = model.link_frames(np.zeros(n))[0]  # (n+1, 4, 4) joint frames in K0 at q = 0
    for j in range(n + 1):
        m = float(masses[j])
        if m <= 0:
            continue
        link = elements[links[j + 1]] if j < n else elements["tool0"]
        T_link = frames0[j] if j < n else model.fk(np.zeros(n))
        com = se3.inv(T_link) @ np.append(np.asarray(coms[j], dtype=float), 1.0)
        inertial = ET.SubElement(link, "inertial")
        ET.SubElement(inertial, "origin", xyz=fmt(com[:3]), rpy="0.0 0.0 0.0")
        ET.SubElement(inertial, "mass", value=fmt(m))
        ET.SubElement(inertial, "inertia", ixx="0.0", ixy="0.0", ixz="0.0", iyy="0.0", iyz="0.0", izz="0.0")


def _fixed(root: ET.Element, name: str, parent: str, child: str, T: np.ndarray) -> None:
    joint = ET.SubElement(root, "joint", name=name, type="fixed")
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=child)
    _origin(joint, T)


def _joints(root: ET.Element, robot: CalibratedRobot, model: LocalPOEModel, links, joint_names, vel, eff) -> None:
    """One revolute / prismatic joint per model joint: identified origin and axis, the robot file's limits."""
    for j in range(model.n):
        kind = "prismatic" if model.joint_types[j] == PRISMATIC else "revolute"
        joint = ET.SubElement(root, "joint", name=joint_names[j], type=kind)
        ET.SubElement(joint, "parent", link=links[j])
        ET.SubElement(joint, "child", link=links[j + 1])
        _origin(joint, model.frames[j])
        axis = model.twists[j, :3] if kind == "prismatic" else model.twists[j, 3:]
        ET.SubElement(joint, "axis", xyz=fmt(axis))
        lo, hi = robot.nominal.limits[j]
        ET.SubElement(joint, "limit", lower=fmt(lo), upper=fmt(hi), effort=fmt(eff[j]), velocity=fmt(vel[j]))
    assert all(t in (REVOLUTE, PRISMATIC) for t in model.joint_types)


def _tool_joints(root: ET.Element, robot: CalibratedRobot, model: LocalPOEModel, links, ur_names: bool) -> None:
    """The fixed joints after the last link: to tool0 (via ur_description's flange), and the measurement tool."""
    n = model.n
    T_tool = model.frames[n]
    if ur_names:
        flange = se3.pose([0, 0, 0], _UR_FLANGE_RPY)
        _fixed(root, "wrist_3-flange", links[n], "flange", T_tool @ flange)
        _fixed(root, "flange-tool0", "flange", "tool0", se3.inv(flange))
        _fixed(root, "base_link-base_fixed_joint", "base_link", "base", se3.pose([0, 0, 0], [0, 0, np.pi]))
    else:
        _fixed(root, "tool_fixed", links[n], "tool0", T_tool)
    if robot.measurement_tool is not None:
        # Robot and tool apart: the fixture the calibration measured through, beside the robot (tool0 stays on tool0)
        ET.SubElement(root, "link", name="measurement_tool")
        _fixed(root, "tool0-measurement_tool", "tool0", "measurement_tool", robot.measurement_tool)
