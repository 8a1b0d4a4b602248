"""A simulated "actual robot": the nominal model plus seeded geometric and non-geometric errors.

Used by the calibration benchmarks and tests, and by the sim drivers (robot + tracker share one instance).

Error sources (paper Section II, eq. 7, plus what real robots add):

- geometric: frame errors δζ_j (j = 1..n+1), joint twist errors δξ_j (axis misalignment), joint offsets δq_j,
  each element ~ N(0, σ) with σ = ``length_std`` (m) for linear and ``angle_std`` (rad) for angular parts;
- joint compliance: each joint deflects by ``c_j τ_j(q)``, τ_j the gravity torque of the links beyond it. The
  compliances are scaled so that joint j's largest deflection over the joint ranges is ``compliance_deflection``;
- gear transmission errors: ``a_j1 sin(q_j + φ_j1) + a_j2 sin(2 q_j + φ_j2)``, amplitudes ~ N(0, ``gear_std``);
- repeatability: a random pose twist per motion (``repeatability`` m / m·rad⁻¹ scaled by reach);
- measurement: Gaussian tracker noise per coordinate (``tracker_noise`` m) and an optional tracker-to-base pose.

Any number m ≥ 1 of targets: ``targets`` is (m, 3) in the tool frame and measured points are (k, m, 3). A target
the tracker did not see is a NaN row; :func:`seen_mask` draws which targets are lost (a seeded drop-out per cell)
and :func:`drop_unseen` blanks them.

Example::

    >>> from labcal.robots import load
    >>> actual = simulate(load("ur10"), ErrorSpec.paper(), seed=1)
    >>> actual.true_points(np.zeros(6), np.eye(3) * 0.1).shape
    (1, 3, 3)
    >>> actual.true_points(np.zeros((4, 6)), np.zeros((1, 3))).shape  # one target: the tool origin
    (4, 1, 3)
    >>> seen = seen_mask(5, 3, 0.3, np.random.default_rng(0), exact=True)
    >>> int((~seen).sum()), bool(seen.any(axis=1).all())  # round(0.3 · 15) cells lost, every row keeps one
    (4, True)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from labcal.kinematics import se3
from labcal.kinematics.metric import parameter_weights
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel
from labcal.robots import RobotSpec

GRAVITY = np.array([0.0, 0.0, -9.81])  # m/s², base frame z up


@dataclass(frozen=True)
class ErrorSpec:
    """How large each simulated error source is. SI units. Zero switches a source off."""

    length_std: float = 0.5e-3
    angle_std: float = 0.5e-3
    joint_offset_std: float = 0.5e-3
    axis_std: float = 0.5e-3
    compliance_deflection: float = 2e-4
    gear_std: float = 5e-5
    repeatability: float = 0.0
    tracker_noise: float = 0.05e-3
    T_tracker_base: np.ndarray | None = field(default=None)

    @classmethod
    def paper(cls, **changes) -> ErrorSpec:
        """The paper's Section V: geometric errors of 0.5 mm / 0.5 mrad, 0.05 mm tracker noise, nothing else."""
        return replace(cls(compliance_deflection=0.0, gear_std=0.0), **changes)

    @classmethod
    def default(cls, **changes) -> ErrorSpec:
        """Geometric plus non-geometric errors (compliance 0.2 mrad, gears 0.05 mrad) at the default scale."""
        return replace(cls(), **changes)

    @classmethod
    def none(cls) -> ErrorSpec:
        """A perfect robot and a perfect tracker (for tests)."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True, eq=False)
class ActualRobot:
    """The true robot behind a nominal model. All methods take q of shape (n,) or (k, n) (commanded joints)."""

    nominal: LocalPOEModel
    geometric: LocalPOEModel  # frames and twists with their errors
    joint_offsets: np.ndarray  # (n,)
    compliance: np.ndarray  # (n,) rad per N·m
    gear: np.ndarray  # (n, 2, 2): [harmonic (1, 2)] × [amplitude, phase]
    masses: np.ndarray  # (n+1,)
    coms: np.ndarray  # (n+1, 3) base frame at q = 0
    errors: ErrorSpec
    T_tracker_base: np.ndarray  # (4, 4)
    delta_zeta: np.ndarray  # (n+1, 6) the frame errors, kept for tests and reports

    @property
    def n(self) -> int:
        return self.nominal.n

    def gravity_torque(self, q) -> np.ndarray:
        """(k, n) generalised gravity forces τ_j = Σ_{i≥j} ξ_jᵀ (f_i, c_i × f_i) on the nominal model, N·m."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        frames, twists = self.nominal.link_frames(q), self.nominal.joint_twists(q)
        frames0 = self.nominal.link_frames(np.zeros(self.n))[0]
        tau = np.zeros(q.shape)
        for i in range(self.n + 1):
            if self.masses[i] == 0.0:
                continue
            # Link i (or the payload, i = n) is rigid with the frame that follows its joint.
            body = frames[:, min(i + 1, self.n)]
            body0 = frames0[min(i + 1, self.n)]
            c_local = se3.inv(body0) @ np.append(self.coms[i], 1.0)
            c = (body @ c_local)[:, :3]
            f = self.masses[i] * GRAVITY
            wrench = np.concatenate([np.broadcast_to(f, c.shape), np.cross(c, f)], axis=1)  # (k, 6)
            upto = min(i + 1, self.n)
            tau[:, :upto] += np.einsum("kaj,ka->kj", twists[:, :, :upto], wrench)
        return tau

    def joint_errors(self, q) -> np.ndarray:
        """(k, n) joint motion errors of the actual robot: offsets + gear harmonics + compliance, rad (m)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        err = np.broadcast_to(self.joint_offsets, q.shape).copy()
        for h in (1, 2):
            amp, phase = self.gear[:, h - 1, 0], self.gear[:, h - 1, 1]
            err += amp * np.sin(h * q + phase)
        if np.any(self.compliance):
            err += self.compliance * self.gravity_torque(q)
        return err

    def true_pose(self, q, rng: np.random.Generator | None = None) -> np.ndarray:
        """(k, 4, 4) pose the real tool reaches in the base frame when commanded q."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        T = self.geometric.fk(q + self.joint_errors(q))
        if rng is not None and self.errors.repeatability > 0:
            scale = parameter_weights(1, self.nominal.reach())
            T = se3.exp_se3(rng.normal(0.0, self.errors.repeatability, size=(q.shape[0], 6)) * scale) @ T
        return T

    def true_points(self, q, targets, rng: np.random.Generator | None = None) -> np.ndarray:
        """(k, m, 3) true target positions in the base frame (targets (m, 3) m in the tool frame, m ≥ 1)."""
        T = self.true_pose(q, rng)
        targets = np.asarray(targets, dtype=float)
        return np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]

    def measure(self, q, targets, rng: np.random.Generator) -> np.ndarray:
        """(k, m, 3) what the tracker reports: true points in the tracker frame plus Gaussian noise (every target
        seen; :func:`drop_unseen` blanks lost ones afterwards, so the noise stream does not depend on drop-outs)."""
        p = self.true_points(q, targets, rng)
        p = np.einsum("ab,kmb->kma", self.T_tracker_base[:3, :3], p) + self.T_tracker_base[:3, 3]
        if self.errors.tracker_noise > 0:
            p = p + rng.normal(0.0, self.errors.tracker_noise, size=p.shape)
        return p


