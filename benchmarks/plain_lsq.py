"""An independent plain least-squares calibration: the measuring stick of the robustness benchmark.

Written for the benchmark only, with no labcal calibration code: numpy for the kinematics, scipy's
``least_squares`` for the fit. It takes the robot's nominal frames (a :class:`LocalPOEModel` is only read for its
frames, twists and joint types) and fits a **global POE** model on every row it is given:

    T(q) = exp(ξ̂_1 q_1) · … · exp(ξ̂_n q_n) · M,      p_i(q) = T_tb · T(q) · t_i

ξ_j: the joint twists in the base frame (revolute: unit axis ω and moment v ⟂ ω; prismatic: unit direction),
M: the tool pose at q = 0, T_tb: the base's pose in the tracker frame (identity and not fitted for base-frame data),
t_i: the m ≥ 1 targets in the tool frame. Joint offsets need no parameter: exp(ξ̂_j δq_j) moves through the following
twists into M. The residuals are the measured minus predicted target points (m) of every row and every target
that was seen (a NaN target row is not seen and gives no residual), plus a 1e-6 ridge on the parameter changes so
the directions the normalisation removes (axis length, moment along the axis) and those the points cannot fix
(with two targets: the tool's rotation about their line) stay put. With a single target point the tool's rotation
(the rotation part of M) is held at the nominal: it would only move that point as a translation does.
Tracker-frame data start with T_tb from a rigid fit of the nominal points to the measured ones and a first fit of
M and T_tb alone (the tool offset of a probe can be far from the nominal flange).

Example::

    >>> from labcal.robots import load
    >>> model = load("ur10").model
    >>> q = np.random.default_rng(0).uniform(-1, 1, (5, 6))
    >>> bool(np.allclose(GlobalPOE(model).fk(GlobalPOE(model).x0(), q), model.fk(q)))
    True
    >>> points = model.target_points(q, np.zeros((1, 3)))   # (5, 1, 3): the tool origin alone
    >>> points[1] = np.nan                                  # not seen in pose 1
    >>> fit = fit_plain(model, q, points, np.zeros((1, 3)))
    >>> bool(np.allclose(fit.predict_points(q, np.zeros((1, 3))), model.target_points(q, np.zeros((1, 3)))))
    True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RIDGE = 1e-6


def _skew(w: np.ndarray) -> np.ndarray:
    W = np.zeros((*w.shape[:-1], 3, 3))
    W[..., 0, 1], W[..., 0, 2], W[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    W[..., 1, 0], W[..., 2, 0], W[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return W


def exp_twist(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(…, 4, 4) exp of twists (v, ω) given as (…, 3) arrays (Rodrigues; any angle |ω|)."""
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    W = _skew(w)
    W2 = W @ W
    small = th < 1e-9
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    c = np.where(small, 1.0 / 6 - th**2 / 120, (ths - np.sin(ths)) / ths**3)
    eye = np.eye(3)
    T = np.zeros((*w.shape[:-1], 4, 4))
    T[..., :3, :3] = eye + a * W + b * W2
    T[..., :3, 3] = ((eye + b * W + c * W2) @ v[..., None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def _adjoint(T: np.ndarray) -> np.ndarray:
    R, p = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3], A[3:, 3:], A[:3, 3:] = R, R, _skew(p) @ R
    return A


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(4, 4) rigid T minimising Σ|T·src − dst|² over (m, 3) point sets."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cd - R @ cs
    return T


@dataclass
class GlobalPOE:
    """The nominal global-POE parameters of a model: base-frame twists (n, 6) as (v, ω) and M (4, 4)."""

    twists: np.ndarray
    M0: np.ndarray
    revolute: np.ndarray

    def __init__(self, model) -> None:
        T = np.eye(4)
        twists = []
        for j in range(model.n):
            T = T @ model.frames[j]
            twists.append(_adjoint(T) @ np.asarray(model.twists[j], float))
        self.twists = np.array(twists)
        self.M0 = T @ model.frames[model.n]
        self.revolute = np.array([t == "revolute" for t in model.joint_types])

    @property
    def n(self) -> int:
        return len(self.twists)

    def x0(self) -> np.ndarray:
        """The parameter vector of the nominal model: 6 per joint (δv, δω), 6 for M."""
        return np.zeros(6 * self.n + 6)

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = x[: 6 * self.n].reshape(self.n, 6)
        xi = self.twists + d
        v, w = xi[:, :3].copy(), xi[:, 3:].copy()
        for j in range(self.n):
            if self.revolute[j]:
                w[j] /= np.linalg.norm(w[j])
                v[j] -= (v[j] @ w[j]) * w[j]  # a revolute joint has zero pitch
            else:
                v[j] /= np.linalg.norm(v[j])
                w[j] = 0.0
        dm = x[6 * self.n : 6 * self.n + 6]
        M = self.M0 @ exp_twist(dm[:3], dm[3:])
        return np.concatenate([v, w], axis=1), M

    def fk(self, x: np.ndarray, q: np.ndarray) -> np.ndarray:
        """(k, 4, 4) tool poses in the base frame for parameters x and joints q (k, n)."""
        xi, M = self.unpack(x)
        q = np.atleast_2d(q)
        T = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4))
        for j in range(self.n):
            T = T @ exp_twist(xi[j, :3] * q[:, j, None], xi[j, 3:] * q[:, j, None])
        return T @ M


