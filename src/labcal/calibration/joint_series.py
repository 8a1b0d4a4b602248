"""A structured learned term: per-joint Fourier series of the equivalent robot's joint motion errors.

What remains after a model-based (local-POE) identification of a real arm is dominated by errors that depend on
each joint's own angle: transmission errors of the reducers, encoder and bearing eccentricity. They repeat once
per revolution of the joint, so each actuated joint j gets a Fourier series of its own angle θ_j
(:func:`labcal.features.harmonics`)::

    δρ_j(q) = c_j + Σ_{h=1..H} a_jh sin(h θ_j) + b_jh cos(h θ_j)        j = 1 … n  (virtual joints: 0)

**Fit in task space, closed form.** The equivalent robot moves target i by δp = P J_ρ δρ (eq. 14, 18), linear in
the coefficients: the design column of coefficient (j, h) is ``P_k J_ρ,k[:, j] · basis_h(θ_kj)``. The
coefficients minimise ``Σ_k ||δp_k − P_k J_ρ,k δρ(q_k)||² + λ s Σ h^p (a_jh² + b_jh²)`` — ridge regression
with a smoothness penalty that grows with the order (p = ``penalty_power``; the constant c_j is penalised like
order 1), s the mean diagonal of the normal matrix so λ is unit-free. Unlike eq. (21) no pseudo-inverse of
P J_ρ is formed, so near-singular configurations simply carry less information instead of producing huge
"observed" joint errors.

**Model selection.** The number of harmonics H (from ``harmonics`` candidates) and λ (from ``lambdas``) are
chosen by k-fold cross-validation on the training rows (seeded fold assignment): the criterion is the mean
over held-out configurations of the RMS target-position residual. Each (fold, H) needs one symmetric
eigen-decomposition; every λ then costs a matrix-vector product. The final coefficients are refitted on all
training rows. Validation rows are never fitted on: their error is reported, and the decision to keep the series
at all (the hybrid's gate) belongs to the caller.

**Gravity terms.** Optionally each joint's error also gets a linear term in the direction of gravity seen from
every link frame (the compensator's ``gravity`` feature, 3n numbers): for a rigid arm every gravity torque is
linear in them, so joint compliance under gravity, δρ_j = c_j τ_j(q), is exactly representable. They are
penalised like order 1. By default cross-validation decides whether to include them, at the chosen H.

**Virtual joints** (robots with n < 6) are not modelled: their errors stay zero. The separable series is a model
of the actuated joints' transmissions; a lower-mobility robot's out-of-plane errors are geometric and belong to
the local-POE stage.

**Redundant arms** (n > 6): every joint gets its series, fitted in task space like any other. The self-motion
(the null space of J_ρ) moves no point, so the data cannot split an error between joints that only differ by it;
the ridge penalty then picks the smallest coefficients that explain the points, and a direction no row sees stays
at zero. Nothing here forms (P J_ρ)⁺, so no minimum-norm choice is needed (see
:mod:`labcal.calibration.equivalent` for the network's).

The result is an ordinary :class:`~labcal.compensator.CalibratedRobot` whose ``network`` is a
:class:`~labcal.compensator.Network` without hidden layer: one weight matrix (N, 2nH), N = max(n, 6) joint motion
errors, that is zero outside each joint's own block, biases c_j, features ``("harmonics:H",)``.

Example (not a doctest: it needs a data set)::

    base, _ = fit_local_poe(obs, nominal)
    robot, info = fit_joint_series(obs, base, seed=0)
    info["harmonics"], info["lambda"], info["val_error"]       # chosen H, λ; mean position error (m) on val
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypedDict

import numpy as np

from labcal import features as feature_lib
from labcal.calibration.equivalent import equivalent_joints, joint_error_observations, learned_robot
from labcal.calibration.metrics import primary_error, validation_error
from labcal.calibration.observations import ObservationError, Observations
from labcal.compensator import CalibratedRobot, Network, input_features

DEFAULT_HARMONICS = (8, 16, 24, 32, 48)
DEFAULT_LAMBDAS = tuple(10.0 ** np.arange(-7.0, 1.01, 0.5))


# fit_joint_series's info (saved with a fit); a call, as "lambda" is a keyword.
SeriesInfo = TypedDict(
    "SeriesInfo",
    {
        "method": str,
        "harmonics": int,
        "gravity": bool,
        "lambda": float,
        "penalty_power": float,
        "candidates": list[int],
        "lambdas": list[float],
        "folds": int,
        "seed": int,
        "cv": dict[str, list[float]],
        "cv_error": float,
        "train_rows": int,
        "val_rows": int,
        "train_error": float,
        "val_error": float,
        "error_metric": str,
        "amplitudes": np.ndarray,
        "constants": np.ndarray,
        "virtual_joints": str,
    },
)


def _check_options(harmonics, penalty_power, lambdas, folds) -> tuple[tuple[int, ...], tuple[float, ...]]:
    cands = (harmonics,) if isinstance(harmonics, (int, np.integer)) else tuple(harmonics)
    if not cands:
        raise ValueError("harmonics must be an int or a non-empty sequence of ints")
    for h in cands:
        if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or not 1 <= h <= feature_lib.MAX_HARMONICS:
            raise ValueError(f"harmonics must be integers in 1 … {feature_lib.MAX_HARMONICS}, got {h!r}")
    lams = tuple(float(x) for x in (DEFAULT_LAMBDAS if lambdas is None else lambdas))
    if not lams or not all(math.isfinite(x) and x > 0 for x in lams):
        raise ValueError(f"lambdas must be positive finite numbers, got {lambdas!r}")
    if not (math.isfinite(penalty_power) and penalty_power >= 0):
        raise ValueError(f"penalty_power must be >= 0, got {penalty_power!r}")
    if int(folds) != folds or folds < 2:
        raise ValueError(f"folds must be an integer >= 2, got {folds!r}")
    return tuple(sorted({int(h) for h in cands})), tuple(sorted(set(lams)))


class _Design:
    """Normal-equation pieces of the task-space fit, accumulated per configuration.

    Per configuration k: C_k = (P J)_kᵀ (P J)_k restricted to the n actuated joints (n × n), g_k = (P J)_kᵀ δp_k,
    and the basis Φ_k (n, m) with m = 1 + 2 H_max columns per joint (constant, then sin/cos by order). The
    normal matrix of any row subset is Σ_k (Φ_k ⊗ …) assembled block by block, which costs n²m² per row instead
    of 9 n² m² for the explicit design matrix.
    """

    def __init__(self, PJ: np.ndarray, delta_p: np.ndarray, basis: np.ndarray, points: np.ndarray | None = None):
        """points: (k,) target points each row saw when some row missed targets (their rows of PJ and δp are
        zero); None when every row saw every target."""
        n = basis.shape[1]
        self.points = points
        self.PJ = PJ[:, :, :n]  # (k, 3m, n): the actuated joints (virtual ones of n < 6 are not modelled)
        self.delta_p = delta_p  # (k, 9)
        self.basis = basis  # (k, n, m)
        self.C = np.einsum("kai,kaj->kij", self.PJ, self.PJ)
        self.g = np.einsum("kai,ka->ki", self.PJ, delta_p)
        self.n, self.m = n, basis.shape[2]

    def normal(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(G, b) of the given rows; unknowns ordered joint-major (every basis column of every joint)."""
        n, m = self.n, self.m
        B = self.basis[rows]  # (r, n, m)
        C = self.C[rows]
        G = np.empty((n * m, n * m))
        for i in range(n):
            Bi = B[:, i]
            for j in range(i, n):
                blk = (Bi * C[:, i, j, None]).T @ B[:, j]
                G[i * m : (i + 1) * m, j * m : (j + 1) * m] = blk
                if j != i:
                    G[j * m : (j + 1) * m, i * m : (i + 1) * m] = blk.T
        b = np.einsum("rim,ri->im", B, self.g[rows]).reshape(-1)
        return G, b

    def rho_sel(self, rows: np.ndarray, coef: np.ndarray, sel: np.ndarray) -> np.ndarray:
        """(r, n) joint motion errors of the rows for coefficients of the selected joint-major unknowns."""
        flat = self.basis[rows].reshape(len(rows), -1)[:, sel].reshape(len(rows), self.n, -1)
        return np.einsum("rim,im->ri", flat, coef.reshape(self.n, -1))

    def residual_score(self, rows: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """(r,) RMS target-position residual of each row after subtracting P J ρ (m)."""
        r = self.delta_p[rows] - np.einsum("rai,ri->ra", self.PJ[rows], rho)
        if self.points is None:
            return np.sqrt(np.mean(r.reshape(len(rows), -1, 3) ** 2, axis=(1, 2)) * 3.0)
        return np.sqrt(np.sum(r**2, axis=1) / self.points[rows])


def _solve_path(G: np.ndarray, b: np.ndarray, pen: np.ndarray, scale: float, lambdas) -> list[np.ndarray]:
    """Ridge solutions of (G + λ s diag(pen)) w = b for every λ, from one eigen-decomposition."""
    d = 1.0 / np.sqrt(pen)
    M = G * d[:, None] * d[None, :]
    e, V = np.linalg.eigh(M)
    e = np.clip(e, 0.0, None)
    Vb = V.T @ (b * d)
    return [d * (V @ (Vb / (e + lam * scale))) for lam in lambdas]


def fit_joint_series(
    obs: Observations,
    base: CalibratedRobot,
    *,
    harmonics=DEFAULT_HARMONICS,
    penalty_power: float = 2.0,
    lambdas=None,
    folds: int = 5,
    seed: int = 0,
    gravity: bool | None = None,
) -> tuple[CalibratedRobot, SeriesInfo]:
    """Fit per-joint Fourier series of the joint motion errors of ``base``'s equivalent robot (module docstring).

    obs: observations; rows labelled "train" or unassigned are fitted (and cross-validated), "val" rows are only
    measured, "test" rows ignored. base: a network-free robot (the identified local-POE robot for the hybrid, the
    registered nominal otherwise). harmonics: an int H, or candidate H values chosen by cross-validation.
    penalty_power: p of the order-weighted ridge penalty λ h^p. lambdas: candidate λ (unit-free, default 1e-7 …
    10). folds: cross-validation folds. seed: fold assignment. gravity: add the gravity terms (module docstring)
    — True, False, or None (default) to let cross-validation decide at the chosen H.

    Returns (robot, info): robot.method "series", network features ``("harmonics:H",)``; info holds
    ``harmonics`` (H), ``lambda``, ``cv`` ({H: [cv score per λ]}, m), ``cv_error`` (m), ``train_error`` and
    ``val_error`` (mean position error of the tool origin, m, where the rows fix a pose, else the mean target-point
    error: ``error_metric`` "pose" or "points"; NaN without val rows), ``amplitudes``
    ((n, H) rad, sqrt(a² + b²) per joint and order), ``constants`` (n,), row counts.
    """
    obs.check_robot(base.n)
    if base.network is not None:
        raise ValueError("base already has a learned term; fit the joint series on a network-free robot")
    cands, lams = _check_options(harmonics, penalty_power, lambdas, folds)
    fit_mask = np.isin(obs.split, ("train", ""))
    k_fit = int(fit_mask.sum())
    if k_fit < 2 * folds:
        raise ObservationError(
            f"the joint series needs at least {2 * folds} training configurations for {folds}-fold "
            f"cross-validation, got {k_fit}"
        )
    train = obs.subset(fit_mask)
    search = _OrderSearch.of(train, base, max(cands), penalty_power, lams, folds, seed)
    cv, cv_error, H, use_gravity, lam = search.choose(cands, gravity)
    coef = search.coefficients(H, use_gravity, lam)
    g_cols = 3 * base.n if use_gravity else 0
    robot = learned_robot(base, _series_network(coef, H, use_gravity), train.q, "series")
    amplitudes = np.hypot(coef[:, 1 + g_cols :: 2], coef[:, 2 + g_cols :: 2])
    train_error, kind = primary_error(robot, train)
    info: SeriesInfo = {
        "method": "series",
        "harmonics": int(H),
        "gravity": bool(use_gravity),
        "lambda": float(lam),
        "penalty_power": float(penalty_power),
        "candidates": list(cands),
        "lambdas": list(lams),
        "folds": int(folds),
        "seed": int(seed),
        "cv": {f"H={h}{'+gravity' if g else ''}": v for (h, g), v in cv.items()},
        "cv_error": float(cv_error),
        "train_rows": k_fit,
        "val_rows": int(np.sum(obs.split == "val")),
        "train_error": train_error,
        "val_error": validation_error(robot, obs),
        "error_metric": kind,
        "amplitudes": amplitudes,
        "constants": coef[:, 0].copy(),
        "virtual_joints": "not modelled (zero)" if base.n < 6 else "none",
    }
    return robot, info


@dataclass(frozen=True)
class _OrderSearch:
    """The series' normal equations at the largest order H_max, once for all rows and once per fold; every
    candidate (H, gravity) is a sub-block of them. Unknowns per joint: a constant, the 3n gravity terms, 2 H_max
    harmonics (joint-major)."""

    design: _Design
    k: int  # rows
    n: int
    penalty_power: float
    lams: tuple[float, ...]
    fold_rows: list[np.ndarray]
    G_max: np.ndarray
    b_max: np.ndarray
    fold_normals: list[tuple[np.ndarray, np.ndarray]]

    @classmethod
    def of(cls, train: Observations, base: CalibratedRobot, h_max: int, penalty_power: float, lams: tuple[float, ...],
           folds: int, seed: int) -> _OrderSearch:  # fmt: skip
        n, k_fit = base.n, train.k
        jeo = joint_error_observations(train, base, max_condition=None)
        grav = input_features(train.q, ("gravity",), base.model)  # (k, 3n), the same for every joint
        types, limits = base.model.joint_types, base.model.limits
        basis = np.concatenate(
            [
                np.ones((k_fit, n, 1)),
                np.broadcast_to(grav[:, None, :], (k_fit, n, 3 * n)),
                feature_lib.harmonics(train.q, h_max, types, limits).reshape(k_fit, n, 2 * h_max),
            ],
            axis=2,
        )
        design = _Design(jeo.PJ, jeo.delta_p, basis, None if train.complete else train.seen.sum(axis=1))
        order = np.random.default_rng(seed).permutation(k_fit)
        fold_rows = [np.sort(f) for f in np.array_split(order, int(folds))]
        G_max, b_max = design.normal(np.arange(k_fit))  # every candidate (H, gravity) is a sub-block of these
        fold_normals = [design.normal(rows) for rows in fold_rows]
        return cls(design, k_fit, n, penalty_power, lams, fold_rows, G_max, b_max, fold_normals)

    def columns(self, H: int, with_gravity: bool) -> tuple[np.ndarray, np.ndarray]:
        """Selected unknowns (joint-major) and their penalty weights for a model (H, gravity)."""
        n, n_grav, m_max = self.n, 3 * self.n, self.design.m  # m_max: 1 + 3n + 2 H_max
        per_joint = [0, *(range(1, 1 + n_grav) if with_gravity else ()), *range(1 + n_grav, 1 + n_grav + 2 * H)]
        sel = (np.arange(n)[:, None] * m_max + np.array(per_joint)[None, :]).reshape(-1)
        orders = np.concatenate([np.ones(1 + (n_grav if with_gravity else 0)), np.repeat(np.arange(1.0, H + 1), 2)])
        return sel, np.tile(orders**self.penalty_power, n)

    def scores(self, H: int, with_gravity: bool) -> list[float]:
        """The cross-validated score of every λ for the model (H, gravity)."""
        sel, pen = self.columns(H, with_gravity)
        G_all, b_all = self.G_max[np.ix_(sel, sel)], self.b_max[sel]
        scale = float(np.mean(np.diag(G_all))) or 1.0
        sums = np.zeros(len(self.lams))
        for rows, (G_f, b_f) in zip(self.fold_rows, self.fold_normals, strict=True):
            G_tr, b_tr = G_all - G_f[np.ix_(sel, sel)], b_all - b_f[sel]
            for i, w in enumerate(_solve_path(G_tr, b_tr, pen, scale, self.lams)):
                sums[i] += float(np.sum(self.design.residual_score(rows, self.design.rho_sel(rows, w, sel))))
        return (sums / self.k).tolist()

    def choose(
        self, cands: tuple[int, ...], gravity: bool | None
    ) -> tuple[dict[tuple[int, bool], list[float]], float, int, bool, float]:
        """The scores of every model tried; the chosen CV error, H, gravity switch and λ."""
        lams = self.lams
        first = (False,) if gravity is None else (bool(gravity),)
        cv = {(H, g): self.scores(H, g) for H in cands for g in first}
        # The smallest CV error; ties go to fewer harmonics and then to the stronger penalty (the smoother series).
        H = min((v[i], h, -lams[i]) for (h, _), v in cv.items() for i in range(len(lams)))[1]
        if gravity is None:  # then let cross-validation decide on the gravity terms at that order
            cv[(H, True)] = self.scores(H, True)
        best = min((v[i], h, g, -lams[i]) for (h, g), v in cv.items() if h == H for i in range(len(lams)))
        return cv, best[0], best[1], best[2], -best[3]

    def coefficients(self, H: int, use_gravity: bool, lam: float) -> np.ndarray:
        """(n, m) the series' coefficients on all rows: constant, gravity terms (if used), harmonics."""
        sel, pen = self.columns(H, use_gravity)
        G_sel = self.G_max[np.ix_(sel, sel)]
        coef = _solve_path(G_sel, self.b_max[sel], pen, float(np.mean(np.diag(G_sel))) or 1.0, [lam])[0]
        return coef.reshape(self.n, 1 + (3 * self.n if use_gravity else 0) + 2 * H)


def _series_network(coef: np.ndarray, H: int, use_gravity: bool) -> Network:
    """The series as a one-layer linear network over the gravity and harmonic features (the exported form)."""
    n = coef.shape[0]
    g_cols = 3 * n if use_gravity else 0
    N = equivalent_joints(n)
    W = np.zeros((N, g_cols + 2 * n * H))
    for j in range(n):
        W[j, :g_cols] = coef[j, 1 : 1 + g_cols]
        W[j, g_cols + 2 * H * j : g_cols + 2 * H * (j + 1)] = coef[j, 1 + g_cols :]
    bias = np.zeros(N)
    bias[:n] = coef[:, 0]
    f = W.shape[1]
    return Network(
        features=(("gravity",) if use_gravity else ()) + (f"{feature_lib.HARMONICS}:{H}",),
        weights=(W,),
        biases=(bias,),
        in_mean=np.zeros(f),
        in_scale=np.ones(f),
        out_mean=np.zeros(N),
        out_scale=np.ones(N),
    )
