"""SE(3) and SO(3) tools: hat/vee, closed-form exponentials and logarithms, adjoints (paper eq. 3-4).

Twists are ordered (v, ω), as in the paper's eq. (4): ``xi[..., :3]`` is the linear part, ``xi[..., 3:]`` the
angular part. Every function is batched over any number of leading axes and exact near zero angle (Taylor series
below 1e-2 rad) and near π (the logarithm switches to the symmetric part of R there).

Example (a quarter turn about z followed by 1 m along the new x)::

    >>> T = exp_se3(np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2]))
    >>> np.round(T[:3, :3] @ [1.0, 0.0, 0.0], 12) + 0.0
    array([0., 1., 0.])
    >>> np.allclose(exp_se3(log_se3(T)), T)
    True
"""

from __future__ import annotations

import numpy as np

_SMALL = 1e-2  # below this angle (rad) the series are exact to machine precision


def skew(w: np.ndarray) -> np.ndarray:
    """(..., 3) → (..., 3, 3) with ``skew(w) @ x == cross(w, x)``."""
    w = np.asarray(w, dtype=float)
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def unskew(W: np.ndarray) -> np.ndarray:
    """(..., 3, 3) → (..., 3); the inverse of :func:`skew` (takes the antisymmetric part)."""
    W = np.asarray(W, dtype=float)
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]], axis=-1
    )


def hat(xi: np.ndarray) -> np.ndarray:
    """(..., 6) twist (v, ω) → (..., 4, 4) element of se(3) (paper eq. 4)."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros((*xi.shape[:-1], 4, 4))
    out[..., :3, :3] = skew(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def vee(X: np.ndarray) -> np.ndarray:
    """(..., 4, 4) element of se(3) → (..., 6) twist (v, ω)."""
    X = np.asarray(X, dtype=float)
    return np.concatenate([X[..., :3, 3], unskew(X[..., :3, :3])], axis=-1)


def _coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A = sinθ/θ, B = (1 − cosθ)/θ², C = (θ − sinθ)/θ³, by series near θ = 0."""
    t2 = theta * theta
    small = theta < _SMALL
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42)), np.sin(safe) / safe)
    # 1 − cosθ = 2 sin²(θ/2) avoids the cancellation that costs 1 − cosθ about 1e-12 relative just above _SMALL.
    half = np.sin(0.5 * safe) / (0.5 * safe)
    b = np.where(small, 0.5 - t2 / 24 * (1 - t2 / 30 * (1 - t2 / 56)), 0.5 * half * half)
    c = np.where(small, 1 / 6 - t2 / 120 * (1 - t2 / 42 * (1 - t2 / 72)), (safe - np.sin(safe)) / safe**3)
    return a, b, c