@dataclass
class PlainFit:
    """A fitted plain-LSQ model: predict target points (k, m, 3) in the data's frame."""

    poe: GlobalPOE
    x: np.ndarray
    T_tb: np.ndarray
    cost: float
    nfev: int
    converged: bool = True

    def predict_points(self, q: np.ndarray, targets: np.ndarray, x: np.ndarray | None = None) -> np.ndarray:
        """(k, m, 3) target points in the data's frame; ``x``: other parameters than the fitted ones."""
        T = self.T_tb @ self.poe.fk(self.x if x is None else x, q)
        return np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]

    def rank(self, q: np.ndarray, targets: np.ndarray, length_scale: float, rtol: float = 1e-6) -> int:
        """Numerical rank of the fitted points' Jacobian w.r.t. the robot's parameters at the solution: central
        differences, angular columns (ω parts) divided by ``length_scale`` (1 rad counts as that many metres, as
        local POE scales its own); singular values above ``rtol`` · the largest. The directions the normalisation
        removes (axis length, moment along the axis) give zero columns and are not counted."""
        cols = []
        for i in range(self.x.size):
            step = np.zeros_like(self.x)
            step[i] = h = 1e-7
            diff = self.predict_points(q, targets, self.x + step) - self.predict_points(q, targets, self.x - step)
            cols.append(diff.ravel() / (2 * h) / (length_scale if i % 6 >= 3 else 1.0))
        s = np.linalg.svd(np.array(cols).T, compute_uv=False)
        return int((s > rtol * s[0]).sum())


def _points(poe: GlobalPOE, x: np.ndarray, T_tb: np.ndarray, q: np.ndarray, targets: np.ndarray) -> np.ndarray:
    T = T_tb @ poe.fk(x, q)
    return np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]


def seen_points(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(k, m) bool: the targets seen in each row of points (k, m, 3); raises for a partly NaN point."""
    points, targets = np.asarray(points, float), np.asarray(targets, float)
    if targets.ndim != 2 or targets.shape[1] != 3 or targets.shape[0] < 1:
        raise ValueError(f"targets must have shape (m, 3) with m ≥ 1, got {targets.shape}")
    if points.ndim != 3 or points.shape[1:] != targets.shape:
        raise ValueError(f"points must have shape (k, {targets.shape[0]}, 3) for {targets.shape[0]} targets, got "
                         f"{points.shape}")  # fmt: skip
    finite = np.isfinite(points)
    seen = finite.all(axis=-1)
    partial = finite.any(axis=-1) & ~seen
    if partial.any():
        r, t = np.argwhere(partial)[0]
        raise ValueError(
            f"point of target t{t + 1} in row {r} is partly NaN: a target is either seen (3 numbers) or not (all NaN)"
        )
    return seen


def fit_plain(
    model, q: np.ndarray, points: np.ndarray, targets: np.ndarray, frame: str = "base", max_nfev: int | None = None
) -> PlainFit:
    """Fit the global POE model (and T_tb for tracker-frame data) to every row by nonlinear least squares.

    points: (k, m, 3) in the data's frame, a NaN row where a target was not seen; targets: (m, 3), m ≥ 1.
    max_nfev: cap on each stage's residual evaluations, finite-difference Jacobians included (default: 200 per
    parameter in the final stage, scipy's in the tool-and-tracker stage); ``PlainFit.converged`` says whether the
    final stage met a tolerance before it (a point near the last joint's axis leaves that axis barely
    observable and least squares crawls along it).
    """
    from scipy.optimize import least_squares  # only the benchmark needs scipy here

    poe = GlobalPOE(model)
    q, points, targets = np.asarray(q, float), np.asarray(points, float), np.asarray(targets, float)
    seen = seen_points(points, targets)
    if not seen.any():
        raise ValueError("no target was seen in any row: nothing to fit")
    measured = points[seen]
    tracker = frame == "tracker"
    x = poe.x0()
    p = len(x)
    T0 = np.eye(4)
    if tracker:
        nominal = _points(poe, x, np.eye(4), q, targets)
        T0 = kabsch(nominal[seen], measured)

    def split(z):
        xx = z[:p]
        if not tracker:
            return xx, T0
        d = z[p:]
        return xx, exp_twist(d[:3], d[3:]) @ T0

    def residual(z):
        xx, T_tb = split(z)
        r = (_points(poe, xx, T_tb, q, targets)[seen] - measured).ravel()
        return np.concatenate([r, RIDGE * z])

    z = np.zeros(p + (6 if tracker else 0))
    # With one target point the tool's rotation moves that point exactly as a translation does: it is held at the
    # nominal. Left free, it drifts along a valley that only the 1e-6 ridge curves, and the fit crawls.
    seen_targets = targets[seen.any(axis=0)]
    one_point = np.ptp(seen_targets, axis=0).max() < 1e-9
    held = np.arange(6 * poe.n + 3, p) if one_point else np.zeros(0, int)

    def solve(fun, free, **options):
        free = np.setdiff1d(free, held)

        def restricted(y):
            zz = z.copy()
            zz[free] = y
            return fun(zz)

        return free, least_squares(restricted, z[free], method="lm", xtol=1e-12, ftol=1e-12, **options)

    if tracker:
        # Tool and tracker pose first, with the joints nominal: a probe can sit far from the nominal flange.
        first_options = {"max_nfev": max_nfev} if max_nfev else {}
        free, first = solve(residual, np.r_[np.arange(6 * poe.n, p), np.arange(p, p + 6)], **first_options)
        z[free] = first.x
    if held.size:
        free, sol = solve(residual, np.arange(len(z)), max_nfev=max_nfev or 200 * (len(z) - held.size))
        z[free] = sol.x
        sol.x = z
    else:
        sol = least_squares(residual, z, method="lm", xtol=1e-12, ftol=1e-12, max_nfev=max_nfev or 200 * len(z))
    xx, T_tb = split(sol.x)
    return PlainFit(poe, xx, T_tb, float(sol.cost), int(sol.nfev), bool(sol.status > 0))
