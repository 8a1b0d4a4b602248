"""Program filter: correct a robot program (TCP poses or nominal joint targets) into joint targets for the real
robot, offline, the way RoboDK's program filter does. Numpy only; arrays in, arrays and text out (reading a
program file is the CLI's job: ``labcal.cli.ops.programs`` reads it the way ``session import`` reads data).

A program is what an integrator taught or planned against the *nominal* model: either TCP poses in the robot's
base frame (``x, y, z, rx, ry, rz``: position and rotation vector, as URScript poses) or the nominal joint targets
themselves. The filter

0. checks the values can be what they claim: a rotation vector's norm is its angle, so a norm above 2π is not a
   rotation vector in radians (degrees read as radians have norms of tens); joint values must lie inside the
   robot's joint limits. Each refusal names the row and, when the program would make sense in the other unit, the
   flag that reads it so (``--angle-unit deg``, ``--length-unit mm``);
1. solves the nominal inverse kinematics of a pose program, by path following from a seed: the first row from
   ``seed`` (e.g. ``--seed-joints``, the robot's current or home joints), every later row from the previous row's
   solution. The pose is moved in small steps from the seed's pose to the target, with a few Gauss-Newton
   iterations per step, so the solution stays on the seed's configuration branch (shoulder, elbow, wrist): a row
   whose path passes a singular configuration (the length-scaled Jacobian's condition above ``max_condition``, or
   its determinant changing sign between two steps, which only happens across a singularity) is refused, naming
   the row and the joint that leaves the singularity fastest, and so is a row the solver cannot reach (pose
   error above ``tol`` after the last step);
2. corrects the nominal joints with the calibrated model (:meth:`CalibratedRobot.correct`: the joints at which the
   calibrated robot reaches the nominal pose), seeded on the nominal solution. A row is refused, naming it, when
   it is near a singular configuration (condition above ``max_condition`` at the nominal or the corrected joints:
   the correction is not defined there, and the nominal and calibrated robots' branches part), when the correction
   lands on another configuration branch of a well-conditioned row (determinant sign), moves a joint by more than
   ``max_correction`` rad, or leaves the calibrated robot away from the pose; and when the row is outside the
   calibrated joint ranges;
3. reports the correction: per row the largest joint change, and the tool position and orientation error the
   calibrated model predicts for the *uncorrected* joints (what the filter removes).

The nominal IK of a pose program is sequential (each row is seeded by the previous one); everything else is
batched over the rows. Joint programs need no IK: their rows are the nominal solutions.

Example::

    from labcal.compensator import load
    from labcal.export.program import filter_poses, joints_csv
    comp = load("ur10.json")
    poses = np.array([[0.6, -0.2, 0.4, 3.1, 0.2, 0.0]])                       # (k, 6) m, rotation vector rad
    result = filter_poses(comp.robot, poses, seed=np.radians([0, -90, 90, -90, -90, 0]))
    result.q_command                                                           # (k, 6) rad
    joints_csv(result, angle_unit="deg")                                       # the program to send, in degrees
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.kinematics.metric import joint_weights, scaled_condition, twist_weights

STEPS = 8  # pose interpolation steps from the seed to each target (path following)
MAX_CONDITION = 1e4  # length-scaled cond(J) above this: a singularity, the branch (and a correction) is not defined
TOL = 1e-10  # pose error (m; rad) a nominal IK solution must reach
MAX_CORRECTION = 0.2  # rad: a calibration correction larger than this is a different solution, not a correction
NEAR_SINGULAR = 300  # a condition above this, below MAX_CONDITION, is named as nearness when the correction fails
REACHED = 1e-6  # m and rad: the calibrated robot at the corrected joints must be this close to the nominal pose
#: Units a program may be written in, and their factor to SI.
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3}
ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}


class ProgramError(ValueError):
    """A program row cannot be filtered (the message names the row and why). ``row``: 1-based, None if not one
    row's fault."""

    def __init__(self, message: str, row: int | None = None) -> None:
        super().__init__(message)
        self.row = row


