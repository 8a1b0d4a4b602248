"""Model-based calibration: identification of the local-POE frame errors (paper eq. 8-11, 18).

Every initial relative frame is right-perturbed, ``A_j(0) · exp(δζ̂_j)`` for j = 1 … n+1 (6n + 6 parameters).
The pose error this causes is the spatial twist ``δy = Σ_j Ad_{j0} δζ_j`` in K0 (eq. 11,
:meth:`LocalPOEModel.frame_jacobian`), and a target point p_i on the tool moves by ``dp_i = δv + δω × p_i``
(eq. 18 written per point: P δy with the rows ``[I, −p̂_i]``). Every measured point gives 3 coordinates (9 per
configuration with three targets; a target a row did not see gives none); the parameters are found by iterated
Gauss-Newton: linearise at the current model, solve the linear least-squares step with a truncated SVD, compose
the step into the frames, repeat until the step is below ``tol``.

**Identifiability.** The 6n + 6 frame errors are not independent. For a revolute joint about the local z axis,
a rotation about z and a translation along z of A_j(0) commute with ``exp(ξ̂_j q_j)`` and can be pushed into
the next frame: 2 redundant directions per revolute joint. A prismatic joint along z commutes with all three
translations and the rotation about z: 4 redundant directions. So the identifiable count is::

    6(n + 1) − 2 n_R − 4 n_P = 4 n_R + 2 n_P + 6

the figure of the kinematic-calibration literature (30 for a 6R arm, 20 for an RRPR SCARA), which the tests
measure as the numerical rank on well-spread data. A tracker-to-base transform adds 6 parameters but no rank:
left-perturbing T_tracker_base is indistinguishable from right-perturbing A_1(0). We therefore fix that gauge by
folding the base frame error into ``T_tracker_base`` (δζ_1 is not a parameter when the base is estimated):
``T_tracker_base`` is then the pose of the *nominal* base frame of the identified robot in the tracker frame.

**Rank-revealing step.** The parameters are rescaled to common units before the SVD: an angular
parameter of 1 rad counts as ``length_scale`` metres (default: the robot's reach), i.e. the angular Jacobian
columns are divided by ``length_scale``, so the singular values of linear and angular directions are comparable
and the truncation does not depend on the choice of units. Singular values below
``rank_rtol · s_max`` (default 1e-6) are treated as zero. The singular values come from the eigenvalues of the
scaled normal matrix, so round-off puts the structurally redundant directions at about sqrt(1e-16) = 1e-8 s_max,
while the smallest identifiable ones on ordinary data sets are ~1e-2 s_max (measured: fanuc-m1000ia, ur10 and
scara4 with 60 random configurations: 1.0e-2 … 2.5e-2 against 1.2e-8 … 1.4e-8); 1e-6 lies well between.
Optional Levenberg-Marquardt damping (``damping``, relative to s_max²) is raised automatically when a step
does not lower the cost.

**Weak directions** (issue 27). A direction of the scaled parameter space with singular value s is estimated with
the noise's standard deviation ``σ / s`` (σ: the tracker noise per coordinate). Where that exceeds ``error_bound``,
a bound on any real geometric error along one direction, the data do not measure it: its step would be noise, and on
narrow data (an ISO-9283 cube at one tool axis) such directions drift by tens of millimetres — the tool length
along the flange axis traded against the base translation — which the points barely see but the compensator turns
into joint motion. So singular values ``s ≤ σ / error_bound`` (defaults 0.05 mm / 5 mm = 0.01) are truncated
like the rank-deficient ones: those directions stay at the start (the nominal). The info counts them
(``weak``, out of the numerical ``rank``: ``identified = rank − weak``) and names each with ``σ / s``. Chosen over a
prior toward the nominal (``weak_rule="prior"``, weight ``(σ / error_bound)²``): on the narrow series both keep the
held-out error and bound the corrections, but the truncation says which directions it held, leaves them exactly at
the nominal (the prior leaves part of the drift), and leaves every fit with no weak direction bit-identical, where the
prior pulls every direction a little (benchmarks/data_speak.py). Its result is the same for bounds of 1-5 mm on the
narrow series; on ordinary data the smallest identified singular value is ~0.3-1, 30× above the threshold.

**What the targets cannot show.** The tool frame's error is one of the parameters, so the points fix it only as
far as the targets span: one target (or targets closer than 1 mm) shows no rotation of the tool about it, 3
directions (the tool's orientation; its position — where the target sits on the flange — is still identified),
and targets on a line show no rotation about that line, 1 direction. These directions are structural, not a
lack of data: the identifiable count is reduced by them (``expected_rank`` in the info), the truncated SVD leaves
them at the starting value (the minimum-norm step), and the info names them in words (``unobservable``). Which
targets count is the set seen in at least one fitting row: the tool frame is the same in every row, so three
targets seen in different rows fix it too. One point on (within :data:`AXIS_TOL` of) the last joint's axis — a
reflector or probe origin on the flange axis — also leaves that axis's two tilts about the point unseen: they are
held too, and named (on arms of 7 or more joints only where the data do not measure them, checked on the fit:
:data:`MEASURED_TILT_MIN_JOINTS`). Held directions are taken out of the Jacobian's image (:func:`_gauss_newton`), so
the robot's redundant parameters cannot carry them back in.

Rows used: ``train`` and unassigned rows; ``include_val=True`` adds the validation rows. "val" rows are a
hold-out a caller chose (:func:`labcal.calibration.fit.fit` makes none by default, so every row is fitted there).
"""

from __future__ import annotations

import math
from typing import Any, NotRequired, TypedDict

import numpy as np

