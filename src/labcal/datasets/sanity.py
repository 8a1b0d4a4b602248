"""Sanity checks on measurements before they become a session (issue 12.1): catch the mistakes that fit and export
would otherwise turn into a compensator that commands nonsense.

Each check has a name; a failed check is an error that names the bad rows or fields and the likely fix, and only
an explicit override that names the check lets the data through (``labcal session import … --allow NAME``,
``allow=["NAME"]`` in Python). The overrides are recorded with the version (import provenance).

====================  ==============================================================================================
check                 what it refuses
====================  ==============================================================================================
``target-distances``  measured distances between targets seen in the same row that do not match the targets file: a
                      length unit slip (×1000, ×0.001, ×25.4 …), a different triangle, or targets in another order
``target-outliers``   single rows whose target distances are off the other rows' by more than 2 mm
``joint-limits``      joint values (model joints, after the robot file's joint map) outside the robot's limits
``joint-span``        with degrees: every joint moving less than 12.6° and no value beyond ±2π (radians read
                      as degrees) although the limits are wide
``nominal``           measured points farther than 25 mm (mean) from where the nominal model puts them, after
                      registering the tracker frame (``frame = "tracker"``) and the probe mount (probe form); the
                      message names the reading that makes the data fit when one does (another unit, frame,
                      target order, a coupled / reversed / offset joint for the ``[joint_map]``); single rows far
                      off the rest are named on their own
``reach``             base-frame points beyond the robot's reach (tracker coordinates imported as base)
``duplicates``        more than half of the rows repeating a pose (identical joint rows are reported in any case)
``few-poses``         fewer distinct poses than twice the joint count: too few to calibrate
====================  ==============================================================================================

Non-finite values, empty files and wrong columns are refused earlier, by the CSV reader, and cannot be overridden.

This module uses numpy, the kinematics and the robot files only, so the importers and the session runner (at
record time) call the same code::

    report = check_measurements(q, points, targets, robot=spec, frame="tracker", allow=["duplicates"])
    report.raise_if_failed()          # SanityError listing every failed check, or nothing

``q`` are controller joints (k, n) in rad / m, ``points`` (k, m, 3) the measured targets in m (m >= 1 targets, a
NaN row for a target not seen in that row: the distance checks use the pairs seen together, the nominal check the
targets seen).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from labcal.kinematics import se3
from labcal.robots import RobotSpec

from ._util import jsonable
from .checks import CHECKS
from .errors import DatasetError
from .targets import LENGTH_UNITS as LENGTH_FACTORS
from .targets import pair_distances, target_layout, target_pairs

#: Every check, with what it guards against (shown by ``labcal session import --help``).

#: A measured/file distance ratio within this factor of a unit ratio is called a unit slip.
UNIT_RATIO_TOL = 1.05
#: Target distances may differ from the file's by this much (m) or TARGET_REL_TOL of the distance, whichever is
#: larger, before the targets file is called wrong: tracker noise is ~0.05 mm, a hand-measured file ~1 mm.
TARGET_ABS_TOL = 1.5e-3
TARGET_REL_TOL = 0.02
#: A single row is an outlier when a distance is off by more than this (m) and 6 robust sd of all rows.
ROW_ABS_TOL = 2e-3
#: Mean distance (m) between measured and nominally predicted points above which the data do not describe this
#: robot as imported. Nominal robots are within a few mm (the real UR10 data set: 0.92 mm after registration); a
#: coupled elbow left unconverted is hundreds of mm before any fit, unit slips are hundreds of mm to metres.
NOMINAL_MEAN_LIMIT = 25e-3
#: Share of rows up to which rows far off the nominal model (while the rest fit it) are named: a minority of bad
#: rows (a block measured with the tracker knocked, swapped targets in some rows); above it the data as a whole are
#: off and the readings of the input are tested instead.
FAR_ROWS_NAMED = 0.45
#: Joints whose whole span is below this (rad) while their limits span more than SPAN_WIDE_LIMITS look like
#: radians read as degrees: a full ±2π rad range read as degrees spans only 4π° ≈ 12.6°.
SPAN_TINY = math.radians(4 * math.pi)
SPAN_WIDE_LIMITS = math.radians(60.0)
#: Joint rows equal to within this (rad or m) are the same pose.
DUPLICATE_TOL = 1e-6
#: Rows used to test alternative explanations (units, frame, joint coupling) for a failed nominal check.
HYPOTHESIS_ROWS = 400

_PAIRS = target_pairs(3)
#: Every order of three targets but the targets file's (a swap or a rotation of the labels).
_REORDERS = list(itertools.permutations(range(3)))[1:]


class SanityError(DatasetError, ValueError):
    """Measurements failed one or more sanity checks. ``report`` holds every finding."""

    def __init__(self, report: SanityReport, message: str) -> None:
        super().__init__(message)
        self.report = report


@dataclass(frozen=True)
class Hints:
    """How to phrase a fix for the caller's interface: CLI flags, mapping keys, or the runner's settings.

    Each field is a format string: ``length`` gets ``{unit}``, ``angle`` ``{unit}``, ``frame`` ``{frame}``,
    ``allow`` ``{check}``. ``rows`` turns 0-based row indices into text (default "row 7").
    """

    length: str = "--length-unit {unit}"
    angle: str = "--angle-unit {unit}"
    frame: str = "--frame {frame}"
    allow: str = "--allow {check}"
    row: Callable[[int], str] | None = None

    def row_text(self, i: int) -> str:
        return self.row(i) if self.row is not None else f"row {i + 1}"

    def rows_text(self, rows: Sequence[int], limit: int = 5, value: Callable[[int], str] | None = None) -> str:
        """The first ``limit`` rows as text, each followed by ``value(row)`` when given ("row 7 31.2 mm")."""
        shown = ", ".join(self.row_text(int(i)) + (f" {value(int(i))}" if value else "") for i in list(rows)[:limit])
        return shown + (f" (+{len(rows) - limit} more)" if len(rows) > limit else "")


@dataclass
class Finding:
    check: str
    message: str
    rows: list[int] = field(default_factory=list)  # 0-based rows at fault (first few), if the fault is per row

    def as_dict(self) -> dict:
        return {"check": self.check, "message": self.message, "rows": [int(r) + 1 for r in self.rows]}


@dataclass
class SanityReport:
    """Outcome of :func:`check_measurements`. ``failures`` block; ``allowed`` would have blocked but were
    overridden; ``notes`` never block (e.g. a few duplicated poses); ``stats`` are the numbers measured."""

    failures: list[Finding] = field(default_factory=list)
    allowed: list[Finding] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    hints: Hints = field(default_factory=Hints)
    allow: frozenset[str] = frozenset()  # the checks whose failure is only recorded (``allowed``)

    @property
    def ok(self) -> bool:
        return not self.failures

    def as_dict(self) -> dict:
        """JSON-ready summary, stored in the version's import provenance."""
        return {
            "allowed": [f.as_dict() for f in self.allowed],
            "notes": list(self.notes),
            "stats": jsonable(self.stats, finite=True),
        }

    def message(self) -> str:
        n = len(self.failures)
        head = f"{n} sanity check{'s' if n > 1 else ''} failed; nothing was written"
        lines = [head, *(f"  [{f.check}] {f.message}" for f in self.failures)]
        flags = " ".join(self.hints.allow.format(check=f.check) for f in self.failures)
        lines.append(f"  Fix the input as suggested; only if the data are right as they are, pass {flags}")
        return "\n".join(lines)

    def raise_if_failed(self) -> None:
        if self.failures:
            raise SanityError(self, self.message())

    def add(self, check: str, message: str, rows: Iterable[int] = ()) -> None:
        """File a finding of ``check`` (rows: 0-based rows at fault, the first few) as a failure, or as allowed."""
        (self.allowed if check in self.allow else self.failures).append(Finding(check, message, [int(i) for i in rows]))


