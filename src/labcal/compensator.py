"""The compensator runtime: a calibrated robot model that predicts poses and corrects joint commands. Numpy only.

A :class:`CalibratedRobot` is the output of every calibration method and the content of every export:

- ``model``: the identified local-POE frames (equal to ``nominal`` for the paper's pure ANN method);
- ``network``: optional learned joint motion errors δρ(q) of the equivalent robot built on ``model`` (eq. 12-16),
  six outputs: the n actuated joints, then 6 − n virtual joints;
- ``T_tracker_base``: the estimated pose of the robot base in the tracker frame (identity for base-frame data).

The real robot commanded q reaches (first order in δρ, eq. 14)::

    T_real(q) = exp( (J_ρ(q) δρ(q))^ ) · T_model(q)

and :meth:`CalibratedRobot.correct` finds q_cmd with ``T_real(q_cmd) = T_nominal(q)``. ``method="paper"`` is
eq. (23-24), ``q_cmd = q − δρ_a(q)``; the default ``"newton"`` iterates on the full calibrated forward model and
is exact for model-based stages too.

:class:`Compensator` is the deployable form: :meth:`Compensator.load` reads a JSON or NPZ export written by
:meth:`CalibratedRobot.save` (schema version, robot model and its hash, identified frames, network, joint ranges,
tracker pose, length scale, joint map, provenance, golden vectors, and a checksum of each of those fields), refuses
a file whose fields do not match their checksums (an edit naming the field: a widened joint range would otherwise
silently switch off the out-of-range guard), re-computes the golden vectors and refuses a file that disagrees.

Joints: :class:`CalibratedRobot` works in the robot model's joints. When the robot file declares a joint map
(controller joints ≠ model joints, :mod:`labcal.robots.joint_map`), the map travels in the export and
:class:`Compensator` takes and returns *controller* joints, converting at its edge.

This module imports numpy, labcal.kinematics and labcal.robots (for the model hash) only, so a controller-side
process can load an export without torch, scipy, pandas or any driver.

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
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from labcal import features as feature_lib
from labcal.kinematics import se3
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel, StackedChains
from labcal.robots import model_hash
from labcal.robots.joint_map import JointMap

FEATURES = ("q", "sincos", "sincos2", "gravity")
_MAX_STEP = 0.02  # rad per damped step: corrections are milliradians, so larger steps mean a singularity
_GN_MAX_STEP = 0.3  # rad: a full Gauss-Newton step this large means a (near-)singular configuration

SCHEMA = "labcal-compensator"
SCHEMA_VERSION = 2  # 2: joint map, and per-field checksums over everything that changes behaviour
GOLDEN_COUNT = 8
GOLDEN_TOL_Q = 1e-10  # rad (m): a loaded file must reproduce its golden q_cmd to this
GOLDEN_TOL_POSE = 1e-10  # m / rad-scaled entries of the predicted pose


def input_features(q: np.ndarray, names: tuple[str, ...], model: LocalPOEModel) -> np.ndarray:
    """(k, n) joint values → (k, f) network inputs.

    - ``q``: the joint values themselves (the paper's choice);
    - ``sincos``: sin q_j, cos q_j (revolute joints; prismatic joints contribute q_j);
    - ``sincos2``: sin 2q_j, cos 2q_j (twice-per-revolution effects such as gear errors);
    - ``gravity``: the direction of gravity (base −z) in each link frame, 3n numbers: every gravity torque on a
      joint is a linear function of these for a rigid arm, whatever its mass model;
    - any feature of :mod:`labcal.features` (e.g. ``harmonics:H``: sin/cos of h q_j, h = 1 … H).
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    revolute = np.array([t == "revolute" for t in model.joint_types])
    parts = []
    for name in names:
        if name == "q":
            parts.append(q)
        elif name == "sincos":
            parts += [np.where(revolute, np.sin(q), q), np.where(revolute, np.cos(q), 0.0)]
        elif name == "sincos2":
            parts += [np.where(revolute, np.sin(2 * q), 0.0), np.where(revolute, np.cos(2 * q), 0.0)]
        elif name == "gravity":
            parts.append(_gravity_features(model.link_frames(q)))
        elif feature_lib.is_feature(name):
            parts.append(feature_lib.compute(q, name, model.joint_types, model.limits))
        else:
            raise ValueError(f"unknown network input feature {name!r}; known: {', '.join(FEATURES)}, harmonics:H")
    return np.concatenate(parts, axis=1)


@dataclass(frozen=True, eq=False)
class Network:
    """A feed-forward network in numpy: normalised features → tanh hidden layers → 6 linear outputs.

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
        """(k, n) joint values → (k, 6) joint motion errors δρ (rad or m)."""
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
        """(k, f) raw (un-normalised) features → (k, 6) outputs; the fast path of __call__."""
        Wt, bs = self._folded
        h = x
        last = len(Wt) - 1
        for i in range(len(Wt)):
            h = h @ Wt[i]
            h += bs[i]
            if i < last:
                np.tanh(h, out=h)
        return h


# ----------------------------------------------------------------------------------------------------------------
# Fast kernels. The runtime evaluates the chain a few times per correction, so the per-call numpy overhead matters
# more than the flops: every joint exponential is built in one vectorised step, the chain costs n small matmuls, and
# small-angle exp/log use series with a handful of array operations.

_I3 = np.eye(3)
_SKEW = np.zeros((3, 9))  # w @ _SKEW = skew(w).ravel()
_SKEW[2, 1], _SKEW[1, 2], _SKEW[2, 3], _SKEW[0, 5], _SKEW[1, 6], _SKEW[0, 7] = -1, 1, 1, -1, -1, 1
_ANTI9 = np.zeros((9, 4))  # R.ravel() @ _ANTI9 = (2 · unskew(R), trace(R))
_ANTI9[7, 0], _ANTI9[5, 0], _ANTI9[2, 1], _ANTI9[6, 1], _ANTI9[3, 2], _ANTI9[1, 2] = 1, -1, 1, -1, 1, -1
_ANTI9[0, 3] = _ANTI9[4, 3] = _ANTI9[8, 3] = 1.0
_SMALL = 1e-2  # rad: below this the series are exact to rounding (as in kinematics.se3)
_ONE = np.ones(1)


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
    if s2.max() >= (0.5 * _SMALL) ** 2:
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


def _tool_pose_lists(Ad: np.ndarray) -> tuple[list, list]:
    """(6, 6) adjoint [[R, p̂R], [0, R]] → (rows of R, p) as Python floats; p from p̂ = (p̂R) Rᵀ."""
    (r00, r01, r02, a00, a01, a02), (r10, r11, r12, a10, a11, a12), (r20, r21, r22, a20, a21, a22) = Ad[:3].tolist()
    p = [a20 * r10 + a21 * r11 + a22 * r12, a00 * r20 + a01 * r21 + a02 * r22, a10 * r00 + a11 * r01 + a12 * r02]
    return [[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]], p


def _pose_error_one(target: tuple[list, list], Ad: np.ndarray) -> np.ndarray:
    """log(T_target · T⁻¹) for one pose T given by its adjoint (6, 6), as a (6,) twist, in Python floats: a dozen
    numpy calls cost more than the math.

    target: (rows of R, p) of T_target as from _tool_pose_lists. Series as in _log_small for rotations below _SMALL
    (the case in every correction step), else the batched code.
    """
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = target[0]
    tx, ty, tz = target[1]
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = (pose := _tool_pose_lists(Ad))[0]
    bx, by, bz = pose[1]
    # dR = R_target R_Tᵀ and dp = p_target − dR p_T
    r00, r01, r02 = (
        a00 * b00 + a01 * b01 + a02 * b02,
        a00 * b10 + a01 * b11 + a02 * b12,
        a00 * b20 + a01 * b21 + a02 * b22,
    )
    r10, r11, r12 = (
        a10 * b00 + a11 * b01 + a12 * b02,
        a10 * b10 + a11 * b11 + a12 * b12,
        a10 * b20 + a11 * b21 + a12 * b22,
    )
    r20, r21, r22 = (
        a20 * b00 + a21 * b01 + a22 * b02,
        a20 * b10 + a21 * b11 + a22 * b12,
        a20 * b20 + a21 * b21 + a22 * b22,
    )
    px = tx - (r00 * bx + r01 * by + r02 * bz)
    py = ty - (r10 * bx + r11 * by + r12 * bz)
    pz = tz - (r20 * bx + r21 * by + r22 * bz)
    ax, ay, az = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    s2 = ax * ax + ay * ay + az * az
    if not s2 < (0.5 * _SMALL) ** 2:
        dR = np.array([[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]])
        return _log_small(dR[None], np.array([[px, py, pz]]))[0]
    theta = math.atan2(math.sqrt(s2), 0.5 * (r00 + r11 + r22 - 1.0))
    t2 = theta * theta
    a = 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42))
    wx, wy, wz = ax / a, ay / a, az / a
    d = 1 / 12 + t2 / 720 + t2 * t2 / 30240
    # V⁻¹ p = p − ½ w × p + d w × (w × p)
    cx, cy, cz = wy * pz - wz * py, wz * px - wx * pz, wx * py - wy * px
    ccx, ccy, ccz = wy * cz - wz * cy, wz * cx - wx * cz, wx * cy - wy * cx
    return np.array([px - 0.5 * cx + d * ccx, py - 0.5 * cy + d * ccy, pz - 0.5 * cz + d * ccz, wx, wy, wz])


try:  # the LAPACK gufunc behind np.linalg.solve
    from numpy.linalg._umath_linalg import solve1 as _lapack_solve1
except ImportError:  # pragma: no cover - other numpy layouts
    _lapack_solve1 = None


def _solve_one(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """J (n, n), r (n,) → J⁻¹ r, non-finite (never an exception) when J is singular.

    For one 6×6 system np.linalg.solve's Python wrapper (dtype checks, errstate, shape juggling) costs about three
    times the LAPACK call it makes, and a correction solves three systems; the gufunc it wraps is called directly
    when this numpy has it (a test checks both paths agree). Call it under ``np.errstate(invalid="ignore")``.
    """
    if _lapack_solve1 is not None:
        return _lapack_solve1(J, r)
    try:
        return np.linalg.solve(J, r)
    except np.linalg.LinAlgError:
        return np.full(r.shape, np.nan)


def _gravity_features(frames: np.ndarray) -> np.ndarray:
    """(k, n+1, 4, 4) link frames (LocalPOEModel.link_frames) → (k, 3n) base −z axis in the frames of links 1..n.
    Their adjoints (k, n+1, 6, 6) give the same: only R is read, and it is the top-left block of both.

    Row 2 of R is Rᵀ e_z: the base z axis in link coordinates.
    """
    return -frames[:, 1:, 2, :3].reshape(frames.shape[0], -1)


def _sincos(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.sin(q), np.cos(q)


@dataclass(frozen=True, eq=False)
class CalibratedRobot:
    """A calibrated robot: what every fit returns and every export stores.

    joint_ranges: (n, 2) the joint ranges the calibration data covered; ``correct`` refuses q outside them unless
    ``extrapolate=True``. length_scale: metres per radian used to build virtual joints (n < 6), fixed at fit time.
    joint_map: the robot file's controller → model joint map (None: identity). Every method here works in *model*
    joints; the map only travels with the robot into its export, where :class:`Compensator` converts through it.
    """

    nominal: LocalPOEModel
    model: LocalPOEModel
    network: Network | None = None
    T_tracker_base: np.ndarray = field(default_factory=lambda: np.eye(4))
    joint_ranges: np.ndarray | None = None
    length_scale: float | None = None
    method: str = "nominal"
    joint_map: JointMap | None = None

    def __post_init__(self) -> None:
        if self.model.n != self.nominal.n:
            raise ValueError(f"model has {self.model.n} joints, nominal has {self.nominal.n}")
        if self.joint_map is not None:
            if self.joint_map.n != self.nominal.n:
                raise ValueError(f"joint map is for {self.joint_map.n} joints, the robot has {self.nominal.n}")
            if self.joint_map.is_identity:
                object.__setattr__(self, "joint_map", None)  # one stored form: no map
        if self.joint_ranges is None:
            object.__setattr__(self, "joint_ranges", self.nominal.limits.copy())
        if self.length_scale is None:
            object.__setattr__(self, "length_scale", self.nominal.reach())
        if self.network is not None and self.n > 6:
            raise ValueError(
                f"a joint-motion-error network needs a robot with at most 6 joints (the equivalent robot has six, "
                f"eq. 12-14); this one has {self.n}"
            )

    @property
    def n(self) -> int:
        return self.nominal.n

    def _batch(self, q) -> tuple[np.ndarray, bool]:
        try:
            q = np.asarray(q, dtype=float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"q must be numbers of shape ({self.n},) or (k, {self.n}): {err}") from err
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

    def _inside_one(self, values: list) -> bool:
        lo, hi = self._range_lists
        return all(a <= v <= b for v, a, b in zip(values, lo, hi, strict=True))

    @functools.cached_property
    def _range_lists(self) -> tuple[list, list]:
        lo, hi = self._ranges
        return lo.tolist(), hi.tolist()

    def _check_range(self, q2: np.ndarray) -> None:
        lo, hi = self._ranges
        if (q2 >= lo).all() and (q2 <= hi).all():
            return
        bad = (q2 < lo) | (q2 > hi)
        i, j = np.argwhere(bad)[0]
        raise ValueError(
            f"configuration {i}: joint {j + 1} = {q2[i, j]:.6f} is outside the calibrated range "
            f"[{self.joint_ranges[j, 0]:.6f}, {self.joint_ranges[j, 1]:.6f}]; pass extrapolate=True to correct it "
            "anyway"
        )

    # -- cached fast-path state (the dataclass is frozen; cached_property writes __dict__ directly) ---------------
    @functools.cached_property
    def _ranges(self) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(self.joint_ranges, dtype=float)
        return r[:, 0] - 1e-12, r[:, 1] + 1e-12

    @functools.cached_property
    def _revolute(self) -> np.ndarray:
        return np.array([t == REVOLUTE for t in self.model.joint_types])

    @functools.cached_property
    def _feature_plan(self) -> tuple:
        if self.network is None:
            return ()
        for name in self.network.features:
            if name not in FEATURES and not feature_lib.is_feature(name):
                raise ValueError(f"unknown network input feature {name!r}; known: {', '.join(FEATURES)}, harmonics:H")
        return tuple(self.network.features)

    def _features(self, q, s, c, initial) -> np.ndarray:
        """The network inputs of input_features, from quantities the chain walk already computed."""
        rev = self._revolute
        allrev = bool(rev.all())
        parts = []
        for name in self._feature_plan:
            if name == "q":
                parts.append(q)
            elif name == "sincos":
                parts += [s, c] if allrev else [np.where(rev, s, q), np.where(rev, c, 0.0)]
            elif name == "sincos2":
                s2, c2 = 2.0 * s * c, c * c - s * s
                parts += [s2, c2] if allrev else [np.where(rev, s2, 0.0), np.where(rev, c2, 0.0)]
            elif name == "gravity":
                parts.append(_gravity_features(initial))
            else:
                parts.append(feature_lib.compute(q, name, self.model.joint_types, self.model.limits))
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)

    def _evaluate(self, q2: np.ndarray, need_twists: bool = True):
        """One walk of the identified chain: (initial frames, actuated twists J (k, 6, n) or None, dy (k, 6) or None).

        dy = J_ρ δρ is the pose error twist the network predicts on top of the model (eq. 14).
        """
        s, c = _sincos(q2)
        if need_twists or self.network is not None:
            initial, J = self.model.frames_and_twists(q2)
        else:
            initial, J = self.model.link_frames(q2), None
        dy = None
        if self.network is not None:
            rho = self.network.forward_features(self._features(q2, s, c, initial))
            J_rho = J if self.n >= 6 else self.model.equivalent_jacobian(q2, length_scale=self.length_scale)
            dy = (J_rho @ rho[:, :, None])[:, :, 0]
        return initial, J, dy

    # -- public model ------------------------------------------------------------------------------------------
    def joint_motion_errors(self, q) -> np.ndarray:
        """(k, 6) predicted joint motion errors δρ(q) of the equivalent robot (zeros without a network)."""
        q2, _ = self._batch(q)
        if self.network is None or q2.shape[0] == 0:
            return np.zeros((q2.shape[0], 6))
        s, c = _sincos(q2)
        initial = self.model.link_frames(q2)
        return self.network.forward_features(self._features(q2, s, c, initial))

    def equivalent_jacobian(self, q) -> np.ndarray:
        """(k, 6, 6) J_ρ of the identified model (actuated + virtual joints, eq. 12-14)."""
        return self.model.equivalent_jacobian(q, length_scale=self.length_scale)

    def predict_pose(self, q) -> np.ndarray:
        """Pose (4, 4) or (k, 4, 4) in the base frame that the real robot reaches when commanded q."""
        q2, single = self._batch(q)
        T = self._predict(q2)
        return T[0] if single else T

    def _predict(self, q2: np.ndarray) -> np.ndarray:
        if q2.shape[0] == 0:
            return np.zeros((0, 4, 4))
        initial, _, dy = self._evaluate(q2, need_twists=False)
        T = initial[:, -1]
        if dy is None:
            return T.copy()
        return _exp_small(dy) @ T

    def predict_points(self, q, targets) -> np.ndarray:
        """(k, m, 3) predicted target positions in the base frame (targets (m, 3) in the tool frame)."""
        q2, _ = self._batch(q)
        T = self._predict(q2)
        targets = np.asarray(targets, dtype=float)
        return np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]

    def correct(
        self,
        q,
        *,
        method: str = "newton",
        iterations: int = 10,
        tol: float = 1e-11,
        extrapolate: bool = False,
    ) -> np.ndarray:
        """Joint commands that make the real robot reach the nominal pose of q. (n,) or (k, n), like q.

        method: ``"newton"`` (default) solves ``T_real(q_cmd) = T_nominal(q)`` by Gauss-Newton on the calibrated
        forward model (least squares in a length-scaled metric for n < 6: only actuated joints are corrected; for
        a redundant arm, n > 6, minimum-norm steps, so q_cmd is a solution near q), stopping when the estimated
        distance to the solution is below ``tol`` (rad); configurations where a full step does not reduce the pose
        error (near a singularity) are re-solved by a damped (Levenberg-Marquardt) iteration that never makes the
        error worse than at q. ``"paper"`` is eq. (24), q − δρ_a(q);
        ``"fixed-point"`` iterates q_cmd = q − δρ_a(q_cmd). Both apply the network alone, so they are refused (a
        ValueError saying why) unless the identified frames are the nominal ones and there is a network: the paper's
        ANN method. An empty (0, n) q gives an empty (0, n) answer.
        """
        n = self.n
        if method == "newton" and n == 6 and isinstance(q, np.ndarray) and q.shape == (n,):
            # One configuration inside the ranges (a control loop's call): checked in Python floats, a few
            # microseconds less than the array checks below, which still give the errors for anything else.
            values = q.tolist()
            if math.isfinite(sum(values)) and (extrapolate or self._inside_one(values)):
                return self._gauss_newton_single(q.astype(float)[None], iterations, tol)[0]
        q2, single = self._batch(q)
        if method not in ("newton", "paper", "fixed-point"):
            raise ValueError(f"method must be 'newton', 'paper' or 'fixed-point', got {method!r}")
        if method != "newton" and (why := self.network_only_error(method)):
            raise ValueError(why)
        if not extrapolate:
            self._check_range(q2)
        if q2.shape[0] == 0:
            return q2.copy()  # nothing to correct: an empty (0, n) answer, like the input
        if method == "paper":
            out = q2 - self.joint_motion_errors(q2)[:, :n]
        elif method == "fixed-point":
            out = q2.copy()
            for _ in range(iterations):
                nxt = q2 - self.joint_motion_errors(out)[:, :n]
                done = np.max(np.abs(nxt - out)) < tol
                out = nxt
                if done:
                    break
        elif method == "newton":
            out = self._gauss_newton(q2, iterations, tol)
        else:
            raise ValueError(f"method must be 'newton', 'paper' or 'fixed-point', got {method!r}")
        return out[0] if single else out

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
        if not self._nominal_frames:
            return (
                f"method={method!r} applies only the learned joint motion errors (eq. 24) and would ignore the "
                f"identified frames of this {self.method} calibration. Use method='newton'"
            )
        return None

    @functools.cached_property
    def _nominal_frames(self) -> bool:
        """True when the identified model is the nominal one (the paper's ANN method)."""
        return bool(
            np.array_equal(self.model.frames, self.nominal.frames)
            and np.array_equal(self.model.twists, self.nominal.twists)
        )

    def _residual(self, qc: np.ndarray, T_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose residual r (k, 6) and the model's joint twists J (k, 6, n) at q_cmd.

        r = log(T_target T_model⁻¹) − J_ρ δρ: zero exactly when exp(J_ρ δρ) T_model = T_target, and it needs no
        exponential of the network's correction. Its Jacobian is −J up to O(|r| + |dδρ/dq|) ≈ 1e-3, so Gauss-Newton
        gains about three digits per step.
        """
        initial, J, dy = self._evaluate(qc)
        T = initial[:, -1]
        if dy is not None and self.n < 6:
            # A least-squares problem: keep the exact residual log(T_target T_real⁻¹) (its minimiser is what the
            # length-scaled metric defines; the difference form above has the same zero but not the same minimum).
            T = _exp_small(dy) @ T
            dy = None
        Rm, pm = T[:, :3, :3], T[:, :3, 3]
        Rt, pt = T_target[:, :3, :3], T_target[:, :3, 3]
        dR = Rt @ Rm.transpose(0, 2, 1)
        dp = pt - (dR @ pm[:, :, None])[:, :, 0]
        r = _log_small(dR, dp)
        if dy is not None:
            r -= dy
        return r, J

    def _gauss_newton(self, q2: np.ndarray, iterations: int, tol: float) -> np.ndarray:
        """Gauss-Newton from q on the rows still moving; rows where a full step fails go to Levenberg-Marquardt.

        A row stops when its estimated distance to the solution, |step| ρ / (1 − ρ) with ρ the ratio of its last
        two steps (linear convergence, ρ ≈ 1e-3 here), is below tol. A row fails when its steps stop contracting
        (a step more than half the previous one), are not finite or exceed _GN_MAX_STEP: that is a (near-)singular
        configuration, solved by the damped iteration instead.
        """
        k, n = q2.shape
        if k == 1 and n == 6:
            return self._gauss_newton_single(q2, iterations, tol)
        T_target = self.nominal.fk(q2)
        scale = None if n >= 6 else np.array([1.0 / self.length_scale] * 3 + [1.0] * 3)
        out = q2.copy()
        active = np.arange(k)
        prev_step = np.full(k, np.inf)
        failed = np.zeros(k, dtype=bool)
        for _ in range(max(iterations, 1)):
            qa, Ta = out[active], T_target[active]
            r, J = self._residual(qa, Ta)
            if scale is not None:
                r, J = r * scale, J * scale[:, None]
            try:
                if n == 6:
                    step = np.linalg.solve(J, r[:, :, None])[:, :, 0]
                elif n > 6:  # a redundant arm: the smallest joint step that removes the error, Jᵀ (J Jᵀ)⁻¹ r
                    Jt = J.transpose(0, 2, 1)
                    step = (Jt @ np.linalg.solve(J @ Jt, r[:, :, None]))[:, :, 0]
                else:
                    Jt = J.transpose(0, 2, 1)
                    step = np.linalg.solve(Jt @ J, Jt @ r[:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:
                step = np.full((len(active), n), np.nan)
            size = np.abs(step).max(axis=1)
            prev = prev_step[active]
            bad = ~(size <= np.minimum(_GN_MAX_STEP, 0.5 * prev))
            ratio = np.where(np.isfinite(prev), np.minimum(size / np.maximum(prev, 1e-300), 0.5), 0.5)
            done = (size * ratio / (1 - ratio) < tol) | (size < 1e-3 * tol)
            step[bad] = 0.0
            out[active] += step
            failed[active[bad]] = True
            prev_step[active] = size
            active = active[~(bad | done)]
            if active.size == 0:
                break
        # Rows still contracting after the iteration budget keep their Gauss-Newton result.
        if failed.any():
            idx = np.flatnonzero(failed)
            out[idx] = self._levenberg_marquardt(q2[idx], T_target[idx], max(iterations, 10) * 3, tol)
        return out

    @functools.cached_property
    def _nominal_and_model(self) -> StackedChains:
        return StackedChains((self.nominal, self.model))

    @functools.cached_property
    def _one_network(self) -> tuple | None:
        """The network as _gauss_newton_single evaluates it: (input plan, first matrix, later (matrix, bias) pairs).

        The inputs are the plan's arrays concatenated, then a 1: the first bias is the first matrix's last row, and
        the gravity inputs' sign (the features are −R_jᵀ e_z, the walk gives R_jᵀ e_z) is folded into their rows.
        None without a network, or when the features need the batched code (prismatic joints, features other than
        q, sincos and gravity).
        """
        net = self.network
        if net is None or not (self._revolute.all() and set(self._feature_plan) <= {"q", "sincos", "gravity"}):
            return None
        Wt, bs = net._folded
        n = self.n
        width = {"q": n, "sincos": 2 * n, "gravity": 3 * n}
        sign = np.concatenate([np.full(width[name], -1.0 if name == "gravity" else 1.0) for name in self._feature_plan])
        W0 = np.vstack([Wt[0] * sign[:, None], bs[0][None, :]])
        return tuple(self._feature_plan), W0, tuple(zip(Wt[1:], bs[1:], strict=True))

    def _joint_errors_one(self, q1, adjoints, c, s) -> np.ndarray:
        """δρ (6,) at one configuration from its runtime walk (adjoints of the link frames, cos q, sin q)."""
        plan = self._one_network
        if plan is None:
            # _gravity_features reads rotation rows, which adjoints hold where frames do
            x = self._features(q1[None], s[None], c[None], adjoints[None])[0]
            return self.network.forward_features(x)
        names, W0, layers = plan
        inputs = []
        for name in names:
            if name == "sincos":
                inputs += (s, c)
            elif name == "gravity":
                inputs.append(adjoints[1:, 2, :3])
            else:
                inputs.append(q1)
        h = np.concatenate((*inputs, _ONE), axis=None) @ W0
        for W, b in layers:
            h = np.tanh(h) @ W + b
        return h

    def _gauss_newton_single(self, q2: np.ndarray, iterations: int, tol: float) -> np.ndarray:
        """_gauss_newton for one configuration (1, n) of a 6-joint robot: the same iterates, with unbatched arrays.

        At one configuration numpy's per-call cost, not the flops, is the price, so every iteration is one walk of the
        chain in the adjoint representation (frames and joint twists at once; the nominal target shares the first
        walk), the pose error in Python floats, one network evaluation and one 6×6 solve: J⁻¹ (r − J δρ) = J⁻¹ r − δρ.
        """
        adjoints, c, s = self._nominal_and_model.runtime_walk(q2[0])
        target = _tool_pose_lists(adjoints[0, -1])
        adjoints = adjoints[1]
        J = (
            adjoints[:6, :, 5].T
            if self.model._all_revolute_z
            else self.model.twists_from_frames(se3.pose_from_adjoint(adjoints))
        )
        walk, network = self.model.runtime_walk, self.network is not None
        out = q2.copy()
        row = out[0]
        prev_step = float("inf")
        isfinite = math.isfinite
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # a singular J gives a NaN step
            for it in range(max(iterations, 1)):
                if it:
                    adjoints, J, c, s = walk(row)
                step = _solve_one(J, _pose_error_one(target, adjoints[-1]))
                if network:
                    step -= self._joint_errors_one(row, adjoints, c, s)
                values = step.tolist()
                size = max(map(abs, values))
                if not (size <= min(_GN_MAX_STEP, 0.5 * prev_step) and isfinite(sum(values))):
                    break
                row += step
                ratio = min(size / prev_step, 0.5) if prev_step < float("inf") else 0.5
                if size * ratio / (1 - ratio) < tol or size < 1e-3 * tol:
                    return out
                prev_step = size
            else:
                return out  # iteration budget spent while still contracting: keep it
        return self._levenberg_marquardt_single(q2, target, max(iterations, 10) * 3, tol)

    def _levenberg_marquardt_single(self, q2: np.ndarray, target: tuple, iterations: int, tol: float) -> np.ndarray:
        """_levenberg_marquardt for one configuration (1, n) of a 6-joint robot, target as from _tool_pose_lists.

        The same iterates (to rounding) with the runtime walk in place of the batched residual: a near-singular
        configuration takes up to 31 evaluations here, and at one configuration each costs the per-call overhead.
        """
        scale = np.array([1.0 / self.length_scale] * 3 + [1.0] * 3)
        walk, network = self.model.runtime_walk, self.network is not None

        def residual(row):
            adjoints, J, c, s = walk(row)
            r = _pose_error_one(target, adjoints[-1])
            if network:
                r -= J @ self._joint_errors_one(row, adjoints, c, s)
            return r * scale, J * scale[:, None]

        out = q2[0].copy()
        err, J = residual(out)
        cost = float(err @ err)
        lam = 1e-6
        eye = np.eye(self.n)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for _ in range(iterations):
                JtJ = J.T @ J
                step = _solve_one(JtJ + (lam * (np.trace(JtJ) / self.n)) * eye, J.T @ err)
                step = np.clip(step, -_MAX_STEP, _MAX_STEP)
                cand = out + step
                err_c, J_c = residual(cand)
                cost_c = float(err_c @ err_c)
                ok = cost_c <= cost
                if ok:
                    out, err, J, cost = cand, err_c, J_c, cost_c
                lam = max(lam / 10, 1e-12) if ok else lam * 10
                # as in the batched loop: a kept step below tol, or damping so strong that no step is kept
                if (ok and float(np.max(np.abs(step))) < tol) or (not ok and lam > 1e6):
                    break
        return out[None]

    def _levenberg_marquardt(self, q2: np.ndarray, target: np.ndarray, iterations: int, tol: float) -> np.ndarray:
        """Levenberg-Marquardt on ``T_real(q_cmd) = T_nominal(q)`` in a length-scaled metric.

        A step is kept only where it lowers the pose error, so near a singularity the correction degrades to
        "no worse than the start" instead of running away.
        """
        out = q2.copy()
        scale = np.array([1.0 / self.length_scale] * 3 + [1.0] * 3)

        def residual(qc):
            r, J = self._residual(qc, target)
            return r * scale, J * scale[:, None]

        err, J = residual(out)
        cost = np.sum(err * err, axis=1)
        lam = np.full(len(out), 1e-6)
        eye = np.eye(self.n)
        for _ in range(iterations):
            JtJ = np.einsum("kai,kaj->kij", J, J)
            mean_diag = (np.trace(JtJ, axis1=1, axis2=2) / self.n)[:, None, None]
            rhs = np.einsum("kai,ka->ki", J, err)[..., None]
            step = np.linalg.solve(JtJ + (lam[:, None, None] * mean_diag) * eye, rhs)[..., 0]
            step = np.clip(step, -_MAX_STEP, _MAX_STEP)
            cand = out + step
            err_c, J_c = residual(cand)
            cost_c = np.sum(err_c * err_c, axis=1)
            ok = cost_c <= cost
            out[ok], err[ok], J[ok], cost[ok] = cand[ok], err_c[ok], J_c[ok], cost_c[ok]
            lam = np.where(ok, np.maximum(lam / 10, 1e-12), lam * 10)
            if np.max(np.abs(step[ok]), initial=0.0) < tol and np.all(ok | (lam > 1e6)):
                break
        return out

    # -- export ------------------------------------------------------------------------------------------------
    def save(self, path, provenance: dict | None = None) -> Path:
        """Write this robot as a compensator export (``.json`` or ``.npz`` by extension); returns the path."""
        return save(self, path, provenance)


# ----------------------------------------------------------------------------------------------------------------
# Export files


class CompensatorFileError(ValueError):
    """A compensator export is unreadable, has the wrong schema, or fails its own golden vectors."""


def _model_dict(model: LocalPOEModel) -> dict:
    return {
        "name": model.name,
        "joint_names": list(model.joint_names),
        "joint_types": list(model.joint_types),
        "frames": model.frames.tolist(),
        "twists": model.twists.tolist(),
        "limits": model.limits.tolist(),
    }


def _model_from(d: dict, what: str) -> LocalPOEModel:
    try:
        return LocalPOEModel(
            np.asarray(d["frames"], dtype=float),
            tuple(d["joint_types"]),
            np.asarray(d["twists"], dtype=float),
            np.asarray(d["limits"], dtype=float),
            str(d.get("name", "")),
            tuple(d.get("joint_names", ())),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise CompensatorFileError(f"{what}: not a valid robot model: {err}") from err


def golden_configurations(robot: CalibratedRobot, count: int = GOLDEN_COUNT, seed: int = 0) -> np.ndarray:
    """(count, n) well-conditioned configurations inside the robot's joint ranges, deterministic for a seed."""
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    rng = np.random.default_rng(seed)
    cand = lo + (hi - lo) * rng.uniform(0.1, 0.9, size=(32 * count, robot.n))
    J = robot.model.equivalent_jacobian(cand, length_scale=robot.length_scale)
    D = np.array([1.0 / robot.length_scale] * 3 + [1.0] * 3)
    cond = np.linalg.cond(D[None, :, None] * J)
    keep = cand[np.argsort(cond, kind="stable")[:count]]
    return keep


# Every field that changes what a loaded compensator does (or what it says about itself) has a checksum in the file.
# The golden vectors only exercise the model and network at a few configurations: they cannot see a widened
# joint range (which silently switches off the out-of-range guard), a moved tracker frame, a changed length scale
# (a different metric for n < 6), a different joint map, or edited provenance (e.g. a forced export made to look
# unforced). A checksum is integrity against edits and damage, not a signature: whoever can rewrite the file can
# rewrite its checksums too.
CHECKED_FIELDS = (
    "robot",
    "model",
    "network",
    "joint_map",
    "length_scale",
    "joint_ranges",
    "T_tracker_base",
    "method",
    "provenance",
    "golden",
)


def _canonical(value):
    """JSON-ready data with every number as a float, so the JSON and NPZ forms of a payload read the same."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int | float | np.number):
        return float(value)
    return value


def field_checksums(payload: dict) -> dict[str, str]:
    """sha256 of each checked field's canonical JSON (floats written exactly): {field: hex}."""
    out = {}
    for name in CHECKED_FIELDS:
        text = json.dumps(_canonical(payload.get(name)), sort_keys=True, separators=(",", ":"))
        out[name] = hashlib.sha256(text.encode()).hexdigest()
    return out


def _check_checksums(data: dict, source: str) -> None:
    stored = data.get("checksums")
    if not isinstance(stored, dict):
        raise CompensatorFileError(
            f"{source}: no checksums field: the file was damaged or edited — refusing to load it"
        )
    got = field_checksums(data)
    for name in CHECKED_FIELDS:
        if stored.get(name) != got[name]:
            raise CompensatorFileError(
                f"{source}: {name} does not match its checksum: the file was edited or damaged — refusing to load it "
                "(export the fit again rather than editing a compensator file)"
            )


def to_payload(robot: CalibratedRobot, provenance: dict | None = None) -> dict:
    """Everything an export holds, as JSON-ready Python data (lists and numbers), with its field checksums."""
    q = golden_configurations(robot)
    net = robot.network
    jm = robot.joint_map
    payload = {
        "format": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "robot": {**_model_dict(robot.nominal), "hash": model_hash(robot.nominal, jm)},
        "model": {**_model_dict(robot.model), "hash": model_hash(robot.model)},
        "network": None
        if net is None
        else {
            "features": list(net.features),
            "weights": [np.asarray(W, float).tolist() for W in net.weights],
            "biases": [np.asarray(b, float).tolist() for b in net.biases],
            "in_mean": np.asarray(net.in_mean, float).tolist(),
            "in_scale": np.asarray(net.in_scale, float).tolist(),
            "out_mean": np.asarray(net.out_mean, float).tolist(),
            "out_scale": np.asarray(net.out_scale, float).tolist(),
        },
        "length_scale": float(robot.length_scale),
        "joint_ranges": np.asarray(robot.joint_ranges, float).tolist(),
        "T_tracker_base": np.asarray(robot.T_tracker_base, float).tolist(),
        "method": robot.method,
        # controller → model joints (q_model = matrix q_controller + offsets); None: the controller's joints are the
        # model's. Golden vectors, joint ranges and the models are in model joints.
        "joint_map": None if jm is None else jm.as_dict(),
        "provenance": dict(provenance or {}),
        "golden": {
            "correct_method": "newton",
            "q": q.tolist(),
            "q_cmd": robot.correct(q, extrapolate=True).tolist(),
            "pose": robot.predict_pose(q).tolist(),
        },
    }
    payload["checksums"] = field_checksums(payload)
    return payload


def from_payload(data: dict, source: str = "<payload>", *, stored: bool = False) -> tuple[CalibratedRobot, dict]:
    """Rebuild (robot, payload) from export data; checks schema, model hash, field checksums and golden vectors.

    stored: the payload is a fit's file inside a session store, whose own sha256 list already guards it. Such a
    file may still be schema 1 (fits stored before joint maps and field checksums): it is read without a joint
    map, so old sessions' fits can still be reported and exported. An export file on its own must be schema 2.
    """
    if not isinstance(data, dict) or data.get("format") != SCHEMA:
        raise CompensatorFileError(f"{source}: not a labcal compensator export (format field is not {SCHEMA!r})")
    version = data.get("schema_version")
    legacy = stored and version == 1
    if version != SCHEMA_VERSION and not legacy:
        hint = "; export the fit again with this labcal" if version == 1 else ""
        raise CompensatorFileError(
            f"{source}: schema_version {version!r} is not supported (this labcal reads {SCHEMA_VERSION}){hint}"
        )
    if not legacy:
        _check_checksums(data, source)
    try:
        nominal = _model_from(data["robot"], f"{source}: robot")
        model = _model_from(data["model"], f"{source}: model")
        jd = None if legacy else data["joint_map"]
        try:
            joint_map = None if jd is None else JointMap(np.asarray(jd["matrix"]), np.asarray(jd["offsets"]))
        except (KeyError, TypeError, ValueError) as err:
            raise CompensatorFileError(f"{source}: joint_map is not a valid joint map: {err}") from err
        if joint_map is not None and joint_map.n != nominal.n:
            raise CompensatorFileError(
                f"{source}: joint_map is not a valid joint map: it maps {joint_map.n} joints, the robot has {nominal.n}"
            )
        if model_hash(nominal, joint_map) != data["robot"].get("hash"):
            raise CompensatorFileError(f"{source}: robot model does not match its hash (file edited or damaged)")
        net = None
        nd = data.get("network")
        if nd is not None:
            net = Network(
                features=tuple(nd["features"]),
                weights=tuple(np.asarray(W, dtype=float) for W in nd["weights"]),
                biases=tuple(np.asarray(b, dtype=float) for b in nd["biases"]),
                in_mean=np.asarray(nd["in_mean"], dtype=float),
                in_scale=np.asarray(nd["in_scale"], dtype=float),
                out_mean=np.asarray(nd["out_mean"], dtype=float),
                out_scale=np.asarray(nd["out_scale"], dtype=float),
            )
        robot = CalibratedRobot(
            nominal=nominal,
            model=model,
            network=net,
            T_tracker_base=np.asarray(data["T_tracker_base"], dtype=float).reshape(4, 4),
            joint_ranges=np.asarray(data["joint_ranges"], dtype=float).reshape(nominal.n, 2),
            length_scale=float(data["length_scale"]),
            method=str(data.get("method", "")),
            joint_map=joint_map,
        )
        golden = data["golden"]
        if np.size(golden["q"]) == 0:
            raise CompensatorFileError(f"{source}: no golden vectors to verify the file against")
        q = np.asarray(golden["q"], dtype=float).reshape(-1, nominal.n)
        q_cmd = np.asarray(golden["q_cmd"], dtype=float).reshape(q.shape)
        pose = np.asarray(golden["pose"], dtype=float).reshape(q.shape[0], 4, 4)
    except CompensatorFileError:
        raise
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise CompensatorFileError(f"{source}: missing or malformed field: {err!r}") from err
    if q.shape[0] == 0:
        raise CompensatorFileError(f"{source}: no golden vectors to verify the file against")
    try:
        got_pose = robot.predict_pose(q)
        if nominal.n > 6:
            # A redundant arm reaches a pose along a whole self-motion, so which q_cmd the solver lands on depends on
            # its details: check that the stored commands still reach the nominal poses instead of re-finding them.
            miss = se3.log_se3(se3.inv(robot.predict_pose(q_cmd)) @ nominal.fk(q))
            dq, what = float(np.max(np.abs(miss))), "pose error at the stored q_cmd (m, rad)"
        else:
            got_q = robot.correct(q, method=golden.get("correct_method", "newton"), extrapolate=True)
            dq, what = float(np.max(np.abs(got_q - q_cmd))), "|Δq_cmd| (rad)"
    except (ValueError, np.linalg.LinAlgError) as err:
        raise CompensatorFileError(f"{source}: cannot evaluate the golden vectors: {err}") from err
    dT = float(np.max(np.abs(got_pose - pose)))
    if not (dq <= GOLDEN_TOL_Q and dT <= GOLDEN_TOL_POSE):
        raise CompensatorFileError(
            f"{source}: golden vectors disagree with the stored model (max {what} = {dq:.3g}, "
            f"max |Δpose| = {dT:.3g}); the file was edited or damaged — refusing to load it"
        )
    return robot, data


def save(robot: CalibratedRobot, path, provenance: dict | None = None) -> Path:
    """Write a compensator export: ``.json`` (text) or ``.npz`` (arrays; metadata as a JSON string, no pickle)."""
    path = Path(path)
    payload = to_payload(robot, provenance)
    suffix = path.suffix.lower()
    if suffix == ".json":
        path.write_text(json.dumps(payload, indent=1) + "\n")
    elif suffix == ".npz":
        arrays: dict[str, np.ndarray] = {}
        meta = _split_arrays(payload, "", arrays)
        arrays["__meta__"] = np.array(json.dumps(meta))
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)
    else:
        raise ValueError(f"compensator export path must end in .json or .npz, got {path.name!r}")
    return path


_ARRAY_KEYS = {"frames", "twists", "limits", "in_mean", "in_scale", "out_mean", "out_scale", "joint_ranges"}
_ARRAY_KEYS |= {"T_tracker_base", "q", "q_cmd", "pose", "matrix", "offsets"}


def _split_arrays(obj, prefix: str, arrays: dict):
    """Move numeric arrays out of the payload into ``arrays`` (referenced as {"$array": key})."""
    if isinstance(obj, dict):
        out = {}
        for key, value in obj.items():
            name = f"{prefix}{key}"
            if key in _ARRAY_KEYS and value is not None:
                arrays[name] = np.asarray(value, dtype=float)
                out[key] = {"$array": name}
            elif key in ("weights", "biases") and isinstance(value, list):
                refs = []
                for i, item in enumerate(value):
                    arrays[f"{name}.{i}"] = np.asarray(item, dtype=float)
                    refs.append({"$array": f"{name}.{i}"})
                out[key] = refs
            elif key in ("provenance", "checksums"):
                out[key] = value  # JSON-able metadata (checksums are strings named like the array fields), kept as is
            else:
                out[key] = _split_arrays(value, f"{name}.", arrays)
        return out
    return obj


def _join_arrays(obj, arrays):
    if isinstance(obj, dict):
        if set(obj) == {"$array"}:
            name = obj["$array"]
            if name not in arrays:
                raise CompensatorFileError(f"array {name!r} referenced by the metadata is missing")
            return arrays[name]
        return {k: _join_arrays(v, arrays) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_join_arrays(v, arrays) for v in obj]
    return obj


def read_payload(path) -> dict:
    """The raw payload of a JSON or NPZ export (arrays as numpy arrays for NPZ), unverified."""
    path = Path(path)
    if not path.is_file():
        raise CompensatorFileError(f"{path}: no such compensator file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            return json.loads(path.read_text())
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                arrays = {name: z[name] for name in z.files}
            if "__meta__" not in arrays:
                raise CompensatorFileError(f"{path}: NPZ file has no __meta__ entry (not a labcal export)")
            meta = json.loads(str(arrays.pop("__meta__")))
            return _join_arrays(meta, arrays)
    except CompensatorFileError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as err:
        raise CompensatorFileError(f"{path}: cannot read the export: {err}") from err
    raise CompensatorFileError(f"{path}: a compensator export ends in .json or .npz")


class Compensator:
    """The deployable runtime of a calibration: correct joint commands, predict poses. Numpy only.

    It speaks the controller's joints: when the robot file declared a joint map (controller joints are not the
    model's, e.g. a coupled elbow), ``correct`` and ``predict_pose`` take controller joints, convert them to model
    joints (q_model = M q_controller + b), work on the calibrated model, and ``correct`` converts its answer back.
    Range checks apply to the model joints (the calibrated ranges are the data's model-joint ranges). Without a map
    (or an identity one) nothing is converted. :attr:`robot` (a :class:`CalibratedRobot`) works in model joints.

    Example::

        comp = Compensator.load("ur10-hybrid.json")   # verifies schema, checksums, model hash and golden vectors
        q_cmd = comp.correct(q)                        # (n,) or (k, n) rad; refuses q outside the trained ranges
        T = comp.predict_pose(q_cmd)                   # (4, 4) base frame: where the real robot goes
        comp.T_tracker_base                            # (4, 4) base pose in the tracker frame
    """

    def __init__(self, robot: CalibratedRobot, provenance: dict | None = None, source: str = "") -> None:
        self.robot = robot
        self.provenance = dict(provenance or {})
        self.source = source
        self._map = robot.joint_map  # None for the identity: the hot path then converts nothing

    @classmethod
    def load(cls, path) -> Compensator:
        """Read and verify a ``.json`` / ``.npz`` export; CompensatorFileError if it is damaged or edited."""
        data = read_payload(path)
        robot, data = from_payload(data, str(path))
        return cls(robot, data.get("provenance") or {}, str(path))

    def save(self, path) -> Path:
        return save(self.robot, path, self.provenance)

    @property
    def n(self) -> int:
        return self.robot.n

    @property
    def method(self) -> str:
        return self.robot.method

    @property
    def joint_ranges(self) -> np.ndarray:
        """(n, 2) the joint ranges the calibration covered (rad, m), in model joints (see :attr:`joint_map`)."""
        return self.robot.joint_ranges

    @property
    def T_tracker_base(self) -> np.ndarray:
        """(4, 4) the pose of the robot base in the tracker frame (identity for base-frame data)."""
        return self.robot.T_tracker_base

    @property
    def joint_map(self) -> JointMap:
        """The controller → model joint map (identity when the robot file declared none)."""
        return self._map if self._map is not None else JointMap.identity(self.n)

    @property
    def robot_hash(self) -> str:
        """sha256 of the nominal robot model and its joint map (labcal.robots.model_hash, = RobotSpec.hash)."""
        return model_hash(self.robot.nominal, self._map)

    def to_model(self, q) -> np.ndarray:
        """Controller joints (n,) or (k, n) → model joints, checked for shape and finite values first."""
        q2, single = self.robot._batch(q)
        out = q2 if self._map is None else self._map.to_model(q2)
        return out[0] if single else out

    def check_range(self, q, extrapolate: bool = False) -> None:
        """Raise ValueError naming the first configuration and joint outside the calibrated ranges (q: controller
        joints; the ranges are the model joints', so a mapped joint is named as the model joint it becomes)."""
        if extrapolate:
            return
        if self._map is None:
            self.robot.check_range(q)
            return
        self._check_model_range(self.to_model(q))

    def _check_model_range(self, q_model: np.ndarray) -> None:
        try:
            self.robot._check_range(np.atleast_2d(q_model))
        except ValueError as err:
            raise ValueError(
                f"{err} (model joints: the robot file's joint map turns the controller joints into these)"
            ) from None

    def correct(self, q, *, extrapolate: bool = False, method: str = "newton") -> np.ndarray:
        """Commanded controller joints (n,) or (k, n) that make the real robot reach the nominal pose of the
        controller joints q (an empty (0, n) q gives an empty answer)."""
        if self._map is None:
            return self.robot.correct(q, extrapolate=extrapolate, method=method)
        q_model = self.to_model(q)
        if not extrapolate:
            self._check_model_range(q_model)
        return self._map.to_controller(self.robot.correct(q_model, extrapolate=True, method=method))

    def predict_pose(self, q, *, extrapolate: bool = False) -> np.ndarray:
        """Pose (4, 4) or (k, 4, 4) in the base frame that the real robot reaches when commanded the controller
        joints q (an empty (0, n) q gives (0, 4, 4))."""
        if self._map is None:
            self.robot.check_range(q, extrapolate)
            return self.robot.predict_pose(q)
        q_model = self.to_model(q)
        if not extrapolate:
            self._check_model_range(q_model)
        return self.robot.predict_pose(q_model)


def load(path) -> Compensator:
    """Shorthand for :meth:`Compensator.load`."""
    return Compensator.load(path)
