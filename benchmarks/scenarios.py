"""Adversarial data sets for tests and benchmarks: seeded, small, and each hard in one named way.

Every generator returns a :class:`Scenario`: model joints ``q`` (k, n) in rad (m for prismatic joints), measured
points ``points`` (k, m, 3) in m — row i of ``points[r]`` is target t(i+1), a NaN row where it was not seen — in
the frame ``frame`` ("base", or "tracker" with the known ``T_tracker_base``), the tool-frame ``targets`` (m, 3) m
(m ≥ 1; three by default), and optional ``group`` labels
(k,) that keep rows which belong together (one sweep, one repeated pose) in one cross-validation fold. A scenario
made in controller joints also carries ``q_controller`` and the ``joint_map`` matrix (q_model = M · q_controller).

Two kinds of generator:

- **hard but honest data** a calibration must handle: :func:`good` (random non-singular poses, the reference),
  :func:`sweeps` (a few dozen poses in single-joint sweeps, most with the wrist singular, as a real lab records
  them), :func:`singular_wrist` (random poses, most with q5 ≈ 0), :func:`coupled_elbow` (controller joints whose
  elbow is measured from the horizontal: model elbow = J2 + J3), :func:`identical_poses`, :func:`few_poses`;
- **fewer targets seen** than the set was measured with: :func:`with_targets` (keep some targets, e.g. t1 alone:
  one reflector), :func:`with_dropout` (a seeded drop-out per cell: NaN target rows, every row keeps one);
- **corruptions of a good set** that must be refused or flagged, not fitted: :func:`unit_slip` (points ×1000,
  ×0.001, ×25.4), :func:`degrees_as_radians`, :func:`swapped_targets`, :func:`wrong_targets`,
  :func:`pure_noise`, :func:`shuffled_rows`, :func:`in_tracker_frame` (points in a tracker frame; importing them
  as ``--frame base`` is the mistake).

Not part of the package: tests and benchmarks import it as ``scenarios`` (pytest and a benchmark script have
benchmarks/ on their path; tests/bench/test_scenarios.py runs the examples below). A scenario gives arrays;
``Observations(**scn.arrays())`` builds the calibration input. The paper's scenarios A and B live in
benchmarks/paper.py.

Example::

    >>> scn = sweeps("ur10", n_poses=30, per_sweep=4, seed=1)
    >>> scn.q.shape, scn.points.shape, scn.targets.shape, scn.group.shape
    ((30, 6), (30, 3, 3), (3, 3), (30,))
    >>> bool(np.mean(np.abs(scn.q[:, 4]) <= WRIST_TOL) > 0.5)
    True
    >>> one = with_dropout(with_targets(good("ur10", 20, seed=0), [0, 1]), 0.25, seed=3)
    >>> one.m, int(np.isnan(one.points[..., 0]).sum())   # 2 targets, 10 of 40 cells lost
    (2, 10)
    >>> slipped = unit_slip(good("ur10", 20, seed=0), 1000.0)
    >>> bool(np.allclose(slipped.points, good("ur10", 20, seed=0).points * 1000.0))
    True
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition
from labcal.kinematics.poe import LocalPOEModel
from labcal.robots import load
from labcal.simulation.actual import ActualRobot, ErrorSpec, drop_unseen, seen_mask, simulate

#: A scalene target triangle (m, tool frame) 50 mm in front of the flange: sides 224, 269, 335 mm (the paper
#: benchmark's triangle, so a scenario and a paper run use the same tool).
TARGETS = np.array([[0.20, 0.00, 0.05], [-0.10, 0.15, 0.05], [0.00, -0.10, 0.05]])
#: |q5| below this counts as "singular wrist" (rad): the controller reports a value this close to zero.
WRIST_TOL = 1e-3
#: Length-scaled cond(J_ρ) above which a pose counts as singular (the paper benchmark's bound).
MAX_CONDITION = 500.0
INCH = 25.4


@dataclass(frozen=True, eq=False)
class Scenario:
    """One data set. Shapes: q (k, n) model joints; points (k, m, 3) m in ``frame`` (NaN rows: targets not seen);
    targets (m, 3) m;
    group (k,) int or None; q_controller (k, n) or None; joint_map (n, n) or None; T_tracker_base (4, 4) or None
    (the pose of the base in the tracker frame when ``frame == "tracker"``); actual: the true robot (None for data
    that no robot produced, e.g. pure noise); description: what is hard about it, one line."""

    name: str
    robot: str
    q: np.ndarray
    points: np.ndarray
    targets: np.ndarray
    frame: str = "base"
    group: np.ndarray | None = None
    q_controller: np.ndarray | None = None
    joint_map: np.ndarray | None = None
    T_tracker_base: np.ndarray | None = None
    actual: ActualRobot | None = None
    seed: int = 0
    description: str = ""

    @property
    def k(self) -> int:
        return int(self.q.shape[0])

    @property
    def n(self) -> int:
        return int(self.q.shape[1])

    @property
    def m(self) -> int:
        """The number of targets."""
        return int(self.targets.shape[0])

    @property
    def seen(self) -> np.ndarray:
        """(k, m) bool: True where the target was measured (its point is not NaN)."""
        return np.isfinite(self.points).all(axis=-1)

    def arrays(self) -> dict:
        """``{"q", "points", "targets", "frame"}``: the keyword arguments of ``Observations``."""
        return {"q": self.q, "points": self.points, "targets": self.targets, "frame": self.frame}

    def subset(self, index) -> Scenario:
        """The rows ``index`` (mask or integer index) of every per-row array."""
        idx = np.asarray(index)

        def pick(a):
            return None if a is None else np.asarray(a)[idx]

        return replace(
            self, q=self.q[idx], points=self.points[idx], group=pick(self.group), q_controller=pick(self.q_controller)
        )

    def changed(self, name: str, description: str, **changes) -> Scenario:
        return replace(self, name=name, description=description, **changes)


# ----------------------------------------------------------------------------------------------------------------
# helpers
def condition(model: LocalPOEModel, q: np.ndarray) -> np.ndarray:
    """(k,) cond of the equivalent Jacobian J_ρ with its translation rows scaled by 1/reach (unitless)."""
    return scaled_condition(model.equivalent_jacobian(np.atleast_2d(q)), model.reach())


def joint_box(model: LocalPOEModel, fraction: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of a box centred in each joint's range, ``fraction`` of its width, clipped to ±π.

    The UR arms have ±2π limits; configurations beyond ±π repeat the same poses and say nothing new.
    """
    lo, hi = np.maximum(model.limits[:, 0], -np.pi), np.minimum(model.limits[:, 1], np.pi)
    mid, half = (lo + hi) / 2, (hi - lo) * fraction / 2
    return mid - half, mid + half


