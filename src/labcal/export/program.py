"""Program filter: correct a robot program (TCP poses or nominal joint targets) into joint targets for the real
robot, offline, the way RoboDK's program filter does. Numpy only.

A program is what an integrator taught or planned against the *nominal* model: either TCP poses in the robot's
base frame (``x, y, z, rx, ry, rz``: position and rotation vector, as URScript poses) or the nominal joint targets
themselves. The filter

1. solves the nominal inverse kinematics of a pose program, by path following from a seed: the first row from
   ``seed`` (e.g. ``--seed-joints``, the robot's current or home joints), every later row from the previous row's
   solution. The pose is moved in small steps from the seed's pose to the target, with a few Gauss-Newton
   iterations per step, so the solution stays on the seed's configuration branch (shoulder, elbow, wrist): a row
   whose path passes a singularity (the length-scaled Jacobian's condition above ``max_condition``, or its
   determinant changing sign, i.e. a branch change) is refused, naming the row, and so is a row the solver cannot
   reach (pose error above ``tol`` after the last step);
2. corrects the nominal joints with the calibrated model (:meth:`CalibratedRobot.correct`: the joints at which the
   calibrated robot reaches the nominal pose), seeded on the nominal solution; a row whose correction leaves the
   branch (determinant sign) or exceeds ``max_correction`` rad is refused, naming the row, and so is a row outside
   the calibrated joint ranges;
3. reports the correction: per row the largest joint change, and the tool position and orientation error the
   calibrated model predicts for the *uncorrected* joints (what the filter removes).

The nominal IK of a pose program is sequential (each row is seeded by the previous one); everything else is
batched over the rows. Joint programs need no IK: their rows are the nominal solutions.

Example::

    from labcal.compensator import load
    from labcal.export.program import filter_poses, read_program
    comp = load("ur10.json")
    poses = read_program("program.csv", kind="poses", length_unit="mm")      # (k, 6) m, rotation vector
    result = filter_poses(comp.robot, poses, seed=np.radians([0, -90, 90, -90, -90, 0]))
    result.q_command                                                           # (k, 6) rad
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition

STEPS = 8  # pose interpolation steps from the seed to each target (path following)
MAX_CONDITION = 1e4  # length-scaled cond(J) above this on the way: a singularity, the branch is not defined
TOL = 1e-10  # pose error (m; rad) a nominal IK solution must reach
MAX_CORRECTION = 0.2  # rad: a calibration correction larger than this is a different solution, not a correction


class ProgramError(ValueError):
    """A program row cannot be filtered (the message names the row and why)."""


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
# reading and writing


def read_program(source, kind: str, length_unit: str = "m", angle_unit: str = "rad", n: int | None = None):
    """(k, 6) TCP poses (m, rotation vector rad) or (k, n) joint targets (rad) from a CSV file or its text.

    kind "poses": columns x, y, z, rx, ry, rz (position in ``length_unit`` m or mm; rotation vector in rad);
    kind "joints": columns q1 … qn (``angle_unit`` rad or deg). Other columns are ignored; a header is required.
    """
    if kind not in ("poses", "joints"):
        raise ValueError(f"kind must be 'poses' or 'joints', got {kind!r}")
    if length_unit not in ("m", "mm"):
        raise ValueError(f"length unit must be 'm' or 'mm', got {length_unit!r}")
    if angle_unit not in ("rad", "deg"):
        raise ValueError(f"angle unit must be 'rad' or 'deg', got {angle_unit!r}")
    text = Path(source).read_text() if isinstance(source, Path) else str(source)
    reader = csv.DictReader(io.StringIO(text))
    header = [h.strip() for h in (reader.fieldnames or [])]
    if kind == "poses":
        columns = ["x", "y", "z", "rx", "ry", "rz"]
    else:
        count = n if n is not None else sum(1 for h in header if h.startswith("q") and h[1:].isdigit())
        columns = [f"q{j + 1}" for j in range(count)]
    missing = [c for c in columns if c not in header]
    if missing or not columns:
        raise ValueError(
            f"program CSV needs the columns {', '.join(columns) or 'q1 … qn'}; missing: {', '.join(missing)} "
            f"(header: {', '.join(header) or 'none'})"
        )
    rows = []
    for number, row in enumerate(reader, start=2):
        clean = {(k or "").strip(): (v or "").strip() for k, v in row.items()}
        try:
            values = [float(clean[c]) for c in columns]
        except ValueError:
            raise ValueError(f"program CSV line {number}: not a number in {', '.join(columns)}") from None
        if not np.all(np.isfinite(values)):
            raise ValueError(f"program CSV line {number}: non-finite value")
        rows.append(values)
    if not rows:
        raise ValueError("program CSV has no rows")
    out = np.array(rows, dtype=float)
    if kind == "poses" and length_unit == "mm":
        out[:, :3] /= 1000.0
    if kind == "joints" and angle_unit == "deg":
        out = np.radians(out)
    return out


def pose_matrix(x: np.ndarray) -> np.ndarray:
    """(k, 6) x, y, z, rx, ry, rz (rotation vector) → (k, 4, 4)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, :3, :3] = se3.exp_so3(x[:, 3:])
    T[:, :3, 3] = x[:, :3]
    return T


