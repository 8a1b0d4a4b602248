"""Calibration input: configurations and the measured target points (1 … m targets, any of them missing).

Every method takes an :class:`Observations`. Measured points are in the base frame (``frame="base"``) or in the
tracker frame (``frame="tracker"``, the tracker-to-base pose is then estimated by the fit).

**Targets.** ``targets`` (m, 3) are the m ≥ 1 target points in the tool frame; ``points[r, i]`` is where target i
was measured in row r, or a whole row of NaN when the tracker did not see it (``seen[r, i]`` False). A row must
see at least one target. The targets may lie on a line or coincide (one reflector): that is not an error, but the
points then cannot show some rotations of the tool; :func:`target_geometry` says which, and the fits report it.
A tool pose is measured (:meth:`Observations.measured_poses`) only in rows that see three non-collinear targets.

Example::

    >>> obs = Observations(q=np.zeros((2, 1)), points=np.zeros((2, 3, 3)) + [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
    ...                    targets=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]))
    >>> obs.k, obs.n, obs.m, obs.split.tolist()
    (2, 1, 3, ['', ''])
    >>> two = Observations(q=np.zeros((2, 1)), points=np.array([[[0, 0, 0], [1, 0, 0]], [[np.nan] * 3, [1, 0, 0]]]),
    ...                    targets=np.array([[0, 0, 0], [1, 0, 0.0]]))      # t1 not seen in row 1
    >>> two.m, two.seen.tolist(), bool(two.pose_rows().any())
    (2, [[True, True], [False, True]], False)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from labcal.kinematics.se3 import rigid_fit

SAME_NEIGHBOURHOOD = np.deg2rad(1.0)  # rad (17 mm of a prismatic joint): closer in every joint, one validation unit
NEIGHBOURHOOD_FOLDS = 10  # neighbours chain into units of at most a tenth of the rows

SPLITS = ("train", "val", "test", "")
MIN_TRIANGLE_AREA = 1e-6  # m²: 1 mm × 2 mm; below this three targets cannot fix an orientation
MIN_SPREAD = 1e-3  # m: targets closer than this to each other are one point (they cannot show a rotation)


class ObservationError(ValueError):
    """The calibration input is unusable; the message names the row, joint or field."""


@dataclass(frozen=True, eq=False)
class Observations:
    """q: (k, n) commanded joints (rad, m); points: (k, m, 3) measured targets (m), rows t1..tm, a NaN row where
    the target was not seen; targets: (m, 3) target positions in the tool frame (m);
    split: (k,) "train" | "val" | "test" | "";
    group: optional (k,) labels of rows that belong together (a session of a pooled fit, a sweep): they are kept
    in one cross-validation fold and on one side of a train/validation split (see :meth:`units`)."""

    q: np.ndarray
    points: np.ndarray
    targets: np.ndarray
    frame: str = "base"
    split: np.ndarray = field(default=None)  # type: ignore[arg-type]  # None: every row unlabelled ("")
    group: np.ndarray | None = None
    if TYPE_CHECKING:  # (k, m) bool, set by __post_init__: derived from points, so not a dataclass field
        _seen: ClassVar[np.ndarray]

    def __post_init__(self) -> None:
        q = np.asarray(self.q, dtype=float)
        points = np.asarray(self.points, dtype=float)
        targets = np.asarray(self.targets, dtype=float)
        if q.ndim != 2:
            raise ObservationError(f"q must have shape (k, n), got {q.shape}")
        k = q.shape[0]
        if targets.ndim != 2 or targets.shape[1] != 3 or targets.shape[0] < 1:
            raise ObservationError(f"targets must have shape (m, 3) with m >= 1 targets, got {targets.shape}")
        m = targets.shape[0]
        if points.shape != (k, m, 3):
            raise ObservationError(
                f"points must have shape ({k}, {m}, 3) for {k} configurations and {m} targets, got {points.shape}"
            )
        check_targets(targets)
        bad = ~np.isfinite(q).all(axis=1)
        if np.any(bad):
            raise ObservationError(f"q of configuration (row) {int(np.argmax(bad))} is not finite")
        seen = _seen(points)
        object.__setattr__(self, "_seen", seen)
        if self.frame not in ("base", "tracker"):
            raise ObservationError(f"frame must be 'base' or 'tracker', got {self.frame!r}")
        split = np.full(k, "", dtype=object) if self.split is None else np.asarray(self.split, dtype=object)
        if split.shape != (k,):
            raise ObservationError(f"split must have shape ({k},), got {split.shape}")
        unknown = [s for s in set(split.tolist()) if s not in SPLITS]
        if unknown:
            row = int(np.argmax([s in unknown for s in split]))
            raise ObservationError(f"split of row {row} is {split[row]!r}; allowed: train, val, test or empty")
        if self.group is not None:
            group = np.asarray(self.group, dtype=object)
            if group.shape != (k,):
                raise ObservationError(f"group must have shape ({k},), got {group.shape}")
            object.__setattr__(self, "group", group)
        for name, arr in (("q", q), ("points", points), ("targets", targets)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "split", split)

    @property
    def k(self) -> int:
        return self.q.shape[0]

    @property
    def m(self) -> int:
        """The number of targets."""
        return self.targets.shape[0]

    @property
    def seen(self) -> np.ndarray:
        """(k, m) bool, read-only: True where the target was measured in that row."""
        return self._seen

    @property
    def complete(self) -> bool:
        """Every target seen in every row."""
        return bool(self._seen.all())

    @property
    def n(self) -> int:
        return self.q.shape[1]

    def check_robot(self, n_joints: int) -> None:
        """Raise if the observations do not belong to a robot with n_joints joints."""
        if self.n != n_joints:
            raise ObservationError(f"observations have {self.n} joint values per row, the robot has {n_joints}")

    def subset(self, mask_or_index) -> Observations:
        """A new Observations of the selected rows (boolean mask or integer index)."""
        idx = np.asarray(mask_or_index)
        group = None if self.group is None else self.group[idx]
        return Observations(self.q[idx], self.points[idx], self.targets, self.frame, self.split[idx], group)

    def with_split(self, split) -> Observations:
        """The same rows with new split labels."""
        return Observations(self.q, self.points, self.targets, self.frame, np.asarray(split, dtype=object), self.group)

    def units(self) -> np.ndarray:
        """(k,) integer unit of every row: rows of one ``group`` label, and rows with identical joint values
        (repeated measurements of one pose), share a unit; so do poses within :data:`SAME_NEIGHBOURHOOD` of each
        other in every joint (the fine steps of a sweep), chained up to a unit of one :data:`NEIGHBOURHOOD_FOLDS`-th
        of the rows, so that sweeps through one home pose stay several units and the folds still exist. Splits and
        cross-validation folds never cut a unit, so a held-out error is never measured on a pose (or a session, or
        a pose a step away from one) that was also fitted. Numbered by first appearance, so the result depends only
        on the data."""
        from scipy.cluster.hierarchy import DisjointSet
        from scipy.spatial import cKDTree

        k = self.k
        units = DisjointSet(range(k))
        if k:
            poses, first_row, inverse = np.unique(self.q, axis=0, return_index=True, return_inverse=True)
            for label in (inverse.reshape(-1), self.group):
                if label is None:
                    continue
                first: dict = {}
                for i, g in enumerate(label.tolist()):
                    if (j := first.setdefault(g, i)) != i:
                        units.merge(j, i)
            # A learned term interpolates between neighbours this close: a fold that fits one and scores the other
            # measures that interpolation, not the error at a new pose (fine sweeps, points paired a row late).
            # Among distinct poses (repeats are joined above), in a fixed order, so the units depend only on the data.
            pairs = cKDTree(poses).query_pairs(SAME_NEIGHBOURHOOD, p=np.inf, output_type="ndarray")
            cap = max(2, k // NEIGHBOURHOOD_FOLDS)
            for a, b in first_row[pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]].tolist():
                if not units.connected(a, b) and units.subset_size(a) + units.subset_size(b) <= cap:
                    units.merge(a, b)
        roots = np.array([units[i] for i in range(k)], dtype=int)
        _, first_index, inverse = np.unique(roots, return_index=True, return_inverse=True)
        order = np.argsort(np.argsort(first_index, kind="stable"), kind="stable")
        return order[inverse.reshape(-1)]

    def where(self, split: str) -> Observations:
        """The rows of one split."""
        return self.subset(self.split == split)

    def with_splits(self, val_fraction: float = 0.5, seed: int = 0) -> Observations:
        """Assign unassigned rows ("") to train/val at random (seeded); rows already assigned stay.

        Whole units (:meth:`units`: a group, repeated measurements of one pose) go to one side, so the validation
        share is round(val_fraction · free rows) up to the size of the last unit drawn."""
        if not 0.0 <= val_fraction < 1.0:
            raise ObservationError(f"val_fraction must be in [0, 1), got {val_fraction}")
        split = self.split.copy()
        free = np.flatnonzero(split == "")
        n_val = round(val_fraction * len(free))
        units = self.units()[free]
        if len(np.unique(units)) == len(free):  # every row its own unit: the row permutation of earlier versions
            order = np.random.default_rng(seed).permutation(free)
            split[order[:n_val]] = "val"
            split[order[n_val:]] = "train"
        else:
            split[free] = "train"
            taken = 0
            for u in np.random.default_rng(seed).permutation(np.unique(units)):
                if taken >= n_val:
                    break
                rows = free[units == u]
                split[rows] = "val"
                taken += len(rows)
        return Observations(self.q, self.points, self.targets, self.frame, split, self.group)

    def pose_rows(self) -> np.ndarray:
        """(k,) bool: rows whose seen targets fix a tool pose (three or more, not collinear)."""
        out = np.zeros(self.k, bool)
        for pattern, rows in seen_patterns(self._seen):
            out[rows] = target_geometry(self.targets[pattern])[0] == "plane"
        return out

    def measured_poses(self) -> np.ndarray:
        """(k, 4, 4) tool poses fitted to the measured points (least squares rigid fit, Kabsch), NaN in rows that
        do not see three non-collinear targets (:meth:`pose_rows`).

        In the observation frame. Noise-free points give the exact pose; noisy ones the best rigid fit.
        """
        out = np.full((self.k, 4, 4), np.nan)
        for pattern, rows in seen_patterns(self._seen):
            if target_geometry(self.targets[pattern])[0] == "plane":
                out[rows] = rigid_fit(self.targets[pattern], self.points[rows][:, pattern])
        return out


def pooled(datasets: Sequence[Any], q: np.ndarray | None = None, group: np.ndarray | None = None) -> Observations:
    """The rows of recorded data sets (anything with ``q``, ``points``, ``split``, ``targets`` and ``frame``, such as
    :class:`labcal.datasets.Dataset`), in order, as one Observations with the first one's targets and frame.

    ``q`` replaces their stacked joints (the CLI passes them converted to model joints); ``group`` labels the rows.
    """
    first = datasets[0]
    return Observations(
        q=np.concatenate([d.q for d in datasets]) if q is None else q,
        points=np.concatenate([d.points for d in datasets]),
        targets=first.targets,
        frame=first.frame,
        split=np.concatenate([d.split for d in datasets]).astype(object),
        group=group,
    )


def check_targets(targets: np.ndarray) -> None:
    """Raise ObservationError if a target is not finite (a row of the targets file names it).

    Collinear or coincident targets are accepted: :func:`target_geometry` reports what they cannot show."""
    targets = np.asarray(targets, dtype=float)
    bad = ~np.isfinite(targets).all(axis=-1)
    if np.any(bad):
        raise ObservationError(f"target t{int(np.argmax(bad)) + 1} has a non-finite coordinate: {targets[bad][0]}")


def target_geometry(targets: np.ndarray) -> tuple[str, np.ndarray]:
    """What a set of tool-frame targets (m, 3) spans: ``("point", centroid)``, ``("line", (point, unit
    direction))`` as a (2, 3) array, or ``("plane", centroid)`` (three or more non-collinear targets).

    Targets within :data:`MIN_SPREAD` of each other are one point (a rotation about it moves none of them); a
    line when no target leaves the line through the two farthest apart by a triangle of :data:`MIN_TRIANGLE_AREA`
    (a rotation about that line moves none of them).

    >>> target_geometry(np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]]))[0]
    'line'
    """
    t = np.asarray(targets, dtype=float).reshape(-1, 3)
    centroid = t.mean(axis=0)
    d = np.linalg.norm(t[:, None] - t[None], axis=-1)
    a, b = np.unravel_index(int(np.argmax(d)), d.shape)
    if d[a, b] < MIN_SPREAD:
        return "point", centroid
    u = (t[b] - t[a]) / d[a, b]
    area = 0.5 * np.linalg.norm(np.cross(t[b] - t[a], t - t[a]), axis=-1)
    if t.shape[0] < 3 or float(np.max(area)) < MIN_TRIANGLE_AREA:
        return "line", np.stack([t[a], u])
    return "plane", centroid


def _seen(points: np.ndarray) -> np.ndarray:
    """(k, m) seen mask of (k, m, 3) points; raises naming the row for a partly empty point or an empty row."""
    nan = np.isnan(points)
    partial = nan.any(axis=-1) & ~nan.all(axis=-1)
    if np.any(partial):
        r, i = np.argwhere(partial)[0]
        raise ObservationError(
            f"point t{i + 1} of configuration (row) {r} is partly empty ({points[r, i].tolist()}): a target is "
            "either seen (x, y and z) or not seen (all three empty)"
        )
    inf = np.isinf(points).any(axis=-1)
    if np.any(inf):
        r, i = np.argwhere(inf)[0]
        raise ObservationError(f"points of configuration (row) {r} are not finite (t{i + 1} is infinite)")
    seen = ~nan.any(axis=-1)
    empty = ~seen.any(axis=1) if seen.shape[1] else np.ones(seen.shape[0], bool)
    if np.any(empty):
        raise ObservationError(
            f"row {int(np.argmax(empty))} has no target seen (every point is empty): it is not a measurement; "
            "drop the row"
        )
    seen.setflags(write=False)
    return seen


def seen_patterns(seen: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(target mask (m,), row indices)] for each distinct seen pattern, in order of first appearance."""
    if seen.shape[0] == 0:
        return []
    uniq, first, inverse = np.unique(seen, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    return [(uniq[u], np.flatnonzero(inverse == u)) for u in np.argsort(first, kind="stable")]