def coupled_map(n: int) -> np.ndarray:
    """(n, n) the coupled-elbow map of an n-joint arm (n ≥ 3): the identity but model J3 = controller J2 + J3.

    >>> coupled_map(7)[2].tolist()
    [0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]
    """
    if n < 3:
        raise ValueError(f"a coupled elbow needs at least 3 joints, got {n}")
    M = np.eye(n)
    M[2, 1] = 1.0
    return M


def wrist_joint(model: LocalPOEModel) -> int | None:
    """The index of the wrist joint whose zero is singular: the last revolute joint j, with revolute neighbours,
    whose zero (inside its limits) turns the axes of joints j − 1 and j + 1 parallel; None if the arm has none.

    q5 (index 4) on the 6R built-ins (UR: axes 4 and 6 parallel to 2 and 3; fanuc: a spherical wrist); q6 (index
    5) on the 7R ones (iiwa: axes 5 and 7 in line; Panda: parallel, 88 mm apart); none on scara4. On a 6R arm it is
    a singularity of the Jacobian; on a 7R arm the redundancy keeps the rank, but the two axes move alike, as a
    lab's data with the wrist held there do.

    >>> from labcal.robots import load
    >>> wrist_joint(load("ur10").model), wrist_joint(load("franka-panda").model), wrist_joint(load("scara4").model)
    (4, 5, None)
    """
    n, revolute = model.n, [t == "revolute" for t in model.joint_types]
    # Other joints at random, from a stream of its own (the scenarios' streams stay untouched).
    q = np.random.default_rng(0).uniform(*joint_box(model), size=(8, n))
    for j in range(n - 2, 0, -1):
        lo, hi = model.limits[j]
        if not (revolute[j - 1] and revolute[j] and revolute[j + 1]) or not lo <= 0.0 <= hi:
            continue
        q0 = q.copy()
        q0[:, j] = 0.0
        w = model.joint_twists(q0)[:, 3:]  # (k, 3, n) axis directions in K0
        if np.all(np.linalg.norm(np.cross(w[:, :, j - 1], w[:, :, j + 1]), axis=1) < 1e-9):
            return j
    return None


