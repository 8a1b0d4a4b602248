"""Robot and tool apart: the identified chain split into the robot to its tool0 frame and the measurement tool.

The local-POE fit (:mod:`labcal.calibration.local_poe`) identifies the last frame A_{n+1} as one of its
parameters, and the data see it through the measurement fixture (probe, SMR nest, targets): what it identifies
there is the fixture, not the robot. Nothing on the last link can tell the flange from what is bolted to it, and a
rotation about / shift along the last joint's axis in A_n commutes with that joint, so the fit's minimum-norm steps
spread the fixture's offset over both frames. :func:`split_tool` undoes that without changing a single predicted
pose:

1. the part of A_n that commutes with the last (revolute, z) joint — a turn about and a shift along its axis —
   moves into A_{n+1}: the joint's identified axis stays, with its zero angle and its origin chosen closest to
   the nominal (minimal tilt from the nominal frame; the origin is the foot of the perpendicular from the nominal
   origin onto the identified axis). Those two numbers are the tool's, as far as any data can tell;
2. the robot's tool0 frame is held at the nominal A_{n+1} (the flange, or the robot file's ``[tool]``) on that
   axis: the part of the flange that is identifiable apart from the tool is none, so the robot's own errors are the
   joints' frames and axes only;
3. the rest is the measurement tool X, the fixture frame in tool0: ``A_{n+1} = A_{n+1}^nominal · X``.

:func:`labcal.calibration.local_poe.tool_std` gives X's standard deviations (the fit's residual σ, its truncated
pseudo-inverse in the split parameters: the two commuting directions of A_n are the tool's and are not parameters
of the robot).

Example (a nominal robot measured through a 93 mm mount)::

    >>> from labcal.robots import load
    >>> from labcal.kinematics import se3
    >>> nominal = load("ur10").model
    >>> frames = np.array(nominal.frames); frames[-1] = frames[-1] @ se3.pose([0.093, 0, 0.02], [0, 0, 0.8])
    >>> robot, X = split_tool(nominal, nominal.replace(frames=frames))
    >>> bool(np.allclose(robot.frames, nominal.frames)), np.round(X[:3, 3], 3).tolist()
    (True, [0.093, 0.0, 0.02])
"""

from __future__ import annotations

import numpy as np

from labcal.kinematics import se3
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel

_Z_TWIST = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])


def _turns_about_z(model: LocalPOEModel, j: int = -1) -> bool:
    """Joint j (default the last) is revolute about its local z axis."""
    return model.joint_types[j] == REVOLUTE and bool(np.array_equal(model.twists[j], _Z_TWIST))


def split_tool(
    nominal: LocalPOEModel, model: LocalPOEModel, canonical: bool = True
) -> tuple[LocalPOEModel, np.ndarray]:
    """(robot to tool0, measurement tool X (4, 4) in tool0) of an identified chain ``model`` (module docstring).

    ``model`` and ``robot.replace(frames=[…, robot.frames[-1] @ X])`` have the same forward kinematics (to
    rounding). A last joint that is not a revolute about its local z axis keeps A_n as identified (step 1 skipped),
    and so does ``canonical=False`` (a model whose A_n was not estimated, or is canonical already).
    """
    if not canonical:
        frames = np.array(model.frames)
        X = se3.inv(nominal.frames[-1]) @ frames[-1]
        frames[-1] = nominal.frames[-1]
        return model.replace(frames=frames), X
    robot, X, _ = split_robot(nominal, model, None)
    return robot, X


def split_robot(
    nominal: LocalPOEModel, model: LocalPOEModel, T_tracker_base: np.ndarray | None, q: np.ndarray | None = None
) -> tuple[LocalPOEModel, np.ndarray, np.ndarray | None]:
    """:func:`split_tool`, and for a tracker-frame fit (``T_tracker_base`` given, A_1 held at nominal) the same at
    the base: A_2's turn about and shift along joint 1's axis commute with joint 1, so they are the base's (the
    pose of the robot in the tracker frame) and move into T_tracker_base. Otherwise the fit's minimum-norm steps
    leave part of the base's height in the robot (an offset of every base-frame pose along joint 1's axis, which
    the tracker never sees), e.g. after starting from a nominal tool that misses the probe mount.

    q: (k, n) the data's configurations: the turns and shifts are then refined so that tool0 is closest to the
    nominal tool0 over them (:func:`_closest_on_data`).

    Returns (robot to tool0, measurement tool X in tool0, T_tracker_base (None when not given)).
    """
    n = nominal.n
    frames = np.array(model.frames)
    if _turns_about_z(model) and _turns_about_z(nominal):
        q0 = np.zeros((1, n))
        K_id, K_nom = model.link_frames(q0)[0, n - 1], nominal.link_frames(q0)[0, n - 1]
        S = _commuting_part(se3.inv(K_nom) @ K_id)  # the identified last-joint frame in the nominal one, at q = 0
        frames[n - 1] = frames[n - 1] @ se3.inv(S)
        frames[n] = S @ frames[n]
    if (
        T_tracker_base is not None
        and n >= 2
        and _turns_about_z(model, 0)
        and np.array_equal(frames[0], nominal.frames[0])
    ):
        # A_1 exp(ẑ q_1) S A_2'' = A_1 S exp(ẑ q_1) A_2'': S (about/along joint 1's axis) joins the base.
        S = se3.inv(_commuting_part(nominal.frames[1] @ se3.inv(frames[1])))
        frames[1] = se3.inv(S) @ frames[1]
        T_tracker_base = np.asarray(T_tracker_base, float) @ frames[0] @ S @ se3.inv(frames[0])
    X = se3.inv(nominal.frames[n]) @ frames[n]
    frames[n] = nominal.frames[n]
    robot = model.replace(frames=frames)
    if q is not None and len(q) and _turns_about_z(model) and _turns_about_z(nominal):
        robot, X, T_tracker_base = _closest_on_data(nominal, robot, X, T_tracker_base, np.asarray(q, float))
    return robot, X, T_tracker_base