def check_names(allow: Iterable[str] | None) -> frozenset[str]:
    """Validate override names; raise naming the unknown ones and listing the valid ones."""
    names = frozenset(str(a).strip() for a in (allow or ()))
    unknown = sorted(names - set(CHECKS))
    if unknown:
        raise DatasetError(f"unknown check(s) {unknown} for --allow; the checks are: {', '.join(CHECKS)}")
    return names


# --------------------------------------------------------------------------------------------------------------
# Geometry: rigid registration (labcal.kinematics.se3.rigid_fit)


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising Σ |R a_i + t − b_i|² (a proper rotation) for (m, 3) point sets a, b;
    with b (k, m, 3) one fit per row: R (k, 3, 3), t (k, 3)."""
    b = np.asarray(b, dtype=float)
    T = se3.rigid_fit(a, b if b.ndim == 3 else b[None])
    return (T[:, :3, :3], T[:, :3, 3]) if b.ndim == 3 else (T[0, :3, :3], T[0, :3, 3])


def _project_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    return R


def _apply(R: np.ndarray, t: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ R.T + t


def _hand_eye(F: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form Y = (R_Y, p_Y) (tracker ← base) with P_i ≈ Y F_i X (X: tool ← probe, unknown), from (k, 4, 4)
    tool poses F and measured probe poses P. Rotation of Y: A R_Y = R_Y B for relative motions A = R_Pi R_Pjᵀ,
    B = R_Fi R_Fjᵀ, a linear null-space problem; then the translations of Y and X by linear least squares (the
    caller registers X's rotation itself, against Y's estimate)."""
    k = len(F)
    RF, RP = F[:, :3, :3], P[:, :3, :3]
    step = max(1, k // 2)
    i = np.arange(k)
    j = np.concatenate([(i + 1) % k, (i + step) % k])
    i = np.concatenate([i, i])
    A = RP[i] @ np.swapaxes(RP[j], 1, 2)
    B = RF[i] @ np.swapaxes(RF[j], 1, 2)
    eye = np.eye(3)
    # vec(A X) = (I ⊗ A) vec(X), vec(X B) = (Bᵀ ⊗ I) vec(X) with column-major vec.
    rows = np.einsum("ab,kcd->kacbd", eye, A).reshape(-1, 9, 9) - np.einsum("kab,cd->kbcad", B, eye).reshape(-1, 9, 9)
    rows = rows.reshape(-1, 9)
    _, vecs = np.linalg.eigh(rows.T @ rows)  # null vector = eigenvector of the smallest eigenvalue (9×9, any k)
    Ry = vecs[:, 0].reshape(3, 3, order="F")
    if np.linalg.det(Ry) < 0:
        Ry = -Ry
    Ry = _project_so3(Ry)
    # p_P − R_Y p_F = R_Y R_F p_X + p_Y
    lhs = np.concatenate([np.einsum("ab,kbc->kac", Ry, RF), np.broadcast_to(eye, (k, 3, 3))], axis=2)
    rhs = P[:, :3, 3] - F[:, :3, 3] @ Ry.T
    sol, *_ = np.linalg.lstsq(lhs.reshape(-1, 6), rhs.reshape(-1), rcond=None)
    return Ry, sol[3:]


def _points_from_poses(F: np.ndarray, X: tuple[np.ndarray, np.ndarray], v: np.ndarray) -> np.ndarray:
    """(k, 3, 3) points F_i · X · v in the frame of F."""
    local = _apply(*X, v)  # (3, 3) in the tool frame
    return np.einsum("kab,mb->kma", F[:, :3, :3], local) + F[:, None, :3, 3]


def registered_residuals(
    robot: RobotSpec,
    q_model: np.ndarray,
    points: np.ndarray,
    targets: np.ndarray,
    *,
    frame: str,
    tool_known: bool = True,
) -> np.ndarray:
    """(k,) mean distance (m) per row between the measured points and the nominal model's.

    ``frame = "base"``: points compared as given; ``"tracker"``: after the best rigid tracker → base registration.
    ``tool_known = False`` (a 6-DOF probe, whose mount on the flange is unknown): the tool → probe transform is
    registered too (closed form, then a few alternating refinements). A registration is fitted again without rows
    far off the rest (> 5 × the median and > 25 mm), so one absurd row does not drag every other row's residual.
    """
    pred = robot.model.target_points(q_model, targets) if tool_known else None
    if pred is not None and frame != "tracker":
        return np.nanmean(np.linalg.norm(points - pred, axis=2), axis=1)  # NaN: a target not seen
    F = None if tool_known else robot.model.fk(q_model)
    res = _registered(F, pred, points, targets, frame, np.ones(len(points), bool))
    keep = res <= max(5 * float(np.median(res)), NOMINAL_MEAN_LIMIT)
    if not keep.all() and keep.sum() >= max(3, len(res) // 2):
        res = _registered(F, pred, points, targets, frame, keep)
    return res


def _registered(F, pred, points, targets, frame, fit_rows) -> np.ndarray:
    """Residuals of every row after registering on ``fit_rows``: tracker only (``pred`` given, tool known), or
    tool mount (``F`` = tool poses) and, for ``frame = "tracker"``, the tracker frame too."""
    if pred is not None:
        a, b = points[fit_rows].reshape(-1, 3), pred[fit_rows].reshape(-1, 3)
        seen = np.isfinite(a).all(axis=1)
        R, t = kabsch(a[seen], b[seen]) if not seen.all() else kabsch(a, b)
        return np.nanmean(np.linalg.norm(_apply(R, t, points) - pred, axis=2), axis=1)
    if frame == "tracker":
        P = se3.rigid_fit(targets, points)  # the measured probe poses
        Y = _hand_eye(F[fit_rows], P[fit_rows])
        base_pts = _apply(Y[0].T, -Y[0].T @ Y[1], points)  # tracker → base with the first estimate
    else:
        base_pts = points
    Finv_R = np.swapaxes(F[:, :3, :3], 1, 2)
    m = int(fit_rows.sum())
    for _ in range(4 if frame == "tracker" else 1):
        local = np.einsum("kab,kmb->kma", Finv_R, base_pts - F[:, None, :3, 3])  # measured, in the tool frame
        X = kabsch(np.tile(targets, (m, 1)), local[fit_rows].reshape(-1, 3))
        pred = _points_from_poses(F, X, targets)
        if frame != "tracker":
            break
        R, t = kabsch(points[fit_rows].reshape(-1, 3), pred[fit_rows].reshape(-1, 3))
        base_pts = _apply(R, t, points)
    return np.linalg.norm(base_pts - pred, axis=2).mean(axis=1)


# --------------------------------------------------------------------------------------------------------------
# The checks


def _mm(x: float) -> str:
    return f"{x * 1e3:.1f} mm" if abs(x) < 10 else f"{x:.3g} m"


def _perm_text(perm: tuple[int, ...]) -> str:
    moved = [i for i in range(3) if perm[i] != i]
    if len(moved) == 2:
        a, b = moved
        return f"t{a + 1}↔t{b + 1}"
    return "CSV " + ", ".join(f"t{i + 1}" for i in range(3)) + " = file " + ", ".join(f"t{p + 1}" for p in perm)


def _unit_pairs(ratio: float) -> list[tuple[str, str]]:
    """The length units (a, b) whose factor a/b a measured/expected length ratio is, within UNIT_RATIO_TOL."""
    return [
        (a, b)
        for a, b in itertools.permutations(LENGTH_FACTORS, 2)
        if abs(math.log(ratio / (LENGTH_FACTORS[a] / LENGTH_FACTORS[b]))) < math.log(UNIT_RATIO_TOL)
    ]


def _unit_slip(ratio: float, used: str, hints: Hints, what: str) -> str | None:
    """Explain a measured/expected length ratio as a unit mix-up (first as data in another unit read as ``used``),
    or None."""
    pairs = _unit_pairs(ratio)
    true = next((b for a, b in pairs if a == used), None)
    if true is not None:
        return (
            f"length unit slip: {what} are {ratio:.4g}× the expected size: the data look like {true} imported as "
            f"{used} — pass {hints.length.format(unit=true)}"
        )
    if pairs:
        a, b = pairs[0]
        return (
            f"length unit slip: {what} are {ratio:.4g}× the expected size (the factor between {b} and {a}): "
            f"check the data's unit ({hints.length.format(unit='…')}, now {used}) and the targets file's unit"
        )
    return None


def _seen_pair_distances(points, targets):
    """(pairs, file distances, (rows, pairs) measured distances, rows used) for the target pairs seen together in
    at least one row; rows seeing no pair are left out. NaN marks a pair not seen together in a row."""
    pairs = target_pairs(len(targets))
    d_file = pair_distances(targets, pairs)
    d = pair_distances(points, pairs) if pairs else None
    if d is None or not np.isnan(d).any():
        return pairs, d_file, d, np.ones(len(points), bool)
    together = ~np.isnan(d).all(axis=0)
    rows = ~np.isnan(d).all(axis=1)
    pairs = tuple(p for p, ok in zip(pairs, together, strict=True) if ok)
    return pairs, d_file[together], d[rows][:, together], rows


def _check_target_distances(points, targets, length_unit, hints, report) -> None:
    """Distances between targets seen together in a row against the targets file (pairs never seen together, and
    sessions with one target, have nothing to compare)."""
    pairs, d_file, d, rows = _seen_pair_distances(points, targets)
    if not pairs:
        return
    points = points[rows]
    partial = np.isnan(d).any()  # the complete three-target data take the plain median, as they always did
    med = np.nanmedian(d, axis=0) if partial else np.median(d, axis=0)
    ratio = float(np.nanmedian(d / d_file) if partial else np.median(d / d_file))
    report.stats["target_distances"] = {
        "file_mm": (d_file * 1e3).round(3).tolist(),
        "measured_median_mm": (med * 1e3).round(3).tolist(),
        "ratio": round(ratio, 6),
    }
    tol = np.maximum(TARGET_ABS_TOL, TARGET_REL_TOL * d_file)
    message = _target_distance_message(pairs, med, d_file, ratio, tol, len(points), targets, length_unit, hints)
    if message is not None:
        report.add("target-distances", message)
        if "target-distances" not in report.allow:
            return  # per-row outliers mean nothing against the wrong triangle
    _check_target_outlier_rows(pairs, d, med, d_file, hints, report)


def _target_distance_message(pairs, med, d_file, ratio, tol, n_rows, targets, length_unit, hints) -> str | None:
    """What the median measured pair distances say against the file's: None (they match), coinciding targets, a
    unit slip, swapped targets, or a triangle that does not match."""
    listing = "; ".join(
        f"t{a + 1}–t{b + 1} {_mm(m)} measured vs {_mm(f)} in the file"
        for (a, b), m, f in zip(pairs, med, d_file, strict=True)
    )
    if np.all(np.abs(med - d_file) <= tol):
        return None
    if not ratio > 0:  # every measured triangle collapsed to a point (zeros, one reflector reported thrice)
        return f"the measured targets coincide ({listing}): the target columns do not hold distinct measured points"
    if (slip := _unit_slip(ratio, length_unit, hints, "the measured distances between the targets")) and np.all(
        np.abs(med / d_file / ratio - 1) < UNIT_RATIO_TOL - 1
    ):
        return f"{slip} (median over {n_rows} rows: {listing})"
    orders = _REORDERS if pairs == _PAIRS else []
    errors = [float(np.max(np.abs(med - pair_distances(targets[list(o)])) - tol)) for o in orders]
    if errors and min(errors) <= 0:
        return (
            f"targets look swapped: {_perm_text(orders[errors.index(min(errors))])} — the measured distances match "
            f"the targets file with the targets in that order ({listing}); reorder the points in the targets file or "
            "the CSV's target columns"
        )
    return (
        f"the targets file's {'triangle does' if pairs == _PAIRS else 'distances do'} not match the data "
        f"({listing}; median over {n_rows} rows, "
        f"tolerance {_mm(float(tol.min()))}): check that the targets file describes the targets that were "
        f"measured, in the same order and unit"
    )


def _check_target_outlier_rows(pairs, d, med, d_file, hints, report) -> None:
    """Rows against the data's own median distances: equal to the file's when the distance check passed, and still
    meaningful when a scale mismatch was allowed."""
    gap = np.abs(d - med)
    dev = np.nanmax(gap, axis=1) if np.isnan(gap).any() else gap.max(axis=1)
    sigma = 1.4826 * float(np.nanmedian(gap) if np.isnan(gap).any() else np.median(gap))
    limit = max(ROW_ABS_TOL * (med / d_file).mean(), 6 * sigma)
    bad = np.flatnonzero(dev > limit)
    report.stats["target_outlier_rows"] = len(bad)
    if len(bad):
        worst = int(bad[np.argmax(dev[bad])])
        pair = int(np.nanargmax(gap[worst]))
        a, b = pairs[pair]
        report.add(
            "target-outliers",
            f"{len(bad)} row(s) have target distances off the other rows' by more than {_mm(limit)}: "
            f"{hints.rows_text(bad)}; worst {hints.row_text(worst)}: t{a + 1}–t{b + 1} "
            f"{_mm(float(d[worst, pair]))} vs {_mm(float(med[pair]))} (median; {_mm(float(d_file[pair]))} in the "
            f"targets file) — a target mis-measured or confused; remove or re-measure those rows",
            bad[:20],
        )


def _revolute(robot: RobotSpec) -> np.ndarray:
    return np.array([t == "revolute" for t in robot.model.joint_types])


def _joint_name(robot: RobotSpec, j: int) -> str:
    name = robot.model.joint_names[j]  # "joint3" when the robot file names none
    return f"joint {j + 1}" + (f" ({name})" if name and name != f"joint{j + 1}" else "")


def _check_joint_limits(q, robot, angle_unit, hints, report) -> None:
    jm = robot.joints
    qm = jm.to_model(q)
    lim = robot.model.limits
    eps = 1e-9
    bad = (qm < lim[:, 0] - eps) | (qm > lim[:, 1] + eps)
    report.stats["joint_limit_violations"] = int(bad.any(axis=1).sum())
    if not bad.any():
        return
    rev = _revolute(robot)
    parts = []
    bad_joints = np.flatnonzero(bad.any(axis=0))
    for j in bad_joints[:3]:
        rows = np.flatnonzero(bad[:, j])
        i = int(rows[0])
        unit = "rad" if rev[j] else "m"
        parts.append(
            f"{_joint_name(robot, j)}: {len(rows)} row(s), first {hints.row_text(i)} = {qm[i, j]:.4g} {unit} outside "
            f"[{lim[j, 0]:.4g}, {lim[j, 1]:.4g}] {unit}"
        )
    if len(bad_joints) > 3:
        parts.append(f"and joint(s) {', '.join(str(j + 1) for j in bad_joints[3:])}")
    mapped = "" if jm.is_identity else " (model joints, after the robot file's [joint_map])"
    fix = "check the joint columns and the robot file's limits"
    if angle_unit == "rad" and rev.any():
        fix = _limits_fix(q, qm, robot, rev, bad_joints, hints) or fix
    message = f"joint values outside the robot's limits{mapped}: " + "; ".join(parts) + f": {fix}"
    report.add("joint-limits", message, np.flatnonzero(bad.any(axis=1))[:20])


def _limits_fix(q, qm, robot, rev, bad_joints, hints) -> str | None:
    """The reading that explains revolute joint values outside the limits, or None; each is offered only when it
    brings every row inside the limits: whole turns off on some columns (a homing or turn-count offset), some
    columns in degrees and the others in radians (no option converts one column), or every joint in degrees
    (--angle-unit deg). q: the file's (controller) joints; the limits apply to the model joints (the joint map)."""
    jm = robot.joints

    def outside(candidate: np.ndarray) -> int:
        return int((~robot.model.within_limits(jm.to_model(candidate))).sum())

    turned, turns = q.copy(), {}
    for c in np.flatnonzero(rev):  # greedy, column by column: a turn that puts more rows inside is kept
        one_turn = 2 * math.pi * np.eye(q.shape[1])[c]
        best = min((1, -1, 2, -2), key=lambda k: outside(turned - k * one_turn))
        if outside(turned - best * one_turn) < outside(turned):
            turned, turns[c] = turned - best * one_turn, best
    if turns and not outside(turned):
        named = ", ".join(f"q{c + 1} by {k:+d} turn(s) ({360 * k:+d}°)" for c, k in turns.items())
        return (
            f"whole turns off: {named} — a homing or turn-count offset; subtract it in the file (2π rad per turn), "
            "since the calibration would otherwise learn it as an error"
        )
    cannot_be_radians = rev & (np.abs(q).max(axis=0) > 2 * math.pi)
    # A joint that moves over half a radian within ±2π reads as radians (in degrees it would hardly move).
    radians = rev & ~cannot_be_radians & (np.ptp(q, axis=0) > 0.5)
    converted = np.where(cannot_be_radians, np.radians(q), q)
    if cannot_be_radians.any() and radians.any() and not outside(converted):
        as_deg = ", ".join(str(j + 1) for j in np.flatnonzero(cannot_be_radians))
        as_rad = ", ".join(str(j + 1) for j in np.flatnonzero(radians))
        return (
            f"joint(s) {as_deg} look like degrees while joint(s) {as_rad} look like radians; no option converts one "
            "column: convert those columns in the file (× π/180)"
        )
    scaled = np.where(rev, np.radians(q), q)
    if cannot_be_radians.any() and not outside(scaled):
        return f"the values look like degrees — pass {hints.angle.format(unit='deg')}"
    return None


def _check_joint_span(q, robot, angle_unit, hints, report) -> None:
    rev = _revolute(robot)
    if angle_unit != "deg" or not rev.any() or len(q) < 3:
        return
    span = np.ptp(q[:, rev], axis=0)
    width = np.diff(robot.model.limits[rev], axis=1)[:, 0]
    report.stats["joint_span_deg_max"] = round(float(np.degrees(span.max())), 4)
    # The raw numbers must also fit radians (|value| ≤ 2π), so a genuinely small sweep in degrees is not accused.
    as_read = np.degrees(np.abs(q[:, rev])).max()
    if np.all(span < SPAN_TINY) and np.all(width > SPAN_WIDE_LIMITS) and as_read <= 2 * math.pi * 1.001:
        j = int(np.flatnonzero(rev)[np.argmax(span)])
        report.add(
            "joint-span",
            f"every joint moves less than {math.degrees(SPAN_TINY):.0f}° over the {len(q)} rows (largest span "
            f"{math.degrees(span.max()):.2f}° on {_joint_name(robot, j)}) though the limits allow "
            f"{math.degrees(width.min()):.0f}° or more: the values look like radians imported as degrees — pass "
            f"{hints.angle.format(unit='rad')}",
        )


@dataclass(frozen=True)
class _Hypothesis:
    text: str  # completes "the mean drops to X mm …"
    cost: int  # how many things it changes: the simplest explanation that fits wins
    q: np.ndarray
    points: np.ndarray
    targets: np.ndarray
    frame: str
    free_tool: bool = False  # register the targets' mount on the flange instead of trusting the targets file


def _hypotheses(
    q_ctrl, points, targets, robot, *, angle_unit, length_unit, frame, form, probe_poses, hints, unit_ratio=None
):
    """Alternative readings of the input that a user could have meant, each with the fix that selects it."""
    rev = _revolute(robot)
    jm = robot.joints
    out = []

    def add(text, q_model, cost=1, pts=points, tgt=targets, fr=frame, free_tool=False):
        out.append(_Hypothesis(text, cost, q_model, pts, tgt, fr, free_tool))

    scaled = np.where(rev, np.radians(q_ctrl) if angle_unit == "rad" else np.degrees(q_ctrl), q_ctrl)
    angle_alts = [("", q_ctrl), (hints.angle.format(unit="deg" if angle_unit == "rad" else "rad"), scaled)]
    length_alts = [("", points)]
    for unit in (u for u in LENGTH_FACTORS if u != length_unit):
        s = LENGTH_FACTORS[unit] / LENGTH_FACTORS[length_unit]
        if probe_poses is not None:  # a probe's offsets are not in the CSV: only its position scales
            R, t = probe_poses
            alt = np.einsum("kab,mb->kma", R, targets) + s * t[:, None, :]
        else:
            alt = points * s
        length_alts.append((hints.length.format(unit=unit), alt))
    frames = [("", frame)] + ([(hints.frame.format(frame="tracker"), "tracker")] if frame == "base" else [])
    for (ta, qa), (tl, pl), (tf, fr) in itertools.product(angle_alts, length_alts, frames):
        changes = [t for t in (ta, tl, tf) if t]
        if changes:
            add(f"with {' and '.join(changes)}", jm.to_model(qa), len(changes), pl, fr=fr)
    if not jm.is_identity:
        add("without the robot file's [joint_map] (the CSV may hold model joints already)", q_ctrl)
    n = q_ctrl.shape[1]
    for j in range(1, n):
        if not (rev[j] and rev[j - 1]):
            continue
        # Coupled neighbours, with either joint possibly reversed: model q_j+1 = ±J_j+1 + c·J_j, q_j = ±J_j (the
        # coupled elbow of several arm makers is q3 = J2 + J3, sometimes with J2 reversed too). c ≠ 0: plain sign
        # flips are below.
        for s1, s2, c in itertools.product((1.0, -1.0), (1.0, -1.0), (1.0, -1.0)):
            M = np.eye(n)
            M[j - 1, j - 1], M[j, j], M[j, j - 1] = s1, s2, c
            rows = "; ".join(_map_row(M, r) for r in (j - 1, j) if not np.array_equal(M[r], np.eye(n)[r]))
            add(f"if model {rows} (coupled or reversed joints, e.g. an elbow measured from the horizontal; declare "
                f"it in the robot file's [joint_map])", jm.to_model(q_ctrl @ M.T),
                1 + int(s1 < 0) + int(s2 < 0))  # fmt: skip
    for j in range(n):
        M = np.eye(n)
        M[j, j] = -1.0
        add(f"if joint {j + 1} counts the other way (declare the sign in the robot file's [joint_map])",
            jm.to_model(q_ctrl @ M.T))  # fmt: skip
    for i, j in itertools.combinations(range(n), 2):  # two joint columns swapped in the file
        swapped = q_ctrl.copy()
        swapped[:, [i, j]] = q_ctrl[:, [j, i]]
        add(f"with the columns of joints {i + 1} and {j + 1} swapped (q{i + 1} holds joint {j + 1}, q{j + 1} joint "
            f"{i + 1}): fix the file's header", jm.to_model(swapped))  # fmt: skip
    for j in np.flatnonzero(rev):
        for offset in (math.pi / 2, -math.pi / 2, math.pi):
            shifted = jm.to_model(q_ctrl)
            shifted[:, j] += offset
            add(f"if joint {j + 1}'s zero is {math.degrees(offset):+.0f}° from the model's (declare the offset in the "
                f"robot file's [joint_map])", shifted)  # fmt: skip
    if unit_ratio is not None:  # the target distances already showed a unit slip between the CSV and targets file
        add(f"once the length units agree (the data scaled by 1/{unit_ratio:.4g}, see target-distances)",
            jm.to_model(q_ctrl), pts=points / unit_ratio)  # fmt: skip
    complete = points.shape[1] == 3 and np.isfinite(points).all() and target_layout(targets) != "line"
    if form == "targets" and complete:  # re-registering the targets' mount needs three seen targets per row
        add("if the targets file's points were given in another frame than the robot file's tool frame (check its "
            "[tool] and the targets file)", jm.to_model(q_ctrl), free_tool=True)  # fmt: skip
        for perm in _REORDERS:
            add(f"with the targets reordered ({_perm_text(perm)}) in the targets file", jm.to_model(q_ctrl),
                tgt=targets[list(perm)])  # fmt: skip
    return out


def _map_row(M: np.ndarray, r: int) -> str:
    """'q3 = J2 + J3' for row r of a joint map matrix."""
    text = " ".join(f"{'−' if M[r, c] < 0 else '+'} J{c + 1}" for c in np.flatnonzero(M[r]))
    return f"q{r + 1} = " + (text[2:] if text.startswith("+ ") else "−" + text[2:])


def _check_nominal(q, points, targets, robot, *, frame, form, angle_unit, length_unit, hints, report) -> None:
    tool_known = form == "targets"
    qm = robot.joints.to_model(q)
    per_row = registered_residuals(robot, qm, points, targets, frame=frame, tool_known=tool_known)
    mean, far = _robust_mean(per_row, FAR_ROWS_NAMED)
    report.stats["nominal_mean_mm"] = round(mean * 1e3, 4)
    report.stats["nominal_p95_mm"] = round(float(np.percentile(per_row, 95)) * 1e3, 4)
    report.stats["nominal_far_rows"] = len(far)
    reach_bad = _far_rows(points, robot, targets) if frame == "base" else np.array([], int)
    report.stats["rows_beyond_reach"] = len(reach_bad)
    if len(far) and mean <= NOMINAL_MEAN_LIMIT:
        # The data as a whole describe this robot; a few rows do not (a typo, a target swapped in one row).
        report.add(
            "nominal",
            f"{len(far)} of {len(q)} rows are far from where the nominal {robot.name} model puts the targets "
            f"while the others are within {_mm(mean)} (mean): "
            + hints.rows_text(far, value=lambda i: _mm(float(per_row[i])))
            + ": a mistyped or mis-measured row; remove or re-measure it",
            far[:20],
        )
    if mean <= NOMINAL_MEAN_LIMIT and not len(reach_bad):
        return
    best, best_mean = _best_reading(
        q, points, targets, robot, frame=frame, form=form, angle_unit=angle_unit, length_unit=length_unit,
        hints=hints, report=report,
    )  # fmt: skip
    explained = best is not None and best_mean <= NOMINAL_MEAN_LIMIT and best_mean < 0.5 * mean
    best_text = "" if best is None else best.text  # said only when explained (best is then not None)
    if explained:
        report.stats["nominal_best_explanation"] = {"fix": best_text, "mean_mm": round(best_mean * 1e3, 4)}
    if len(reach_bad):
        i = int(reach_bad[0])
        dist = float(np.nanmax(np.linalg.norm(points[i], axis=1)))
        fix = (
            f"the data fit the nominal model to {_mm(best_mean)} mean {best_text}"
            if explained
            else f"the points look like tracker coordinates — pass {hints.frame.format(frame='tracker')}"
        )
        report.add(
            "reach",
            f"{len(reach_bad)} of {len(q)} rows have points farther from the base origin than the robot can "
            f"reach ({_mm(_reach(robot, targets))}), e.g. {hints.row_text(i)} at {_mm(dist)}: {fix}",
            reach_bad[:20],
        )
    if mean > NOMINAL_MEAN_LIMIT:
        drop = f"the mean drops to {_mm(best_mean)} {best_text}" if explained else None
        report.add("nominal", _nominal_mismatch(q, per_row, mean, robot, frame, tool_known, hints, drop))


def _nominal_mismatch(q, per_row, mean, robot, frame, tool_known, hints, fix: str | None) -> str:
    """The data as a whole are far from the nominal model: how far, where, the worst rows, and the fix (the
    reading of the input that explains it, else the likely causes)."""
    where = {
        ("base", True): "in the base frame as given",
        ("tracker", True): "after the best rigid tracker → base registration",
        ("base", False): "after registering the probe's mount on the flange",
        ("tracker", False): "after registering the tracker frame and the probe's mount on the flange",
    }[(frame, tool_known)]
    worst = np.argsort(per_row)[::-1][:3]
    worst_text = hints.rows_text(worst, value=lambda i: _mm(float(per_row[i])))
    if fix is None:
        fix = (
            f"no single fix found; likely causes: the joint angle unit ({hints.angle.format(unit='deg|rad')}), "
            f"controller joints that are not the model's joints (coupled or reversed joints: the robot file's "
            f"[joint_map]), the frame of the points ({hints.frame.format(frame='base|tracker')}), the targets file, "
            f"or the wrong robot file"
        )
    return (
        f"the measured points are {_mm(mean)} (mean over {len(q)} rows) from where the nominal "
        f"{robot.name} model puts them {where}; a robot matching its model is within a few mm (limit "
        f"{_mm(NOMINAL_MEAN_LIMIT)}); worst {worst_text}: {fix}"
    )


def _best_reading(q, points, targets, robot, *, frame, form, angle_unit, length_unit, hints, report):
    """(the alternative reading of the input (:func:`_hypotheses`) that brings the data nearest the nominal model,
    among those about as near as the nearest one the one that changes least; its robust mean residual), or
    (None, inf) when none can be scored."""
    tool_known = form == "targets"
    # Which reading of the input would make the data agree with the model? Test on a spread subset of rows.
    idx = np.unique(np.linspace(0, len(q) - 1, min(len(q), HYPOTHESIS_ROWS)).astype(int))
    probe_poses = kabsch(targets, points[idx]) if form == "probe" else None
    scored = []
    for h in _hypotheses(q[idx], points[idx], targets, robot, angle_unit=angle_unit, length_unit=length_unit,
                         frame=frame, form=form, probe_poses=probe_poses, hints=hints,
                         unit_ratio=_known_unit_ratio(report.stats)):  # fmt: skip
        try:
            m = _robust_mean(registered_residuals(robot, h.q, h.points, h.targets, frame=h.frame,
                                                  tool_known=tool_known and not h.free_tool))[0]  # fmt: skip
        except (np.linalg.LinAlgError, ValueError):
            continue
        if np.isfinite(m):
            scored.append((h, m))
    best, best_mean = None, np.inf
    if scored:
        lowest = min(m for _, m in scored)
        # Among the readings about as good as the best one, name the one that changes least (a registration
        # absorbs a little noise, so "--length-unit mm and --frame tracker" may score a hair under "--length-unit mm").
        near = [(h, m) for h, m in scored if m <= max(1.5 * lowest, lowest + 2e-3)]
        best, best_mean = min(near, key=lambda hm: (hm[0].cost, hm[1]))
    return best, best_mean


def _robust_mean(per_row: np.ndarray, share: float = 0.1) -> tuple[float, np.ndarray]:
    """Mean residual without the rows far off the rest (> 5 × median and > 25 mm) when those are at most ``share``
    of the rows, else the plain mean; and the far rows. The data's own check names far rows up to a minority
    (:data:`FAR_ROWS_NAMED`); scoring a reading of the input sets aside only a tenth, so that a reading which fits
    half of the rows does not look like a fix."""
    far = np.flatnonzero(per_row > max(5 * float(np.median(per_row)), NOMINAL_MEAN_LIMIT))
    if 0 < len(far) <= share * len(per_row):
        return float(np.delete(per_row, far).mean()), far
    return float(per_row.mean()), np.array([], int)


def _known_unit_ratio(stats: dict) -> float | None:
    """The unit ratio (1000, 25.4, …) the target distances showed, or None."""
    ratio = stats.get("target_distances", {}).get("ratio")
    pairs = _unit_pairs(ratio) if ratio and ratio > 0 else []
    return LENGTH_FACTORS[pairs[0][0]] / LENGTH_FACTORS[pairs[0][1]] if pairs else None


def _reach(robot: RobotSpec, targets: np.ndarray) -> float:
    return robot.model.reach() + float(np.linalg.norm(targets, axis=1).max())


def _far_rows(points: np.ndarray, robot: RobotSpec, targets: np.ndarray) -> np.ndarray:
    """Rows with a point beyond the robot's reach (a generous bound: every link offset laid end to end, + 10 %)."""
    limit = 1.1 * _reach(robot, targets) + 0.05
    dist = np.linalg.norm(points, axis=2)
    return np.flatnonzero((np.nanmax(dist, axis=1) if np.isnan(dist).any() else dist.max(axis=1)) > limit)


def _check_duplicates(q, existing_q, final, hints, report) -> None:
    all_q = q if existing_q is None or not len(existing_q) else np.concatenate([existing_q, q])
    offset = 0 if existing_q is None else len(existing_q)
    keys = np.round(all_q / DUPLICATE_TOL).astype(np.int64)
    _, first, inverse, counts = np.unique(keys, axis=0, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    n_distinct = len(counts)
    dup_rows = np.flatnonzero(first[inverse] != np.arange(len(all_q)))
    report.stats["distinct_poses"] = int(n_distinct)
    report.stats["duplicate_rows"] = len(dup_rows)
    if len(dup_rows):
        groups = np.flatnonzero(counts > 1)
        members = [np.flatnonzero(inverse == g)[:4] for g in groups[:3]]
        examples = [" = ".join(_row_or_earlier(int(m), offset, hints) for m in pose) for pose in members]
        report.notes.append(
            f"{len(dup_rows)} row(s) repeat an earlier pose ({len(groups)} pose(s) measured more than once; "
            f"identical joints: {'; '.join(examples)}{' …' if len(groups) > 3 else ''}); a fit keeps repeats of one "
            f"pose together when it splits the data"
        )
    if len(dup_rows) > 0.5 * len(all_q):
        report.add("duplicates", f"{len(dup_rows)} of {len(all_q)} rows repeat a pose (only {n_distinct} "
                   f"distinct): a fit would learn the repeats, not the robot; measure distinct poses",
                   [int(i) - offset for i in dup_rows[:20] if i >= offset])  # fmt: skip
    need = 2 * all_q.shape[1]
    if final and n_distinct < need:
        report.add("few-poses", f"only {n_distinct} distinct pose(s) in {len(all_q)} rows; calibrating "
                   f"{all_q.shape[1]} joints needs at least {need} (2 per joint) spread over the workspace: "
                   f"measure more poses")  # fmt: skip


def _row_or_earlier(i: int, offset: int, hints: Hints) -> str:
    return f"earlier pose {i}" if i < offset else hints.row_text(i - offset)


def check_measurements(
    q: np.ndarray,
    points: np.ndarray,
    targets: np.ndarray,
    *,
    robot: RobotSpec | None = None,
    frame: str = "base",
    form: str = "targets",
    length_unit: str = "m",
    angle_unit: str = "rad",
    allow: Iterable[str] = (),
    hints: Hints | None = None,
    existing_q: np.ndarray | None = None,
    final: bool = True,
) -> SanityReport:
    """Run every sanity check on measurements (already converted to SI with the given units); return the report.

    q: (k, n) controller joints (rad / m); points: (k, m, 3) measured targets (m) in ``frame``, a NaN row for a
    target not seen; targets: (m, 3) m in the tool frame (for ``form = "probe"`` the probe's virtual offsets).
    ``robot``: the nominal robot; without
    it only the data-only checks run (target distances, duplicates). ``length_unit`` / ``angle_unit``: the units the
    numbers were read in, so a suggestion can name the other one. ``allow``: check names to override (they are
    still run and reported in ``report.allowed``). ``existing_q``: joints already in the session (appending), for
    the duplicate count. ``final = False`` (a session still recording): skip the too-few-poses rule.
    """
    hints = hints or Hints()
    report = SanityReport(hints=hints, allow=check_names(allow))
    q = np.asarray(q, dtype=float)
    points = np.asarray(points, dtype=float)
    targets = np.asarray(targets, dtype=float)
    m = targets.shape[0] if targets.ndim == 2 else 0
    if q.ndim != 2 or targets.shape != (m, 3) or m < 1 or points.shape != (len(q), m, 3):
        raise DatasetError(f"sanity checks need q (k, n), points (k, m, 3), targets (m, 3); got {q.shape}, "
                           f"{points.shape}, {targets.shape}")  # fmt: skip
    # A target not seen is a NaN row; a row is left out when a joint or a partly seen target is non-finite, or
    # nothing was seen.
    nan_rows = np.isnan(points).all(axis=2)
    finite = (
        np.isfinite(q).all(axis=1) & (np.isfinite(points).all(axis=2) | nan_rows).all(axis=1) & ~nan_rows.all(axis=1)
    )
    if not finite.all():
        report.notes.append(f"{int((~finite).sum())} row(s) with non-finite values were left out of the checks")
        keep = np.flatnonzero(finite)
        q, points = q[keep], points[keep]
        caller = hints  # rows named as the caller counts them
        hints = replace(hints, row=lambda i: caller.row_text(int(keep[i])))
        report.hints = hints
    report.stats["rows"] = len(q)
    layout = target_layout(targets) if form == "targets" else "plane"
    if layout in ("point", "line"):
        report.notes.append(
            "one target: the points do not measure the tool's orientation"
            if layout == "point"
            else "the targets lie on one line: the points do not measure the tool's rotation about it"
        )
    if len(q) == 0:
        return report
    if robot is not None and q.shape[1] != robot.model.n:
        raise DatasetError(f"{q.shape[1]} joint values per row but robot {robot.name} has {robot.model.n} joints")
    if form == "targets":
        _check_target_distances(points, targets, length_unit, hints, report)
    if robot is not None:
        _check_joint_limits(q, robot, angle_unit, hints, report)
        _check_joint_span(q, robot, angle_unit, hints, report)
        if len(q) >= 3:
            _check_nominal(q, points, targets, robot, frame=frame, form=form, angle_unit=angle_unit,
                           length_unit=length_unit, hints=hints, report=report)  # fmt: skip
    _check_duplicates(q, existing_q, final, hints, report)
    return report