def _wrist(model: LocalPOEModel, robot: str) -> int:
    w = wrist_joint(model)
    if w is None:
        raise ValueError(f"{robot!r} has no wrist joint whose zero is singular")
    return w


def _measure(actual: ActualRobot, q: np.ndarray, targets: np.ndarray, seed: int) -> np.ndarray:
    # A separate stream from the robot's own seed, so changing the poses never changes the true robot.
    return actual.measure(q, targets, np.random.default_rng([seed, 7919]))


def _robot(robot: str, errors: ErrorSpec | None, seed: int) -> tuple[LocalPOEModel, ActualRobot]:
    spec = load(robot)
    return spec.model, simulate(spec, errors or ErrorSpec.default(), seed=seed)


def nonsingular(
    model: LocalPOEModel, k: int, rng: np.random.Generator, fraction: float = 0.5, max_condition: float = MAX_CONDITION
) -> np.ndarray:
    """(k, n) uniform configurations in :func:`joint_box` whose :func:`condition` ≤ ``max_condition``."""
    lo, hi = joint_box(model, fraction)
    out: list[np.ndarray] = []
    have = 0
    for _ in range(1000):
        q = rng.uniform(lo, hi, size=(max(2 * (k - have), 16), model.n))
        q = q[condition(model, q) <= max_condition]
        out.append(q)
        have += len(q)
        if have >= k:
            return np.concatenate(out)[:k]
    raise RuntimeError(f"could not draw {k} non-singular configurations of {model.name!r}")


# ----------------------------------------------------------------------------------------------------------------
# hard but honest data
def good(robot: str = "ur10", k: int = 60, *, errors: ErrorSpec | None = None, seed: int = 0, targets=None) -> Scenario:
    """k random non-singular poses over the middle half of each joint range, base frame: the reference set.

    errors: the true robot's errors (default :meth:`ErrorSpec.default`); the true robot is ``simulate(…, seed)``
    and the poses and tracker noise come from their own streams of the same seed.

    >>> good("fanuc-m1000ia", 10, seed=2).points.shape
    (10, 3, 3)
    """
    model, actual = _robot(robot, errors, seed)
    targets = TARGETS if targets is None else np.asarray(targets, float)
    q = nonsingular(model, k, np.random.default_rng([seed, 1]))
    return Scenario(
        "good", robot, q, _measure(actual, q, targets, seed), targets, actual=actual, seed=seed,
        description=f"{k} random non-singular poses, base frame",
    )  # fmt: skip


def few_poses(robot: str = "ur10", k: int = 10, *, errors: ErrorSpec | None = None, seed: int = 0) -> Scenario:
    """Only ``k`` good poses (fewer than the identifiable parameters of a 6R arm, about 30; 34 for a 7R arm)."""
    scn = good(robot, k, errors=errors, seed=seed)
    prismatic = sum(t != "revolute" for t in scn.actual.nominal.joint_types)
    arm = f"{scn.n}R" if not prismatic else f"{scn.n}-joint"
    count = 4 * (scn.n - prismatic) + 2 * prismatic + 6  # the local POE fit's rank (4 per revolute, 2 per prismatic)
    return scn.changed("few-poses", f"only {k} poses (a {arm} arm has about {count} identifiable parameters)")