from labcal.calibration.observations import Observations, rigid_fit, target_geometry
from labcal.calibration.tool import split_robot, split_tool
from labcal.compensator import CalibratedRobot
from labcal.kinematics import metric, se3
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel

AXES = ("vx", "vy", "vz", "wx", "wy", "wz")
DEFAULT_RANK_RTOL = 1e-6
# m: the tracker noise per coordinate that the weak-direction rule assumes (the simulation's default tracker; laser
# trackers quote 0.01-0.05 mm over a cell, and a fit's residual of 0.05 mm includes the non-geometric errors too)
TRACKER_NOISE = 0.05e-3
# m (angles times the length scale): a bound on the real geometric error along any one direction of the scaled
# parameter space. Robots' frame errors are tenths of a millimetre to a few millimetres; a direction whose estimate
# the noise alone moves by more than this is not measured by the data, and stays at the nominal. On the narrow
# series of benchmarks/data_speak.py bounds of 1-5 mm hold the same directions (10 mm and above fewer).
ERROR_BOUND = 5e-3


class IdentificationError(ValueError):
    """The data cannot identify the requested parameters (too few configurations, wrong robot …)."""


class TargetNull(TypedDict):
    """:func:`target_null`: the tool rotations the targets cannot show."""

    geometry: str
    count: int
    words: list[str]
    basis: np.ndarray
    tilt: int


class RegisterInfo(TypedDict):
    """:func:`register`'s info (only the first three keys when nothing is estimated)."""

    estimated: list[str]
    iterations: int
    T_tracker_base: np.ndarray
    converged: NotRequired[bool]
    residual_rms: NotRequired[float]
    unobservable: NotRequired[list[str]]


class Identification(TypedDict):
    """What local POE identified (:func:`_identification_info`); :class:`LocalPOEInfo` adds the fit's numbers."""

    rank: int
    weak: int
    identified: int
    weak_directions: list[str]
    weak_space: np.ndarray
    weak_threshold: float
    noise: float
    error_bound: float
    expected_rank: int
    n_params: int
    unidentifiable: int
    null_directions: list[str]
    null_space: np.ndarray
    param_labels: list[str]
    rank_deficient: bool
    target_geometry: str
    unobservable: list[str]
    singular_values: np.ndarray


class LocalPOEInfo(Identification):
    """:func:`fit_local_poe`'s info (its docstring says what each key holds)."""

    delta_zeta: np.ndarray
    std: np.ndarray
    T_tracker_base: np.ndarray
    T_tracker_base_std: np.ndarray
    sigma: float
    iterations: int
    converged: bool
    cost_history: list[float]
    rows: int
    residual_rms: float
    length_scale: float
    warnings: list[str]
    measurement_tool: np.ndarray | None
    measurement_tool_std: np.ndarray | None
    warning: NotRequired[str]


def expected_rank(model: LocalPOEModel) -> int:
    """Identifiable local-POE frame errors: 4 per revolute + 2 per prismatic joint + 6 (module docstring)."""
    return sum(4 if t == REVOLUTE else 2 for t in model.joint_types) + 6  # a joint is revolute or prismatic


STRUCTURAL = {"point": 3, "line": 1, "plane": 0}  # tool rotations a target set cannot show (module docstring)
# m: a single target closer than this to the last joint's axis leaves the tilt of that axis to a lever of a few
# millimetres: a milliradian of tilt moves it by microns, under any tracker's noise, so the data would fit noise
# there (measured on the real UR10 with the probe origin 0.3 mm off joint 6's axis: 50 mrad of tilt, and a
# correction that turned the wrist by 0.4 rad). Holding the tilt at the nominal costs the point at most the true
# tilt times this distance: microns.
AXIS_TOL = 0.02
# Arms with at least this many joints hold those tilts only where the data do not measure them (the weak-direction
# rule's test, made on the fit itself: :func:`_tilts_measured`), not for being within AXIS_TOL alone. A reflector in
# a nest on a 7-joint arm's small flange sits within 20 mm of joint 7's axis, yet 5-20 mm of lever over a few dozen
# poses measures the tilts: held, they left the fit up to 3.8 % above an independent least-squares fit on its
# training points with a rank two short of it, 26 % with four times the geometric errors, where its held-out error
# was up to 25 % worse too (benchmarks/seven_joints_lsq.py: simulated Panda, reflector 15 mm off the axis, or 17.5 mm
# off where the targets file put it on the axis), and the projection that holds them made Gauss-Newton crawl (up to
# the 50-iteration cap instead of 4-5). The same is true of 6-joint arms, which keep the distance
# rule so that their fits stay bit-identical (the fit fingerprint); switching them is a decision of its own.
MEASURED_TILT_MIN_JOINTS = 7


def fitting_rows(obs: Observations, include_val: bool = False) -> np.ndarray:
    """Boolean mask of the rows a model-based fit uses: train + unassigned (+ val when include_val)."""
    allowed = ("train", "", "val") if include_val else ("train", "")
    return np.isin(obs.split, allowed)


def _frame_name(j: int, n: int) -> str:
    if j == -1:
        return "T_tracker_base"
    if j == n:
        return "tool frame A_{n+1}"
    return f"frame A_{j + 1} (before joint {j + 1})"


def _param_labels(frames: list[int], estimate_base: bool, n: int) -> list[str]:
    return [f"{_frame_name(j, n)} {a}" for j in [*frames, *([-1] if estimate_base else [])] for a in AXES]


