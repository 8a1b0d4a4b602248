"""Structured input features of learned error terms, numpy only (the compensator runtime evaluates them).

``harmonics:H`` — a separable Fourier basis of each joint's own angle, orders 1 … H::

    x[:, j·2H + 2(h−1)]     = sin(h θ_j)
    x[:, j·2H + 2(h−1) + 1] = cos(h θ_j)          j = 0 … n−1, h = 1 … H

θ_j = q_j for a revolute joint (rad), so the basis spans every error that repeats once per joint revolution and
depends on that joint alone: encoder eccentricity (h = 1), gear and bearing run-out and the transmission errors
of a reducer's output stages (orders set by the gearing). A linear map from these features to the equivalent
robot's joint motion errors with zeros outside each joint's own block is the per-joint Fourier series
``δρ_j(q_j) = Σ_h a_jh sin(h q_j) + b_jh cos(h q_j)`` (:mod:`labcal.calibration.joint_series`).

A prismatic joint has no natural period: θ_j = π (q_j − lo_j) / (hi_j − lo_j) maps its joint range (from the
model's limits) onto [0, π], so the sines and cosines form a smooth series over the stroke that does not force
the two ends to agree.

Example::

    >>> x = harmonics(np.array([[0.5, -1.0]]), 2)
    >>> x.shape, bool(np.isclose(x[0, 2], np.sin(2 * 0.5))), bool(np.isclose(x[0, 5], np.cos(-1.0)))
    ((1, 8), True, True)

This module imports numpy only.
"""

from __future__ import annotations

import numpy as np

HARMONICS = "harmonics"
MAX_HARMONICS = 512  # a sanity bound: orders above this cannot be sampled by any calibration data set


def parse(name: str) -> tuple[str, int] | None:
    """``"harmonics:H"`` → ("harmonics", H); None for a name this module does not define.

    Raises ValueError for a malformed name of a feature this module defines (e.g. ``"harmonics:x"``).
    """
    if not isinstance(name, str) or not name.startswith(HARMONICS + ":"):
        return None
    text = name[len(HARMONICS) + 1 :]
    try:
        order = int(text)
    except ValueError:
        raise ValueError(f"feature {name!r}: the number of harmonics must be an integer, got {text!r}") from None
    if not 1 <= order <= MAX_HARMONICS:
        raise ValueError(f"feature {name!r}: the number of harmonics must be in 1 … {MAX_HARMONICS}, got {order}")
    return HARMONICS, order


def is_feature(name: str) -> bool:
    """True for a well-formed feature name defined here (``harmonics:H``)."""
    try:
        return parse(name) is not None
    except ValueError:
        return False


def size(name: str, n: int) -> int:
    """Number of feature columns of ``name`` for a robot with n joints."""
    kind = parse(name)
    if kind is None:
        raise ValueError(f"unknown feature {name!r}; labcal.features defines 'harmonics:H'")
    return 2 * n * kind[1]


def joint_angles(q: np.ndarray, joint_types=None, limits=None) -> np.ndarray:
    """(k, n) joint values → (k, n) angles θ: q for revolute joints, the stroke mapped onto [0, π] for prismatic.

    joint_types: n strings ("revolute" / "prismatic"; default all revolute); limits: (n, 2), needed only when a
    joint is prismatic.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n = q.shape[1]
    if joint_types is None:
        return q
    types = tuple(joint_types)
    if len(types) != n:
        raise ValueError(f"joint_types has {len(types)} entries for {n} joint values")
    prismatic = np.array([t == "prismatic" for t in types])
    if not prismatic.any():
        return q
    if limits is None:
        raise ValueError("harmonics of a prismatic joint need the joint limits (the stroke sets the period)")
    lim = np.asarray(limits, dtype=float).reshape(n, 2)
    span = lim[:, 1] - lim[:, 0]
    bad = prismatic & ~(np.isfinite(span) & (span > 0))
    if bad.any():
        j = int(np.argmax(bad))
        raise ValueError(f"joint {j + 1} is prismatic with limits {lim[j].tolist()}: need finite lo < hi")
    safe = np.where(prismatic, span, 1.0)
    return np.where(prismatic, np.pi * (q - lim[:, 0]) / safe, q)


def harmonics(q: np.ndarray, order: int, joint_types=None, limits=None) -> np.ndarray:
    """(k, n) joint values → (k, 2·n·order) features sin(h θ_j), cos(h θ_j) (layout in the module docstring)."""
    order = int(order)
    if not 1 <= order <= MAX_HARMONICS:
        raise ValueError(f"order must be in 1 … {MAX_HARMONICS}, got {order}")
    theta = joint_angles(q, joint_types, limits)
    k, n = theta.shape
    angle = theta[:, :, None] * np.arange(1, order + 1, dtype=float)  # (k, n, H)
    out = np.empty((k, n, order, 2))
    out[..., 0] = np.sin(angle)
    out[..., 1] = np.cos(angle)
    return out.reshape(k, 2 * n * order)


def compute(q: np.ndarray, name: str, joint_types=None, limits=None) -> np.ndarray:
    """Evaluate the feature ``name`` (e.g. ``"harmonics:24"``) at (k, n) joint values → (k, f)."""
    kind = parse(name)
    if kind is None:
        raise ValueError(f"unknown feature {name!r}; labcal.features defines 'harmonics:H'")
    return harmonics(q, kind[1], joint_types, limits)


def harmonic_orders(order: int, n: int) -> np.ndarray:
    """(2·n·order,) the harmonic order h of every column of ``harmonics(…, order)`` (for penalties, spectra)."""
    return np.tile(np.repeat(np.arange(1, order + 1), 2), n)


def column_joints(order: int, n: int) -> np.ndarray:
    """(2·n·order,) the joint index (0-based) every column of ``harmonics(…, order)`` belongs to."""
    return np.repeat(np.arange(n), 2 * order)
