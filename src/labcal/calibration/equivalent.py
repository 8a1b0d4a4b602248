"""Observations of the joint motion errors of an equivalent robot (paper eq. 12-14, 18, 21).

The equivalent robot explains every pose error of the real robot by joint motion errors δρ (max(n, 6) per
configuration: the n actuated joints, then 6 − n virtual joints for n < 6; a redundant arm's n > 6 joints and no
virtual ones) of a *base* robot — the nominal model for the paper's method, the identified local-POE model for the
hybrid. At configuration k:

- the base robot predicts target points p̂_i (base frame) and, through ``T_tracker_base``, in the observation frame;
- δp_k = measured − predicted (3m,), rotated back into the base frame (so it matches eq. 18 in K0);
- ``P_k = [[I, r̂_1], …, [I, r̂_m]]`` with r_i = −p̂_i, the vector from target i to the origin of K0:
  a twist δy = (δv, δω) moves a point p by δv + δω × p = δv + r̂ δω (eq. 18);
- J_ρ,k is the base robot's equivalent Jacobian (eq. 14, virtual joints for n < 6; (6, n) for n > 6);
- the observation is δρ_k = (P_k J_ρ,k)^+ δp_k (eq. 21), computed once.

**Redundant arms (n > 6).** P J_ρ is (3m, n) with rank at most 6: a joint-error direction in the null space of
J_ρ (the self-motion, e.g. a 7-joint arm's elbow turning about the shoulder-wrist line) moves no point, so no
measurement says anything about it. δρ_k is then the minimum-norm solution in the length-scaled metric, truncated
at the row's rank (6 with three non-collinear targets, fewer with fewer points, as below), i.e. the δρ with no
self-motion component. Minimum norm rather than a regularised (Tikhonov) solution because (1) the null-space
component is exactly unobservable, so the only honest choice is to add none of it, and it changes no predicted
pose (J_ρ δρ is the same); (2) a ridge term would also shrink the observed directions, biasing every δρ towards
zero by an amount that depends on an arbitrary λ, whereas the directions that are poorly (not un-) observed near a
singularity are already handled by the condition filter below, for every n alike; (3) the compensator's redundant
steps are minimum norm too (:mod:`labcal.compensator.solve`), so the learned δρ never asks for a self-motion the
user did not command. Rows of a redundant arm therefore always take the truncated path below; their ``rank`` is
what the points see (at most 6) and their ``condition`` is σ_max / σ_rank.

**Fewer than three targets in a row.** Eq. (21) uses the rows of P that the pose has: a target the tracker did not
see gets zero rows in P J_ρ and in δp (so it adds nothing to any fit built on them: the joint series' normal
equations, the network's task loss). Three non-collinear points fix all six joint errors; two fix five (a
rotation about the line through them moves neither), one fixes three. Such a row's ``rank`` is 5 or 3 and its
δρ is the minimum-norm solution — only the part of δρ the points see, not δρ itself — so a network trained on
these observations must use the point loss (eq. 20; :func:`labcal.calibration.ann.fit_ann` switches to it and
says so). Its ``condition`` is σ_max / σ_rank of P J_ρ S: the conditioning of what the points can see.

**Condition filter.** Near a singular configuration (a wrist at q5 ≈ 0, an elbow stretched out) J_ρ loses rank
and eq. 21 turns millimetres of noise into radians of "joint error" (DESIGN.md section 1). Each observation's
``condition`` is cond(P J_ρ S) in a length-scaled metric: S = diag(1 for revolute and virtual joints, L for
prismatic joints), L the base robot's ``length_scale``; δp stays in metres. So every δρ coordinate is measured
in the same unit (radians, or metres divided by the reach L — the virtual joints of
:meth:`~labcal.kinematics.poe.LocalPOEModel.equivalent_jacobian` already are), and the number is the ratio of the
largest to the smallest noise amplification over all joint-error directions. It includes a floor set by the
target geometry (rotations are seen through the target spacing, a few decimetres against a reach of metres).

Observations above ``max_condition`` are dropped (with the reason recorded); between ``soft_condition`` and
``max_condition`` they can be down-weighted by (soft / cond)².

Defaults: :data:`MAX_CONDITION` = 1e3 (drop) and :data:`SOFT_CONDITION` = 1e2 (weight (1e2 / cond)² above it, an
inverse-variance weight: the noise of δρ grows in proportion to the condition). Measured on 20,000 uniform random
configurations over the full joint ranges, ``ErrorSpec.paper()`` errors and 0.05 mm tracker noise, targets
(0.1, 0, 0), (0, 0.15, 0), (0, 0, 0.2) m in the tool frame:

=================  ========  ==========  =============  ==========================================
robot              median    > 1e2       > 1e3 dropped  median δρ observation error (cond band)
=================  ========  ==========  =============  ==========================================
fanuc-m1000ia      58        32 %        3.7 %          0.2 mrad (< 30), 1.4 (300-1e3), 4.9 (1e3-3e3)
ur10               31        19 %        2.4 %          0.25 mrad (< 30), 3.6 (300-1e3), 11 (1e3-3e3)
=================  ========  ==========  =============  ==========================================

Above 1e3 the observation error is over twenty times its value at well-conditioned configurations, and the true
δρ itself exceeds 0.07 rad (the equivalent robot's joint errors diverge at a singularity, so they are not even
small there). A smaller target triangle raises every condition number: with targets (0, 0, 0), (0.1, 0, 0),
(0, 0.07, 0) m the medians are 150 / 75 and 8.8 % / 4.9 % of random configurations are dropped.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass
from typing import NotRequired, TypedDict

import numpy as np

from labcal.calibration.metrics import statistics
from labcal.calibration.observations import Observations, seen_patterns, target_geometry
from labcal.compensator import CalibratedRobot, Network
from labcal.kinematics import metric, se3

MAX_CONDITION = 1e3
SOFT_CONDITION = 1e2
_PROBE_STEP = 0.1  # rad (revolute) or fraction of the reach (prismatic): the move that shows which joint causes it


class DroppedCause(TypedDict):
    """One group of :meth:`JointErrorObservations.causes`."""

    rows: int
    joint: int
    lost: list[int]
    value: float
    cause: str


class FilterSummary(TypedDict):
    """:meth:`JointErrorObservations.summary`."""

    count: int
    dropped: int
    dropped_reasons: dict[str, int]
    downweighted: int
    condition: dict[str, float]
    rank_below_6: NotRequired[int]


@dataclass(frozen=True, eq=False)
class JointErrorObservations:
    """Eq. 21 for every configuration of an :class:`Observations`, plus the condition filter's verdict.

    q: (k, n) joints; delta_p: (k, 3m) measured − predicted target positions in the base frame (m; 0 for a
    target the row did not see); PJ: (k, 3m, N) P_k J_ρ,k with N = max(n, 6) joint motion errors (zero rows for
    unseen targets); delta_rho: (k, N) observed joint motion errors (rad, m for prismatic joints; the minimum-norm
    solution where ``rank`` < N, so always for n > 6; NaN where PJ is numerically singular); condition: (k,)
    cond(P J_ρ S) (see module docstring);
    weight: (k,) 0 for dropped rows, (soft/cond)² in the down-weighted band, else 1;
    reason: (k,) "" for kept rows, else why the row was dropped;
    targets: (m, 3) the targets in the tool frame (to name the cause of dropped rows, :meth:`causes`);
    seen: (k, m) the targets each row saw (None: all); rank: (k,) the joint-error directions the row's points
    can see (6, 5 with two points or a line of them, 3 with one; None: 6 everywhere, n ≤ 6 only).
    """

    q: np.ndarray
    delta_p: np.ndarray
    PJ: np.ndarray
    delta_rho: np.ndarray
    condition: np.ndarray
    weight: np.ndarray
    reason: np.ndarray
    targets: np.ndarray
    seen: np.ndarray | None = None
    rank: np.ndarray | None = None

    @property
    def kept(self) -> np.ndarray:
        return self.weight > 0

    @property
    def partial(self) -> bool:
        """Some row cannot see all six joint-error directions (rank < 6)."""
        return self.rank is not None and bool(np.any(self.rank < 6))

    def causes(self, base: CalibratedRobot) -> list[DroppedCause]:
        """Name the cause of every row the condition filter dropped, grouped into one entry per cause.

        For each dropped row: the joints whose motion errors the row cannot see (the largest components of the
        smallest right singular vector of P J_ρ S — e.g. joints 4 and 6 when a wrist's axes align), and the joint
        whose value puts the robot there (the joint whose move by 0.1 rad lowers the condition number most, e.g.
        joint 5 of a UR10 at q5 ≈ 0). Returns ``[{"rows": count, "joint": j (1-based, 0 if none found),
        "lost": [joints], "value": median q_j of the rows, "cause": text}]``, largest group first; the text reads
        like "joint 5 near a singular value (q5 ≈ 0.002): joints 4, 6 cannot be told apart" (the joints lost in
        most rows of the group).
        """
        dropped = np.flatnonzero(~self.kept)
        if dropped.size == 0:
            return []
        scale = metric_scale(base)
        n = base.n
        q = self.q[dropped]
        _, _, Vt = np.linalg.svd(self.PJ[dropped] * scale, full_matrices=False)
        if self.rank is None:
            null = np.abs(Vt[:, -1, :])  # (d, 6): n <= 6 here (a redundant arm's rows always carry their rank)
        else:  # the weakest direction the row's points can see
            null = np.abs(np.take_along_axis(Vt, (self.rank[dropped] - 1)[:, None, None], axis=1)[:, 0])
        cond0 = self.condition[dropped]
        best_gain = np.ones(dropped.size)
        culprit = np.zeros(dropped.size, dtype=int)
        seen = np.ones((dropped.size, len(self.targets)), bool) if self.seen is None else self.seen[dropped]
        rank = None if self.rank is None else self.rank[dropped]
        for j in range(n):
            step = _PROBE_STEP * (_length_scale(base) if base.model.joint_types[j] == "prismatic" else 1.0)
            moved = q.copy()
            moved[:, j] += step
            cond = condition_numbers(_masked_pj(base, moved, self.targets, seen)[1], scale, rank)
            with np.errstate(divide="ignore", invalid="ignore"):
                gain = np.where(np.isfinite(cond0), cond0 / cond, np.where(np.isfinite(cond), np.inf, 1.0))
            better = gain > np.maximum(best_gain, 2.0)
            best_gain[better], culprit[better] = gain[better], j + 1
        lost_sets = [np.flatnonzero(null[i] > 0.3 * null[i].max()) + 1 for i in range(dropped.size)]
        out: list[DroppedCause] = []
        for joint in sorted(set(culprit.tolist())):
            rows = np.flatnonzero(culprit == joint)
            counts = np.bincount(np.concatenate([lost_sets[i] for i in rows]), minlength=equivalent_joints(n) + 1)
            lost = [int(j) for j in np.flatnonzero(counts >= max(1, len(rows) / 2))]  # lost in most of these rows
            names = ", ".join(str(j) if j <= n else f"virtual {j}" for j in lost)
            what = (
                f"joints {names} cannot be told apart" if len(lost) > 1 else f"the error of joint {names} is not seen"
            )
            value = float(np.median(q[rows, joint - 1])) if joint else float("nan")
            if joint:
                cause = f"joint {joint} near a singular value (q{joint} ≈ {value:.2g}): {what}"
            else:
                cause = f"ill-conditioned configuration or target geometry: {what}"
            out.append({"rows": len(rows), "joint": int(joint), "lost": lost, "value": value, "cause": cause})
        out.sort(key=lambda c: (-c["rows"], c["joint"], c["lost"]))
        return out

    def summary(self) -> FilterSummary:
        """Counts of dropped rows by reason and condition statistics of all rows (JSON-friendly); with fewer than
        three targets in some row also ``rank_below_6``, the rows whose δρ is a minimum-norm solution."""
        reasons = dict(Counter(str(r) for r in self.reason[~self.kept]))
        finite = self.condition[np.isfinite(self.condition)]
        stats = statistics(finite, ("min", "median", "p95", "max")) if finite.size else {}
        out: FilterSummary = {
            "count": len(self.q),
            "dropped": int(np.sum(~self.kept)),
            "dropped_reasons": reasons,
            "downweighted": int(np.sum(self.kept & (self.weight < 1.0))),
            "condition": stats,
        }
        if self.rank is not None:  # rows whose δρ is a minimum-norm solution (module docstring)
            out["rank_below_6"] = int(np.sum(self.rank < 6))
        return out


def learned_robot(base: CalibratedRobot, network: Network, q: np.ndarray, method: str) -> CalibratedRobot:
    """``base`` with a learned joint-error term, calibrated over the joint ranges of the fitting rows q (k, n): every
    row the fit was given, including the ones the condition filter kept out of training — the ranges say where the
    calibration data lie, and the learned term is smooth across the dropped (singular) points."""
    ranges = np.stack([q.min(axis=0), q.max(axis=0)], axis=1)
    return dataclasses.replace(base, network=network, joint_ranges=ranges, method=method, validity=None)


def point_matrix(points: np.ndarray) -> np.ndarray:
    """P of eq. (18): predicted points (k, m, 3) in the base frame → (k, 3m, 6), δp = P δy with δy = (δv, δω)."""
    points = np.asarray(points, dtype=float)
    return se3.point_jacobian(points).reshape(points.shape[0], -1, 6)  # the m (3, 6) blocks stacked per row


def equivalent_joints(n: int) -> int:
    """The number of joint motion errors of an n-joint robot's equivalent robot: max(n, 6) (eq. 12-14).

    >>> equivalent_joints(4), equivalent_joints(6), equivalent_joints(7)
    (6, 6, 7)
    """
    return max(int(n), 6)


def metric_scale(base: CalibratedRobot) -> np.ndarray:
    """(N,) column scaling S of the length-scaled metric (N = max(n, 6)): L for prismatic actuated joints, 1
    otherwise."""
    return metric.joint_weights(base.model.joint_types, _length_scale(base), size=equivalent_joints(base.n))


def _length_scale(base: CalibratedRobot) -> float:
    """The robot's metres per radian (CalibratedRobot always sets it: the nominal's reach unless given)."""
    assert base.length_scale is not None
    return base.length_scale


def condition_numbers(PJ: np.ndarray, scale: np.ndarray, rank: np.ndarray | None = None) -> np.ndarray:
    """(k, 3m, N) P J_ρ and (N,) column scaling → (k,) condition numbers (inf where rank deficient).

    rank: (k,) the directions each row can see (module docstring); the condition is then σ_max / σ_rank."""
    sv = np.linalg.svd(PJ * scale, compute_uv=False)
    low = sv[:, -1] if rank is None else sv[np.arange(len(sv)), np.asarray(rank, int) - 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(low > 0, sv[:, 0] / np.where(low > 0, low, 1.0), np.inf)


_RANK = {"point": 3, "line": 5, "plane": 6}  # joint-error directions the points of a row can see


def row_ranks(targets: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(k,) joint-error directions each row's seen targets can see: 6, 5 (a line of targets) or 3 (one point)."""
    rank = np.full(seen.shape[0], 6)
    for pattern, rows in seen_patterns(seen):
        rank[rows] = _RANK[target_geometry(targets[pattern])[0]]
    return rank


