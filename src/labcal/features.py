"""The network input features: the one place that knows their names, sizes and numpy computation. Numpy only.

A learned error term (the paper's network, the per-joint series) maps features of the joint values to the
equivalent robot's joint motion errors δρ. Fitting (:mod:`labcal.calibration`), the runtime
(:mod:`labcal.compensator`) and the URScript exporter all read the features from here:

=================  ===========  ===========================================================================
name               columns      meaning (n joints, θ_j the joint angle, see :func:`joint_angles`)
=================  ===========  ===========================================================================
``q``              n            the joint values themselves (the paper's choice)
``sincos``         2n           sin q_j (all j), then cos q_j; a prismatic joint gives q_j and 0
``sincos2``        2n           sin 2q_j, then cos 2q_j (twice-per-revolution effects); prismatic: 0 and 0
``gravity``        3n           base −z in the frames of links 1 … n: −(row 2 of R_j), j = 1 … n. Every
                                gravity torque of a rigid arm is linear in these, whatever its mass model
``harmonics:H``    2nH          sin(h θ_j), cos(h θ_j), h = 1 … H, joint by joint (layout below)
=================  ===========  ===========================================================================

``harmonics:H`` is a separable Fourier basis of each joint's own angle::

    x[:, j·2H + 2(h−1)]     = sin(h θ_j)
    x[:, j·2H + 2(h−1) + 1] = cos(h θ_j)          j = 0 … n−1, h = 1 … H

θ_j = q_j for a revolute joint (rad), so the basis spans every error that repeats once per joint revolution and
depends on that joint alone: encoder eccentricity (h = 1), gear and bearing run-out and the transmission errors
of a reducer's output stages (orders set by the gearing). A linear map from these features to the equivalent
robot's joint motion errors with zeros outside each joint's own block is the per-joint Fourier series
``δρ_j(q_j) = Σ_h a_jh sin(h q_j) + b_jh cos(h q_j)`` (:mod:`labcal.calibration.joint_series`). A prismatic joint
has no natural period: θ_j = π (q_j − lo_j) / (hi_j − lo_j) maps its joint range (from the model's limits) onto
[0, π], so the sines and cosines form a smooth series over the stroke that does not force the two ends to agree.

The registry: :func:`get` turns a name into a :class:`Feature` (size, ``compute``, and ``columns``: one
:class:`Column` recipe per column for code generators such as the URScript exporter); :func:`compute_all`
evaluates a tuple of names into one (k, f) input matrix.

Example::

    >>> x = harmonics(np.array([[0.5, -1.0]]), 2)
    >>> x.shape, bool(np.isclose(x[0, 2], np.sin(2 * 0.5))), bool(np.isclose(x[0, 5], np.cos(-1.0)))
    ((1, 8), True, True)
    >>> get("sincos").size(6), get("harmonics:3").size(6), get("gravity").needs_frames
    (12, 36, True)
    >>> [c.op for c in get("sincos").columns(("revolute", "prismatic"))]
    ['sin', 'q', 'cos', 'zero']
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

HARMONICS = "harmonics"
MAX_HARMONICS = 512  # a sanity bound: orders above this cannot be sampled by any calibration data set
SIMPLE = ("q", "sincos", "sincos2", "gravity")  # the names without a parameter
NAMES = (*SIMPLE, HARMONICS + ":H")  # for messages: every name the registry accepts


@dataclass(frozen=True)
class Column:
    """How to compute one feature column, for code generators (e.g. URScript). Ops:

    - ``"q"``: q_j;  ``"zero"``: 0;
    - ``"sin"`` / ``"cos"``: sin(order · θ_j) / cos(order · θ_j), θ_j = q_j, or for ``stroke = (lo, hi)`` (a
      prismatic joint's harmonics) θ_j = π (q_j − lo) / (hi − lo);
    - ``"gravity"``: −R_link[2, axis], R_link the rotation of link frame ``link`` (1 … n; index ``link`` of
      :meth:`LocalPOEModel.link_frames`, the frame before its joint moves it).
    """

    op: str
    joint: int = -1
    order: int = 1
    stroke: tuple[float, float] | None = None
    link: int = 0
    axis: int = 0


@dataclass(frozen=True)
class Feature:
    """One registered input feature: ``kind`` ∈ SIMPLE or "harmonics" (then ``order`` = H). See the module table."""

    name: str
    kind: str
    order: int = 0

    @property
    def needs_frames(self) -> bool:
        """True when :meth:`compute` needs the link frames (the gravity directions)."""
        return self.kind == "gravity"

    def size(self, n: int) -> int:
        """Number of columns for a robot with n joints (the joint types change what a column holds, not how many)."""
        return len(self.columns(("revolute",) * n))

    def compute(self, q: np.ndarray, joint_types=None, limits=None, frames=None) -> np.ndarray:
        """(k, n) joint values → (k, size) columns.

        joint_types: n strings (default all revolute); limits: (n, 2), needed by harmonics of a prismatic joint;
        frames: (k, n+1, 4, 4) link frames at q (or their (k, n+1, 6, 6) adjoints: only rotation rows are read),
        needed by ``gravity``.
        """
        return self.prepare(joint_types, limits)(np.atleast_2d(np.asarray(q, dtype=float)), frames)

    def prepare(self, joint_types=None, limits=None):
        """:meth:`compute` for one robot, with its joint-type masks and constants worked out once: a function
        ``(q (k, n) float array, frames or None) → (k, size)`` (what a runtime calls at every solver step)."""
        kind = self.kind
        if kind == "harmonics":
            order = self.order
            if joint_types is not None and _prismatic(tuple(joint_types)).any():
                return lambda q, frames=None: harmonics(q, order, joint_types, limits)
            return lambda q, frames=None: _harmonics_of_angles(q, order)
        if kind == "gravity":
            return functools.partial(_gravity, self.name)
        if kind == "q":
            return lambda q, frames=None: q
        if kind not in ("sincos", "sincos2"):
            raise ValueError(_unknown_kind(kind, "Feature.prepare"))
        h = 1 if kind == "sincos" else 2  # a prismatic joint gives q_j and 0 for sincos, 0 and 0 for sincos2
        rev = None if joint_types is None else _revolute(joint_types, len(tuple(joint_types)))
        if rev is None:
            return lambda q, frames=None: np.concatenate([np.sin(h * q), np.cos(h * q)], axis=1)
        return lambda q, frames=None: np.concatenate(
            [np.where(rev, np.sin(h * q), q if h == 1 else 0.0), np.where(rev, np.cos(h * q), 0.0)], axis=1
        )

    def columns(self, joint_types, limits=None) -> tuple[Column, ...]:
        """One :class:`Column` recipe per column, in :meth:`compute`'s order (limits: for prismatic harmonics)."""
        types = tuple(joint_types)
        n = len(types)
        rev = [t != "prismatic" for t in types]
        if self.kind == "q":
            return tuple(Column("q", j) for j in range(n))
        if self.kind == "gravity":
            return tuple(Column("gravity", link=j, axis=a) for j in range(1, n + 1) for a in range(3))
        if self.kind in ("sincos", "sincos2"):
            h = 1 if self.kind == "sincos" else 2
            other = "q" if h == 1 else "zero"
            sines = [Column("sin", j, h) if rev[j] else Column(other, j) for j in range(n)]
            return tuple(sines + [Column("cos", j, h) if rev[j] else Column("zero", j) for j in range(n)])
        if self.kind != HARMONICS:
            raise ValueError(_unknown_kind(self.kind, "Feature.columns"))
        lim = None if limits is None else np.asarray(limits, dtype=float).reshape(n, 2)
        out = []
        for j in range(n):
            stroke = None
            if not rev[j]:
                if lim is None:
                    raise ValueError("harmonics of a prismatic joint need the joint limits (the stroke: the period)")
                stroke = (float(lim[j, 0]), float(lim[j, 1]))
            for h in range(1, self.order + 1):
                out += [Column("sin", j, h, stroke), Column("cos", j, h, stroke)]
        return tuple(out)


def _unknown_kind(kind: str, where: str) -> str:
    # a kind added to the registry's names without its computation must fail loudly, not compute another kind
    return f"feature kind {kind!r} has no computation in {where}: a new kind needs a branch there"


@functools.lru_cache(maxsize=256)
def get(name: str) -> Feature:
    """The registered feature called ``name``; ValueError naming the known names, or for a malformed harmonics name
    (``"harmonics:x"``, ``"harmonics:0"``) what is wrong with it."""
    if name in SIMPLE:
        return Feature(name, name)
    if not isinstance(name, str) or not name.startswith(HARMONICS + ":"):
        raise ValueError(f"unknown feature {name!r}; known: {', '.join(NAMES)}")
    text = name[len(HARMONICS) + 1 :]
    try:
        order = int(text)
    except ValueError:
        raise ValueError(f"feature {name!r}: the number of harmonics must be an integer, got {text!r}") from None
    if not 1 <= order <= MAX_HARMONICS:
        raise ValueError(f"feature {name!r}: the number of harmonics must be in 1 … {MAX_HARMONICS}, got {order}")
    return Feature(name, HARMONICS, order)


def is_feature(name: str) -> bool:
    """True for a well-formed registered feature name (``q``, ``sincos``, …, ``harmonics:H``)."""
    try:
        get(name)
    except ValueError:
        return False
    return True


def compute_all(q: np.ndarray, names, joint_types=None, limits=None, frames=None) -> np.ndarray:
    """(k, n) joint values → (k, f) network inputs: the features ``names`` side by side (see Feature.compute)."""
    return evaluator(tuple(names), joint_types, limits)(np.atleast_2d(np.asarray(q, dtype=float)), frames)


def evaluator(names: tuple[str, ...], joint_types=None, limits=None):
    """The features ``names`` of one robot as one prepared function ``(q (k, n), frames or None) → (k, f)``
    (:meth:`Feature.prepare`); ValueError for an unknown name. ``needs_frames`` tells whether frames are read."""
    parts = [get(name).prepare(joint_types, limits) for name in names]
    if not parts:
        raise ValueError("no features given")

    def run(q: np.ndarray, frames=None) -> np.ndarray:
        if len(parts) == 1:
            return parts[0](q, frames)
        return np.concatenate([part(q, frames) for part in parts], axis=1)

    run.needs_frames = any(get(name).needs_frames for name in names)
    return run


def _gravity(name: str, q: np.ndarray, frames) -> np.ndarray:
    if frames is None:
        raise ValueError(f"feature {name!r} needs the link frames at q (frames=model.link_frames(q))")
    return -frames[:, 1:, 2, :3].reshape(frames.shape[0], -1)


def _harmonics_of_angles(theta: np.ndarray, order: int) -> np.ndarray:
    """(k, n) angles → (k, 2·n·order) sin(h θ_j), cos(h θ_j) (layout in the module docstring)."""
    angle = theta[:, :, None] * _orders(order)  # (k, n, H)
    out = np.empty((*angle.shape, 2))
    np.sin(angle, out=out[..., 0])
    np.cos(angle, out=out[..., 1])
    return out.reshape(theta.shape[0], -1)


def harmonics_of_joints(cos_theta: np.ndarray, sin_theta: np.ndarray, order: int) -> np.ndarray:
    """:func:`harmonics` by a running product, joint-major and complex: cos θ and sin θ (n, k) → (n, order, k)
    complex ``sin h θ_j + i cos h θ_j`` (= i e^{−i h θ_j}) at order h = 1 … order of joint j, configuration i.

    The running product by doubling: with orders 1 … m known, ``i e^{−i (h+m) θ} = i e^{−i h θ} · e^{−i m θ}`` gives
    orders m+1 … 2m in one vectorised product, and e^{−i 2m θ} = (e^{−i m θ})². Six products for 32 orders instead
    of 2·n·32 sines and cosines, or of an accumulate along the short order axis, which numpy runs one configuration
    at a time (five times slower on a batch). Rounding grows about linearly with the order (a few ulps). A
    runtime with real weights a (sin) and b (cos) per order gets ``Σ_h a_h sin h θ + b_h cos h θ`` as the real part
    of ``(a − i b) @ out[j]``: one product per joint.

    Example::

        >>> theta = np.array([[0.3, 0.5], [-1.2, 2.0]])  # (n = 2, k = 2)
        >>> x = harmonics_of_joints(np.cos(theta), np.sin(theta), 3)
        >>> x.shape, bool(np.isclose(x[1, 2, 0].real, np.sin(3 * -1.2))), bool(np.isclose(x[0, 1, 1].imag, np.cos(1.0)))
        ((2, 3, 2), True, True)
    """
    out = np.empty((cos_theta.shape[0], order, cos_theta.shape[1]), dtype=complex)
    out[:, 0].real, out[:, 0].imag = sin_theta, cos_theta  # i e^{−iθ} = sin θ + i cos θ
    factor = np.empty(cos_theta.shape, dtype=complex)
    factor.real, factor.imag = cos_theta, -sin_theta  # e^{−i m θ} for the m orders known, here m = 1
    known = 1
    while known < order:
        more = min(known, order - known)
        np.multiply(out[:, :more], factor[:, None], out=out[:, known : known + more])
        known += more
        if known < order:
            factor *= factor
    return out


def _revolute(joint_types, n: int) -> np.ndarray | None:
    """(n,) bool revolute mask, or None when every joint is revolute (the common case: no np.where needed)."""
    if joint_types is None:
        return None
    prismatic = _prismatic(tuple(joint_types))
    if len(prismatic) != n:
        raise ValueError(f"joint_types has {len(prismatic)} entries for {n} joint values")
    return ~prismatic if prismatic.any() else None


def joint_angles(q: np.ndarray, joint_types=None, limits=None) -> np.ndarray:
    """(k, n) joint values → (k, n) angles θ: q for revolute joints, the stroke mapped onto [0, π] for prismatic.

    joint_types: n strings ("revolute" / "prismatic"; default all revolute); limits: (n, 2), needed only when a
    joint is prismatic.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n = q.shape[1]
    revolute = _revolute(joint_types, n)
    if revolute is None:
        return q
    prismatic = ~revolute
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
    return _harmonics_of_angles(joint_angles(q, joint_types, limits), order)


@functools.lru_cache(maxsize=64)
def _orders(order: int) -> np.ndarray:
    """(H,) 1.0 … H (cached: the runtime evaluates the harmonics at every solver step)."""
    out = np.arange(1, order + 1, dtype=float)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=64)
def _prismatic(joint_types: tuple[str, ...]) -> np.ndarray:
    out = np.array([t == "prismatic" for t in joint_types], dtype=bool)
    out.setflags(write=False)
    return out
