"""The calibrated robot: identified frames, learned joint motion errors, and the corrections they imply.

A :class:`CalibratedRobot` is the output of every calibration method and the content of every export:

- ``model``: the identified local-POE frames (equal to ``nominal`` for the paper's pure ANN method);
- ``network``: optional learned joint motion errors δρ(q) of the equivalent robot built on ``model`` (eq. 12-16),
  max(n, 6) outputs: the n actuated joints, then 6 − n virtual joints for n < 6; its inputs are
  :mod:`labcal.features`;
- ``T_tracker_base``: the estimated pose of the robot base in the tracker frame (identity for base-frame data);
- ``measurement_tool``: the identified pose of the measurement fixture (the frame the calibration's targets were
  given in: probe, SMR nest) in the robot's tool0 frame (the last frame of ``nominal``: the flange, or the robot
  file's ``[tool]``); None when it is tool0 itself. ``model`` ends at tool0: it describes the robot only, so a
  calibration survives a tool change.

Tool frames. :meth:`CalibratedRobot.predict_pose` and :meth:`CalibratedRobot.correct` work at a TCP given in tool0
(``tcp=``; default tool0, i.e. the robot file's tool); :meth:`CalibratedRobot.predict_points` places targets on the
measurement fixture (the calibration's own targets). For a 6-joint arm the exact correction is the same for every
TCP (the flange reaching its nominal pose brings every rigidly attached point there); the TCP sets where the pose
error is measured while the solver is not yet exact (damped steps near a singularity, least squares for n < 6).

The real robot commanded q reaches (first order in δρ, eq. 14)::

    T_real(q) = exp( (J_ρ(q) δρ(q))^ ) · T_model(q)

and :meth:`CalibratedRobot.correct` finds q_cmd with ``T_real(q_cmd) = T_nominal(q)`` by
:func:`labcal.compensator.solve.solve` over the residual :meth:`CalibratedRobot.residual`. ``method="paper"`` is
eq. (23-24), ``q_cmd = q − δρ_a(q)``.

Example::

    >>> from labcal.robots import load
    >>> nominal = load("ur10").model
    >>> robot = CalibratedRobot(nominal=nominal, model=nominal)       # an uncalibrated robot
    >>> q = np.array([0.1, -1.2, 1.0, -1.4, -1.5, 0.2])
    >>> np.allclose(robot.correct(q), q)
    True
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from labcal import features as feature_lib
from labcal.compensator import kernel as kernel_lib
from labcal.compensator import solve as solver
from labcal.compensator.validity import ValidityRegion
from labcal.kinematics import metric, se3
from labcal.kinematics.poe import LocalPOEModel
from labcal.robots.joint_map import JointMap

_FLOAT64 = np.dtype(np.float64)  # numpy's one float64 descriptor: an identity test is the cheapest dtype check


def input_features(q: np.ndarray, names: tuple[str, ...], model: LocalPOEModel, frames=None) -> np.ndarray:
    """(k, n) joint values → (k, f) network inputs: the :mod:`labcal.features` ``names`` side by side.

    frames: the model's link frames at q when the caller has them (``gravity`` needs them; computed otherwise).
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    run = feature_lib.evaluator(tuple(names), model.joint_types, model.limits)  # ValueError for an unknown name
    if frames is None and run.needs_frames:
        frames = model.link_frames(q)
    return run(q, frames)


