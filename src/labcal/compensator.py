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

This module imports numpy and labcal.kinematics only, so a controller-side process can load an export without
torch, scipy, pandas or any driver.

Example::

    >>> from labcal.robots import load
    >>> nominal = load("ur10").model
    >>> robot = CalibratedRobot(nominal=nominal, model=nominal)       # an uncalibrated robot
    >>> q = np.array([0.1, -1.2, 1.0, -1.4, -1.5, 0.2])
    >>> np.allclose(robot.correct(q), q)
    True
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from labcal.kinematics import se3
from labcal.kinematics.poe import LocalPOEModel

FEATURES = ("q", "sincos", "sincos2", "gravity")
_MAX_STEP = 0.02  # rad per Newton step: corrections are milliradians, so larger steps mean a singularity


def input_features(q: np.ndarray, names: tuple[str, ...], model: LocalPOEModel) -> np.ndarray:
    """(k, n) joint values → (k, f) network inputs.

    - ``q``: the joint values themselves (the paper's choice);
    - ``sincos``: sin q_j, cos q_j (revolute joints; prismatic joints contribute q_j);
    - ``sincos2``: sin 2q_j, cos 2q_j (twice-per-revolution effects such as gear errors);
    - ``gravity``: the direction of gravity (base −z) in each link frame, 3n numbers: every gravity torque on a
      joint is a linear function of these for a rigid arm, whatever its mass model.
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
            frames = model.link_frames(q)[:, 1:]  # frames rigid with links 1..n
            down = -frames[:, :, 2, :3]  # row 2 of R = R^T e_z: base z axis in link coordinates
            parts.append(down.reshape(q.shape[0], -1))
        else:
            raise ValueError(f"unknown network input feature {name!r}; known: {', '.join(FEATURES)}")
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


@dataclass(frozen=True, eq=False)
class CalibratedRobot:
    """A calibrated robot: what every fit returns and every export stores.

    joint_ranges: (n, 2) the joint ranges the calibration data covered; ``correct`` refuses q outside them unless
    ``extrapolate=True``. length_scale: metres per radian used to build virtual joints (n < 6), fixed at fit time.
    """

    nominal: LocalPOEModel
    model: LocalPOEModel
    network: Network | None = None
    T_tracker_base: np.ndarray = field(default_factory=lambda: np.eye(4))
    joint_ranges: np.ndarray | None = None
    length_scale: float | None = None
    method: str = "nominal"

    def __post_init__(self) -> None:
        if self.model.n != self.nominal.n:
            raise ValueError(f"model has {self.model.n} joints, nominal has {self.nominal.n}")
        if self.joint_ranges is None:
            object.__setattr__(self, "joint_ranges", self.nominal.limits.copy())
        if self.length_scale is None:
            object.__setattr__(self, "length_scale", self.nominal.reach())

    @property
    def n(self) -> int:
        return self.nominal.n

    def _batch(self, q) -> tuple[np.ndarray, bool]:
        q = np.asarray(q, dtype=float)
        single = q.ndim == 1
        q2 = np.atleast_2d(q)
        if q2.ndim != 2 or q2.shape[1] != self.n:
            raise ValueError(f"q must have shape ({self.n},) or (k, {self.n}), got {q.shape}")
        if not np.all(np.isfinite(q2)):
            raise ValueError("q contains non-finite values")
        return q2, single

    def check_range(self, q, extrapolate: bool = False) -> None:
        """Raise ValueError naming the first configuration and joint outside the calibrated joint ranges."""
        if extrapolate:
            return
        q2, _ = self._batch(q)
        lo, hi = self.joint_ranges[:, 0], self.joint_ranges[:, 1]
        bad = (q2 < lo - 1e-12) | (q2 > hi + 1e-12)
        if np.any(bad):
            i, j = np.argwhere(bad)[0]
            raise ValueError(
                f"configuration {i}: joint {j + 1} = {q2[i, j]:.6f} is outside the calibrated range "
                f"[{lo[j]:.6f}, {hi[j]:.6f}]; pass extrapolate=True to correct it anyway"
            )

    def joint_motion_errors(self, q) -> np.ndarray:
        """(k, 6) predicted joint motion errors δρ(q) of the equivalent robot (zeros without a network)."""
        q2, _ = self._batch(q)
        if self.network is None:
            return np.zeros((q2.shape[0], 6))
        return self.network(q2, self.model)

    def equivalent_jacobian(self, q) -> np.ndarray:
        """(k, 6, 6) J_ρ of the identified model (actuated + virtual joints, eq. 12-14)."""
        return self.model.equivalent_jacobian(q, length_scale=self.length_scale)

    def predict_pose(self, q) -> np.ndarray:
        """Pose (4, 4) or (k, 4, 4) in the base frame that the real robot reaches when commanded q."""
        q2, single = self._batch(q)
        T = self._predict(q2)
        return T[0] if single else T

    def _predict(self, q2: np.ndarray) -> np.ndarray:
        if self.network is None:
            return self.model.fk(q2)
        if self.n >= 6:
            T, J = self.model.fk_and_twists(q2)
        else:
            T = self.model.fk(q2)
            J = self.equivalent_jacobian(q2)
        dy = np.einsum("kab,kb->ka", J, self.network(q2, self.model))
        return se3.exp_se3(dy) @ T

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
        tol: float = 1e-10,
        extrapolate: bool = False,
    ) -> np.ndarray:
        """Joint commands that make the real robot reach the nominal pose of q. (n,) or (k, n), like q.

        method: ``"newton"`` (default) solves ``T_real(q_cmd) = T_nominal(q)`` by Gauss-Newton on the calibrated
        forward model (least squares in a length-scaled metric for n < 6: only actuated joints are corrected);
        ``"paper"`` is eq. (24), q − δρ_a(q); ``"fixed-point"`` iterates q_cmd = q − δρ_a(q_cmd).
        """
        q2, single = self._batch(q)
        self.check_range(q2, extrapolate)
        n = self.n
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
            out = self._newton(q2, iterations, tol)
        else:
            raise ValueError(f"method must be 'newton', 'paper' or 'fixed-point', got {method!r}")
        return out[0] if single else out

    def _pose_and_jacobian(self, q2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted poses (k, 4, 4) and the actuated joint twists (k, 6, n) of the identified model."""
        T, J = self.model.fk_and_twists(q2)
        if self.network is not None:
            J_rho = J if self.n >= 6 else self.equivalent_jacobian(q2)
            T = se3.exp_se3(np.einsum("kab,kb->ka", J_rho, self.network(q2, self.model))) @ T
        return T, J

    def _newton(self, q2: np.ndarray, iterations: int, tol: float) -> np.ndarray:
        """Levenberg-Marquardt on ``T_real(q_cmd) = T_nominal(q)`` in a length-scaled metric.

        A step is kept only where it lowers the pose error, so near a singularity the correction degrades to
        "no worse than the start" instead of running away.
        """
        target = self.nominal.fk(q2)
        out = q2.copy()
        if self.network is not None:
            out = out - self.joint_motion_errors(out)[:, : self.n]  # eq. (24) as the first guess
        scale = np.array([1.0 / self.length_scale] * 3 + [1.0] * 3)

        def residual(qc):
            T, J = self._pose_and_jacobian(qc)
            # dδρ/dq is second order and left out of the Jacobian.
            return se3.log_se3(target @ se3.inv(T)) * scale, J * scale[:, None]

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