def joints_csv(result: FilteredProgram) -> str:
    """The corrected program: one row per program row, q1 … qn (rad) to command, then the nominal joints and the
    sizes (joint correction in mrad, predicted uncorrected tool error in mm and mrad)."""
    n = result.q_command.shape[1]
    head = [f"q{j + 1}" for j in range(n)] + [f"nominal_q{j + 1}" for j in range(n)]
    head += ["correction_mrad", "uncorrected_error_mm", "uncorrected_error_mrad"]
    lines = [",".join(["row", *head])]
    dq = np.max(np.abs(result.correction), axis=1)
    for i in range(len(dq)):
        values = [*result.q_command[i], *result.q_nominal[i]]
        values += [1e3 * dq[i], 1e3 * result.position_error[i], 1e3 * result.rotation_error[i]]
        lines.append(",".join([str(i + 1), *(repr(float(v)) for v in values)]))
    return "\n".join(lines) + "\n"


def movej_program(q: np.ndarray, name: str = "labcal_filtered", a: float = 1.4, v: float = 1.05) -> str:
    """A URScript ``def`` program that moves through the joint targets q (k, 6) with movej (a rad/s², v rad/s)."""
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
# inverse kinematics and the filter


def _pose_error(T_target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(k, 6) twist (v, ω) in the base frame taking T to T_target: log(T_target T⁻¹)."""
    return se3.log_se3(T_target @ se3.inv(T))


def _det_sign(robot: CalibratedRobot, model, q: np.ndarray) -> np.ndarray:
    J = model.equivalent_jacobian(q, length_scale=robot.length_scale)
    return np.sign(np.linalg.det(J))


def _follow(robot: CalibratedRobot, q0: np.ndarray, T_target: np.ndarray, row: int, max_condition: float, tol: float):
    """Nominal IK of one target by path following from q0; ProgramError naming the row on a branch change,
    a singularity on the way, or a target it cannot reach."""
    model = robot.nominal
    distance, reach = float(np.linalg.norm(T_target[:3, 3])), 1.1 * model.reach() + 0.05  # generous, as the import's
    if distance > reach:  # before path following, whose failure there would blame a branch or a singularity
        in_mm = 10 * reach < distance <= 1000 * reach  # hundreds of "metres": a program in millimetres
        unit = " (millimetres read as metres? pass --length-unit mm)" if in_mm else ""
        raise ProgramError(
            f"row {row}: unreachable: the pose is {distance:.4g} m from the base, beyond the robot's reach of "
            f"{reach:.3g} m{unit}"
        )
    q = q0.copy()
    T0 = model.fk(q)
    step = se3.log_se3(se3.inv(T0) @ T_target)
    sign0 = _det_sign(robot, model, q[None])[0]
    for s in range(1, STEPS + 1):
        T_s = T0 @ se3.exp_se3(step * (s / STEPS))
        for _ in range(20 if s == STEPS else 4):
            J = model.equivalent_jacobian(q[None], length_scale=robot.length_scale)[0][:, : model.n]
            cond = scaled_condition(J[None], robot.length_scale, model.joint_types)[0]
            if not cond <= max_condition:
                raise ProgramError(
                    f"row {row}: the path from the previous point passes a singular configuration (condition "
                    f"{cond:.3g}); the branch is not defined there: split the move or give --seed-joints near it"
                )
            r = _pose_error(T_s, model.fk(q))
            dq = np.linalg.lstsq(J, r, rcond=None)[0]
            q = q + dq
            if np.max(np.abs(dq)) < tol:
                break
        if _det_sign(robot, model, q[None])[0] != sign0:
            raise ProgramError(f"row {row}: the solution changes configuration branch (the Jacobian's sign flips)")
    err = _pose_error(T_target, model.fk(q))
    L = robot.length_scale
    size = max(float(np.linalg.norm(err[:3])), L * float(np.linalg.norm(err[3:])))
    if not size <= max(tol, 1e-9) * max(1.0, L):
        raise ProgramError(
            f"row {row}: unreachable: the nominal model ends {1e3 * np.linalg.norm(err[:3]):.3f} mm / "
            f"{1e3 * np.linalg.norm(err[3:]):.3f} mrad from the pose (outside the workspace or the robot's "
            "kinematics cannot make this orientation)"
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
    robot: CalibratedRobot, q_nominal: np.ndarray, *, max_correction: float = MAX_CORRECTION
) -> FilteredProgram:
    """Correct nominal joint targets (k, n): the joints at which the calibrated robot reaches their nominal poses."""
    q_nominal = np.atleast_2d(np.asarray(q_nominal, dtype=float))
    if q_nominal.shape[1] != robot.n:
        raise ProgramError(f"the program has {q_nominal.shape[1]} joints per row, the robot {robot.n}")
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    outside = (q_nominal < lo) | (q_nominal > hi)
    if outside.any():
        i, j = (int(x) for x in np.argwhere(outside)[0])
        raise ProgramError(
            f"row {i + 1}: joint {j + 1} = {q_nominal[i, j]:.6g} is outside the calibrated range "
            f"[{lo[j]:.6g}, {hi[j]:.6g}]: the calibration has no data there"
        )
    q_cmd = robot.correct(q_nominal)
    dq = np.max(np.abs(q_cmd - q_nominal), axis=1)
    bad = ~(dq <= max_correction)
    same = _det_sign(robot, robot.model, q_cmd) == _det_sign(robot, robot.nominal, q_nominal)
    bad |= ~same
    if bad.any():
        i = int(np.argmax(bad))
        why = "changes configuration branch" if not same[i] else f"moves a joint by {dq[i]:.3g} rad"
        raise ProgramError(
            f"row {i + 1}: the calibrated solution {why} (more than a correction): the row is at or near a singular "
            "configuration; move it away or split the move"
        )
    T_nominal = robot.nominal.fk(q_nominal)
    dp, dr = se3.pose_distance(robot.predict_pose(q_nominal), T_nominal)
    return FilteredProgram(q_nominal, q_cmd, dp, dr)


def filter_poses(
    robot: CalibratedRobot,
    poses: np.ndarray,
    seed: np.ndarray,
    *,
    tcp: np.ndarray | None = None,
    max_condition: float = MAX_CONDITION,
    max_correction: float = MAX_CORRECTION,
) -> FilteredProgram:
    """Correct a program of (k, 6) TCP poses (base frame; m, rotation vector) into joint targets.

    tcp: (6,) the program's TCP in the model's tool frame (m, rotation vector; None: the tool frame itself).
    """
    T = pose_matrix(poses)
    if tcp is not None:
        T = T @ se3.inv(pose_matrix(tcp)[0])
    q_nominal = nominal_ik(robot, T, seed, max_condition=max_condition)
    return filter_joints(robot, q_nominal, max_correction=max_correction)