@dataclass(frozen=True, eq=False)
class Network:
    """A feed-forward network in numpy: normalised features → tanh hidden layers → N linear outputs (N = max(n, 6),
    the equivalent robot's joint motion errors).

    weights[i]: (out_i, in_i); biases[i]: (out_i,). Inputs are standardised with in_mean/in_scale and outputs
    de-standardised with out_mean/out_scale, so the stored weights act on unit-scale numbers.
    """

    features: tuple[str, ...]
    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]
    in_mean: np.ndarray
    in_scale: np.ndarray
    out_mean: np.ndarray
    out_scale: np.ndarray

    def __call__(self, q: np.ndarray, model: LocalPOEModel) -> np.ndarray:
        """(k, n) joint values → (k, N) joint motion errors δρ (rad or m)."""
        h = (input_features(q, self.features, model) - self.in_mean) / self.in_scale
        last = len(self.weights) - 1
        for i, (W, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = h @ W.T + b
            if i < last:
                h = np.tanh(h)
        return h * self.out_scale + self.out_mean

    @property
    def hidden(self) -> tuple[int, ...]:
        return tuple(W.shape[0] for W in self.weights[:-1])

    @property
    def outputs(self) -> int:
        """N, the joint motion errors it predicts (the last layer's rows)."""
        return int(np.shape(self.weights[-1])[0])

    @functools.cached_property
    def _folded(self) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """Transposed weights with the input/output standardisation folded into the first/last layer."""
        Ws = [np.array(W, dtype=float) for W in self.weights]
        bs = [np.array(b, dtype=float) for b in self.biases]
        W0 = Ws[0] / self.in_scale
        bs[0] = bs[0] - W0 @ self.in_mean
        Ws[0] = W0
        Ws[-1] = Ws[-1] * self.out_scale[:, None]
        bs[-1] = bs[-1] * self.out_scale + self.out_mean
        return tuple(np.ascontiguousarray(W.T) for W in Ws), tuple(bs)

    def forward_features(self, x: np.ndarray) -> np.ndarray:
        """(k, f) raw (un-normalised) features → (k, N) outputs; the fast path of __call__."""
        Wt, bs = self._folded
        h = x
        last = len(Wt) - 1
        for i in range(len(Wt)):
            h = h @ Wt[i]
            h += bs[i]
            if i < last:
                np.tanh(h, out=h)
        return h


# Small-angle exponential and logarithm: a correction's pose errors are milliradians, where a few series terms are
# exact to rounding and cost a handful of array operations instead of kinematics.se3's general branches.
_I3 = np.eye(3)
_SKEW = np.zeros((3, 9))  # w @ _SKEW = skew(w).ravel()
_SKEW[2, 1], _SKEW[1, 2], _SKEW[2, 3], _SKEW[0, 5], _SKEW[1, 6], _SKEW[0, 7] = -1, 1, 1, -1, -1, 1
_ANTI9 = np.zeros((9, 4))  # R.ravel() @ _ANTI9 = (2 · unskew(R), trace(R))
_ANTI9[7, 0], _ANTI9[5, 0], _ANTI9[2, 1], _ANTI9[6, 1], _ANTI9[3, 2], _ANTI9[1, 2] = 1, -1, 1, -1, 1, -1
_ANTI9[0, 3] = _ANTI9[4, 3] = _ANTI9[8, 3] = 1.0
_SMALL = 1e-2  # rad: below this the series are exact to rounding (as in kinematics.se3)


def _exp_small(xi: np.ndarray) -> np.ndarray:
    """(k, 6) twists → (k, 4, 4); series for rotations below _SMALL, else kinematics.se3."""
    w = xi[:, 3:]
    t2 = np.einsum("ka,ka->k", w, w)
    if t2.size and t2.max() >= _SMALL * _SMALL:
        return se3.exp_se3(xi)
    k = xi.shape[0]
    a = (1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42)))[:, None, None]
    b = (0.5 - t2 / 24 * (1 - t2 / 30 * (1 - t2 / 56)))[:, None, None]
    c = (1 / 6 - t2 / 120 * (1 - t2 / 42 * (1 - t2 / 72)))[:, None, None]
    K = (w @ _SKEW).reshape(k, 3, 3)
    K2 = K @ K
    out = np.zeros((k, 4, 4))
    out[:, :3, :3] = _I3 + a * K + b * K2
    out[:, :3, 3] = ((_I3 + b * K + c * K2) @ xi[:, :3, None])[:, :, 0]
    out[:, 3, 3] = 1.0
    return out