def _masked_pj(base: CalibratedRobot, q: np.ndarray, targets: np.ndarray, seen: np.ndarray):
    """(predicted points (k, m, 3), P J_ρ (k, 3m, N)) with zero rows for the targets a row did not see."""
    predicted = base.predict_points(q, targets)
    PJ = np.einsum("kab,kbc->kac", point_matrix(predicted), base.equivalent_jacobian(q))
    PJ[~np.repeat(seen, 3, axis=1)] = 0.0
    return predicted, PJ


def _min_norm(PJ: np.ndarray, delta_p: np.ndarray, rank: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(k, N) minimum-norm solutions of P J_ρ δρ = δp in the length-scaled metric, truncated at each row's rank."""
    U, s, Vt = np.linalg.svd(PJ * scale, full_matrices=False)
    keep = np.arange(s.shape[1])[None, :] < rank[:, None]
    coef = np.where(keep, np.einsum("kai,ka->ki", U, delta_p) / np.where(keep, s, 1.0), 0.0)
    return scale * np.einsum("kij,ki->kj", Vt, coef)


def joint_error_observations(
    obs: Observations,
    base: CalibratedRobot,
    *,
    max_condition: float | None = MAX_CONDITION,
    soft_condition: float | None = None,
) -> JointErrorObservations:
    """Observe the joint motion errors δρ of ``base``'s equivalent robot at every configuration (eq. 18, 21).

    base: the robot whose equivalent robot is observed; it must not carry a network already (its δρ would be
    double-counted). ``max_condition=None`` keeps every finite observation; ``soft_condition`` (< max_condition)
    turns on down-weighting.
    """
    obs.check_robot(base.n)
    if base.network is not None:
        raise ValueError("base already has a network; observe joint motion errors of a network-free base robot")
    if max_condition is not None and not max_condition > 1.0:
        raise ValueError(f"max_condition must be > 1, got {max_condition}")
    if soft_condition is not None:
        if not soft_condition >= 1.0:
            raise ValueError(f"soft_condition must be >= 1, got {soft_condition}")
        if max_condition is not None and soft_condition > max_condition:
            raise ValueError(f"soft_condition {soft_condition} exceeds max_condition {max_condition}")
    q, k, m, seen = obs.q, obs.k, obs.m, obs.seen
    # Every row sees the same three non-collinear targets and P J_ρ is square: eq. (21) as the paper writes it.
    # Otherwise (a redundant arm's P J_ρ always has a null space, the self-motion; fewer targets see fewer
    # directions) each row's truncated minimum-norm solution.
    dense = base.n <= 6 and obs.complete and m == 3 and target_geometry(obs.targets)[0] == "plane"
    rank = None if dense else row_ranks(obs.targets, seen)
    N = equivalent_joints(base.n)
    predicted, PJ = _masked_pj(base, q, obs.targets, seen) if k else (np.zeros((0, m, 3)), np.zeros((0, 3 * m, N)))
    R, t = base.T_tracker_base[:3, :3], base.T_tracker_base[:3, 3]
    in_obs_frame = np.einsum("ab,kmb->kma", R, predicted) + t
    # Residuals are formed where the data live, then expressed in K0 where eq. (18) holds.
    diff = np.where(seen[..., None], obs.points - in_obs_frame, 0.0)
    delta_p = np.einsum("ba,kmb->kma", R, diff).reshape(k, 3 * m)
    scale = metric_scale(base)
    condition = condition_numbers(PJ, scale, rank) if k else np.zeros(0)
    reason, weight, ok = _screen(condition, max_condition, soft_condition)
    delta_rho = np.full((k, N), np.nan)
    if np.any(ok) and rank is None:  # dense
        delta_rho[ok] = np.einsum("kab,kb->ka", np.linalg.pinv(PJ[ok]), delta_p[ok])
    elif np.any(ok) and rank is not None:
        delta_rho[ok] = _min_norm(PJ[ok], delta_p[ok], rank[ok], scale)
    return JointErrorObservations(
        q, delta_p, PJ, delta_rho, condition, weight, reason, obs.targets, None if dense else seen, rank
    )


def _screen(condition: np.ndarray, max_condition, soft_condition) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row, from the condition of P·J_ρ: (reason it is dropped or "", weight, finite and not singular).

    A singular row is dropped; above ``max_condition`` it is dropped with that reason; above ``soft_condition`` its
    weight falls as (soft / condition)², so near-singular observations count less instead of wrecking the fit."""
    reason = np.full(len(condition), "", dtype=object)
    weight = np.ones(len(condition))
    singular = ~np.isfinite(condition) | (condition > 1e12)
    reason[singular] = "singular P·J_rho (rank deficient)"
    if max_condition is not None:
        high = ~singular & (condition > max_condition)
        reason[high] = f"condition > {max_condition:g}"
    weight[reason != ""] = 0.0
    if soft_condition is not None:
        band = (weight > 0) & (condition > soft_condition)
        weight[band] = (soft_condition / condition[band]) ** 2
    return reason, weight, ~singular