@dataclass(frozen=True)
class FilteredProgram:
    """The filter's answer. Shapes: (k, n) joints in rad (m for prismatic joints), (k,) sizes in m and rad."""

    q_nominal: np.ndarray  # the program as the nominal model reads it
    q_command: np.ndarray  # what to send to the real robot
    position_error: np.ndarray  # tool position error the calibrated model predicts for q_nominal (m)
    rotation_error: np.ndarray  # … and orientation error (rad)

    @property
    def correction(self) -> np.ndarray:
        """(k, n) q_command − q_nominal."""
        return self.q_command - self.q_nominal

    def summary(self) -> str:
        """One line: rows, the joint correction and the tool error it removes (mean / max)."""
        dq = np.max(np.abs(self.correction), axis=1)
        return (
            f"{len(dq)} rows: joint correction {1e3 * dq.mean():.3f} / {1e3 * dq.max():.3f} mrad (mean / max), "
            f"removing a predicted tool error of {1e3 * self.position_error.mean():.3f} / "
            f"{1e3 * self.position_error.max():.3f} mm and {1e3 * self.rotation_error.mean():.3f} / "
            f"{1e3 * self.rotation_error.max():.3f} mrad"
        )


# ------------------------------------------------------------------------------------------------------------
# units, checks and writing


def joint_factors(joint_types, length_unit: str = "m", angle_unit: str = "rad") -> np.ndarray:
    """(n,) factors from a program's joint columns to SI: the angle unit for a revolute joint, the length unit for
    a prismatic one. ``joint_factors(("revolute", "prismatic"), "mm", "deg")`` → [π/180, 0.001]."""
    if length_unit not in LENGTH_UNITS:
        raise ValueError(f"length unit must be 'm' or 'mm', got {length_unit!r}")
    if angle_unit not in ANGLE_UNITS:
        raise ValueError(f"angle unit must be 'rad' or 'deg', got {angle_unit!r}")
    return np.array([LENGTH_UNITS[length_unit] if t == "prismatic" else ANGLE_UNITS[angle_unit] for t in joint_types])


def check_rotation_vectors(poses: np.ndarray, angle_unit: str = "rad") -> None:
    """Refuse a pose row (k, 6; m, rad) whose rotation vector has a norm above 2π, naming the first row.

    A rotation vector's norm is its angle: every rotation has one of norm ≤ π, and controllers that keep vectors
    continuous along a path give up to 2π; more is not a rotation vector in radians but, nearly always, degrees
    read as radians (a tool pointing down is 180, not 3.14). ``angle_unit``: the unit the program was read in
    (for the message and its hint only).
    """
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    norms = np.linalg.norm(poses[:, 3:6], axis=1)
    bad = ~(norms <= 2 * np.pi + 1e-9)
    if not bad.any():
        return
    i = int(np.argmax(bad))
    f = ANGLE_UNITS.get(angle_unit, 1.0)
    shown = ", ".join(f"{v / f:.6g}" for v in poses[i, 3:6])
    limit = "360 deg" if angle_unit == "deg" else "2π rad"
    hint = " (degrees read as radians? pass --angle-unit deg)" if angle_unit == "rad" and norms[i] <= 360.0 else ""
    more = f"; {int(bad.sum()) - 1} more row(s) like it" if bad.sum() > 1 else ""
    raise ProgramError(
        f"row {i + 1}: rx, ry, rz = {shown} has the norm {norms[i] / f:.6g} {angle_unit}: a rotation vector's norm "
        f"is its angle, at most {limit}{hint}{more}",
        i + 1,
    )


def _degree_hint(robot: CalibratedRobot, q: np.ndarray, ranges: np.ndarray, angle_unit: str) -> str:
    """The --angle-unit deg hint, for joints read in rad that look like degrees: read as degrees they lie inside
    ``ranges``, and at least a quarter of the revolute values are beyond a full turn (no radian program near a
    robot's home has that many; a program in degrees nearly always does: 90 is 90°). One wild value in a program in
    radians gets no hint."""
    if angle_unit != "rad":
        return ""
    revolute = np.array([t == "revolute" for t in robot.nominal.joint_types])
    as_deg = np.where(revolute, np.radians(q), q)
    turns = np.abs(q[:, revolute]) > 2 * np.pi
    if np.all((as_deg >= ranges[:, 0]) & (as_deg <= ranges[:, 1])) and turns.size and turns.mean() >= 0.25:
        return " (degrees read as radians? pass --angle-unit deg)"
    return ""