def seen_mask(k: int, m: int, dropout, rng: np.random.Generator, *, exact: bool = False) -> np.ndarray:
    """(k, m) bool, True where the tracker saw target i in row r: a seeded drop-out per cell.

    dropout: the probability (float, or (m,) one per target) that a target is lost in a row, independently per
    cell; with ``exact`` (float only) exactly ``round(dropout · k · m)`` cells are lost, at random. Either way every
    row keeps at least one target (a row with none seen is not a measurement: drivers reject it, importers report
    it), so a row that would lose all of them keeps one drawn at random — ``exact`` needs dropout ≤ (m − 1) / m.

    >>> seen_mask(3, 2, 0.0, np.random.default_rng(0)).all()
    np.True_
    """
    p = np.broadcast_to(np.asarray(dropout, dtype=float), (m,))
    if np.any(p < 0) or np.any(p > 1) or not np.all(np.isfinite(p)):
        raise ValueError(f"dropout must be a probability in [0, 1], got {dropout!r}")
    # One uniform score per cell decides which cells are lost; a separate draw names the cell each row keeps when
    # it would lose them all (drawn for every row, so the stream does not depend on the outcome).
    score = rng.random((k, m))
    keep = np.zeros((k, m), bool)
    keep[np.arange(k), rng.integers(0, m, size=k)] = True
    if exact:
        if np.ndim(dropout) != 0:
            raise ValueError("exact drop-out takes one fraction for every target, not one per target")
        lost = round(float(dropout) * k * m)
        if lost > k * (m - 1):
            raise ValueError(
                f"cannot lose {lost} of {k * m} cells and keep one target per row: dropout ≤ {(m - 1) / m:.3f} for "
                f"{m} target(s)"
            )
        free = np.where(keep, -np.inf, score).ravel()
        seen = np.ones(k * m, bool)
        seen[np.argsort(-free, kind="stable")[:lost]] = False
        return seen.reshape(k, m)
    seen = score >= p
    empty = ~seen.any(axis=1)
    seen[empty] = keep[empty]
    return seen


