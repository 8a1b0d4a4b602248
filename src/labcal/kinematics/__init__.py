"""Pure numpy kinematics: SE(3) tools, the local POE model and its definition, DH/MDH/URDF conversions, and the
length-scaled metric (:mod:`labcal.kinematics.metric`)."""

from labcal.kinematics.conversions import from_dh, from_mdh, from_urdf, to_urdf
from labcal.kinematics.poe import PRISMATIC, REVOLUTE, LocalPOEModel, poe_fk, poe_joint_twists, poe_link_frames
from labcal.kinematics.se3 import (
    adjoint,
    exp_se3,
    exp_so3,
    hat,
    inv,
    log_se3,
    log_so3,
    matrix_to_rpy,
    pose,
    pose_distance,
    rpy_to_matrix,
    skew,
    unskew,
    vee,
)

__all__ = [
    "PRISMATIC",
    "REVOLUTE",
    "LocalPOEModel",
    "adjoint",
    "exp_se3",
    "exp_so3",
    "from_dh",
    "from_mdh",
    "from_urdf",
    "hat",
    "inv",
    "log_se3",
    "log_so3",
    "matrix_to_rpy",
    "poe_fk",
    "poe_joint_twists",
    "poe_link_frames",
    "pose",
    "pose_distance",
    "rpy_to_matrix",
    "skew",
    "to_urdf",
    "unskew",
    "vee",
]