def _residual_and_jacobian(
    model: LocalPOEModel,
    T_tb: np.ndarray,
    q: np.ndarray,
    targets: np.ndarray,
    measured: np.ndarray,
    frames: list[int],
    estimate_base: bool,
    seen: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Residual (3s,) measured − predicted and its Jacobian (3s, p) w.r.t. the parameters (SI units), s the seen
    points: every point when ``seen`` is None, else the (k, m) cells marked seen (in row order)."""
    k, m = q.shape[0], targets.shape[0]
    initial = model.link_frames(q)
    T = initial[:, model.n]
    p_base = np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]  # (k, m, 3)
    R_tb = T_tb[:3, :3]
    p_meas_frame = np.einsum("ab,kmb->kma", R_tb, p_base) + T_tb[:3, 3]
    residual = (measured - p_meas_frame).reshape(-1) if seen is None else (measured - p_meas_frame)[seen].reshape(-1)
    blocks = []
    if frames:
        # dp_i = [I, −p̂_i] δy in the base frame, rotated into the measurement frame.
        G = np.einsum("ab,kmbc->kmac", R_tb, se3.point_jacobian(p_base))
        Ad = se3.adjoint(initial[:, frames])  # (k, f, 6, 6)
        Jf = np.einsum("kmac,kfcd->kmafd", G, Ad).reshape(k, m, 3, 6 * len(frames))
        blocks.append(Jf.reshape(3 * m * k, -1) if seen is None else Jf[seen].reshape(-1, 6 * len(frames)))
    if estimate_base:
        # Left perturbation exp(δβ̂)·T_tb moves a point m by δβ_v + δβ_ω × m.
        Gb = se3.point_jacobian(p_meas_frame)
        blocks.append(Gb.reshape(3 * m * k, 6) if seen is None else Gb[seen].reshape(-1, 6))
    return residual, np.concatenate(blocks, axis=1)


def _apply(model, T_tb, step, frames, estimate_base):
    dz = np.zeros((model.n + 1, 6))
    if frames:
        dz[frames] = step[: 6 * len(frames)].reshape(len(frames), 6)
    new_model = model.perturbed(dz)
    new_T = se3.exp_se3(step[-6:]) @ T_tb if estimate_base else T_tb
    return new_model, new_T


def _gauss_newton(
    model: LocalPOEModel,
    T_tb: np.ndarray,
    q: np.ndarray,
    targets: np.ndarray,
    measured: np.ndarray,
    frames: list[int],
    estimate_base: bool,
    *,
    length_scale: float,
    max_iter: int,
    tol: float,
    rank_rtol: float = DEFAULT_RANK_RTOL,
    damping: float = 0.0,
    seen: np.ndarray | None = None,
    fixed: np.ndarray | None = None,
    s_min: float = 0.0,
    prior: bool = False,
) -> dict:
    """Iterated, rank-revealing Gauss-Newton / LM. Returns the final model, T_tb and diagnostics.

    seen: (k, m) cells with a measured point, None when every point was seen. fixed: (p, f) parameter directions
    (SI units) the targets cannot show (:func:`target_null`). The point motions they cause (exactly none for a
    rotation about the targets, a lever of millimetres for a near-miss such as a point beside the last joint's
    axis) are removed from the Jacobian's columns, so every parameter combination that acts only through them —
    those directions and whatever the robot's redundant parameters turn them into — is a null direction of every
    step and stays at the start.

    s_min: the weak-direction threshold (module docstring, "Weak directions"): singular values of the scaled
    Jacobian at or below it are held like the rank-deficient ones; ``weak`` counts them (among the numerical rank)
    and ``weak_space`` is their basis (SI units). prior: instead of holding them, pull every direction toward the
    start with the weight ``s_min²`` (a Gaussian prior of std ``error_bound`` on the scaled parameters; the
    alternative the benchmark compares, benchmarks/data_speak.py)."""
    n_params = 6 * len(frames) + (6 if estimate_base else 0)
    # Parameter scaling: angular parameters in units of length_scale metres (unit-consistent truncation).
    scale = metric.parameter_weights(n_params // 6, length_scale)
    F = None if fixed is None or fixed.shape[1] == 0 else fixed / scale[:, None]

    def scaled(J: np.ndarray) -> np.ndarray:
        return _without_image(J * scale, F)

    r, J = _residual_and_jacobian(model, T_tb, q, targets, measured, frames, estimate_base, seen)
    cost = float(r @ r)
    history = [cost]
    lam, converged, iterations = damping, False, 0
    mu, offset = (s_min**2, np.zeros(n_params)) if prior else (0.0, None)  # the prior's weight, scaled offset
    truncate = 0.0 if prior else s_min
    for iterations in range(1, max_iter + 1):  # noqa: B007 - the count is reported
        lam_k, V, keep = _eig(scaled(J), rank_rtol, truncate)
        grad = scaled(J).T @ r if offset is None else scaled(J).T @ r - mu * offset
        g = V[:, keep].T @ grad
        step = scale * (V[:, keep] @ (g / (lam_k[keep] + mu + lam * lam_k[-1])))
        cand_model, cand_T = _apply(model, T_tb, step, frames, estimate_base)
        r_c, J_c = _residual_and_jacobian(cand_model, cand_T, q, targets, measured, frames, estimate_base, seen)
        cost_c = float(r_c @ r_c)
        offset_c = None
        if offset is not None:
            offset_c = offset + step / scale
            cost_c += mu * float(offset_c @ offset_c)
        step_size = float(np.linalg.norm(step / scale))
        if cost_c <= cost * (1 + 1e-12) or step_size < tol:
            model, T_tb, r, J, cost, offset = cand_model, cand_T, r_c, J_c, cost_c, offset_c
            history.append(cost)
            lam = lam / 10 if lam > 1e-12 else 0.0
            if step_size < tol:
                converged = True
                break
        else:
            lam = max(lam * 10, 1e-9)
            if lam > 1e6:
                break
    return dict(
        model=model,
        T_tb=T_tb,
        **_at_solution(scaled(J), r, cost, scale, rank_rtol, truncate),
        iterations=iterations,
        converged=converged,
        cost_history=history,
        residual=r,
    )


def _at_solution(
    Js: np.ndarray, r: np.ndarray, cost: float, scale: np.ndarray, rank_rtol: float, truncate: float
) -> dict[str, Any]:
    """The final linearisation (scaled Jacobian Js, residual r): numerical rank, null and weak spaces (SI units),
    singular values and the residual σ at the solution (:func:`_gauss_newton`; the parameters' standard deviations
    are those of the split chain, :func:`_split_std`)."""
    lam_k, V, keep = _eig(Js, rank_rtol, truncate)
    numeric = np.sqrt(lam_k) > rank_rtol * np.sqrt(lam_k[-1])  # the rank-revealing threshold alone
    weak = numeric & ~keep
    dof = max(r.size - int(keep.sum()), 1)
    return dict(
        rank=int(numeric.sum()),
        singular_values=np.sqrt(np.clip(lam_k, 0, None))[::-1],
        sigma=math.sqrt(cost / dof),
        null_space=V[:, ~numeric] * scale[:, None],
        weak=int(weak.sum()),
        weak_space=V[:, weak] * scale[:, None],
        weak_singular_values=np.sqrt(np.clip(lam_k[weak], 0, None)),
    )


def _without_image(Js: np.ndarray, F: np.ndarray | None) -> np.ndarray:
    """The scaled Jacobian Js (rows, p) with the point motions of the held directions F (p, f; scaled units)
    removed from its columns (:func:`_gauss_newton`); Js itself when nothing is held."""
    if F is None:
        return Js
    U, s, _ = np.linalg.svd(Js @ F, full_matrices=False)
    U = U[:, s > 1e-12 * max(float(np.abs(Js).max()), 1e-300)]
    return Js - U @ (U.T @ Js)


def _tilts_measured(
    out: dict, fit_args: _FitArgs, seen, structural: TargetNull, length_scale: float, rank_rtol: float, s_min: float
) -> bool:
    """Whether the data measure the two held tilts of the last joint's axis (:data:`MEASURED_TILT_MIN_JOINTS`).

    Judged at the fit that held them, where the target sits where the data put it (a targets file may place a
    reflector on the axis that really sits beside it): the tilts are measured when freeing them adds two
    directions that the rank and weak-direction thresholds both keep (``_eig``), i.e. when the weak-direction rule
    itself would not hold them. ``fit_args``: (q, targets, measured, frames, estimate_base) of the fit.
    """
    _, J = _residual_and_jacobian(out["model"], out["T_tb"], *fit_args, seen)
    scale = metric.parameter_weights(J.shape[1] // 6, length_scale)
    basis = structural["basis"] / scale[:, None]
    tilt = structural["tilt"]
    held = _eig(_without_image(J * scale, basis), rank_rtol, s_min)[2].sum()
    freed = _eig(_without_image(J * scale, basis[:, :-tilt]), rank_rtol, s_min)[2].sum()
    return int(freed - held) == tilt


def _free_tilts(structural: TargetNull) -> TargetNull:
    """The structural directions without the last joint's axis tilts (the last columns and words of
    :func:`target_null`)."""
    tilt = structural["tilt"]
    return {
        **structural,
        "count": structural["count"] - tilt,
        "basis": structural["basis"][:, :-tilt],
        "words": structural["words"][:-1],
        "tilt": 0,
    }


def _weak_threshold(noise: float, error_bound: float) -> float:
    """The singular value (scaled Jacobian, unitless) at or below which a direction is weak: noise / error_bound."""
    if not (noise >= 0 and error_bound > 0):
        raise ValueError(f"noise must be ≥ 0 and error_bound > 0 (m), got {noise!r} and {error_bound!r}")
    return float(noise / error_bound)


def tool_std(
    J: np.ndarray, scale: np.ndarray, n_frames: int, sigma: float, X: np.ndarray, fixed=None, rank_rtol: float = 1e-6
) -> np.ndarray:
    """(6,) standard deviations of the measurement tool's position and rotation (m, rad, along tool0's axes) from a
    fit's Jacobian at the split model (right perturbations X·exp(δ) of the tool, turned into tool0 by X's rotation;
    :mod:`labcal.calibration.tool`).

    J: (r, p) the point residuals' Jacobian over the frames' right perturbations (``n_frames`` frames, the tool
    last, then any base parameters), in SI units; scale: (p,) the fit's parameter weights; sigma: the residual σ
    per coordinate (m); fixed: (p, c) directions the targets cannot show (held: NaN where the tool only moves
    along them). The last joint frame's turn about and shift along its axis are the tool's (not parameters).
    """
    held = fixed is not None and fixed.shape[1] > 0
    Js = _without_image(J * scale, fixed / scale[:, None] if held else None)
    keep_cols = np.ones(Js.shape[1], bool)
    last_joint = 6 * (n_frames - 2)
    if n_frames >= 2:
        keep_cols[[last_joint + 2, last_joint + 5]] = False
    lam, V, keep = _eig(Js[:, keep_cols], rank_rtol)
    Vk = V[:, keep] / np.sqrt(lam[keep])
    tool = slice(6 * (n_frames - 1), 6 * n_frames)
    rows = np.flatnonzero(keep_cols[: tool.stop])[-6:]  # the tool's columns among the kept ones
    B = Vk[np.searchsorted(np.flatnonzero(keep_cols), rows)] * scale[tool][:, None]
    R = np.kron(np.eye(2), X[:3, :3])
    cov = sigma**2 * (R @ B) @ (R @ B).T
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    if held:
        # a tool direction the targets cannot show has no variance, not a small one
        unseen = np.abs(fixed[tool]).max(axis=1) > 0
        std[unseen & (np.arange(6) >= 3)] = np.nan
    return std


def _eig(Js: np.ndarray, rank_rtol: float, s_min: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-decomposition of the scaled normal matrix: eigenvalues λ = s² (ascending), vectors, kept mask
    (s above ``rank_rtol · s_max`` and above ``s_min``, the weak-direction threshold).

    The normal matrix (p × p) replaces an SVD of the tall Jacobian: LAPACK's SVD was up to 100× slower on a
    loaded 2-core machine (threaded OpenBLAS), and with s > rank_rtol · s_max, rank_rtol ≥ 1e-7, squaring the
    singular values loses nothing that the threshold keeps.
    """
    lam, V = np.linalg.eigh(Js.T @ Js)
    lam = np.clip(lam, 0.0, None)
    s = np.sqrt(lam)
    keep = (s > rank_rtol * s[-1]) & (s > s_min)
    return lam, V, keep