def check_joints(robot: CalibratedRobot, q: np.ndarray, angle_unit: str = "rad", *, seed: bool = False) -> None:
    """Refuse joint values (k, n; rad, m) outside the robot's joint limits, the calibrated ranges or the
    calibration's validity region, naming the first bad row (and joint); ``angle_unit`` (the unit they were read
    in) phrases the hint. ``seed``: q is the
    one row of ``--seed-joints``, which only picks a branch: the robot's limits apply, not the calibrated ranges."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    checks = [(robot.nominal.limits, "the robot's joint limits")]
    if not seed:
        checks.append((robot.joint_ranges, "the calibrated range (the calibration has no data there)"))
    for ranges, what in checks:
        lo, hi = ranges[:, 0], ranges[:, 1]
        outside = ~((q >= lo) & (q <= hi))
        if outside.any():
            i, j = (int(x) for x in np.argwhere(outside)[0])
            name = "--seed-joints" if seed else f"row {i + 1}"
            raise ProgramError(
                f"{name}: joint {j + 1} = {q[i, j]:.6g} is outside {what} [{lo[j]:.6g}, {hi[j]:.6g}]"
                f"{_degree_hint(robot, q, ranges, angle_unit)}",
                None if seed else i + 1,
            )
    validity = robot.validity
    if not seed and validity is not None:  # correct() refuses these too; here the row is named
        distance = validity.distance(q)
        far = ~(distance <= validity.radius)
        if far.any():
            i = int(np.argmax(far))
            raise ProgramError(
                f"row {i + 1}: outside the calibration's validity region ({distance[i]:.3g} of the data's joint "
                f"spreads from the nearest measured configuration; its radius is {validity.radius:.3g}): the data say "
                "nothing there, so it is not corrected. Measure poses near it and fit again",
                i + 1,
            )


def pose_matrix(x: np.ndarray) -> np.ndarray:
    """(k, 6) x, y, z, rx, ry, rz (rotation vector) → (k, 4, 4)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, :3, :3] = se3.exp_so3(x[:, 3:])
    T[:, :3, 3] = x[:, :3]
    return T


def joints_csv(result: FilteredProgram, *, angle_unit: str = "rad", length_unit: str = "m", joint_types=None) -> str:
    """The corrected program: one row per program row, q1 … qn to command, then the nominal joints (both in
    ``angle_unit`` for revolute joints, ``length_unit`` for prismatic ones: ``joint_types``, default all revolute),
    then the sizes in the units their names say (joint correction in mrad, predicted uncorrected tool error in mm
    and mrad). The header keeps the names q1 … qn, so the file reads back as a joint program in the same units."""
    n = result.q_command.shape[1]
    factors = joint_factors(joint_types or ("revolute",) * n, length_unit, angle_unit)
    head = [f"q{j + 1}" for j in range(n)] + [f"nominal_q{j + 1}" for j in range(n)]
    head += ["correction_mrad", "uncorrected_error_mm", "uncorrected_error_mrad"]
    dq = np.max(np.abs(result.correction), axis=1)
    sizes = [1e3 * dq, 1e3 * result.position_error, 1e3 * result.rotation_error]
    table = np.column_stack([result.q_command / factors, result.q_nominal / factors, *sizes])
    lines = [",".join(["row", *head])]
    lines += [",".join([str(i), *map(repr, row)]) for i, row in enumerate(table.tolist(), start=1)]
    return "\n".join(lines) + "\n"


def movej_program(q: np.ndarray, name: str = "labcal_filtered", a: float = 1.4, v: float = 1.05) -> str:
    """A URScript ``def`` program that moves through the joint targets q (k, 6; rad, as movej takes them) with
    movej (a rad/s², v rad/s)."""
    if not name.isidentifier():
        raise ValueError(f"program name {name!r} is not an identifier")
    if not (0 < a <= 40 and 0 < v <= 3.14):
        raise ValueError(f"movej needs 0 < a <= 40 rad/s² and 0 < v <= 3.14 rad/s, got a={a}, v={v}")
    lines = [f"def {name}():"]
    for i, row in enumerate(np.atleast_2d(q), start=1):
        joints = ", ".join(repr(float(x) + 0.0) for x in row)
        lines.append(f"  # program row {i}")
        lines.append(f"  movej([{joints}], a={float(a)!r}, v={float(v)!r})")
    lines.append("end")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------------------