def exp_so3(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vector → (..., 3, 3) rotation matrix (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)
    a, b, _ = _coefficients(theta)
    K = skew(w)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrix → (..., 3) rotation vector with angle in [0, π].

    Near π the antisymmetric part of R vanishes, so the axis is read from the symmetric part instead.
    """
    R = np.asarray(R, dtype=float)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    anti = unskew(R)  # = sinθ · axis
    # atan2 keeps full precision at both ends, where arccos of the trace loses half the digits.
    theta = np.arctan2(np.linalg.norm(anti, axis=-1), cos)
    a, _, _ = _coefficients(theta)
    w = anti / np.where(theta < 0.75 * np.pi, a, 1.0)[..., None]

    near_pi = theta >= 0.75 * np.pi
    if np.any(near_pi):
        Rp, thp, antip = R[near_pi], theta[near_pi], anti[near_pi]
        sym = 0.5 * (Rp + np.swapaxes(Rp, -1, -2))
        # sym = cosθ I + (1 − cosθ) a aᵀ; its largest diagonal entry gives a well-conditioned column of a aᵀ.
        aat = (sym - np.cos(thp)[:, None, None] * np.eye(3)) / (1 - np.cos(thp))[:, None, None]
        i = np.argmax(np.diagonal(aat, axis1=-2, axis2=-1), axis=-1)
        col = aat[np.arange(len(i)), :, i]
        axis = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.sum(axis * antip, axis=-1) < 0, -1.0, 1.0)
        w = w.copy()
        w[near_pi] = axis * (sign * thp)[:, None]
    return w


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """(..., 6) twist (v, ω) → (..., 4, 4) homogeneous transform (paper eq. 3)."""
    xi = np.asarray(xi, dtype=float)
    v, w = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(w, axis=-1)
    a, b, c = _coefficients(theta)
    K = skew(w)
    K2 = K @ K
    out = np.zeros((*xi.shape[:-1], 4, 4))
    out[..., :3, :3] = np.eye(3) + a[..., None, None] * K + b[..., None, None] * K2
    V = np.eye(3) + b[..., None, None] * K + c[..., None, None] * K2
    out[..., :3, 3] = np.einsum("...ij,...j->...i", V, v)
    out[..., 3, 3] = 1.0
    return out


def log_se3(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) homogeneous transform → (..., 6) twist (v, ω) with rotation angle in [0, π]."""
    T = np.asarray(T, dtype=float)
    w = log_so3(T[..., :3, :3])
    theta = np.linalg.norm(w, axis=-1)
    t2 = theta * theta
    small = theta < _SMALL
    safe = np.where(small, 1.0, theta)
    # V⁻¹ = I − K/2 + D K², D = (1 − A/(2B))/θ² = (1 − (θ/2) cot(θ/2))/θ²  (series 1/12 + θ²/720 + θ⁴/30240 near
    # zero). The half-angle form has no 1 − cosθ in it, which would lose ~1e-12 of the translation above _SMALL.
    half = 0.5 * safe
    d = np.where(small, 1 / 12 + t2 / 720 + t2 * t2 / 30240, (1 - half * np.cos(half) / np.sin(half)) / safe**2)
    K = skew(w)
    V_inv = np.eye(3) - 0.5 * K + d[..., None, None] * (K @ K)
    v = np.einsum("...ij,...j->...i", V_inv, T[..., :3, 3])
    return np.concatenate([v, w], axis=-1)


def inv(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) → inverse homogeneous transform (Rᵀ, −Rᵀp)."""
    T = np.asarray(T, dtype=float)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def adjoint(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) → (..., 6, 6) adjoint for (v, ω) twists: ``Ad_T = [[R, p̂R], [0, R]]``.

    It maps a twist expressed in frame T to the frame T is expressed in:
    ``T exp(ξ̂) T⁻¹ = exp((Ad_T ξ)^)``.
    """
    T = np.asarray(T, dtype=float)
    R, p = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros((*T.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = skew(p) @ R
    return out


def point_jacobian(p: np.ndarray) -> np.ndarray:
    """(..., 3) points → (..., 3, 6) ``[I, −p̂]``: a point p of a frame moved by a small twist δy = (δv, δω) moves by
    ``δp = δv + δω × p = [I, −p̂] δy`` (paper eq. 18, one point). For p = (0, 0, 1) m the δω_x column is
    (0, −1, 0): a rotation about x moves the point along −y."""
    p = np.asarray(p, dtype=float)
    out = np.zeros((*p.shape[:-1], 3, 6))
    out[..., :3] = np.eye(3)
    out[..., 3:] = -skew(p)
    return out


def rpy_to_matrix(rpy: np.ndarray) -> np.ndarray:
    """(..., 3) URDF roll-pitch-yaw (fixed axes x, y, z) → (..., 3, 3): ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    rpy = np.asarray(rpy, dtype=float)
    r, p, y = rpy[..., 0], rpy[..., 1], rpy[..., 2]
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.empty((*rpy.shape[:-1], 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


def matrix_to_rpy(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) → (..., 3) URDF roll-pitch-yaw; at pitch = ±π/2 the roll is set to 0 (gimbal lock).

    Exact to rounding everywhere, including next to the lock: the pitch comes from atan2 (arcsin of R₂₀ loses half
    the digits near ±1), and the yaw is solved given the roll, so the pair stays consistent when both are ill-defined.
    """
    R = np.asarray(R, dtype=float)
    cos_pitch = np.hypot(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arctan2(-R[..., 2, 0], cos_pitch)
    # Below 1e-14 the roll is rounding noise; 0 then changes R by at most ~1e-14.
    locked = cos_pitch < 1e-14
    roll = np.where(locked, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    cr, sr = np.cos(roll), np.sin(roll)
    # Second column of R Rx(roll)ᵀ = Rz(yaw) Ry(pitch) e_y = (−sin yaw, cos yaw, 0).
    yaw = np.arctan2(sr * R[..., 0, 2] - cr * R[..., 0, 1], cr * R[..., 1, 1] - sr * R[..., 1, 2])
    return np.stack([roll, pitch, yaw], axis=-1)


def pose(xyz: np.ndarray, rpy: np.ndarray | None = None) -> np.ndarray:
    """Homogeneous transform from a translation (..., 3) in m and URDF rpy (..., 3) in rad."""
    xyz = np.asarray(xyz, dtype=float)
    out = np.zeros((*xyz.shape[:-1], 4, 4))
    out[..., :3, :3] = np.eye(3) if rpy is None else rpy_to_matrix(rpy)
    out[..., :3, 3] = xyz
    out[..., 3, 3] = 1.0
    return out


def pose_distance(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error (m) and orientation error (rad, angle of R_a R_bᵀ) between poses (..., 4, 4).

    The orientation error is measured on the manifold, ``|log(R_a R_bᵀ)|``, never element by element.
    """
    T_a, T_b = np.asarray(T_a, dtype=float), np.asarray(T_b, dtype=float)
    dp = np.linalg.norm(T_a[..., :3, 3] - T_b[..., :3, 3], axis=-1)
    dR = T_a[..., :3, :3] @ np.swapaxes(T_b[..., :3, :3], -1, -2)
    return dp, np.linalg.norm(log_so3(dR), axis=-1)


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Best rigid transforms T with ``dst[k] ≈ T[k] · src`` (Kabsch): src (m, 3), dst (k, m, 3) → (k, 4, 4).

    Example::

        >>> src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
        >>> T = pose([0.1, 0.2, 0.3], [0.0, 0.0, 0.5])
        >>> dst = src @ T[:3, :3].T + T[:3, 3]
        >>> bool(np.allclose(rigid_fit(src, dst[None])[0], T))
        True
    """
    src = np.asarray(src, dtype=float)
    dst = np.atleast_3d(np.asarray(dst, dtype=float))
    cs, cd = src.mean(axis=0), dst.mean(axis=1)
    H = np.einsum("ma,kmb->kab", src - cs, dst - cd[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    d[d == 0] = 1.0  # coincident or collinear points: any proper rotation of the best fit will do
    D = np.zeros((len(d), 3, 3))
    D[:, 0, 0], D[:, 1, 1], D[:, 2, 2] = 1.0, 1.0, d
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    T = np.zeros((len(d), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, cd - np.einsum("kab,b->ka", R, cs), 1.0
    return T