def sweeps(
    robot: str = "ur10",
    n_poses: int = 30,
    per_sweep: int = 4,
    *,
    singular_wrist: bool = True,
    span: float = 0.6,
    errors: ErrorSpec | None = None,
    seed: int = 0,
    targets=None,
) -> Scenario:
    """Single-joint sweeps as a lab records them: ``n_poses`` poses in sweeps of ``per_sweep`` poses each.

    Sweep s moves joint ``s mod n`` through ``per_sweep`` evenly spaced values over ``span`` rad (centred on its
    start) while every other joint keeps the sweep's start configuration; starts are drawn near one home pose
    (±0.3 rad). With ``singular_wrist`` the wrist joint (:func:`wrist_joint`: q5 on a 6R arm, q6 on the 7R
    built-ins; none on scara4) is held within ±:data:`WRIST_TOL` of zero except in its own sweeps, so most rows are
    singular (5/6 of the sweeps on a 6R arm). ``group`` = sweep index.
    The last sweep is shortened when ``per_sweep`` does not divide ``n_poses``.

    >>> scn = sweeps("fanuc-m1000ia", 24, 3, seed=0)
    >>> len(set(scn.group.tolist())), scn.k
    (8, 24)
    """
    if per_sweep < 2 or n_poses < per_sweep:
        raise ValueError(f"need per_sweep ≥ 2 and n_poses ≥ per_sweep, got {per_sweep} and {n_poses}")
    model, actual = _robot(robot, errors, seed)
    targets = TARGETS if targets is None else np.asarray(targets, float)
    rng = np.random.default_rng([seed, 2])
    lo, hi = joint_box(model, 0.5)
    home = nonsingular(model, 1, rng)[0]
    wrist = wrist_joint(model) if singular_wrist else None
    rows, groups = [], []
    n_sweeps = -(-n_poses // per_sweep)
    for s in range(n_sweeps):
        joint = s % model.n
        start = np.clip(home + rng.uniform(-0.3, 0.3, model.n), lo, hi)
        if wrist is not None:
            start[wrist] = rng.uniform(-WRIST_TOL, WRIST_TOL) / 2
        values = start[joint] + np.linspace(-span / 2, span / 2, per_sweep)
        block = np.tile(start, (per_sweep, 1))
        block[:, joint] = np.clip(values, model.limits[joint, 0], model.limits[joint, 1])
        rows.append(block)
        groups += [s] * per_sweep
    q = np.concatenate(rows)[:n_poses]
    group = np.asarray(groups[:n_poses])
    wrist = f"most with the wrist singular (|q{wrist + 1}| < 1 mrad)" if wrist is not None else "wrist free"
    return Scenario(
        "sweeps" + ("-singular-wrist" if singular_wrist else ""), robot, q, _measure(actual, q, targets, seed),
        targets, group=group, actual=actual, seed=seed,
        description=f"{n_poses} poses in {n_sweeps} single-joint sweeps of {per_sweep}, {wrist}",
    )  # fmt: skip


def singular_wrist(
    robot: str = "ur10",
    k: int = 40,
    *,
    fraction: float = 0.8,
    errors: ErrorSpec | None = None,
    seed: int = 0,
    targets=None,
) -> Scenario:
    """k random poses, ``fraction`` of them (rounded, at random rows) with the wrist joint (:func:`wrist_joint`, q5
    on a 6R arm) within :data:`WRIST_TOL` of zero (singular)."""
    model, actual = _robot(robot, errors, seed)
    wrist = _wrist(model, robot)
    targets = TARGETS if targets is None else np.asarray(targets, float)
    rng = np.random.default_rng([seed, 3])
    q = nonsingular(model, k, rng)
    rows = rng.permutation(k)[: round(fraction * k)]
    q[rows, wrist] = rng.uniform(-WRIST_TOL, WRIST_TOL, size=len(rows)) / 2
    return Scenario(
        "singular-wrist", robot, q, _measure(actual, q, targets, seed), targets, actual=actual, seed=seed,
        description=f"{k} random poses, {len(rows)} of them with |q{wrist + 1}| < 1 mrad",
    )  # fmt: skip


def coupled_elbow(
    robot: str = "ur10", k: int = 40, *, errors: ErrorSpec | None = None, seed: int = 0, targets=None
) -> Scenario:
    """Good poses recorded by a controller whose elbow is measured from the horizontal: model J3 = J2 + J3.

    ``q`` are the model joints the measurements belong to, ``q_controller = M⁻¹ q`` what the controller (and a
    CSV) reports, ``joint_map = M`` (:func:`coupled_map`). Importing
    ``q_controller`` as model joints is the mistake; converting through the map gives ``q`` back exactly.
    """
    scn = good(robot, k, errors=errors, seed=seed, targets=targets)
    if scn.n < 3:
        raise ValueError(f"coupled_elbow needs an arm of at least 3 joints, {robot!r} has {scn.n}")
    M = coupled_map(scn.n)
    q_ctrl = scn.q @ np.linalg.inv(M).T
    return scn.changed(
        "coupled-elbow",
        f"{k} poses; controller elbow measured from horizontal (model J3 = J2 + J3)",
        q_controller=q_ctrl,
        joint_map=M,
    )


def identical_poses(
    robot: str = "ur10", k: int = 60, *, errors: ErrorSpec | None = None, seed: int = 0, targets=None
) -> Scenario:
    """One non-singular configuration measured k times (only the tracker noise differs); one group."""
    scn = good(robot, 1, errors=errors, seed=seed, targets=targets)
    q = np.repeat(scn.q, k, axis=0)
    return Scenario(
        "identical-poses", robot, q, _measure(scn.actual, q, scn.targets, seed), scn.targets,
        group=np.zeros(k, int), actual=scn.actual, seed=seed, description=f"one configuration measured {k} times",
    )  # fmt: skip


# ----------------------------------------------------------------------------------------------------------------
# fewer targets seen
def with_targets(scn: Scenario, index) -> Scenario:
    """The same rows with only the targets ``index`` (e.g. ``[0]``: t1 alone, one reflector per pose).

    >>> with_targets(good("ur10", 5, seed=0), [0]).points.shape
    (5, 1, 3)
    """
    idx = np.atleast_1d(np.asarray(index, dtype=int))
    if idx.size == 0 or np.any(idx < 0) or np.any(idx >= scn.m) or len(set(idx.tolist())) != idx.size:
        raise ValueError(f"target index must name distinct targets among 0 … {scn.m - 1}, got {index!r}")
    names = "+".join(f"t{i + 1}" for i in idx)
    return scn.changed(
        f"{scn.name}-{names}", f"{scn.description}; only {names} measured", points=scn.points[:, idx],
        targets=scn.targets[idx],
    )  # fmt: skip


def with_dropout(scn: Scenario, dropout, *, seed: int = 0, exact: bool = True) -> Scenario:
    """Targets lost at random (seeded): NaN rows in ``points``; every row keeps at least one target.

    dropout: fraction of the cells lost (``exact``: exactly round(dropout · k · m) of them), or with ``exact=False``
    the probability (float or (m,) per target) that each cell is lost, as the sim rig draws it
    (:func:`labcal.simulation.actual.seen_mask`).
    """
    seen = scn.seen & seen_mask(scn.k, scn.m, dropout, np.random.default_rng([seed, 17]), exact=exact)
    lost = int((~seen).sum())
    return scn.changed(
        f"{scn.name}-dropout", f"{scn.description}; {lost} of {scn.k * scn.m} target cells not seen",
        points=drop_unseen(scn.points, seen),
    )  # fmt: skip


# ----------------------------------------------------------------------------------------------------------------
# corruptions of a good set
def unit_slip(scn: Scenario, factor: float) -> Scenario:
    """The points multiplied by ``factor``: 1000 = a mm file read as m; 0.001 = a m file read with
    ``--length-unit mm``; 25.4 = inches read as mm. Joints and targets are untouched."""
    return scn.changed(
        f"unit-slip-x{factor:g}",
        f"{scn.description}; points ×{factor:g} (length-unit slip)",
        points=scn.points * factor,
    )


def degrees_as_radians(scn: Scenario) -> Scenario:
    """Joint values in degrees taken for radians (×57.3): ``q`` and ``q_controller`` are converted."""
    qc = None if scn.q_controller is None else np.degrees(scn.q_controller)
    return scn.changed(
        "degrees-as-radians", f"{scn.description}; joints in degrees read as radians", q=np.degrees(scn.q),
        q_controller=qc,
    )  # fmt: skip


def swapped_targets(scn: Scenario, i: int = 0, j: int = 1) -> Scenario:
    """Measured targets t(i+1) and t(j+1) exchanged in every row (a mislabelled reflector or targets file)."""
    if max(i, j) >= scn.m or i == j:
        raise ValueError(f"swapping needs two distinct targets among the {scn.m} measured, got t{i + 1} and t{j + 1}")
    p = scn.points.copy()
    p[:, [i, j]] = p[:, [j, i]]
    return scn.changed(
        f"swapped-t{i + 1}-t{j + 1}", f"{scn.description}; targets t{i + 1} and t{j + 1} swapped", points=p
    )


def wrong_targets(scn: Scenario, targets=None) -> Scenario:
    """The same measurements with another tool's targets file (default: the triangle scaled 0.7 and rotated)."""
    if targets is None:
        targets = scn.targets @ se3.exp_so3(np.array([0.0, 0.0, 0.6])).T * 0.7
    return scn.changed("wrong-targets", f"{scn.description}; targets file of another tool", targets=np.asarray(targets))


def pure_noise(scn: Scenario, *, rigid: bool = False, seed: int = 0) -> Scenario:
    """Measurements unrelated to the joints.

    rigid=False: every coordinate uniform in the bounding box of the measured points (the triangle breaks too);
    rigid=True: the true target triangle at a random position in that box and a random orientation, so every
    row looks like a valid measurement and only the fit can tell. ``actual`` is dropped (no robot made them).
    """
    rng = np.random.default_rng([seed, 11])
    lo, hi = np.nanmin(scn.points.reshape(-1, 3), axis=0), np.nanmax(scn.points.reshape(-1, 3), axis=0)
    if not rigid:
        points = rng.uniform(lo, hi, size=scn.points.shape)
    else:
        R = se3.exp_so3(rng.normal(size=(scn.k, 3)) * 3.0)
        t = rng.uniform(lo, hi, size=(scn.k, 3))
        points = np.einsum("kab,mb->kma", R, scn.targets) + t[:, None]
    kind = "rigid triangles at random poses" if rigid else "uniform random points"
    return scn.changed(
        "pure-noise" + ("-rigid" if rigid else ""), f"{scn.k} rows of {kind}", points=points, actual=None
    )


def shuffled_rows(scn: Scenario, *, seed: int = 0) -> Scenario:
    """Joint rows and measurement rows paired at random (a merge of two files on the wrong key)."""
    order = np.random.default_rng([seed, 13]).permutation(scn.k)
    return scn.changed(
        "shuffled-rows", f"{scn.description}; points paired with the wrong joints", points=scn.points[order]
    )


def in_tracker_frame(scn: Scenario, T_tracker_base=None) -> Scenario:
    """The points expressed in a tracker frame: ``frame="tracker"``, ``T_tracker_base`` the base's pose in it.

    Default pose: 3 m in front of the robot, 0.5 m down, rotated 2.5 rad about z — far enough that reading the
    points as base-frame coordinates puts them out of the robot's reach.
    """
    if T_tracker_base is None:
        T_tracker_base = se3.pose(np.array([3.0, 1.0, -0.5])) @ _rot_z(2.5)
    T = np.asarray(T_tracker_base, float)
    if scn.frame != "base":
        raise ValueError("in_tracker_frame expects base-frame points")
    points = np.einsum("ab,kmb->kma", T[:3, :3], scn.points) + T[:3, 3]
    return scn.changed(
        scn.name + "-tracker-frame", f"{scn.description}; points in a tracker frame", points=points, frame="tracker",
        T_tracker_base=T,
    )  # fmt: skip


def _rot_z(angle: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = se3.exp_so3(np.array([0.0, 0.0, angle]))
    return T