# singularities, inverse kinematics and the filter


def _pose_error(T_target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(k, 6) twist (v, ω) in the base frame taking T to T_target: log(T_target T⁻¹)."""
    return se3.log_se3(T_target @ se3.inv(T))


def _det_sign(robot: CalibratedRobot, model, q: np.ndarray) -> np.ndarray:
    """(k,) sign of det J at q (k, n): which configuration branch q is on. A redundant arm (n > 6) has no square
    Jacobian and no finite set of branches (its self-motion joins them), so every q gets +1: its branch is kept by
    path following from the seed, the correction bound and the condition checks alone."""
    J = model.equivalent_jacobian(q, length_scale=robot.length_scale)
    if J.shape[-1] != 6:
        return np.ones(len(J))
    return np.sign(np.linalg.det(J))


def _jacobian(robot: CalibratedRobot, model, q: np.ndarray) -> np.ndarray:
    """(k, 6, n) the actuated joints' columns of the model's Jacobian at q (k, n)."""
    return model.equivalent_jacobian(q, length_scale=robot.length_scale)[:, :, : model.n]


def _condition(robot: CalibratedRobot, model, q: np.ndarray) -> np.ndarray:
    """(k,) length-scaled condition numbers of the actuated Jacobian at q (k, n)."""
    return scaled_condition(_jacobian(robot, model, q), robot.length_scale, model.joint_types)


def _escape_joint(robot: CalibratedRobot, model, q: np.ndarray, h: float = 1e-4) -> int:
    """0-based joint whose motion takes q (n,) away from its singularity fastest: the largest change of the smallest
    singular value of the length-scaled Jacobian under a step h of one joint (a UR arm stretched at the elbow: q3;
    at the wrist singularity: q5, though the motion the wrist loses is q4 against q6)."""
    w_rows, w_cols = twist_weights(robot.length_scale)[:, None], joint_weights(model.joint_types, robot.length_scale)
    steps = np.concatenate([np.zeros((1, model.n)), h * np.eye(model.n), -h * np.eye(model.n)])
    s = np.linalg.svd(w_rows * _jacobian(robot, model, q + steps) * w_cols, compute_uv=False)[:, -1]
    change = np.maximum(np.abs(s[1 : model.n + 1] - s[0]), np.abs(s[model.n + 1 :] - s[0]))
    return int(np.argmax(change))


def _singular(
    robot: CalibratedRobot, model, row: int, q: np.ndarray, cond: float, where: str, limit: float
) -> ProgramError:
    """The ProgramError of a row ``where`` near a singular configuration, naming the joint that leaves it fastest."""
    j = _escape_joint(robot, model, q)
    return ProgramError(
        f"row {row}: singular: {where} near a singular configuration (length-scaled Jacobian condition {cond:.3g} > "
        f"{limit:g}; q{j + 1} = {q[j]:.6g} is the joint that leaves it fastest): the correction and the "
        "configuration branch are not defined there; move the row away from it or split the move",
        row,
    )


def _follow(robot: CalibratedRobot, q0: np.ndarray, T_target: np.ndarray, row: int, max_condition: float, tol: float):
    """Nominal IK of one target by path following from q0; ProgramError naming the row on a singularity on the
    way (a condition above max_condition or a determinant sign change between two steps), or a target it cannot
    reach."""
    model = robot.nominal
    distance, reach = float(np.linalg.norm(T_target[:3, 3])), 1.1 * model.reach() + 0.05  # generous, as the import's
    if distance > reach:  # before path following, whose failure there would blame a branch or a singularity
        in_mm = 10 * reach < distance <= 1000 * reach  # hundreds of "metres": a program in millimetres
        unit = " (millimetres read as metres? pass --length-unit mm)" if in_mm else ""
        raise ProgramError(
            f"row {row}: unreachable: the pose is {distance:.4g} m from the base, beyond the robot's reach of "
            f"{reach:.3g} m{unit}",
            row,
        )
    q = q0.copy()
    T0 = model.fk(q)
    step = se3.log_se3(se3.inv(T0) @ T_target)
    sign0 = _det_sign(robot, model, q[None])[0]
    for s in range(1, STEPS + 1):
        T_s = T0 @ se3.exp_se3(step * (s / STEPS))
        q_before = q
        for _ in range(20 if s == STEPS else 4):
            J = _jacobian(robot, model, q[None])[0]
            cond = scaled_condition(J[None], robot.length_scale, model.joint_types)[0]
            if not cond <= max_condition:
                where = "the path from the previous point passes" if s < STEPS else "the row's solution is"
                raise _singular(robot, model, row, q, cond, where, max_condition)
            r = _pose_error(T_s, model.fk(q))
            dq = np.linalg.lstsq(J, r, rcond=None)[0]
            q = q + dq
            if np.max(np.abs(dq)) < tol:
                break
        if _det_sign(robot, model, q[None])[0] != sign0:
            # det J is continuous in q: a sign change between two steps crosses det J = 0, a singular configuration
            # (too narrow for the sampled condition to see), on the way to another configuration branch.
            mid = 0.5 * (q_before + q)
            j = _escape_joint(robot, model, mid)
            cond = float(_condition(robot, model, mid[None])[0])
            raise ProgramError(
                f"row {row}: singular: the path from the previous point crosses a singular configuration between two "
                f"steps (the Jacobian's determinant changes sign, condition {cond:.3g} half-way, q{j + 1} ≈ "
                f"{mid[j]:.6g} the joint that leaves it fastest) and would leave the seed's configuration branch: "
                "split the move or give --seed-joints on the branch of this row",
                row,
            )
    err = _pose_error(T_target, model.fk(q))
    L = robot.length_scale
    size = max(float(np.linalg.norm(err[:3])), L * float(np.linalg.norm(err[3:])))
    if not size <= max(tol, 1e-9) * max(1.0, L):
        raise ProgramError(
            f"row {row}: unreachable: the nominal model ends {1e3 * np.linalg.norm(err[:3]):.3f} mm / "
            f"{1e3 * np.linalg.norm(err[3:]):.3f} mrad from the pose (outside the workspace or the robot's "
            "kinematics cannot make this orientation)",
            row,
        )
    return q


def nominal_ik(
    robot: CalibratedRobot,
    T_target: np.ndarray,
    seed: np.ndarray,
    *,
    max_condition: float = MAX_CONDITION,
    tol: float = TOL,
) -> np.ndarray:
    """(k, n) nominal joint solutions of (k, 4, 4) tool poses, each seeded by the previous one (the first by seed)."""
    T_target = np.asarray(T_target, dtype=float).reshape(-1, 4, 4)
    seed = np.asarray(seed, dtype=float).reshape(robot.n)
    out = np.empty((len(T_target), robot.n))
    q = seed
    for i, T in enumerate(T_target):
        q = _follow(robot, q, T, i + 1, max_condition, tol)
        out[i] = q
    return out


def filter_joints(
    robot: CalibratedRobot,
    q_nominal: np.ndarray,
    *,
    max_correction: float = MAX_CORRECTION,
    max_condition: float = MAX_CONDITION,
    angle_unit: str = "rad",
    tcp: np.ndarray | None = None,
) -> FilteredProgram:
    """Correct nominal joint targets (k, n): the joints at which the calibrated robot reaches their nominal poses.

    ``angle_unit``: the unit the program was written in (only to phrase a refusal's hint). tcp: (4, 4) the working
    TCP in tool0 (None: tool0, the robot file's tool): the correction is solved and its errors reported there."""
    q_nominal = np.atleast_2d(np.asarray(q_nominal, dtype=float))
    if q_nominal.shape[1] != robot.n:
        raise ProgramError(f"the program has {q_nominal.shape[1]} joints per row, the robot {robot.n}")
    check_joints(robot, q_nominal, angle_unit)
    cond_nominal = _condition(robot, robot.nominal, q_nominal)
    singular = ~(cond_nominal <= max_condition)
    if singular.any():  # before correct(): its answer there is whatever the damped fallback stopped at
        i = int(np.argmax(singular))
        raise _singular(robot, robot.nominal, i + 1, q_nominal[i], cond_nominal[i], "the row is", max_condition)
    q_cmd = robot.correct(q_nominal, tcp=tcp)
    T_nominal = robot.nominal.fk(q_nominal) if tcp is None else robot.nominal.fk(q_nominal) @ tcp
    dq = np.max(np.abs(q_cmd - q_nominal), axis=1)
    cond_cmd = _condition(robot, robot.model, q_cmd)
    same = _det_sign(robot, robot.model, q_cmd) == _det_sign(robot, robot.nominal, q_nominal)
    missed_p, missed_r = se3.pose_distance(robot.predict_pose(q_cmd, tcp=tcp), T_nominal)
    bad = ~(dq <= max_correction) | ~same | ~(cond_cmd <= max_condition)
    bad |= ~(missed_p <= REACHED) | ~(missed_r <= REACHED)
    if bad.any():
        i = int(np.argmax(bad))
        if not (cond_cmd[i] <= max_condition):
            where = "the calibrated solution is"
            raise _singular(robot, robot.model, i + 1, q_cmd[i], cond_cmd[i], where, max_condition)
        if not same[i] and dq[i] <= max_correction:
            # det J is continuous: a sign change under a correction of a few mrad crosses det J = 0 between the two
            # solutions, so the row is as close to a singularity as the calibration moves it, whatever its condition.
            j = _escape_joint(robot, robot.nominal, q_nominal[i])
            raise ProgramError(
                f"row {i + 1}: singular: the row is so close to a singular configuration that the calibrated solution "
                f"lies on its other side (the Jacobian's determinant changes sign under a correction of "
                f"{1e3 * dq[i]:.3g} mrad; condition {cond_nominal[i]:.3g}; q{j + 1} = "
                f"{q_nominal[i, j]:.6g} is the joint that leaves it fastest): move the row away from it or split the "
                "move",
                i + 1,
            )
        if not same[i]:
            why = "changes configuration branch (the Jacobian's determinant changes sign at a well-conditioned row)"
        elif not (dq[i] <= max_correction):
            why = f"moves a joint by {dq[i]:.3g} rad"
        else:
            j = _escape_joint(robot, robot.nominal, q_nominal[i])
            near = (
                f"; the row is near a singular configuration, q{j + 1} = {q_nominal[i, j]:.6g} leaves it fastest"
                if cond_nominal[i] > NEAR_SINGULAR
                else ""
            )
            raise ProgramError(
                f"row {i + 1}: the calibrated robot does not reach the row's pose: it stays {1e3 * missed_p[i]:.3g} mm"
                f" / {1e3 * missed_r[i]:.3g} mrad away after the correction (condition {cond_nominal[i]:.3g}{near}): "
                "move the row or split the move",
                i + 1,
            )
        raise ProgramError(
            f"row {i + 1}: the calibrated solution {why}: another solution, not a correction; check the "
            "calibration or the row",
            i + 1,
        )
    dp, dr = se3.pose_distance(robot.predict_pose(q_nominal, tcp=tcp), T_nominal)
    return FilteredProgram(q_nominal, q_cmd, dp, dr)


def filter_poses(
    robot: CalibratedRobot,
    poses: np.ndarray,
    seed: np.ndarray,
    *,
    tcp: np.ndarray | None = None,
    max_condition: float = MAX_CONDITION,
    max_correction: float = MAX_CORRECTION,
    angle_unit: str = "rad",
) -> FilteredProgram:
    """Correct a program of (k, 6) TCP poses (base frame; m, rotation vector in rad) into joint targets.

    tcp: (6,) the program's TCP in the model's tool frame (m, rotation vector; None: the tool frame itself).
    ``angle_unit``: the unit the program was written in (only to phrase a refusal's hint). The seed must lie inside
    the robot's joint limits (a seed in degrees read as radians is refused with a hint, not followed).
    """
    poses = np.atleast_2d(np.asarray(poses, dtype=float))
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise ProgramError(f"a pose program has 6 values per row (x, y, z, rx, ry, rz), got shape {poses.shape}")
    check_rotation_vectors(poses, angle_unit)
    seed = np.asarray(seed, dtype=float).reshape(robot.n)
    check_joints(robot, seed[None], angle_unit, seed=True)
    T = pose_matrix(poses)
    tcp4 = None if tcp is None else pose_matrix(np.asarray(tcp, dtype=float).reshape(1, 6))[0]
    if tcp4 is not None:
        T = T @ se3.inv(tcp4)
    q_nominal = nominal_ik(robot, T, seed, max_condition=max_condition)
    return filter_joints(
        robot, q_nominal, max_correction=max_correction, max_condition=max_condition, angle_unit=angle_unit, tcp=tcp4
    )
