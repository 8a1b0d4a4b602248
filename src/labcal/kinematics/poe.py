"""The local product-of-exponentials model of a serial robot (paper eq. 1-7, 10-14).

Each link j carries a frame K_j on joint j's axis. At joint value q_j the relative pose of K_j is
``A_j(0) · exp(ξ̂_j q_j)``, with the unit twist ξ_j expressed in K_j (z by default, eq. 5). The tool pose is::

    T_base_tool(q) = A_1(0) e^{ξ̂_1 q_1} · A_2(0) e^{ξ̂_2 q_2} ··· A_n(0) e^{ξ̂_n q_n} · A_{n+1}(0)

Pose errors are spatial twists δy in the base frame K0, defined by ``T_actual = exp(δŷ) · T_nominal``.

The definition is :func:`poe_link_frames` (with :func:`poe_fk` and :func:`poe_joint_twists`): the product above,
one :func:`se3.exp_se3` per joint. :class:`LocalPOEModel` computes the same numbers with two kernels, each kept
because ``benchmarks/speed.py`` shows what it earns against the definition, each tested against the definition
(tests/kinematics/test_kinematics_poe.py):

- ``_walk``: a batch, batch axis last (whole-array multiply-adds: throughput), below ``_SMALL_BATCH``
  configurations handing over to
- ``_walk_small``: a few configurations, one 4×4 matmul per joint (few numpy calls).

A compensator's single correction walks the chain in compiled code (:mod:`labcal.compensator._jit`), tested against
these through the compensator's batched definition.

Fits have always run on these kernels, so their rounding is what the fits' bit-for-bit reproducibility rests on.

Worked example (a planar 2R arm, 1 m links)::

    >>> from labcal.kinematics.se3 import pose
    >>> m = LocalPOEModel.from_frames([pose([0, 0, 0]), pose([1, 0, 0]), pose([1, 0, 0])], ("revolute",) * 2)
    >>> np.round(m.fk(np.array([np.pi / 2, 0.0]))[:3, 3], 12) + 0.0
    array([0., 2., 0.])
    >>> m.joint_twists(np.zeros(2)).shape   # (k, 6, n), k = 1 for a single configuration
    (1, 6, 2)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from labcal.kinematics import metric, se3

REVOLUTE, PRISMATIC = "revolute", "prismatic"
# Below this many configurations the chain is walked with 4×4 matmuls (few numpy calls), from it on batch-last.
_SMALL_BATCH = 128
_Z_REVOLUTE = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
_Z_PRISMATIC = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])


def default_twist(joint_type: str) -> np.ndarray:
    """The unit joint twist of eq. (5) in the local frame: rotation about z or translation along z."""
    if joint_type == REVOLUTE:
        return _Z_REVOLUTE.copy()
    if joint_type == PRISMATIC:
        return _Z_PRISMATIC.copy()
    raise ValueError(f"joint type must be 'revolute' or 'prismatic', got {joint_type!r}")


def poe_link_frames(frames, twists, q) -> np.ndarray:
    """The local product of exponentials by definition (eq. 1; Modern Robotics' ``FKinSpace`` written with local
    frames): the poses in K0 of K_1 … K_{n+1}, each before its own joint moves it.

    frames: (n+1, 4, 4) initial relative frames A_1(0) … A_{n+1}(0); twists: (n, 6) unit joint twists (v, ω) in the
    local frames; q: (n,) or (k, n). Returns (k, n+1, 4, 4) with::

        out[:, 0] = A_1(0)
        out[:, j] = out[:, j-1] · exp(ξ̂_j q_j) · A_{j+1}(0)          j = 1 … n

    so ``out[:, n]`` is the tool pose T_base_tool(q) (:func:`poe_fk`). This is the definition the fast kernels of
    :class:`LocalPOEModel` are tested against; it builds every exponential with :func:`se3.exp_se3`.

    Example (a planar 2R arm with 1 m links, elbow at 90°)::

        >>> from labcal.kinematics.se3 import pose
        >>> frames = np.array([pose([0, 0, 0]), pose([1, 0, 0]), pose([1, 0, 0])])
        >>> z = np.array([[0, 0, 0, 0, 0, 1.0]] * 2)
        >>> np.round(poe_link_frames(frames, z, [0.0, np.pi / 2])[0, :, :2, 3], 12) + 0.0
        array([[0., 0.],
               [1., 0.],
               [1., 1.]])
    """
    frames, twists = np.asarray(frames, dtype=float), np.asarray(twists, dtype=float)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    k, n = q.shape
    out = np.empty((k, n + 1, 4, 4))
    out[:, 0] = frames[0]
    for j in range(n):
        out[:, j + 1] = out[:, j] @ se3.exp_se3(twists[j] * q[:, j, None]) @ frames[j + 1]
    return out


def poe_fk(frames, twists, q) -> np.ndarray:
    """Tool pose by the product of exponentials (:func:`poe_link_frames`): q (n,) → (4, 4), (k, n) → (k, 4, 4)."""
    T = poe_link_frames(frames, twists, q)[:, -1]
    return T[0] if np.ndim(q) == 1 else T


def poe_joint_twists(frames, twists, q) -> np.ndarray:
    """Joint twists in K0 by definition, ``Ad(K_j) ξ_j``: (k, 6, n), the spatial Jacobian (q as in poe_link_frames)."""
    K = poe_link_frames(frames, twists, q)[:, :-1]  # (k, n, 4, 4)
    return np.einsum("kjab,jb->kaj", se3.adjoint(K), np.asarray(twists, dtype=float))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over axis 1 of (m, 3, ...) arrays (batch last); np.cross wants the vector axis last."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class LocalPOEModel:
    """An immutable local-POE robot model.

    frames: (n+1, 4, 4) initial relative frames A_1(0) … A_{n+1}(0); the last is the tool frame.
    joint_types: n entries, "revolute" or "prismatic".
    twists: (n, 6) unit joint twists (v, ω) in the local frames K_j.
    limits: (n, 2) joint limits [lo, hi] in rad (m for prismatic joints).
    """

    frames: np.ndarray
    joint_types: tuple[str, ...]
    twists: np.ndarray
    limits: np.ndarray
    name: str = ""
    joint_names: tuple[str, ...] = field(default=())
    # Derived in __post_init__ (not arguments): the kernels' dispatch. Declared so that they are typed; excluded
    # from repr and from replace().
    _revolute_mask: np.ndarray = field(init=False, repr=False)
    _z_joint: tuple[bool, ...] = field(init=False, repr=False)
    _all_revolute_z: bool = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = len(self.joint_types)
        frames, twists, limits = _readonly(self.frames), _readonly(self.twists), _readonly(self.limits)
        if frames.shape != (n + 1, 4, 4):
            raise ValueError(f"frames must have shape ({n + 1}, 4, 4) for {n} joints, got {frames.shape}")
        if twists.shape != (n, 6):
            raise ValueError(f"twists must have shape ({n}, 6), got {twists.shape}")
        if limits.shape != (n, 2) or np.any(limits[:, 0] > limits[:, 1]):
            raise ValueError(f"limits must be ({n}, 2) with lo <= hi, got {limits.tolist()}")
        for j, (t, xi) in enumerate(zip(self.joint_types, twists, strict=True)):
            default_twist(t)  # validates the type
            part = xi[3:] if t == REVOLUTE else xi[:3]
            if not np.isclose(np.linalg.norm(part), 1.0, atol=1e-9):
                raise ValueError(f"joint {j + 1}: the twist's {'axis' if t == REVOLUTE else 'direction'} is not unit")
            if t == PRISMATIC and np.linalg.norm(xi[3:]) > 1e-12:
                raise ValueError(f"joint {j + 1}: a prismatic twist has no angular part")
        if not np.all(np.isfinite(frames)) or not np.allclose(frames[:, 3], [0, 0, 0, 1]):
            raise ValueError("frames must be finite homogeneous transforms")
        names = tuple(self.joint_names) or tuple(f"joint{j + 1}" for j in range(n))
        if len(names) != n:
            raise ValueError(f"joint_names has {len(names)} entries for {n} joints")
        object.__setattr__(self, "frames", frames)
        object.__setattr__(self, "twists", twists)
        object.__setattr__(self, "limits", limits)
        object.__setattr__(self, "joint_types", tuple(self.joint_types))
        object.__setattr__(self, "joint_names", names)
        # Joints about the local z axis get a closed-form cos/sin exponential (the common case: 10x faster).
        object.__setattr__(self, "_revolute_mask", np.array([t == REVOLUTE for t in self.joint_types]))
        z_joint = tuple(np.array_equal(xi, default_twist(t)) for t, xi in zip(self.joint_types, twists, strict=True))
        object.__setattr__(self, "_z_joint", z_joint)
        object.__setattr__(self, "_all_revolute_z", all(z_joint) and bool(self._revolute_mask.all()))

    @classmethod
    def from_frames(
        cls,
        frames,
        joint_types,
        twists=None,
        limits=None,
        name: str = "",
        joint_names=(),
    ) -> LocalPOEModel:
        """Build a model; default twists from eq. (5), default limits ±π (revolute) / ±1 m (prismatic)."""
        joint_types = tuple(joint_types)
        if twists is None:
            twists = np.array([default_twist(t) for t in joint_types]).reshape(len(joint_types), 6)
        if limits is None:
            limits = np.array([[-np.pi, np.pi] if t == REVOLUTE else [-1.0, 1.0] for t in joint_types])
        return cls(frames, joint_types, twists, limits, name, joint_names)  # __post_init__ makes arrays and tuples

    # ----------------------------------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of actuated joints."""
        return len(self.joint_types)

    def _as_batch(self, q) -> tuple[np.ndarray, bool]:
        q = np.asarray(q, dtype=float)
        single = q.ndim == 1
        q2 = q[None, :] if single else q
        if q2.ndim != 2 or q2.shape[1] != self.n:
            raise ValueError(f"q must have shape ({self.n},) or (k, {self.n}), got {q.shape}")
        return q2, single

    def _walk(self, q2: np.ndarray) -> np.ndarray:
        """Walk the chain once: (n+1, 3, 4, k) top three rows of the frames K_1 … K_{n+1} in K0, each before its own
        joint moves it (see :meth:`link_frames`). The batch axis is last so that every step is a handful of whole-array
        multiply-adds over k numbers; the bottom row of a homogeneous transform is never stored or multiplied.
        """
        k, n = q2.shape[0], self.n
        if k < _SMALL_BATCH:
            return self._walk_small(q2)[:, :, :3, :].transpose(1, 2, 3, 0)
        W = np.empty((n + 1, 3, 4, k))
        W[0] = self.frames[0, :3, :, None]
        tmp = np.empty((3, k))
        for j in range(n):
            M, qj = W[j], q2[:, j]
            if self._z_joint[j] and self.joint_types[j] == REVOLUTE:
                # M · Rz(q): only columns 0 and 1 change.
                c, s = np.cos(qj), np.sin(qj)
                cols = (M[:, 0] * c + M[:, 1] * s, M[:, 1] * c - M[:, 0] * s, M[:, 2], M[:, 3])
            elif self._z_joint[j]:
                cols = (M[:, 0], M[:, 1], M[:, 2], M[:, 3] + M[:, 2] * qj)  # M · Tz(q)
            else:
                E = se3.exp_se3(self.twists[j] * qj[:, None])  # (k, 4, 4), bottom row (0, 0, 0, 1)
                cols = tuple(
                    M[:, 0] * E[:, 0, b] + M[:, 1] * E[:, 1, b] + M[:, 2] * E[:, 2, b] + (M[:, 3] if b == 3 else 0.0)
                    for b in range(4)
                )
            # (M · exp) · A_{j+1}(0), column by column; A's bottom row is (0, 0, 0, 1).
            F, out = self.frames[j + 1], W[j + 1]
            for b in range(4):
                acc = out[:, b]
                np.multiply(cols[0], F[0, b], out=acc)
                for i in (1, 2):
                    np.multiply(cols[i], F[i, b], out=tmp)
                    acc += tmp
                if b == 3:
                    acc += cols[3]
        return W

    def _walk_small(self, q2: np.ndarray) -> np.ndarray:
        """The chain for a few configurations, as :meth:`link_frames`' (k, n+1, 4, 4) frames: fewer, larger numpy calls
        (one 4×4 matmul per joint) than :meth:`_walk`, which pays per call and wins only on large batches.

        For z-axis joints every step ``exp(ξ̂_j q_j) · A_{j+1}(0)`` is built for all joints at once: ``Rz(q) · A``
        mixes rows 0 and 1 of A by (cos q, sin q), ``Tz(q) · A`` adds q to A's z translation; another axis's step is
        ``exp_se3(ξ_j q_j) · A``.
        """
        k, n = q2.shape[0], self.n
        frames = np.empty((k, n + 1, 4, 4))
        T = frames[:, 0] = self.frames[0]
        F = self.frames[1:]  # (n, 4, 4)
        revolute = self._revolute_mask
        s = np.where(revolute, np.sin(q2), 0.0)[:, :, None]
        c = np.where(revolute, np.cos(q2), 1.0)[:, :, None]
        G = np.empty((k, n, 4, 4))
        G[:, :, 0] = c * F[:, 0] - s * F[:, 1]
        G[:, :, 1] = s * F[:, 0] + c * F[:, 1]
        G[:, :, 2:] = F[:, 2:]
        if not revolute.all():
            G[:, :, 2, 3] += np.where(revolute, 0.0, q2)
        for j in range(n):
            if not self._z_joint[j]:
                G[:, j] = se3.exp_se3(self.twists[j] * q2[:, j, None]) @ F[j]
            T = frames[:, j + 1] = T @ G[:, j]
        return frames

    @staticmethod
    def _to_matrices(top: np.ndarray) -> np.ndarray:
        """(..., 3, 4, k) top rows, batch last → (k, ..., 4, 4) homogeneous transforms, batch first."""
        lead = top.shape[:-3]
        axes = (top.ndim - 1, *range(len(lead)), top.ndim - 3, top.ndim - 2)
        out = np.empty((top.shape[-1], *lead, 4, 4))
        out[..., :3, :] = top.transpose(axes)
        out[..., 3, :3] = 0.0
        out[..., 3, 3] = 1.0
        return out

    def _twists_from_walk(self, W: np.ndarray) -> np.ndarray:
        """(k, 6, n) joint twists Ad(K_j) ξ_j in K0 from a walk: ω = R ω_loc, v = R v_loc + p × ω."""
        n = self.n
        R, p = W[:n, :, :3], W[:n, :, 3]  # (n, 3, 3, k), (n, 3, k)
        v_loc, w_loc = self.twists[:, :3, None, None], self.twists[:, 3:, None, None]
        if all(self._z_joint):
            # ξ = (0, e_z) or (e_z, 0): ω or v is the third column of R, exactly.
            revolute = self._revolute_mask[:, None, None]
            w = np.where(revolute, R[:, :, 2], 0.0)
            v = np.where(revolute, 0.0, R[:, :, 2])
        else:
            w = R[:, :, 0] * w_loc[:, 0] + R[:, :, 1] * w_loc[:, 1] + R[:, :, 2] * w_loc[:, 2]
            v = R[:, :, 0] * v_loc[:, 0] + R[:, :, 1] * v_loc[:, 1] + R[:, :, 2] * v_loc[:, 2]
        v = v + _cross(p, w)
        out = np.empty((W.shape[-1], 6, n))
        out[:, :3] = v.transpose(2, 1, 0)
        out[:, 3:] = w.transpose(2, 1, 0)
        return out

    # ----------------------------------------------------------------------------------------------------------
    def fk(self, q) -> np.ndarray:
        """Tool pose T_base_tool: q (n,) → (4, 4); q (k, n) → (k, 4, 4).

        By definition :func:`poe_fk` (the product of exponentials); computed by the chain walk kernels, which agree
        with it to rounding (tests/kinematics) and are what fits have always used (their rounding is kept).
        """
        q2, single = self._as_batch(q)
        if q2.shape[0] < _SMALL_BATCH:
            T = self._walk_small(q2)[:, self.n]
        else:
            T = self._to_matrices(self._walk(q2)[self.n])
        return T[0] if single else T

    def link_frames(self, q) -> np.ndarray:
        """(k, n+1, 4, 4) poses in K0 of K_1 … K_{n+1} before their joints move them: ``[:, j]`` is
        ``prod_{i<=j}(A_i e^{ξ_i q_i}) · A_{j+1}(0)``, the frame whose adjoint is Ad_{j0} in eq. (10); ``[:, n]`` is the
        tool pose."""
        q2, _ = self._as_batch(q)
        return self._walk_small(q2) if q2.shape[0] < _SMALL_BATCH else self._to_matrices(self._walk(q2))

    def frames_and_twists(self, q) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`link_frames` (k, n+1, 4, 4; the tool pose is ``[:, n]``) and :meth:`joint_twists` (k, 6, n) from
        one walk of the chain: what a runtime needs to predict poses, joint twists and gravity directions at once."""
        frames = self.link_frames(q)
        return frames, self._twists_from_walk(frames[:, :, :3, :].transpose(1, 2, 3, 0))  # the top rows, batch last

    def fk_and_twists(self, q) -> tuple[np.ndarray, np.ndarray]:
        """(k, 4, 4) tool poses and (k, 6, n) actuated joint twists in K0, from one walk of the chain."""
        frames, twists = self.frames_and_twists(q)
        return frames[:, self.n], twists

    def joint_twists(self, q) -> np.ndarray:
        """Actuated joint twists in K0, (k, 6, n): the spatial Jacobian, J_ρ of eq. (14) when n = 6.

        Column j is ``Ad(K_j) ξ_j``: the pose error twist caused by a small motion error of joint j.
        """
        q2, _ = self._as_batch(q)
        return self._twists_from_walk(self._walk(q2))

    def equivalent_jacobian(self, q, length_scale: float | None = None) -> np.ndarray:
        """(k, 6, 6) Jacobian of the equivalent robot (eq. 12-14): actuated twists, then 6 − n virtual twists.

        For n < 6 the virtual joints span the motions the ideal robot cannot make. They are built from the
        orthogonal complement of the actuated twists in a length-scaled metric (linear parts divided by
        ``length_scale``, default: the robot's reach at q = 0, at least 0.1 m): the six unit coordinate twists are
        projected onto that complement, 6 − n of them are chosen one by one, each time the one with the largest part
        outside the actuated twists and those already chosen (ties broken by index), and the chosen projections are
        orthonormalised in index order. For the usual lower-mobility robots (e.g. a SCARA, whose complement is
        spanned by rotations about x and y) this picks a constant basis, so the virtual joint errors are smooth
        functions of q.
        """
        _, J = self.fk_and_twists(q)
        k, n = J.shape[0], self.n
        if n >= 6:
            return J
        D = metric.twist_weights(length_scale if length_scale is not None else self.reach())
        out = np.empty((k, 6, 6))
        out[:, :, :n] = J
        Q, _ = np.linalg.qr(D[:, None] * J)  # (k, 6, n), one LAPACK call per configuration
        P = np.eye(6) - Q @ Q.transpose(0, 2, 1)  # projector onto the complement
        # Greedy pivoting: take the coordinate twist with the largest part left outside the actuated span and the
        # twists already taken. Picking the 6 − n largest projections at once can pick dependent ones (say ±(e_x −
        # e_y) when the span holds a translation along x + y), whose Gram-Schmidt leaves rounding noise as a "joint".
        # A pivot's residual is at least 1/√6 of unit length (the residual projector has trace ≥ 1), so never noise.
        rows = np.arange(k)
        residual = P.copy()
        chosen = np.empty((k, 6 - n), dtype=int)
        for m in range(6 - n):
            norms = np.linalg.norm(residual, axis=1)  # (k, 6); argmax breaks exact ties by index
            c = np.argmax(norms, axis=1)
            u = residual[rows, :, c] / norms[rows, c][:, None]
            residual -= u[:, :, None] * u[:, None, :]
            chosen[:, m] = c
        chosen = np.sort(chosen, axis=1)
        cols = np.take_along_axis(P, chosen[:, None, :], axis=2)  # (k, 6, 6 − n)
        basis = np.empty_like(cols)
        for m in range(6 - n):  # modified Gram-Schmidt in index order
            u = cols[:, :, m].copy()
            for b in range(m):
                u -= np.einsum("ka,ka->k", basis[:, :, b], u)[:, None] * basis[:, :, b]
            basis[:, :, m] = u / np.linalg.norm(u, axis=1, keepdims=True)
        out[:, :, n:] = basis / D[:, None]
        return out

    def frame_jacobian(self, q) -> np.ndarray:
        """(k, 6, 6(n+1)): d δy / d δζ for right-perturbed frames ``A_j(0) · exp(δζ̂_j)``, j = 1 … n+1 (eq. 11).

        Block j is Ad_{j0}, the adjoint of frame K_j at the configuration before its joint moves it.
        """
        q2, _ = self._as_batch(q)
        k = q2.shape[0]
        if k < _SMALL_BATCH:
            Ad = se3.adjoint(self._walk_small(q2))  # (k, n+1, 6, 6)
            return Ad.transpose(0, 2, 1, 3).reshape(k, 6, 6 * (self.n + 1))
        W = self._walk(q2)
        R, p = W[:, :, :3], W[:, :, 3]  # (n+1, 3, 3, k), (n+1, 3, k)
        pR = _cross(p[:, :, None], R)  # column c of p̂R is p × R e_c
        # Laid out as (k, row, frame, column) so that the reshape puts block j at columns 6j … 6j+5.
        out = np.zeros((q2.shape[0], 6, self.n + 1, 6))
        Rt = R.transpose(3, 1, 0, 2)
        out[:, :3, :, :3] = Rt
        out[:, 3:, :, 3:] = Rt
        out[:, :3, :, 3:] = pR.transpose(3, 1, 0, 2)
        return out.reshape(q2.shape[0], 6, 6 * (self.n + 1))

    def target_points(self, q, targets) -> np.ndarray:
        """Positions in K0 of target points given in the tool frame: targets (m, 3) → (k, m, 3)."""
        q2, _ = self._as_batch(q)
        T = self._walk(q2)[self.n]  # (3, 4, k)
        targets = np.asarray(targets, dtype=float)
        return np.einsum("abk,mb->kma", T[:, :3], targets) + T[:, 3].T[:, None, :]

    def reach(self) -> float:
        """Distance from the base origin to the tool at q = 0 plus the link offsets: a length scale (m)."""
        offsets = np.linalg.norm(self.frames[:, :3, 3], axis=1).sum()
        return float(max(offsets, 0.1))

    # ----------------------------------------------------------------------------------------------------------
    def perturbed(self, delta_zeta) -> LocalPOEModel:
        """A new model with frames ``A_j(0) · exp(δζ̂_j)``; delta_zeta (n+1, 6) or flat (6(n+1),)."""
        dz = np.asarray(delta_zeta, dtype=float).reshape(self.n + 1, 6)
        return self.replace(frames=self.frames @ se3.exp_se3(dz))

    def replace(self, **changes) -> LocalPOEModel:
        """A copy with some fields replaced (frames, twists, limits, name …)."""
        return dataclasses.replace(self, **changes)

    def with_tool(self, T_flange_tool) -> LocalPOEModel:
        """A copy whose tool frame is moved by T_flange_tool (4, 4), expressed in the current tool frame."""
        frames = self.frames.copy()
        frames[-1] = frames[-1] @ np.asarray(T_flange_tool, float)
        return self.replace(frames=frames)

    def with_base(self, T_world_base) -> LocalPOEModel:
        """A copy expressed in another world frame: K0 becomes the frame in which T_world_base is given."""
        frames = self.frames.copy()
        frames[0] = np.asarray(T_world_base, float) @ frames[0]
        return self.replace(frames=frames)

    def within_limits(self, q, margin: float = 0.0) -> np.ndarray:
        """(k,) bool: every joint inside [lo + margin, hi − margin]."""
        q2, _ = self._as_batch(q)
        return np.all((q2 >= self.limits[:, 0] + margin) & (q2 <= self.limits[:, 1] - margin), axis=1)
