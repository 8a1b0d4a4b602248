"""Calibrated URDF export: the identified local-POE frames as joint origins and axes.

A URDF joint (origin xyz/rpy + axis) is exactly one local-POE frame A_j(0) and unit twist ξ_j, so the identified
geometric model is represented without approximation (17 significant digits). What a URDF cannot hold is written
in a comment at the top and left out: a learned joint-motion-error network (ann / hybrid) and the tracker-to-base
transform. Use the JSON/NPZ export (the compensator) for those.

Example::

    from labcal.export.urdf import write_urdf
    write_urdf(fit.robot, "ur10-calibrated.urdf")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labcal.compensator import CalibratedRobot
from labcal.export.zform import ZAxisForm
from labcal.kinematics.conversions import to_urdf
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel, default_twist
from labcal.robots import model_hash


def urdf_model(model: LocalPOEModel) -> LocalPOEModel:
    """The same robot with every joint frame on its axis line and the axis along local z (URDF-representable).

    A URDF axis is a direction through the joint origin, while a local-POE twist may also carry an axis-line
    offset (v = r × ω); the frames are moved onto the axis line, which changes no forward kinematics. A revolute
    twist with a pitch (ω·v ≠ 0, a screw joint) has no URDF form and is refused.
    """
    kin = ZAxisForm(model)
    if kin.has_pitch and np.max(np.abs(kin.pitch)) > 1e-12:
        j = int(np.argmax(np.abs(kin.pitch)))
        raise ValueError(f"joint {j + 1} is a screw (pitch {kin.pitch[j]:.3g} m/rad): a URDF cannot represent it")
    if kin.identity_C:
        return model
    frames = np.concatenate([kin.A0[None], kin.A_rest])
    twists = np.array([default_twist(t) for t in model.joint_types])
    assert all(t in (REVOLUTE, "prismatic") for t in model.joint_types)
    return model.replace(frames=frames, twists=twists)


def urdf_text(robot: CalibratedRobot, provenance: dict | None = None) -> str:
    """The URDF document of robot.model (the identified frames).

    Refused for a robot with a joint map: a URDF's joint values are the model's, and whatever reads it (a ROS
    controller stack, a simulator) would feed it the controller's joints, silently wrong for a coupled joint.
    """
    if robot.joint_map is not None:
        raise ValueError(
            "URDF export of a robot with a joint map (controller joints are not the model's joints) is refused: a "
            "URDF has no way to say so, and a controller feeding it its own joints would get wrong poses; use the "
            "json/npz compensator, which converts controller joints"
        )
    notes = [
        f"labcal calibrated URDF: method {robot.method}",
        f"nominal robot {robot.nominal.name or '?'} sha256 {model_hash(robot.nominal)}",
        f"identified model sha256 {model_hash(robot.model)}",
    ]
    if robot.network is not None:
        notes.append("NOT INCLUDED: the learned joint motion error network (use the json/npz compensator export)")
    notes += [f"{k}: {v}" for k, v in sorted((provenance or {}).items())]
    name = f"{robot.nominal.name or 'robot'}_calibrated"
    return to_urdf(urdf_model(robot.model), robot_name=name, comment="; ".join(notes))


def write_urdf(robot: CalibratedRobot, path, provenance: dict | None = None) -> Path:
    path = Path(path)
    path.write_text(urdf_text(robot, provenance))
    return path