def _describe_null(null: np.ndarray, labels: list[str], top: int = 2, rotate: bool = True) -> list[str]:
    """One line per unidentifiable direction: its largest components (after a canonicalising rotation unless
    ``rotate`` is False: the weak directions are singular vectors, each with its own singular value)."""
    if null.shape[1] == 0:
        return []
    if not rotate:
        return [_describe_null(null[:, [i]], labels, top)[0] for i in range(null.shape[1])]
    # Rotate the basis so each vector is as concentrated as possible (pivoted QR on the transpose).
    import scipy.linalg

    _, _, piv = scipy.linalg.qr(null.T, pivoting=True)
    pivots = piv[: null.shape[1]]
    B = null.T  # (d, p)
    sub = B[:, pivots]
    basis = np.linalg.solve(sub, B)  # each row has 1 at its pivot and 0 at the others
    lines = []
    for row in basis:
        row = row / np.max(np.abs(row))
        order = np.argsort(-np.abs(row), kind="stable")[:top]
        parts = [f"{row[i]:+.2f}·{labels[i]}" for i in order if abs(row[i]) > 1e-6]
        lines.append(" ".join(parts))
    return lines


def _check(obs: Observations, nominal: LocalPOEModel, rows: np.ndarray, needed: int, what: str) -> None:
    obs.check_robot(nominal.n)
    k = int(rows.sum())
    points = int(obs.seen[rows].sum())
    if 3 * points < needed:
        per_row = points / k if k else float(obs.m)
        raise IdentificationError(
            f"{what} needs at least {needed} measured coordinates but the fitting rows hold {3 * points} "
            f"({k} configuration(s), {points} target point(s) seen × 3): measure at least "
            f"{math.ceil(needed / (3 * max(per_row, 1.0)))} configurations (well spread; several times more to "
            "average the noise)"
        )


