"""Configuration planning: which joint configurations to measure. Pure numpy, no driver calls.

Two planners:

- :func:`random_configurations` draws joint configurations uniformly within the joint limits (optionally a
  fraction of each range about its middle) and keeps those that pass every requested check:

  * **conditioning** — the equivalent-robot Jacobian J_ρ(q) (``model.equivalent_jacobian``, paper eq. 12-15)
    must be well conditioned, because the learned methods invert it per configuration (eq. 21) and a
    near-singular J_ρ turns millimetres of pose error into radians of "joint error". The metric is the 2-norm
    condition number σ_max/σ_min of ``D · J_ρ`` with ``D = diag(1/L, 1/L, 1/L, 1, 1, 1)``: the linear rows (m)
    are divided by the robot's reach L (``model.reach()``, m) so that both halves of the twist are
    dimensionless. Default threshold :data:`DEFAULT_MAX_CONDITION` = 100: it rejects configurations near a
    singularity (e.g. a 6R wrist near q5 = 0) and keeps the typical ones (``benchmarks/planning.py`` counts them);
  and the cell a real robot will accept (``safety``: the robot driver's own :class:`SafetyLimits`, checked with
  the same ``SafetyLimits.within`` its moves are checked with; ``workspace``: the allowed and keep-out boxes of
  the robot profile, on the targets, the tool origin and every link origin; ``facing``: every target's normal
  within its acceptance angle of the tracker, :class:`TargetFacing`).

- :func:`optimal_configurations` picks, from a large pool of such candidates, the subset that maximises the
  observability of the frame errors δζ (paper eq. 8-11) from the measured target points (1..k targets): greedy
  D-optimality (maximise log det of the information matrix on the identifiable subspace) with rank-3m Woodbury updates,
  followed by exchange passes. For a fixed number of configurations this also maximises the O1 index
  (Borm & Menq): ``O1 = (σ_1 ⋯ σ_L)^(1/L) / √m``. By default it then exchanges configurations to minimise the
  average prediction variance over the workspace (I-optimality; benchmarks/planning.py measures both indices): a large
  determinant alone did not lower the held-out error much; the prediction variance is what held-out error
  measures.

:func:`order_for_motion` orders the chosen configurations for the least motion time at the robot's speed and
acceleration caps (nearest neighbour, then 2-opt and or-opt over trapezoidal move times; deterministic).

The identification Jacobian of one configuration is the 3m × 6(n+1) matrix ``G = P · frame_jacobian(q)`` with
``P`` stacking ``[I, −skew(p_i)]`` for the m targets p_i (base frame): δp_i = δv + δω × p_i. The indices count
the points actually measured: with ``seen`` (rows, m) only the rows of the targets seen enter (3 per seen target),
and with a drop-out probability ``dropout`` (one for all targets, or one per target) each target's rows carry the
expected information (1 − p) GᵢᵀGᵢ, so ``rows`` is the expected number of measured coordinates. Its angular
parameter columns are divided by L, so every parameter is a length (m) and the indices do not depend on
whether lengths are in metres or millimetres. Only about 4n + 6 of the 6(n+1) parameters are identifiable
(4 per revolute, 2 per prismatic joint, plus 6); the indices are computed on that subspace
(:func:`identifiable_basis`).

Example::

    >>> from labcal.robots import load
    >>> model = load("ur10").model
    >>> q = random_configurations(model, 5, seed=1)
    >>> q.shape, bool(model.within_limits(q).all())
    ((5, 6), True)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from labcal.drivers.base import SafetyLimits, move_time
from labcal.drivers.workspace import Workspace
from labcal.kinematics.metric import parameter_weights, scaled_condition
from labcal.kinematics.poe import LocalPOEModel
from labcal.kinematics.se3 import point_jacobian
from labcal.robots.joint_map import JointMap

#: Default bound on the length-scaled condition number of J_ρ (see the module docstring).
DEFAULT_MAX_CONDITION = 100.0


class PlanningError(ValueError):
    """The planner cannot satisfy the request (too few configurations pass the checks, bad argument)."""


@dataclass(frozen=True, eq=False)
class TargetFacing:
    """Which way the targets face, and where the tracker is: a reflector (SMR) returns the beam only within its
    acceptance angle about its normal.

    tracker: (3,) tracker origin in the robot base frame, m; normals: (m, 3) target normals in the tool frame
    (normalised here); acceptance: (m,) half-angles, rad, in (0, π/2] (SMRs: about 0.52 to 1.05, ±30° to ±60°).

    >>> f = TargetFacing((0.0, 0.0, 2.0), [[0.0, 0.0, 1.0]], [np.radians(30)])
    >>> f.facing(np.array([[[0.0, 0.0, 0.0]], [[1.5, 0.0, 0.0]]]), np.array([[[0.0, 0.0, 1.0]]] * 2)).tolist()
    [[True], [False]]
    """

    tracker: tuple[float, float, float]
    normals: np.ndarray
    acceptance: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.tracker, dtype=float)
        n = np.asarray(self.normals, dtype=float)
        a = np.asarray(self.acceptance, dtype=float).reshape(-1)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise PlanningError(f"TargetFacing.tracker must be 3 finite numbers (m), got {self.tracker!r}")
        if n.ndim != 2 or n.shape[1] != 3 or not np.all(np.isfinite(n)) or np.any(np.linalg.norm(n, axis=1) < 1e-12):
            raise PlanningError("TargetFacing.normals must be (m, 3) finite non-zero vectors (tool frame)")
        a = np.broadcast_to(a, (n.shape[0],)) if a.size == 1 else a
        if a.shape != (n.shape[0],) or not np.all((a > 0) & (a <= np.pi / 2)):
            raise PlanningError(f"TargetFacing.acceptance must be one or {n.shape[0]} angles in (0, π/2] rad")
        object.__setattr__(self, "tracker", tuple(float(x) for x in t))
        object.__setattr__(self, "normals", n / np.linalg.norm(n, axis=1, keepdims=True))
        object.__setattr__(self, "acceptance", np.array(a, dtype=float))

    def facing(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """points (k, m, 3) and normals (k, m, 3) in the base frame → (k, m) bool: the tracker within acceptance."""
        to_tracker = np.asarray(self.tracker) - np.asarray(points, dtype=float)
        dist = np.maximum(np.linalg.norm(to_tracker, axis=-1), 1e-15)
        cos = np.einsum("kma,kma->km", normals, to_tracker) / dist
        return cos >= np.cos(self.acceptance)

    def visible(self, model: LocalPOEModel, q, targets) -> np.ndarray:
        """(k, m) bool: target i of pose q[k] (targets (m, 3) m, tool frame) faces the tracker."""
        T = model.fk(np.atleast_2d(np.asarray(q, dtype=float)))
        points = np.einsum("kab,mb->kma", T[:, :3, :3], np.asarray(targets, dtype=float)) + T[:, None, :3, 3]
        normals = np.einsum("kab,mb->kma", T[:, :3, :3], self.normals)
        return self.facing(points, normals)


# --------------------------------------------------------------------------------------------------------------
# The cell: joint limits the runner checks, the workspace


def runner_accepts(q, safety: SafetyLimits, joint_map: JointMap | None = None) -> np.ndarray:
    """(k, n) model joints → (k,) bool: the robot driver's own limit check (``safety.within``) accepts the
    controller joints the runner would command."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    return safety.within(q if joint_map is None else joint_map.to_controller(q))