def _log_small(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Rotation (k, 3, 3) and translation (k, 3) → (k, 6) twist of the pose; series below _SMALL."""
    k = R.shape[0]
    at = R.reshape(k, 9) @ _ANTI9  # (2 · unskew(R), trace(R))
    anti = 0.5 * at[:, :3]
    s2 = (anti * anti).sum(axis=1)
    if s2.max() >= (0.5 * _SMALL) ** 2 or at[:, 3].min() <= 1.0:  # a large angle, or one near π (cos θ ≤ 0)
        T = np.zeros((k, 4, 4))
        T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, p, 1.0
        return se3.log_se3(T)
    theta = np.arctan2(np.sqrt(s2), 0.5 * (at[:, 3] - 1.0))
    t2 = theta * theta
    out = np.empty((k, 6))
    w = out[:, 3:]
    np.divide(anti, (1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42)))[:, None], out=w)
    d = (1 / 12 + t2 / 720 + t2 * t2 / 30240)[:, None, None]
    K = (w @ _SKEW).reshape(k, 3, 3)
    out[:, :3] = ((_I3 - 0.5 * K + d * (K @ K)) @ p[:, :, None])[:, :, 0]
    return out


def _pose_log(T_target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(k, 4, 4) targets and poses → (k, 6) twists log(T_target T⁻¹) (series for small rotations, as _log_small)."""
    Rm, pm = T[:, :3, :3], T[:, :3, 3]
    dR = T_target[:, :3, :3] @ Rm.transpose(0, 2, 1)
    return _log_small(dR, T_target[:, :3, 3] - (dR @ pm[:, :, None])[:, :, 0])


# ad(ξ) of a twist ξ = (v, ω), [[ω̂, v̂], [0, ω̂]], as a linear map: ξ @ _AD = ad(ξ).ravel()
_AD: np.ndarray = np.zeros((6, 6, 6))
for _a, (_i, _j) in enumerate(((2, 1), (0, 2), (1, 0))):  # ŵ[i, j] = +w_a, ŵ[j, i] = −w_a
    for _row, _col, _src in ((0, 0, 3), (3, 3, 3), (0, 3, 0)):
        _AD[_src + _a, _row + _i, _col + _j], _AD[_src + _a, _row + _j, _col + _i] = 1.0, -1.0
_AD = _AD.reshape(6, 36)


def _bracket(J: np.ndarray, dy: np.ndarray, e: np.ndarray) -> np.ndarray:
    """(6, n) columns ad(ξ_i) (Σ_{j>i} δρ_j ξ_j − e/2): the change of ``J δρ`` with q_i at fixed δρ (joint i turns
    the twists after it) plus the first-order term of d log(E)/dq at the pose error e = log(E), for joint twists
    J = (ξ_i) and dy = (δρ_j ξ_j), both (6, n), and e (6,); leading batch axes pass through ((k, 6, n), (k, 6))."""
    n = J.shape[-1]
    # matmul and einsum on contiguous rows, not ndarray.dot and a stacked matmul of 6 × 6 matrices by strided
    # vectors: on a batch those run five to twenty times slower, at one configuration all cost the same
    z = dy @ _after(n) - 0.5 * e[..., None]  # (…, 6, n) Σ_{j>i} δρ_j ξ_j − e/2
    ad = (J.swapaxes(-1, -2) @ _AD).reshape(*J.shape[:-2], n, 6, 6)  # ad(ξ_i) of every joint
    return np.einsum("...iab,...ib->...ai", ad, np.ascontiguousarray(z.swapaxes(-1, -2)))


@functools.lru_cache(maxsize=8)
def _after(n: int) -> np.ndarray:
    """(n, n) U with U[j, i] = 1 for j > i: ``a @ U`` sums each row's later columns."""
    out = np.tril(np.ones((n, n)), -1)
    out.setflags(write=False)
    return out


def _check_solver_options(iterations, tol, damped_iterations) -> None:
    """Refuse solver options of the wrong kind by name (before, a string or a negative budget surfaced as a
    TypeError or an IndexError deep in the solver)."""
    if type(iterations) is int and type(tol) is float and damped_iterations is None:
        return  # the defaults' kinds: a control loop's call pays no more (numpy's abstract classes cost ~1 µs)
    if not isinstance(iterations, int | np.integer):
        raise ValueError(f"iterations must be a whole number, got {iterations!r}")
    if damped_iterations is not None and not (
        isinstance(damped_iterations, int | np.integer) and damped_iterations >= 0
    ):
        raise ValueError(f"damped_iterations must be None or a whole number >= 0, got {damped_iterations!r}")
    if not isinstance(tol, int | float | np.integer | np.floating) or isinstance(tol, bool):
        raise ValueError(f"tol must be a number (rad), got {tol!r}")


def _check_pose(T, what: str) -> np.ndarray:
    """A (4, 4) rigid transform as a read-only float array, or a ValueError naming ``what``."""
    try:
        T = np.array(T, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} must be a (4, 4) rigid transform: {err}") from None
    if (
        T.shape != (4, 4)
        or not np.isfinite(T).all()
        or not np.allclose(T[3], [0, 0, 0, 1])
        or not np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
        or np.linalg.det(T[:3, :3]) < 0
    ):
        raise ValueError(f"{what} must be a finite (4, 4) rigid transform (rotation + translation, last row 0 0 0 1)")
    T.setflags(write=False)
    return T


def _about_point(residual, points: np.ndarray):
    """The solver's residual re-expressed as twists about ``points`` (k, 3) instead of the base origin: the linear
    velocity becomes the velocity of that point, v + ω × p (a constant linear map of r and J per configuration, so
    an exact solution is unchanged while the damped steps and the metric of a least-squares solve measure at p)."""

    def moved(qc: np.ndarray, rows: np.ndarray, jacobian: bool = True):
        r, J = residual(qc, rows, jacobian)
        p = points[rows]
        r = np.concatenate([r[:, :3] + np.cross(r[:, 3:], p), r[:, 3:]], axis=1)
        if J is not None:
            Jv = J[:, :3] + np.cross(J[:, 3:].transpose(0, 2, 1), p[:, None, :]).transpose(0, 2, 1)
            J = np.concatenate([Jv, J[:, 3:]], axis=1)
        return r, J

    return moved


@dataclass(frozen=True, eq=False)
class CalibratedRobot:
    """A calibrated robot: what every fit returns and every export stores.

    joint_ranges: (n, 2) the joint ranges the calibration data covered; ``correct`` refuses q outside them unless
    ``extrapolate=True``. length_scale: metres per radian used to build virtual joints (n < 6), fixed at fit time.
    joint_map: the robot file's controller → model joint map (None: identity). Every method here works in *model*
    joints; the map only travels with the robot into its export, where :class:`Compensator` converts through it.
    validity: the neighbourhood of the fitted configurations (:mod:`labcal.compensator.validity`); when set,
    ``correct`` and ``check_range`` also refuse q farther than its radius from every fitted configuration
    (None: the joint ranges alone, as files written before it).
    """

    nominal: LocalPOEModel
    model: LocalPOEModel
    network: Network | None = None
    T_tracker_base: np.ndarray = field(default_factory=lambda: np.eye(4))
    joint_ranges: np.ndarray | None = None
    length_scale: float | None = None
    method: str = "nominal"
    joint_map: JointMap | None = None
    measurement_tool: np.ndarray | None = None
    measurement_tool_std: np.ndarray | None = None
    validity: ValidityRegion | None = None

    def __post_init__(self) -> None:
        if self.measurement_tool is not None:
            X = _check_pose(self.measurement_tool, "measurement_tool")
            object.__setattr__(self, "measurement_tool", None if np.array_equal(X, np.eye(4)) else X)
        if self.measurement_tool_std is not None:
            std = np.array(self.measurement_tool_std, dtype=float).reshape(6)
            std.setflags(write=False)
            object.__setattr__(self, "measurement_tool_std", std)
        if self.model.n != self.nominal.n:
            raise ValueError(f"model has {self.model.n} joints, nominal has {self.nominal.n}")
        if self.joint_map is not None:
            if self.joint_map.n != self.nominal.n:
                raise ValueError(f"joint map is for {self.joint_map.n} joints, the robot has {self.nominal.n}")
            if self.joint_map.is_identity:
                object.__setattr__(self, "joint_map", None)  # one stored form: no map
        if self.joint_ranges is None:
            object.__setattr__(self, "joint_ranges", self.nominal.limits.copy())
        length_scale = self.length_scale
        if length_scale is None:
            length_scale = self.nominal.reach()
            object.__setattr__(self, "length_scale", length_scale)
        if not (math.isfinite(length_scale) and length_scale > 0):
            raise ValueError(f"length_scale must be a positive number of metres per radian, got {self.length_scale!r}")
        if self.network is not None and self.network.outputs != max(self.n, 6):
            raise ValueError(
                f"the joint-motion-error network has {self.network.outputs} outputs; the equivalent robot of this "
                f"{self.n}-joint robot has {max(self.n, 6)} joint motion errors (eq. 12-14: max(n, 6))"
            )

    @property
    def n(self) -> int:
        return self.nominal.n

    def _batch(self, q) -> tuple[np.ndarray, bool]:
        if np.ma.isMaskedArray(q) and np.ma.getmaskarray(q).any():
            raise ValueError("q has masked values: fill or drop them first (a masked joint has no value to correct)")
        try:
            given = np.asarray(q)  # converted once: its dtype says what the caller passed
            kind = given.dtype.kind
            if kind not in "cUSV":  # complex would lose its imaginary part, text would be parsed: both hide a bug
                q = given.astype(float, copy=False)
        except (TypeError, ValueError) as err:
            raise ValueError(f"q must be numbers of shape ({self.n},) or (k, {self.n}): {err}") from err
        if kind in "cUSV":
            what = "complex numbers" if kind == "c" else "text"
            raise ValueError(f"q must be real numbers of shape ({self.n},) or (k, {self.n}), got {what}")
        single = q.ndim == 1
        q2 = q[None, :] if single else q
        if q2.ndim != 2 or q2.shape[1] != self.n:
            raise ValueError(
                f"q must have shape ({self.n},) or (k, {self.n}) for this {self.n}-joint robot, got {q.shape}"
            )
        if not np.isfinite(q2).all():
            i, j = np.argwhere(~np.isfinite(q2))[0]
            raise ValueError(f"q contains non-finite values: configuration {i}, joint {j + 1} is {q2[i, j]}")
        return q2, single

    def check_range(self, q, extrapolate: bool = False) -> None:
        """Raise ValueError naming the first configuration and joint outside the calibrated joint ranges."""
        if extrapolate:
            return
        q2, _ = self._batch(q)
        self._check_range(q2)

    def _check_range(self, q2: np.ndarray) -> None:
        lo, hi = self._ranges
        if (q2 >= lo).all() and (q2 <= hi).all():
            self._check_validity(q2)
            return
        bad = (q2 < lo) | (q2 > hi)
        i, j = np.argwhere(bad)[0]
        ranges = self.joint_ranges
        assert ranges is not None  # __post_init__ sets it
        raise ValueError(
            f"configuration {i}: joint {j + 1} = {q2[i, j]:.6f} is outside the calibrated range "
            f"[{ranges[j, 0]:.6f}, {ranges[j, 1]:.6f}]; pass extrapolate=True to correct it "
            "anyway"
        )

    def _check_validity(self, q2: np.ndarray) -> None:
        """Raise ValueError naming the first configuration farther than the validity radius from the data."""
        region = self.validity
        if region is None or q2.shape[0] == 0:
            return
        d = region.distance(q2)
        if (d <= region.radius).all():
            return
        i = int(np.argmax(d > region.radius))
        raise ValueError(
            f"configuration {i} is {d[i]:.3g} (joint distance in units of each joint's spread in the data) from the "
            f"nearest configuration the calibration measured, beyond its validity radius {region.radius:.3g}: the "
            "data say nothing there; "
            "measure poses near it, or pass extrapolate=True to correct it anyway"
        )

    @functools.cached_property
    def _kernel(self):
        """The compiled single correction (:func:`labcal.compensator.kernel.build`), None for the numpy path."""
        return kernel_lib.build(self)

    # the dataclass is frozen; cached_property writes __dict__ directly
    @functools.cached_property
    def _ranges(self) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(self.joint_ranges, dtype=float)
        return r[:, 0] - 1e-12, r[:, 1] + 1e-12

    @functools.cached_property
    def _twist_weights(self) -> np.ndarray:
        """(6,) the length-scaled metric of pose errors (:func:`labcal.kinematics.metric.twist_weights`)."""
        assert self.length_scale is not None  # __post_init__ sets it
        return metric.twist_weights(self.length_scale)

    @functools.cached_property
    def _inputs(self):
        """The network's input features for this model (:func:`labcal.features.evaluator`), prepared once."""
        return feature_lib.evaluator(tuple(self.network.features), self.model.joint_types, self.model.limits)

    @functools.cached_property
    def _linear_series(self):
        """δρ and its slope of a 6-joint z-revolute arm whose network is linear in one ``harmonics:H`` and
        optionally ``gravity`` and ``q`` (the joint series and the hybrid's learned term): a function ``(q (k, n),
        link frames (k, n+1, 4, 4)) → (δρ (k, 6), S (k, 6, n))``; None for any other network. The features are the
        registry's (:mod:`labcal.features`; the harmonics by :func:`~labcal.features.harmonics_of_joints`), so δρ
        equals the network up to rounding. S is
        dδρ/dq without the gravity terms' part (gravity features turn slowly with q: their slope saved a tenth of a
        Gauss-Newton step per call and cost more, benchmarks/compensator_tail.py).
        """
        network, model, n = self.network, self.model, self.n
        if len(network.weights) != 1 or n != 6 or not model._all_revolute_z:
            return None
        (Wt,), (bias,) = network._folded  # δρ = x @ Wt + bias
        H, harmonic, gravity, linear, start = 0, None, None, None, 0
        for name in network.features:
            feature = feature_lib.get(name)
            width = feature.size(n)
            block, start = Wt[start : start + width], start + width
            if feature.kind == "harmonics" and harmonic is None:
                H, harmonic = feature.order, block.reshape(n, feature.order, 2, 6)  # (joint, h − 1, sin/cos, out)
            elif feature.kind == "gravity" and gravity is None:
                gravity = (block.reshape(n, 3, 6), feature.prepare())
            elif feature.kind == "q" and linear is None:
                linear = block
            else:
                return None
        if harmonic is None:
            return None
        # Per joint j one (12, H) complex block acts on its harmonics, which come as complex sin h q + i cos h q
        # (features.harmonics_of_joints): columns δρ (6), then joint j's own slope dδρ/dq_j (6). A sin row a and a cos
        # row b become one complex row a − i b, so the real part of the product is a sin h q + b cos h q; the slope's
        # rows are (−h b, h a) (d sin(h q)/dq = h cos(h q), d cos(h q)/dq = −h sin(h q)). Only these blocks are
        # multiplied, not a dense product of all joints' features: joint j's harmonics reach δρ and joint j's slope,
        # nothing else. The gravity rows act on δρ alone.
        W_sin, W_cos, h = harmonic[:, :, 0], harmonic[:, :, 1], np.arange(1.0, H + 1)[:, None]
        sin_rows = np.concatenate([W_sin, -h * W_cos], axis=2)  # (n, H, 12)
        cos_rows = np.concatenate([W_cos, h * W_sin], axis=2)
        joint_W = (sin_rows - 1j * cos_rows).transpose(0, 2, 1)  # (n, 12, H), laid out (n, H, 12)
        gravity_W, gravity_of = (None, None) if gravity is None else (gravity[0].reshape(n * 3, 6), gravity[1])
        chunk = 2048  # configurations per product: bounds the harmonics in memory (n · H · chunk complex, 6 MB)

        def batch(q, frames) -> tuple[np.ndarray, np.ndarray]:  # the same terms for (k, n) q and their link frames
            k = q.shape[0]
            theta = np.ascontiguousarray(q.T)  # joint-major: every recurrence step is a contiguous vector
            cos_q, sin_q = np.cos(theta), np.sin(theta)
            out = np.empty((n, 12, k))  # per joint: its harmonics' part of δρ, then its slope column
            for start in range(0, k, chunk):
                rows = slice(start, start + chunk)
                x = feature_lib.harmonics_of_joints(cos_q[:, rows], sin_q[:, rows], H)  # (n, H, rows) complex
                out[:, :, rows] = (joint_W @ x).real
            rho = bias + out[:, :6].sum(axis=0).T
            if gravity_of is not None:
                rho += gravity_of(q, frames) @ gravity_W
            slope = np.ascontiguousarray(out[:, 6:].transpose(2, 1, 0))  # (k, 6, n): slope[i, :, j] = dδρ/dq_j
            if linear is not None:
                rho, slope = rho + q @ linear, slope + linear.T
            return rho, slope

        return batch

    # -- the calibrated forward model ----------------------------------------------------------------------------
    def _evaluate(self, q2: np.ndarray, need_twists: bool = True):
        """One walk of the identified chain: (link frames (k, n+1, 4, 4), actuated twists J (k, 6, n) or None,
        dy (k, 6) or None): dy = J_ρ δρ is the pose error twist the network predicts on top of the model (eq. 14).
        """
        if need_twists or self.network is not None:
            frames, J = self.model.frames_and_twists(q2)
        else:
            frames, J = self.model.link_frames(q2), None
        dy = None
        if self.network is not None:
            rho = self.network.forward_features(self._inputs(q2, frames))
            J_rho = J if self.n >= 6 else self.model.equivalent_jacobian(q2, length_scale=self.length_scale)
            dy = (J_rho @ rho[:, :, None])[:, :, 0]
        return frames, J, dy

    def joint_motion_errors(self, q) -> np.ndarray:
        """(k, N) predicted joint motion errors δρ(q) of the equivalent robot, N = max(n, 6) (zeros without a
        network)."""
        q2, _ = self._batch(q)
        if self.network is None or q2.shape[0] == 0:
            return np.zeros((q2.shape[0], max(self.n, 6)))
        frames = self.model.link_frames(q2) if self._inputs.needs_frames else None
        return self.network.forward_features(self._inputs(q2, frames))

    def equivalent_jacobian(self, q) -> np.ndarray:
        """(k, 6, N) J_ρ of the identified model (actuated + virtual joints, eq. 12-14; N = max(n, 6))."""
        return self.model.equivalent_jacobian(q, length_scale=self.length_scale)

    def predict_pose(self, q, *, tcp=None) -> np.ndarray:
        """Pose (4, 4) or (k, 4, 4) in the base frame of the TCP that the real robot reaches when commanded q.

        tcp: (4, 4) the TCP in tool0 (default: tool0 itself, the robot file's tool); ``tcp=robot.measurement_tool``
        gives the pose of the fixture the calibration measured."""
        q2, single = self._batch(q)
        T = self._predict(q2)
        if tcp is not None:
            T = T @ _check_pose(tcp, "tcp")
        return T[0] if single else T

    def _predict(self, q2: np.ndarray) -> np.ndarray:
        if q2.shape[0] == 0:
            return np.zeros((0, 4, 4))
        frames, _, dy = self._evaluate(q2, need_twists=False)
        T = frames[:, -1]
        if dy is None:
            return T.copy()
        return _exp_small(dy) @ T

    def predict_points(self, q, targets) -> np.ndarray:
        """(k, m, 3) predicted target positions in the base frame (targets (m, 3) as the calibration data give
        them: in the measurement fixture's frame, which sits at ``measurement_tool`` in tool0)."""
        q2, _ = self._batch(q)
        T = self._predict(q2)
        if self.measurement_tool is not None:
            T = T @ self.measurement_tool
        targets = np.asarray(targets, dtype=float)
        return np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]

    def residual(
        self, qc: np.ndarray, T_target: np.ndarray, jacobian: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Pose residual r (k, 6) and the steps' Jacobian J (k, 6, n) at q_cmd (k, n), targets (k, 4, 4).

        r = log(T_target T_model⁻¹) − J_ρ δρ: zero exactly when exp(J_ρ δρ) T_model = T_target, and it needs no
        exponential of the network's correction. J is the model's joint twists, −dr/dq up to O(|r| + |dδρ/dq|), so
        Gauss-Newton gains a few digits per step; for the joint series (:attr:`_linear_series`) it is the Newton
        Jacobian J + J dδρ/dq + the twists' turn under δρ + the log's first-order term (:func:`_bracket`)
        (``jacobian=False``, a settled step that reuses the last J: its Newton terms are skipped and J is None).
        For n < 6 (a least-squares problem) r is the exact log(T_target T_real⁻¹), whose minimiser is what the
        length-scaled metric defines (the difference form has the same zero but not the same minimum).
        """
        series = None if self.network is None else self._linear_series
        if series is not None:
            frames, J = self.model.frames_and_twists(qc)
            rho, slope = series(qc, frames)
            e = _pose_log(T_target, frames[:, -1])
            dy = J * rho[:, None, :]  # (k, 6, n): column j is δρ_j ξ_j
            if not jacobian:
                return e - dy.sum(axis=2), None
            return e - dy.sum(axis=2), J + J @ slope + _bracket(J, dy, e)
        frames, J, dy = self._evaluate(qc)
        T = frames[:, -1]
        if dy is not None and self.n < 6:
            return _pose_log(T_target, _exp_small(dy) @ T), J
        r = _pose_log(T_target, T)
        if dy is not None:
            r -= dy
        return r, J

    # -- corrections -------------------------------------------------------------------------------------------
    def correct(
        self,
        q,
        *,
        method: str = "newton",
        iterations: int = 10,
        tol: float = 1e-11,
        extrapolate: bool = False,
        damped_iterations: int | None = None,
        tcp=None,
    ) -> np.ndarray:
        """Joint commands that make the real robot reach the nominal pose of q. (n,) or (k, n), like q.

        tcp: (4, 4) the working TCP in tool0 (default tool0: the robot file's tool). Both the real and the nominal
        robot carry it, so an exact correction is the same for every TCP; it sets the point about which the pose
        error is measured where the solver is not exact (module docstring).

        method: ``"newton"`` (default) solves ``T_real(q_cmd) = T_nominal(q)`` on the calibrated forward model with
        :func:`labcal.compensator.solve.solve`: Gauss-Newton (least squares in the length-scaled metric for n < 6:
        only actuated joints are corrected; for a redundant arm, n > 6, the least joint change q_cmd − q that
        reaches the pose, so no self-motion is added) until the estimated distance to the solution is below
        ``tol`` (rad), and where a full step does not contract (near a singularity) a damped iteration from q that
        never makes the error worse than at q.
        ``"paper"`` is eq. (24), q − δρ_a(q); ``"fixed-point"`` iterates q_cmd = q − δρ_a(q_cmd). Both apply the
        network alone, so they are refused (a ValueError saying why) unless the identified frames are the nominal
        ones and there is a network: the paper's ANN method. An empty (0, n) q gives an empty (0, n) answer.
        A robot with a validity region (every fit's) never returns ``|q_cmd − q|`` above
        :data:`labcal.compensator.solve.MAX_CORRECTION` (0.1 rad, the URScript's refusal bound) at a configuration
        inside the region: where Gauss-Newton's answer lies beyond it (an ill-conditioned configuration: q5 ≈ 0, a
        stretched elbow) the damped iteration finds the best pose within that box. Configurations outside the
        region that ``extrapolate=True`` lets through are solved without the bound (the model's extrapolation, as
        asked for). Corrections are full-pose also with one or two targets: the identified
        joint axes determine the orientation, and a position-only solve was 3× worse at a tool point 150 mm from
        the reflector (benchmarks/data_speak.py).
        damped_iterations: the damped iteration's step budget (default solve.DAMPED_BUDGET); a control loop
        that must bound its worst-case time lowers it (near-singular configurations then stop earlier, no worse
        than at q).
        """
        _check_solver_options(iterations, tol, damped_iterations)
        if method == "newton" and type(q) is np.ndarray and q.dtype is _FLOAT64 and q.shape == (self.n,):
            # one configuration (a control loop's call): the compiled kernel checks the ranges and the validity
            # region itself and takes the definition's steps; None (no kernel, or q not finite / outside: the
            # batched path below names what is wrong) falls through
            kernel = self._kernel
            if kernel is not None and tcp is not None:
                try:
                    pose = _check_pose(tcp, "tcp")
                except ValueError:  # the batched path raises it, after the errors it names first (q's)
                    kernel = None
            else:
                pose = None
            if kernel is not None:
                out1 = kernel(q, extrapolate, iterations, tol, damped_iterations, pose)
                if out1 is not None:
                    return out1
        if method not in ("newton", "paper", "fixed-point"):
            raise ValueError(f"method must be 'newton', 'paper' or 'fixed-point', got {method!r}")
        if method != "newton" and (why := self.network_only_error(method)):
            raise ValueError(why)
        q2, single = self._batch(q)
        if not extrapolate:
            self._check_range(q2)
        if q2.shape[0] == 0:
            return q2.copy()  # nothing to correct: an empty (0, n) answer, like the input
        if method == "newton":
            tcp = None if tcp is None else _check_pose(tcp, "tcp")
            out = self._newton(q2, iterations, tol, damped_iterations, tcp, self._bounded_rows(q2, extrapolate))
        else:
            out = self._network_only(q2, method, iterations, tol)
        return out[0] if single else out

    def _bounded_rows(self, q2: np.ndarray, extrapolate: bool) -> np.ndarray | bool:
        """Which rows of q2 get the MAX_CORRECTION bound: those inside the validity region (all of them unless
        ``extrapolate`` let some through; none without a region)."""
        if self.validity is None:
            return False
        if not extrapolate:
            return True  # correct() refused every row outside the region
        # the refusal's own distances (_check_validity): a row correct() accepts without extrapolate is bounded with
        # it too (a |c − x|² test, summed otherwise, parts from them at the boundary's last ulp)
        return self.validity.inside(q2)

    def _newton(
        self,
        q2: np.ndarray,
        iterations: int,
        tol: float,
        damped_iterations: int | None,
        tcp: np.ndarray | None = None,
        bounded: np.ndarray | bool = False,
    ) -> np.ndarray:
        """method="newton": the solver over :meth:`residual` (the definition; :mod:`labcal.compensator.kernel`
        takes the same steps compiled); with a tcp, residual and Jacobian are twists about the TCP's nominal position.
        bounded:
        the rows (a (k,) mask, or True / False for all) whose correction is held within MAX_CORRECTION."""
        if not isinstance(bounded, bool):
            if bounded.all() or not bounded.any():
                bounded = bool(bounded.all())
            else:  # some rows inside the region, some extrapolated: two solves, each under its own rule
                out = np.empty_like(q2)
                for rows, bound in ((bounded, True), (~bounded, False)):
                    out[rows] = self._newton(q2[rows], iterations, tol, damped_iterations, tcp, bound)
                return out
        T_target = self.nominal.fk(q2)

        def residual(qc: np.ndarray, rows: np.ndarray, jacobian: bool = True):
            return self.residual(qc, T_target[rows], jacobian)

        if tcp is not None:
            residual = _about_point(residual, (T_target @ tcp)[:, :3, 3])
        weights, budget = self._twist_weights, damped_iterations
        # Inside the validity region a correction is bounded as the URScript bounds it (issue 27): there the data
        # speak, and beyond 0.1 rad only an ill-conditioned configuration amplifying the model's noise asks for
        # more. Outside it (extrapolate=True) the bound is lifted: the caller asked for the model's extrapolation,
        # and near singular configurations far from the data its large corrections are the model's answer (the
        # paper benchmark's compensated held-out means grew 1.24x when they were clipped).
        limit = solver.MAX_CORRECTION if bounded else None
        return solver.solve(
            residual, q2, iterations=iterations, tol=tol, weights=weights, damped_iterations=budget,
            max_correction=limit,
        )  # fmt: skip

    def _network_only(self, q2: np.ndarray, method: str, iterations: int, tol: float) -> np.ndarray:
        """method="paper": eq. (24), q − δρ_a(q); "fixed-point": q_cmd = q − δρ_a(q_cmd), iterated."""
        n = self.n
        if method == "paper":
            return q2 - self.joint_motion_errors(q2)[:, :n]
        out = q2.copy()
        for _ in range(max(iterations, 1)):  # as the Newton solver: at least one step
            nxt = q2 - self.joint_motion_errors(out)[:, :n]
            done = np.max(np.abs(nxt - out)) < tol
            out = nxt
            if done:
                break
        return out

    def network_only_error(self, method: str = "paper") -> str | None:
        """Why ``method`` ("paper" / "fixed-point": q − δρ_a, the network alone) cannot correct this robot, or None.

        It would silently return q unchanged without a network, and silently drop the identified frames' correction
        of a local-POE or hybrid calibration: both are refused rather than applied halfway.
        """
        if self.network is None:
            return (
                f"method={method!r} applies only the learned joint motion errors (eq. 24), and this {self.method} "
                "calibration has no network: it would return q uncorrected. Use method='newton'"
            )
        model, nominal = self.model, self.nominal  # the same for the paper's ANN method alone
        if not (np.array_equal(model.frames, nominal.frames) and np.array_equal(model.twists, nominal.twists)):
            return (
                f"method={method!r} applies only the learned joint motion errors (eq. 24) and would ignore the "
                f"identified frames of this {self.method} calibration. Use method='newton'"
            )
        return None

    @functools.cached_property
    def measurement_model(self) -> LocalPOEModel:
        """The identified chain ending at the measurement fixture (``model`` with ``measurement_tool`` appended):
        what the calibration data saw."""
        if self.measurement_tool is None:
            return self.model
        frames = np.array(self.model.frames)
        frames[-1] = frames[-1] @ self.measurement_tool
        return self.model.replace(frames=frames)