def _seen_rows(obs: Observations, rows: np.ndarray) -> np.ndarray | None:
    """The (k_rows, m) seen mask of the fitting rows, None when every point of them was seen (the dense path)."""
    seen = obs.seen[rows]
    return None if seen.all() else seen


def target_null(
    obs: Observations, rows: np.ndarray, n_frames_before_tool: int, n_params: int, model: LocalPOEModel | None = None
) -> TargetNull:
    """The tool rotations the targets seen in the fitting rows cannot show (module docstring).

    Returns {"geometry": "point"|"line"|"plane", "count": directions, "words": [text], "basis": (n_params, count)
    parameter vectors (SI units) of those directions — the tool frame's parameters sit at
    ``6 · n_frames_before_tool``, the last joint's frame A_n just before}. With ``model`` and a single point
    within :data:`AXIS_TOL` of the last (revolute) joint's axis, the two tilts of that axis about the point are
    added: the last joint then barely moves the point, so its axis is seen only through a lever of millimetres.
    """
    used = obs.seen[rows].any(axis=0) if rows.any() else np.ones(obs.m, bool)
    names = [f"t{i + 1}" for i in np.flatnonzero(used)]
    kind, where = target_geometry(obs.targets[used])
    col = 6 * n_frames_before_tool
    basis = np.zeros((n_params, 0))
    # A right perturbation (δv, δω) of the tool frame moves a tool-frame point t by δv + δω × t: a rotation δω
    # about an axis through c with δv = −δω × c leaves every target on that axis where it was.
    if kind == "point":
        basis = _turns(n_params, col, np.eye(3), where)
        words = [
            f"the orientation of the tool (any rotation of the tool frame about target {names[0]}"
            + (f" and the coincident {', '.join(names[1:])}" if len(names) > 1 else "")
            + ", 3 directions): one point per pose shows no rotation of the tool; its orientation stays nominal"
        ]
    elif kind == "line":
        on, u = where
        basis = _turns(n_params, col, u[None], on)
        words = [
            f"the rotation of the tool about the line through {', '.join(names)} (direction "
            f"({u[0]:+.3f}, {u[1]:+.3f}, {u[2]:+.3f}) in the tool frame, 1 direction): targets on a line do not "
            "move when the tool turns about it"
        ]
    else:
        words = []
    if kind == "point" and model is not None and n_frames_before_tool >= 1 and model.joint_types[-1] == REVOLUTE:
        A = model.frames[-1]  # the tool frame in K_n: the last joint turns about K_n's z axis
        p = A[:3, :3] @ where + A[:3, 3]
        off = float(np.hypot(p[0], p[1]))
        if off < AXIS_TOL:
            # A_n right-perturbed by (δv, δω) with δv = −δω × p tilts joint n's axis about the point, which stays on
            # it: no value of q_n moves the point then.
            tilt = _turns(n_params, 6 * (n_frames_before_tool - 1), np.eye(3)[:2], p)
            basis = np.concatenate([basis, tilt], axis=1)
            last = model.n
            words.append(
                f"the tilt of joint {last}'s axis about target {names[0]} (2 directions): the target sits "
                f"{off * 1e3:.1f} mm from that axis, so turning joint {last} hardly moves it; the axis stays nominal "
                f"(moving the target ≥ {AXIS_TOL * 1e3:g} mm off the axis of joint {last} lets the data see it)"
            )
    tilts = basis.shape[1] - STRUCTURAL[kind]  # the axis tilts, the last columns (and the last line of words)
    return {"geometry": kind, "count": basis.shape[1], "words": words, "basis": basis, "tilt": tilts}