def drop_unseen(points: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """A copy of points (k, m, 3) with the whole row of every unseen target (``seen`` (k, m) False) NaN."""
    out = np.array(points, dtype=float, copy=True)
    out[~np.asarray(seen, bool)] = np.nan
    return out


def simulate(spec: RobotSpec, errors: ErrorSpec | None = None, seed: int = 0) -> ActualRobot:
    """Draw a true robot for a nominal robot spec. Same spec, errors and seed ⇒ the same robot."""
    errors = errors or ErrorSpec.default()
    nominal = spec.model
    n = nominal.n
    rng = np.random.default_rng(seed)
    sd = np.array([errors.length_std] * 3 + [errors.angle_std] * 3)
    delta_zeta = rng.normal(size=(n + 1, 6)) * sd
    geometric = nominal.perturbed(delta_zeta)

    twists = nominal.twists.copy()
    raw_axis = rng.normal(size=(n, 6))
    for j in range(n):
        if errors.axis_std == 0:
            break
        if nominal.joint_types[j] == REVOLUTE:
            w = twists[j, 3:] + raw_axis[j, 3:] * errors.axis_std
            w /= np.linalg.norm(w)
            v = twists[j, :3] + raw_axis[j, :3] * errors.axis_std * 1.0  # axis line shift, m
            twists[j] = np.concatenate([v - (v @ w) * w, w])
        else:
            d = twists[j, :3] + raw_axis[j, :3] * errors.axis_std
            twists[j] = np.concatenate([d / np.linalg.norm(d), np.zeros(3)])
    geometric = geometric.replace(twists=twists)

    offsets = rng.normal(size=n) * errors.joint_offset_std
    gear = np.zeros((n, 2, 2))
    gear[:, :, 0] = rng.normal(size=(n, 2)) * errors.gear_std
    gear[:, :, 1] = rng.uniform(-np.pi, np.pi, size=(n, 2))

    T_tb = np.eye(4) if errors.T_tracker_base is None else np.asarray(errors.T_tracker_base, float)
    actual = ActualRobot(
        nominal=nominal,
        geometric=geometric,
        joint_offsets=offsets,
        compliance=np.zeros(n),
        gear=gear,
        masses=np.asarray(spec.masses, float),
        coms=np.asarray(spec.coms, float),
        errors=errors,
        T_tracker_base=T_tb,
        delta_zeta=delta_zeta,
    )
    if errors.compliance_deflection > 0 and np.any(spec.masses > 0):
        # Scale per joint so its largest gravity deflection over the joint ranges is the requested angle.
        probe = np.random.default_rng(12345).uniform(nominal.limits[:, 0], nominal.limits[:, 1], size=(2000, n))
        tau_max = np.abs(actual.gravity_torque(probe)).max(axis=0)
        compliance = np.where(tau_max > 1e-9, errors.compliance_deflection / np.maximum(tau_max, 1e-9), 0.0)
        actual = replace(actual, compliance=compliance)
    return actual