def _moved(robot, X, T_tb, p):
    """The same chain with the commuting parts p = (turn, shift) about/along the last joint's axis (moved from tool0
    into the tool) and, with T_tb, about/along joint 1's axis (moved from the robot into the base)."""
    frames = np.array(robot.frames)
    n = robot.n
    S = se3.exp_se3(np.array([0, 0, p[1], 0, 0, p[0]]))
    frames[n - 1] = frames[n - 1] @ se3.inv(S)
    X = S @ X  # tool0 turns back by S, so the fixture's pose in it turns by S
    if T_tb is not None:
        B = se3.exp_se3(np.array([0, 0, p[3], 0, 0, p[2]]))
        frames[1] = se3.inv(B) @ frames[1]
        T_tb = T_tb @ frames[0] @ B @ se3.inv(frames[0])
    return robot.replace(frames=frames), X, T_tb


def _closest_on_data(nominal, robot, X, T_tb, q, steps: int = 4):
    """Choose the commuting parts so that tool0 is closest to the nominal tool0 over the data's configurations
    (least squares of the pose difference, angles weighted by the reach): the turn and shift that no data can
    tell apart from the tool (or the base) are set where the robot's own errors look smallest where it was
    measured, not at one configuration (q = 0 may be far from the data, where the chain's errors tilt the axis)."""
    w = np.array([1.0, 1, 1, nominal.reach(), nominal.reach(), nominal.reach()])
    T_nom_inv = se3.inv(nominal.fk(q))
    k = 2 if T_tb is None else 4
    p = np.zeros(k)

    def residual(p):
        r, _, _ = _moved(robot, X, T_tb, np.pad(p, (0, 4 - k)))
        return (se3.log_se3(T_nom_inv @ r.fk(q)) * w).reshape(-1)

    for _ in range(steps):
        r0 = residual(p)
        h = 1e-6
        J = np.stack([(residual(p + h * e) - r0) / h for e in np.eye(k)], axis=1)
        step = np.linalg.lstsq(J, -r0, rcond=None)[0]
        p = p + step
        if np.max(np.abs(step)) < 1e-12:
            break
    return _moved(robot, X, T_tb, np.pad(p, (0, 4 - k)))


def _commuting_part(D: np.ndarray) -> np.ndarray:
    """S, a turn about z and a shift along z, with D = D' S and D' the frame on D's z axis closest to the identity:
    minimal tilt of the z axis, origin at the foot of the perpendicular from the origin onto D's z axis."""
    z = D[:3, 2]
    tilt = np.cross([0.0, 0.0, 1.0], z)
    angle = float(np.arctan2(np.linalg.norm(tilt), z[2]))
    axis = tilt / np.linalg.norm(tilt) if np.linalg.norm(tilt) > 0 else np.zeros(3)
    canonical = np.eye(4)
    canonical[:3, :3] = se3.exp_so3(axis * angle)
    canonical[:3, 3] = D[:3, 3] - float(D[:3, 3] @ z) * z
    return se3.inv(canonical) @ D


def tool_lines(X: np.ndarray, std: np.ndarray | None) -> list[str]:
    """Human lines: the identified measurement tool against the robot file's tool (tool0), in mm and degrees."""
    xyz, rot = X[:3, 3] * 1e3, np.rad2deg(se3.log_so3(X[:3, :3]))
    s = np.full(6, np.nan) if std is None else np.asarray(std, float)

    def pm(v, e, unit):
        return f"{v:+.3f} ± {e:.3f} {unit}" if np.isfinite(e) else f"{v:+.3f} {unit} (not seen: held)"

    return [
        "measurement tool in tool0 (the robot file's tool; identified fixture, the targets' frame):",
        "  position  "
        + ", ".join(pm(v, e * 1e3, "mm") for v, e in zip(xyz, s[:3], strict=True))
        + f"  (|p| {np.linalg.norm(xyz):.3f} mm)",
        "  rotation  "
        + ", ".join(pm(v, np.rad2deg(e), "°") for v, e in zip(rot, s[3:], strict=True))
        + f"  (|θ| {np.linalg.norm(rot):.3f}°, rotation vector)",
    ]