def _turns(n_params: int, col: int, axes: np.ndarray, through: np.ndarray) -> np.ndarray:
    """(n_params, len(axes)) parameter vectors turning the frame whose parameters start at ``col`` about each of the
    axes (rows, unit) through the point ``through`` of that frame: δω = w, δv = −w × through."""
    out = np.zeros((n_params, len(axes)))
    for a, w in enumerate(axes):
        out[col : col + 3, a], out[col + 3 : col + 6, a] = -np.cross(w, through), w
    return out


def _without(null: np.ndarray, known: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The part of a null-space basis (SI units) not spanned by the known structural directions, in the scaled
    metric the rank decision uses."""
    if known.shape[1] == 0 or null.shape[1] == 0:
        return null
    N, K = null / scale[:, None], known / scale[:, None]
    Qk, _ = np.linalg.qr(K)
    rest = N - Qk @ (Qk.T @ N)
    U, s, _ = np.linalg.svd(rest, full_matrices=False)
    keep = s > 1e-6 * max(1.0, float(s[0]) if s.size else 1.0)
    return U[:, keep] * scale[:, None]


def _initial_base(obs: Observations, model: LocalPOEModel, rows: np.ndarray) -> np.ndarray:
    """Closed-form T_tracker_base: Kabsch over all seen points, model-predicted (base) vs measured (tracker).

    One target per row is enough once its points over the rows are not collinear (a few spread poses)."""
    seen = obs.seen[rows]
    pred = model.target_points(obs.q[rows], obs.targets)[seen]
    return rigid_fit(pred, obs.points[rows][seen][None])[0]


def register(
    obs: Observations,
    nominal: LocalPOEModel,
    *,
    estimate_tool: bool = False,
) -> tuple[CalibratedRobot, RegisterInfo]:
    """The "registered nominal": nominal geometry, with only T_tracker_base (tracker-frame data) and optionally
    the tool frame A_{n+1} estimated. The reference ("before") every method is compared against.

    Base-frame data without tool estimation return the nominal robot unchanged. Fits the "train" and unassigned
    rows (:func:`fitting_rows`) as :func:`fit_local_poe` does by default.
    """
    rows = fitting_rows(obs)
    estimate_base = obs.frame == "tracker"
    frames = [nominal.n] if estimate_tool else []
    structural = target_null(obs, rows, 0, 6 * len(frames) + 6 * estimate_base) if estimate_tool else None
    needed = 6 * (len(frames) + estimate_base) - (structural["count"] if structural else 0)
    _check(obs, nominal, rows, max(needed, 1), "registration")
    if not frames and not estimate_base:
        robot = CalibratedRobot(nominal=nominal, model=nominal, T_tracker_base=np.eye(4), method="nominal")
        return robot, {"estimated": [], "iterations": 0, "T_tracker_base": np.eye(4)}
    T0 = _initial_base(obs, nominal, rows) if estimate_base else np.eye(4)
    fit_args: _FitArgs = (obs.q[rows], obs.targets, obs.points[rows], frames, estimate_base)
    seen, fixed = _seen_rows(obs, rows), None if structural is None else structural["basis"]
    out = _gauss_newton(
        nominal, T0, *fit_args, length_scale=nominal.reach(), max_iter=50, tol=1e-12, seen=seen, fixed=fixed
    )
    # Robot and tool apart (labcal.calibration.tool): the robot ends at tool0, the fixture is the measurement tool
    # (the registration estimates no joint frame: nothing commutes into the tool).
    model, X = (nominal, None) if out["model"] is nominal else split_tool(nominal, out["model"], canonical=False)
    robot = CalibratedRobot(
        nominal=nominal, model=model, T_tracker_base=out["T_tb"], method="nominal", measurement_tool=X
    )
    info: RegisterInfo = {
        "estimated": (["tool"] if estimate_tool else []) + (["T_tracker_base"] if estimate_base else []),
        "iterations": out["iterations"],
        "converged": out["converged"],
        "T_tracker_base": out["T_tb"],
        "residual_rms": float(np.sqrt(np.mean(out["residual"] ** 2))),
    }
    if structural and structural["count"]:
        info["unobservable"] = structural["words"]
    return robot, info


def fit_local_poe(
    obs: Observations,
    nominal: LocalPOEModel,
    *,
    estimate_base: bool | None = None,
    include_val: bool = False,
    max_iter: int = 50,
    tol: float = 1e-12,
    rank_rtol: float = DEFAULT_RANK_RTOL,
    damping: float = 0.0,
    length_scale: float | None = None,
    start: CalibratedRobot | None = None,
    noise: float = TRACKER_NOISE,
    error_bound: float = ERROR_BOUND,
    weak_rule: str = "truncate",
) -> tuple[CalibratedRobot, LocalPOEInfo]:
    """Identify the local-POE frame errors δζ_j, j = 1 … n+1 (eq. 11) from three-point measurements.

    obs: observations of a robot with ``nominal.n`` joints (base or tracker frame). estimate_base: also estimate
    T_tracker_base (default: when ``obs.frame == "tracker"``; δζ_1 is then folded into it, see the module
    docstring). tol: stop when the step's norm (m, angular parts times ``length_scale``) is below it.
    rank_rtol: relative singular-value threshold of the truncated SVD. damping: initial LM damping relative
    to s_max² (0: pure Gauss-Newton with automatic damping on a failed step). start: a robot to start the
    iteration from instead of the nominal (cross-validation starts each fold from the fit on all rows: the
    iteration converges to the same minimum in a few steps; identified errors stay relative to ``nominal``).
    noise, error_bound: the weak-direction rule (module docstring): a direction whose singular value is at or below
    ``noise / error_bound`` stays where it started (``error_bound=math.inf`` switches the rule off). weak_rule:
    ``"truncate"`` (that rule) or ``"prior"`` (a prior toward the start of std error_bound instead; for comparison).

    Returns the calibrated robot (identified frames, no network) and an info dict:
    ``rank``, ``expected_rank``, ``n_params``, ``unidentifiable`` (count), ``null_directions`` (text: the
    largest components of each unidentifiable direction) and ``null_space`` ((n_params, unidentifiable) basis
    in SI units, rows labelled by ``param_labels``),
    ``target_geometry`` ("point", "line" or "plane": the targets seen), ``unobservable`` (words: the tool
    rotations those targets cannot show, counted out of ``expected_rank``; empty for three non-collinear targets),
    ``weak`` (count of identifiable directions held at the nominal by the weak-direction rule, counted out of
    ``identified`` = ``rank − weak``), ``weak_directions`` (text, as ``null_directions``, each with the noise's
    standard deviation along it), ``weak_space`` ((n_params, weak) basis, SI units), ``weak_threshold``,
    ``delta_zeta`` (n+1, 6) total identified frame errors w.r.t. the nominal frames (zero rows for frames that
    were not estimated), ``std`` (n+1, 6) their standard deviations (from the residual variance and the truncated
    pseudo-inverse; NaN where not estimated), ``T_tracker_base`` (+ ``T_tracker_base_std`` (6,)), ``sigma`` (m,
    residual standard deviation per coordinate), ``iterations``, ``converged``, ``cost_history`` (sum of squared
    residuals, m²), ``rows`` (count), ``residual_rms`` (m).
    """
    if weak_rule not in ("truncate", "prior"):
        raise ValueError(f"weak_rule must be 'truncate' or 'prior', got {weak_rule!r}")
    estimate_base = obs.frame == "tracker" if estimate_base is None else bool(estimate_base)
    rows = fitting_rows(obs, include_val)
    n = nominal.n
    frames = list(range(1 if estimate_base else 0, n + 1))
    labels = _param_labels(frames, estimate_base, n)
    structural = target_null(obs, rows, len(frames) - 1, len(labels), nominal)
    needed = expected_rank(nominal) - structural["count"]
    _check(obs, nominal, rows, needed, f"local-POE identification of {nominal.name or 'the robot'}")
    L = float(length_scale or nominal.reach())
    model0, T0 = _start(obs, nominal, rows, start, estimate_base)
    fit_args: _FitArgs = (obs.q[rows], obs.targets, obs.points[rows], frames, estimate_base)
    options: dict[str, Any] = dict(
        length_scale=L,
        max_iter=max_iter,
        tol=tol,
        rank_rtol=rank_rtol,
        damping=damping,
        seen=_seen_rows(obs, rows),
        s_min=_weak_threshold(noise, error_bound),
        prior=weak_rule == "prior",
    )
    out, structural = _iterate(nominal, model0, T0, fit_args, options, structural)
    return _identified(nominal, obs.q[rows], out, structural, labels, fit_args, options, noise, error_bound)


# _gauss_newton's data arguments: q (k, n), targets (m, 3), measured points (k, m, 3), frames, estimate_base
_FitArgs = tuple[np.ndarray, np.ndarray, np.ndarray, list[int], bool]


def _identified(
    nominal: LocalPOEModel,
    q: np.ndarray,
    out: dict,
    structural: TargetNull,
    labels: list[str],
    fit_args: _FitArgs,
    options: dict[str, Any],
    noise: float,
    error_bound: float,
) -> tuple[CalibratedRobot, LocalPOEInfo]:
    """fit_local_poe's robot and info from the fit ``out``: the chain split into robot and measurement tool, the
    standard deviations of the split chain, the identification in words."""
    _, _, _, frames, estimate_base = fit_args
    L = options["length_scale"]
    n, needed = nominal.n, expected_rank(nominal) - structural["count"]
    robot_model, X, T_split = split_robot(nominal, out["model"], out["T_tb"] if estimate_base else None, q)
    T_tb = out["T_tb"] if T_split is None else T_split
    model = robot_model.replace(frames=np.concatenate([robot_model.frames[:-1], (nominal.frames[-1] @ X)[None]]))
    _, J_split = _residual_and_jacobian(model, T_tb, *fit_args, options["seen"])
    scale = metric.parameter_weights(len(labels) // 6, L)
    X_std = tool_std(J_split, scale, len(frames), out["sigma"], X, structural["basis"], options["rank_rtol"])
    std, split_std = _split_std(J_split, scale, out, frames, n)
    info: LocalPOEInfo = {
        **_identification_info(out, structural, labels, scale, noise, error_bound, needed),
        # the last row: the measurement tool in tool0
        "delta_zeta": se3.log_se3(se3.inv(nominal.frames) @ model.frames),
        "std": std,
        "T_tracker_base": T_tb,
        "T_tracker_base_std": split_std[-6:] if estimate_base else np.zeros(6),
        "sigma": out["sigma"],
        "iterations": out["iterations"],
        "converged": out["converged"],
        "cost_history": out["cost_history"],
        "rows": int(q.shape[0]),
        "residual_rms": float(np.sqrt(np.mean(out["residual"] ** 2))),
        "length_scale": L,
        "warnings": [],
        "measurement_tool": X,
        "measurement_tool_std": X_std,
    }
    if out["rank"] < needed:
        info["warning"] = (
            f"numerical rank {out['rank']} < {needed} identifiable parameters: the configurations do not excite "
            "every identifiable direction; measure more, better spread configurations"
        )
        info["warnings"] = [info["warning"]]  # the key the CLI's stored diagnostics keep
    robot = CalibratedRobot(nominal=nominal, model=robot_model, T_tracker_base=T_tb, method="local-poe",
                            measurement_tool=X, measurement_tool_std=X_std)  # fmt: skip
    return robot, info


def _iterate(
    nominal: LocalPOEModel,
    model0: LocalPOEModel,
    T0: np.ndarray,
    fit_args: _FitArgs,
    options: dict[str, Any],
    structural: TargetNull,
) -> tuple[dict, TargetNull]:
    """Gauss-Newton from (model0, T0) holding the directions the targets cannot show; a 7+ joint arm whose data
    do measure the tool's tilts (from the start, or once the fit moved the target off the axis) frees them.
    Returns the fit (:func:`_gauss_newton`) and the structural record it ended with."""

    def measured_tilts(at: dict) -> bool:  # MEASURED_TILT_MIN_JOINTS: only arms of 7+ joints ask
        return (
            bool(structural["tilt"])
            and nominal.n >= MEASURED_TILT_MIN_JOINTS
            and _tilts_measured(at, fit_args, options["seen"], structural, options["length_scale"],
                                options["rank_rtol"], options["s_min"])
        )  # fmt: skip

    if measured_tilts({"model": model0, "T_tb": T0}):  # seen from the start: never held
        structural = _free_tilts(structural)
    out = _gauss_newton(model0, T0, *fit_args, fixed=structural["basis"], **options)
    if measured_tilts(out):
        # Measured once the target sits where the data put it (the targets file had it on the axis): go on from
        # the fit that held them, with them free.
        structural = _free_tilts(structural)
        held = out
        out = _gauss_newton(held["model"], held["T_tb"], *fit_args, fixed=structural["basis"], **options)
        out["iterations"] += held["iterations"]
        out["cost_history"] = held["cost_history"] + out["cost_history"][1:]
    return out, structural


def _start(
    obs: Observations, nominal: LocalPOEModel, rows: np.ndarray, start: CalibratedRobot | None, estimate_base: bool
) -> tuple[LocalPOEModel, np.ndarray]:
    """Where the iteration starts: ``start``'s chain to the fixture, else the nominal (with a first T_tracker_base
    from a rigid fit when it is estimated)."""
    if start is not None:
        if start.model.n != nominal.n:
            raise ValueError(f"start has {start.model.n} joints, the nominal {nominal.n}")
        return start.measurement_model, np.asarray(start.T_tracker_base, float)
    return nominal, _initial_base(obs, nominal, rows) if estimate_base else np.eye(4)


def _split_std(
    J_split: np.ndarray, scale: np.ndarray, out: dict, frames: list[int], n: int
) -> tuple[np.ndarray, np.ndarray]:
    """(n+1, 6) standard deviations of the split chain's frame parameters (A_n and the tool moved; NaN where not
    estimated) and all of them flat: σ² (JᵀJ)⁺ on the fit's rank."""
    std = np.full((n + 1, 6), np.nan)
    Js = J_split * scale
    lam_s, V_s = np.linalg.eigh(Js.T @ Js)
    Vk = V_s[:, lam_s.size - out["rank"] :] / np.sqrt(lam_s[lam_s.size - out["rank"] :])
    split_std = np.sqrt(np.einsum("ij,ij->i", Vk, Vk)) * out["sigma"] * scale
    std[frames] = split_std[: 6 * len(frames)].reshape(len(frames), 6)
    return std, split_std