def checked_points(model: LocalPOEModel, q, targets) -> np.ndarray:
    """(k, m + n + 2, 3) m: the points the workspace check covers, base frame: the targets, the tool origin and
    the origin of every link frame (K_1 … K_{n+1})."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    links = model.link_frames(q)[:, :, :3, 3]
    tool = model.fk(q)[:, None, :3, 3]
    return np.concatenate([model.target_points(q, targets), tool, links], axis=1)


# --------------------------------------------------------------------------------------------------------------
# Sampling


def length_scaled_condition(model: LocalPOEModel, q, length_scale: float | None = None) -> np.ndarray:
    """(k,) condition numbers of ``diag(1/L,1/L,1/L,1,1,1) · J_ρ(q)`` (L = ``length_scale``, default reach).

    Infinite for a singular J_ρ.
    """
    L = model.reach() if length_scale is None else float(length_scale)
    return scaled_condition(model.equivalent_jacobian(q, length_scale=L), L)


def random_configurations(
    model: LocalPOEModel,
    count: int,
    *,
    seed: int,
    range_fraction: float = 1.0,
    max_condition: float | None = DEFAULT_MAX_CONDITION,
    targets=None,
    max_tries: int | None = None,
    safety: SafetyLimits | None = None,
    joint_map: JointMap | None = None,
    workspace: Workspace | None = None,
    facing: TargetFacing | None = None,
) -> np.ndarray:
    """Draw ``count`` configurations (count, n) uniformly within the joint ranges that pass every check.

    The cell (what the lab's robot will accept): safety: the robot driver's :class:`SafetyLimits` (``robot.limits``,
    the object the runner's moves are checked against): configurations are drawn inside the model's limits ∩
    these and each is checked with ``safety.within`` on the controller joints ``joint_map`` (``spec.joints``) gives,
    so no planned pose is refused for its joints. workspace: every checked point (:func:`checked_points`) inside
    its allowed box and out of its keep-out boxes. facing: every target's normal within its acceptance angle of
    the direction to the tracker (:class:`TargetFacing`; needs ``targets``).

    range_fraction: keep this fraction of each joint range about its middle. max_condition: bound on
    :func:`length_scaled_condition` (None: no check). targets: (m, 3) m in the tool frame, used by the workspace and
    facing checks (default: the tool origin). max_tries: most configurations drawn (default max(10 000,
    200·count)); :class:`PlanningError`, with the rejection counts, if too few pass.
    Same arguments and seed ⇒ the same configurations.
    """
    if isinstance(count, bool) or not isinstance(count, int | np.integer) or count < 1:
        raise PlanningError(f"count must be a positive integer, got {count!r}")
    ranges, draw_lo, draw_hi, through_map = _sampling_box(model, range_fraction, safety, joint_map)
    if max_condition is not None and not max_condition >= 1:
        raise PlanningError(f"max_condition must be >= 1 (or None), got {max_condition!r}")
    pts = _check_targets(targets, facing)
    workspace = _check_workspace(model, workspace)
    max_tries = max(10_000, 200 * int(count)) if max_tries is None else int(max_tries)
    if max_tries < count:
        raise PlanningError(f"max_tries ({max_tries}) is smaller than count ({count})")
    example: list[str] = []  # what the first pose the workspace refused ran into, for the error message
    checks = _checks(model, ranges, through_map, safety, joint_map, workspace, facing, max_condition, pts, example)
    rejected = dict.fromkeys(("joint limits", "workspace", "facing away", "condition"), 0)

    rng = np.random.default_rng(seed)
    chosen: list[np.ndarray] = []
    have, drawn = 0, 0
    batch = max(256, 4 * int(count))
    while have < count and drawn < max_tries:
        size = min(batch, max_tries - drawn)
        q = rng.uniform(draw_lo, draw_hi, size=(size, model.n))
        drawn += size
        q = joint_map.to_model(q) if through_map and joint_map is not None else q  # (through_map needs a map)
        ok = np.ones(size, dtype=bool)
        for name, every, passes in checks:
            idx = np.arange(size) if every else np.flatnonzero(ok)
            if len(idx):
                good = passes(q[idx])
                rejected[name] += int(np.sum(~good))
                ok[idx[~good]] = False
        chosen.append(q[ok])
        have += len(chosen[-1])
    if have < count:
        why = ", ".join(f"{k}: {v}" for k, v in rejected.items() if v) or "none"
        hint = f" (e.g. {', '.join(example)})" if example else ""
        raise PlanningError(
            f"only {have} of {count} configurations passed after {drawn} draws (max_tries); rejected by {why}{hint}. "
            "Loosen max_condition or the workspace, or raise max_tries."
        )
    return np.concatenate(chosen)[:count]


def joint_ranges(limits, range_fraction: float = 1.0) -> np.ndarray:
    """(n, 2) sampling ranges: ``limits`` (n, 2) [lo, hi] per joint shrunk to ``range_fraction`` about their middle."""
    if not (0 < range_fraction <= 1):
        raise PlanningError(f"range_fraction must be in (0, 1], got {range_fraction!r}")
    lim = np.asarray(limits, dtype=float)
    mid, half = lim.mean(axis=1), 0.5 * (lim[:, 1] - lim[:, 0]) * range_fraction
    return np.stack([mid - half, mid + half], axis=1)


def _sampling_box(model: LocalPOEModel, range_fraction: float, safety, joint_map):
    """(model joint ranges (n, 2), draw low (n,), draw high (n,), whether draws go through the joint map).

    The model's limits, narrowed by the runner's ``safety.joint_limits`` where those are model joints (the safety
    limits carry the joint map, or controller and model joints agree). joint_map: model → controller joints as the
    runner commands them (``spec.joints``). Limits on controller joints through a coupling map are a slanted box in
    model joints: the draws are uniform in the controller box instead (a linear map keeps a uniform density
    uniform), then checked against the model's ranges and by the per-pose check (:func:`runner_accepts`).
    """
    lim = np.array(model.limits, dtype=float)
    through_map = (
        safety is not None and safety.joint_map is None and joint_map is not None and not joint_map.is_identity
    )
    if safety is not None:
        sl = np.asarray(safety.joint_limits, dtype=float)
        if sl.shape != lim.shape:
            raise PlanningError(f"the robot's joint limits are for {sl.shape[0]} joints, the model has {model.n}")
        if through_map:
            ctrl = joint_ranges(sl, range_fraction)
            return joint_ranges(lim, range_fraction), ctrl[:, 0], ctrl[:, 1], True
        lim = np.stack([np.maximum(lim[:, 0], sl[:, 0]), np.minimum(lim[:, 1], sl[:, 1])], axis=1)
        for j in np.flatnonzero(lim[:, 0] > lim[:, 1]):
            raise PlanningError(
                f"joint {j + 1}: the robot's limits [{sl[j, 0]:.6f}, {sl[j, 1]:.6f}] rad and the model's "
                f"[{model.limits[j, 0]:.6f}, {model.limits[j, 1]:.6f}] rad do not overlap; fix the robot profile"
            )
    ranges = joint_ranges(lim, range_fraction)
    return ranges, ranges[:, 0], ranges[:, 1], False


def _check_targets(targets, facing) -> np.ndarray:
    """The target points (m, 3) in the tool frame (the tool origin without targets), checked against ``facing``."""
    pts = np.zeros((1, 3)) if targets is None else np.asarray(targets, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise PlanningError(f"targets must be a finite (m, 3) array in m (tool frame), got shape {pts.shape}")
    if facing is not None and (targets is None or facing.normals.shape[0] != pts.shape[0]):
        raise PlanningError(f"facing has {facing.normals.shape[0]} normals; give targets with as many points")
    return pts


def _check_workspace(model: LocalPOEModel, workspace: Workspace | None) -> Workspace | None:
    """The workspace to check draws against (None when it bounds nothing); refused when it refuses the base."""
    if workspace is None or not workspace.bounds_motion:
        return None
    # The base frame's origin never moves: a keep-out box around it (a table drawn up to z = 0) refuses every
    # pose, which is worth saying outright instead of after thousands of draws.
    base = model.link_frames(np.zeros((1, model.n)))[:, :1, :3, 3]
    if not workspace.admits(base)[0]:
        raise PlanningError(
            f"the workspace refuses the robot's base (link 1 origin {np.round(base[0, 0], 4).tolist()} m): "
            f"{', '.join(workspace.offenders(base[0]))}; a keep-out box must leave the base out (e.g. a "
            "table's top just below it)"
        )
    return workspace


def _checks(model, ranges, through_map, safety, joint_map, workspace, facing, max_condition, pts, example) -> list:
    """The checks of :func:`random_configurations`, cheap ones first: (what a refusal counts as, whether the check
    runs on every draw or only on those still in, test of model-joint poses (k, n) → (k,) bool). through_map: the
    draws are controller joints, mapped to model joints and then checked against the model's ranges. The workspace
    check keeps the reasons of its first refusal in ``example``."""
    checks: list[tuple[str, bool, Callable[[np.ndarray], np.ndarray]]] = []
    if through_map:
        checks.append(("joint limits", True, lambda q: np.all((q >= ranges[:, 0]) & (q <= ranges[:, 1]), axis=1)))
    if safety is not None:
        checks.append(("joint limits", True, lambda q: runner_accepts(q, safety, joint_map)))
    if workspace is not None:

        def admitted(q: np.ndarray) -> np.ndarray:
            points = checked_points(model, q, pts)
            inside = workspace.admits(points)
            if not example and not inside.all():
                example.extend(workspace.offenders(points[np.flatnonzero(~inside)[0]]))
            return inside

        checks.append(("workspace", False, admitted))
    if facing is not None:
        checks.append(("facing away", False, lambda q: facing.visible(model, q, pts).all(axis=1)))
    if max_condition is not None:
        checks.append(("condition", False, lambda q: length_scaled_condition(model, q) <= max_condition))
    return checks


# --------------------------------------------------------------------------------------------------------------
# Observability


def target_weights(m: int, dropout=None) -> np.ndarray:
    """(1, m) weight of each target's information: 1 − p for a drop-out probability p (scalar or (m,)), else ones.

    >>> target_weights(2, dropout=[0.0, 0.5]).tolist()
    [[1.0, 0.5]]
    """
    w = np.ones((1, m))
    if dropout is not None:
        p = np.broadcast_to(np.asarray(dropout, dtype=float), (m,))
        if not np.all((p >= 0) & (p < 1)):
            raise PlanningError(f"dropout must be probabilities in [0, 1) (one, or one per target), got {dropout!r}")
        w = w * (1.0 - p)
    return w


def weighted_rows(G: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(k, 3m, r) Jacobian rows scaled by √weight (weights (k, m) or (1, m)) of their target, so GᵀG is the expected
    information."""
    k, rows, r = G.shape
    m = rows // 3
    root = np.sqrt(np.broadcast_to(weights, (k, m)))
    return (G.reshape(k, m, 3, r) * root[:, :, None, None]).reshape(k, rows, r)


def identification_jacobian(model: LocalPOEModel, q, targets, length_scale: float | None = None) -> np.ndarray:
    """(k, 3m, 6(n+1)) d(target positions)/d(δζ) for targets (m, 3) m in the tool frame.

    Rows: t1 x,y,z, t2 x,y,z … (m). Columns: δζ_1 … δζ_{n+1} as (v, ω); the ω columns are divided by L
    (``length_scale``, default reach) so all parameters are lengths. (Rows of targets not seen: the callers weigh
    them, :func:`weighted_rows`.)
    """
    q2 = np.atleast_2d(np.asarray(q, dtype=float))
    t = np.asarray(targets, dtype=float)
    if t.ndim != 2 or t.shape[1] != 3:
        raise PlanningError(f"targets must be (m, 3) m in the tool frame, got shape {t.shape}")
    L = model.reach() if length_scale is None else float(length_scale)
    p = model.target_points(q2, t)  # (k, m, 3)
    k, m = p.shape[:2]
    A = model.frame_jacobian(q2)  # (k, 6, 6(n+1))
    G = np.einsum("kmab,kbc->kmac", point_jacobian(p), A).reshape(k, 3 * m, -1)
    return G * parameter_weights(model.n + 1, L)


def identifiable_basis(
    model: LocalPOEModel, targets, *, seed: int = 0, count: int = 200, rtol: float = 1e-6
) -> np.ndarray:
    """(6(n+1), r) orthonormal basis of the δζ directions that measurements of these targets can identify
    (fewer for one or two targets: the rotation of the last frame about a single target's point is unobservable).

    The unidentifiable directions are structural (the same for almost every set of configurations), so they are
    found once from ``count`` uniform random configurations: eigenvectors of GᵀG whose singular value
    √λ exceeds rtol·σ_max. Round-off leaves the structural null directions near 1e-8·σ_max, while identifiable
    ones are above 1e-3·σ_max on such data, so the default 1e-6 separates them with margin.
    """
    rng = np.random.default_rng(seed)
    q = rng.uniform(model.limits[:, 0], model.limits[:, 1], size=(count, model.n))
    G = identification_jacobian(model, q, targets)
    lam, V = np.linalg.eigh(np.einsum("kmr,kms->rs", G, G))
    keep = lam > (rtol**2) * lam[-1]
    return V[:, keep][:, ::-1]


def greedy_d_optimal(jacobians: np.ndarray, count: int, *, exchange_passes: int = 2) -> np.ndarray:
    """Indices (count,) of the rows-blocks of ``jacobians`` (k, m, r) whose stacked information ΣGᵀG has the
    largest log det: greedy additions with Woodbury updates, then exchange passes (swap a chosen block for the
    best unchosen one while that increases log det). Deterministic; ties go to the lower index.
    """
    G = np.asarray(jacobians, dtype=float)
    k, _, r = G.shape
    if not 1 <= count <= k:
        raise PlanningError(f"cannot choose {count} of {k} candidates")
    Finv = np.eye(r) / _ridge(G)
    chosen: list[int] = []
    free = np.ones(k, dtype=bool)
    for _ in range(count):
        gain = _logdet_gains(G, Finv)
        gain[~free] = -np.inf
        best = int(np.argmax(gain))
        Finv = _woodbury(Finv, G[best], +1.0)
        chosen.append(best)
        free[best] = False

    def gains(Fminus: np.ndarray, out: int) -> tuple[np.ndarray, float]:
        return _logdet_gains(G, Fminus), _logdet_gains(G[out : out + 1], Fminus)[0] + 1e-9

    return _exchange(G, Finv, chosen, free, exchange_passes, gains)


def exchange_i_optimal(jacobians: np.ndarray, weight: np.ndarray, start, *, passes: int = 3) -> np.ndarray:
    """Improve a selection (indices ``start``) of the blocks of ``jacobians`` (k, m, r) by exchanges that lower
    the average prediction variance ``trace(F⁻¹ W)`` (I-optimality), F = Σ GᵢᵀGᵢ over the chosen blocks and
    ``weight`` W (r, r) the average information of the workspace where predictions matter. Each exchange swaps
    one chosen block for the unchosen one that lowers the criterion most; stops after ``passes`` passes or
    when no swap helps. Deterministic; returns the new indices.
    """
    G = np.asarray(jacobians, dtype=float)
    W = np.asarray(weight, dtype=float)
    k, m, r = G.shape
    chosen = [int(i) for i in start]
    if len(set(chosen)) != len(chosen) or not all(0 <= i < k for i in chosen):
        raise PlanningError(f"start must be distinct indices into {k} candidates, got {chosen}")
    Finv = np.linalg.inv(np.einsum("kmr,kms->rs", G[chosen], G[chosen]) + _ridge(G) * np.eye(r))
    free = np.ones(k, dtype=bool)
    free[chosen] = False

    def gains(Fminus: np.ndarray, out: int) -> tuple[np.ndarray, float]:
        # Adding block g lowers trace(F⁻¹W) by trace(S⁻¹ g F⁻¹WF⁻¹ gᵀ), S = I + g F⁻¹ gᵀ.
        S = np.eye(m) + (G @ Fminus) @ G.transpose(0, 2, 1)
        N = (G @ (Fminus @ W @ Fminus)) @ G.transpose(0, 2, 1)
        gain = np.trace(np.linalg.solve(S, N), axis1=1, axis2=2)
        return gain, gain[out] * (1 + 1e-9)

    return _exchange(G, Finv, chosen, free, passes, gains)


def _ridge(G: np.ndarray) -> float:
    """A tiny ridge (far below any real information) that makes a still rank-deficient F invertible."""
    k, _, r = G.shape
    return 1e-9 * float(np.einsum("kmr,kmr->", G, G)) / (k * r)


def _exchange(G: np.ndarray, Finv: np.ndarray, chosen: list[int], free: np.ndarray, passes: int, gains) -> np.ndarray:
    """Exchange passes over a selection: swap chosen block ``out`` for the free block of largest gain when that gain
    beats the threshold, ``gains(F⁻¹ without out, out)`` → (gain per block (k,), threshold). Stops after ``passes``
    passes or a pass without a swap; updates ``chosen`` and ``free`` in place and returns the indices."""
    for _ in range(passes):
        improved = False
        for pos in range(len(chosen)):
            out = chosen[pos]
            Fminus = _woodbury(Finv, G[out], -1.0)
            gain, threshold = gains(Fminus, out)
            gain[~free] = -np.inf
            best = int(np.argmax(gain))
            if gain[best] > threshold:
                chosen[pos] = best
                free[out], free[best] = True, False
                Finv = _woodbury(Fminus, G[best], +1.0)
                improved = True
        if not improved:
            break
    return np.array(chosen)


def _logdet_gains(G: np.ndarray, Finv: np.ndarray) -> np.ndarray:
    """log det(F + GᵢᵀGᵢ) − log det F = log det(I + Gᵢ F⁻¹ Gᵢᵀ) for every block i."""
    S = np.eye(G.shape[1]) + (G @ Finv) @ G.transpose(0, 2, 1)
    sign, logdet = np.linalg.slogdet(S)
    return np.where(sign > 0, logdet, -np.inf)


def _woodbury(Finv: np.ndarray, g: np.ndarray, sign: float) -> np.ndarray:
    """(F ± gᵀg)⁻¹ from F⁻¹ (r, r) and a block g (m, r)."""
    FG = Finv @ g.T
    S = np.eye(g.shape[0]) * sign + g @ FG
    out = Finv - FG @ np.linalg.solve(S, FG.T)
    return 0.5 * (out + out.T)


CRITERIA = ("d", "i")


def optimal_configurations(
    model: LocalPOEModel,
    count: int,
    *,
    seed: int,
    targets,
    candidates: int = 2000,
    pool: np.ndarray | None = None,
    criterion: str = "i",
    exchange_passes: int = 2,
    dropout=None,
    **sampling,
) -> np.ndarray:
    """(count, n) configurations chosen from a candidate pool to make the identification most accurate.

    criterion ``"d"``: D-optimal (greedy + exchange on log det, i.e. the O1 index). ``"i"`` (default):
    start from the D-optimal set, then exchange to minimise the average prediction variance over the pool
    (``trace(F⁻¹ W)``, the pool standing for the workspace), which is what held-out accuracy
    measures. ``benchmarks/planning.py`` compares both with random sets on the paper's Scenario A (held-out error
    and its spread between simulated robots); the numbers live there and in the README.

    The pool is ``pool`` (k, n) if given, else ``candidates`` configurations from :func:`random_configurations`
    (``seed`` and the ``sampling`` keyword arguments: range_fraction, max_condition, max_tries, safety,
    joint_map, workspace, facing — so every chosen configuration passed the same checks). targets: (m, 3) m
    in the tool frame. dropout: probability that the tracker loses a target (scalar or (m,)): the selection then
    maximises the expected information of the points that will be measured.
    """
    if criterion not in CRITERIA:
        raise PlanningError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    t = np.asarray(targets, dtype=float)
    if pool is None:
        pool = random_configurations(model, candidates, seed=seed, targets=t, **sampling)
    elif sampling:
        raise PlanningError(f"sampling options {sorted(sampling)} have no effect with an explicit pool")
    pool = np.asarray(pool, dtype=float)
    if pool.ndim != 2 or pool.shape[1] != model.n:
        raise PlanningError(f"pool must be (k, {model.n}) joint configurations, got shape {pool.shape}")
    if count > len(pool):
        raise PlanningError(f"cannot choose {count} configurations from a pool of {len(pool)}")
    basis = identifiable_basis(model, t, seed=seed)
    G = identification_jacobian(model, pool, t)
    if dropout is not None:
        G = weighted_rows(G, target_weights(len(t), dropout))
    G = G @ basis
    idx = greedy_d_optimal(G, count, exchange_passes=exchange_passes)
    if criterion == "i":
        W = np.einsum("kmr,kms->rs", G, G) / len(pool)
        idx = exchange_i_optimal(G, W, idx, passes=max(exchange_passes, 1))
    return pool[idx]


# --------------------------------------------------------------------------------------------------------------
# Order: less motion


def move_time_matrix(a, b, speed, acceleration) -> np.ndarray:
    """(k, l) seconds of the joint move from each configuration a (k, n) to each b (l, n): the longest of the
    joints' trapezoidal times (:func:`labcal.drivers.base.move_time`) at ``speed`` rad/s and ``acceleration``
    rad/s² (scalars, or (n,) per-joint caps)."""
    a, b = np.atleast_2d(np.asarray(a, dtype=float)), np.atleast_2d(np.asarray(b, dtype=float))
    out = np.empty((len(a), len(b)))
    for i in range(len(a)):  # row by row: (l, n) at a time keeps 10,000 poses at a few hundred MB
        out[i] = move_time(b - a[i], speed, acceleration).max(axis=1)
    return out


def _path_time(D: np.ndarray, order: np.ndarray) -> float:
    return float(D[order[:-1], order[1:]].sum())


def _nearest_neighbour(D: np.ndarray, first: int) -> np.ndarray:
    order = [first]
    free = np.ones(len(D), dtype=bool)
    free[first] = False
    while free.any():
        here = int(np.argmin(np.where(free, D[order[-1]], np.inf)))  # ties: the lowest index (reproducible)
        order.append(here)
        free[here] = False
    return np.array(order)


def _two_opt(D: np.ndarray, order: np.ndarray, max_passes: int) -> np.ndarray:
    """Reverse segments of an open path while that shortens it (D symmetric, padded: index -1 is a free end, every
    edge to it costs 0); its first pose is free too."""
    order = order.copy()
    k = len(order)
    for _ in range(max_passes):
        improved = False
        for i in range(k - 1):
            # Reverse order[i..j] for every j > i: the edges (i-1, i) and (j, j+1) become (i-1, j) and (i, j+1).
            j = np.arange(i + 1, k)
            p, q = order[i], order[j]
            before = order[i - 1] if i > 0 else -1
            after = np.append(order[i + 2 :], -1)  # order[j + 1], the free end after the last pose
            gain = D[before, p] + D[q, after] - D[before, q] - D[p, after]
            best = int(np.argmax(gain))
            if gain[best] > 1e-9:
                order[i : j[best] + 1] = order[i : j[best] + 1][::-1].copy()
                improved = True
        if not improved:
            break
    return order


def _or_opt(D: np.ndarray, order: np.ndarray, max_passes: int) -> np.ndarray:
    """Move segments of 1 to 3 poses (as they are or reversed) to the place in the path where they cost least,
    while that shortens it. D padded as for :func:`_two_opt`: index -1 stands for either free end of the path."""
    order = order.copy()
    k = len(order)
    for _ in range(max_passes):
        improved = False
        for length in (1, 2, 3):
            for i in range(k - length + 1):
                seg = order[i : i + length]
                prev = order[i - 1] if i > 0 else -1
                nxt = order[i + length] if i + length < k else -1
                removed = D[prev, seg[0]] + D[seg[-1], nxt] - D[prev, nxt]
                rest = np.concatenate([order[:i], order[i + length :]])
                # insert between ends[g] and ends[g + 1] (g = 0 … len(rest)): the rest of the path and its free ends
                ends = np.concatenate([[-1], rest, [-1]])
                old_link = D[ends[:-1], ends[1:]]
                best_gain, best = 1e-9, None
                for piece in (seg, seg[::-1]):
                    gain = removed - (D[ends[:-1], piece[0]] + D[piece[-1], ends[1:]] - old_link)
                    g = int(np.argmax(gain))
                    if gain[g] > best_gain:
                        best_gain, best = float(gain[g]), (g, piece.copy())
                if best is not None:
                    g, piece = best
                    order = np.concatenate([rest[:g], piece, rest[g:]])
                    improved = True
        if not improved:
            break
    return order


def order_for_motion(q, speed, acceleration, *, max_passes: int = 200, starts: int = 4) -> np.ndarray:
    """(k,) permutation of the configurations q (k, n) that shortens the total motion time of visiting them.

    Move times: :func:`move_time_matrix` at ``speed`` / ``acceleration`` (the robot profile's caps). Nearest
    neighbour from every pose, the ``starts`` shortest kept, then 2-opt (segment reversals) and or-opt (segment
    moves) until neither shortens the path or ``max_passes``. No randomness
    and ties go to the lowest index: the same configurations give the same order.

    >>> order_for_motion(np.array([[0.0], [3.0], [1.0], [2.0]]), 0.5, 1.0).tolist()
    [0, 2, 3, 1]
    """
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or len(q) == 0 or not np.all(np.isfinite(q)):
        raise PlanningError(f"q must be a finite (k, n) array of configurations, got shape {q.shape}")
    if len(q) < 3:
        return np.arange(len(q))
    D = move_time_matrix(q, q, speed, acceleration)
    padded = np.pad(D, (0, 1))  # a last row and column of zeros: index -1, the path's free ends
    candidates = [_nearest_neighbour(D, first) for first in range(len(q))]
    times = np.array([_path_time(D, c) for c in candidates])
    best: np.ndarray | None = None
    for c in np.argsort(times, kind="stable")[:starts]:
        order = candidates[int(c)]
        for _ in range(max_passes):  # alternate until neither improves
            before = _path_time(D, order)
            order = _or_opt(padded, _two_opt(padded, order, max_passes), max_passes)
            if _path_time(D, order) >= before - 1e-9:
                break
        if best is None or _path_time(D, order) < _path_time(D, best) - 1e-9:
            best = order
    return best
