"""A robot model rewritten so that every joint is a screw about its local z axis (for the exporters).

URScript and URDF can only express joints about z (URScript: our unrolled ``Rz(q) Tz(h q)`` chain) or about an axis
through the frame origin (URDF). With a constant frame C_j whose z axis is joint j's axis (revolute: placed on the
axis line, pitch h_j = ω·v; prismatic: along the direction), ``exp(ξ̂_j q) = C_j Rz(q) Tz(h_j q) C_j⁻¹``
(prismatic: ``C_j Tz(q) C_j⁻¹``), and the frames become ``A'_j = C_{j-1}⁻¹ A_j C_j``. For the usual z-axis twists
every C_j is the identity and nothing changes numerically.

Example::

    >>> from labcal.robots import load
    >>> form = ZAxisForm(load("ur10").model)
    >>> form.identity_C, form.A_rest.shape
    (True, (6, 4, 4))
"""

from __future__ import annotations

import numpy as np

from labcal.kinematics import se3
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel


def _z_to(axis: np.ndarray) -> np.ndarray:
    """A rotation (3, 3) taking e_z to the unit vector ``axis`` (identity when it already is e_z)."""
    z = np.array([0.0, 0.0, 1.0])
    if np.array_equal(axis, z):
        return np.eye(3)
    c = float(axis @ z)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    K = se3.skew(np.cross(z, axis))
    return np.eye(3) + K + K @ K / (1 + c)


class ZAxisForm:
    """The z-axis screw form of a model: A0 (4, 4), A_rest (n, 4, 4) = A'_1 … A'_n+1 after A0, per-joint ``lin``
    (translation per unit q along z), ``pitch`` (revolute joints' h_j), ``revolute`` flags, and ``RC_T`` (n, 3, 3),
    the transposed rotations of C_1 … C_n (to express link-frame vectors in the rewritten frames)."""

    def __init__(self, model: LocalPOEModel) -> None:
        n = model.n
        self.n = n
        rev = np.array([t == REVOLUTE for t in model.joint_types])
        self.revolute = rev
        C = np.tile(np.eye(4), (n + 1, 1, 1))
        lin = np.zeros(n)
        for j in range(n):
            v, w = model.twists[j, :3], model.twists[j, 3:]
            if rev[j]:
                C[j, :3, :3] = _z_to(w)
                C[j, :3, 3] = np.cross(w, v)
                lin[j] = float(w @ v)
            else:
                C[j, :3, :3] = _z_to(v)
                lin[j] = 1.0
        self.identity_C = bool(np.all(C == np.eye(4)))
        A = np.array(model.frames)
        if not self.identity_C:
            C_prev = np.concatenate([np.eye(4)[None], C[:n]])
            A = se3.inv(C_prev) @ A @ C
        self.A0 = A[0]
        self.A_rest = A[1:]
        self.lin = lin
        self.pitch = np.where(rev, lin, 0.0)
        self.RC_T = np.ascontiguousarray(C[1 : n + 1, :3, :3].transpose(0, 2, 1))


def without_pitch(model: LocalPOEModel) -> ZAxisForm:
    """The z-axis form of a model whose revolute joints have no screw pitch (a URDF joint, and ur_description's,
    has none); ValueError naming the first screw joint."""
    kin = ZAxisForm(model)
    if np.max(np.abs(kin.pitch)) > 1e-12:
        j = int(np.argmax(np.abs(kin.pitch)))
        raise ValueError(f"joint {j + 1} is a screw (pitch {kin.pitch[j]:.3g} m/rad): a URDF cannot represent it")
    return kin