def _identification_info(
    out: dict,
    structural: TargetNull,
    labels: list[str],
    scale: np.ndarray,
    noise: float,
    error_bound: float,
    needed: int,
) -> Identification:
    """fit_local_poe's info on what was identified: rank, weak and null directions in words, observability."""
    null_lines = _describe_null(_without(out["null_space"], structural["basis"], scale), labels)
    weak_words = _describe_null(out["weak_space"], labels, 3, rotate=False)
    weak_lines = [
        f"{line} (the noise alone would move it by ±{noise / sv * 1e3:.3g} mm)"
        for line, sv in zip(weak_words, out["weak_singular_values"], strict=True)
    ]
    return {
        "rank": out["rank"],
        "weak": out["weak"],
        "identified": out["rank"] - out["weak"],
        "weak_directions": weak_lines,
        "weak_space": out["weak_space"],
        "weak_threshold": _weak_threshold(noise, error_bound),
        "noise": float(noise),
        "error_bound": float(error_bound),
        "expected_rank": needed,
        "n_params": len(labels),
        "unidentifiable": len(labels) - out["rank"],
        "null_directions": null_lines,
        "null_space": out["null_space"],
        "param_labels": labels,
        "rank_deficient": out["rank"] < needed,
        "target_geometry": structural["geometry"],
        "unobservable": structural["words"],
        "singular_values": out["singular_values"],
    }
