"""Calibration input: configurations and the three measured target points, validated once.

Every method takes an :class:`Observations`. Measured points are in the base frame (``frame="base"``) or in the
tracker frame (``frame="tracker"``, the tracker-to-base pose is then estimated by the fit).

Example::

    >>> obs = Observations(q=np.zeros((2, 1)), points=np.zeros((2, 3, 3)) + [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
    ...                    targets=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]))
    >>> obs.k, obs.n, obs.split.tolist()
    (2, 1, ['', ''])
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from labcal.kinematics.se3 import rigid_fit

SPLITS = ("train", "val", "test", "")
MIN_TRIANGLE_AREA = 1e-6  # m²: 1 mm × 2 mm; below this the three targets cannot fix an orientation


class ObservationError(ValueError):
    """The calibration input is unusable; the message names the row, joint or field."""


@dataclass(frozen=True, eq=False)
class Observations:
    """q: (k, n) commanded joints (rad, m); points: (k, 3, 3) measured targets (m), rows t1..t3;
    targets: (3, 3) target positions in the tool frame (m); split: (k,) "train" | "val" | "test" | "";
    group: optional (k,) labels of rows that belong together (a session of a pooled fit, a sweep): they are kept
    in one cross-validation fold and on one side of a train/validation split (see :meth:`units`)."""

    q: np.ndarray
    points: np.ndarray
    targets: np.ndarray
    frame: str = "base"
    split: np.ndarray = field(default=None)  # type: ignore[assignment]
    group: np.ndarray | None = None

    def __post_init__(self) -> None:
        q = np.asarray(self.q, dtype=float)
        points = np.asarray(self.points, dtype=float)
        targets = np.asarray(self.targets, dtype=float)
        if q.ndim != 2:
            raise ObservationError(f"q must have shape (k, n), got {q.shape}")
        k = q.shape[0]
        if points.shape != (k, 3, 3):
            raise ObservationError(f"points must have shape ({k}, 3, 3) for {k} configurations, got {points.shape}")
        if targets.shape != (3, 3):
            raise ObservationError(f"targets must have shape (3, 3), got {targets.shape}")
        check_targets(targets)
        for name, arr in (("q", q), ("points", points)):
            bad = ~np.isfinite(arr.reshape(k, int(np.prod(arr.shape[1:])))).all(axis=1)
            if np.any(bad):
                raise ObservationError(f"{name} of configuration (row) {int(np.argmax(bad))} is not finite")
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
        (repeated measurements of one pose), share a unit. Splits and cross-validation folds never cut a unit,
        so a held-out error is never measured on a pose (or a session) that was also fitted. Numbered by first
        appearance, so the result depends only on the data."""
        k = self.k
        parent = np.arange(k)

        def find(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        def join(rows: np.ndarray) -> None:
            root = find(int(rows[0]))
            for r in rows[1:]:
                other = find(int(r))
                if other != root:
                    parent[max(other, root)] = min(other, root)
                    root = min(other, root)

        if k:
            _, inverse = np.unique(self.q, axis=0, return_inverse=True)
            for label in (inverse.reshape(-1), None if self.group is None else self.group):
                if label is None:
                    continue
                first: dict = {}
                for i, g in enumerate(label.tolist()):
                    first.setdefault(g, []).append(i)
                for rows in first.values():
                    if len(rows) > 1:
                        join(np.array(rows))
        roots = np.array([find(i) for i in range(k)], dtype=int)
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

    def measured_poses(self) -> np.ndarray:
        """(k, 4, 4) tool poses fitted to the three measured points (least squares rigid fit, Kabsch).

        In the observation frame. Noise-free points give the exact pose; noisy ones the best rigid fit.
        """
        return rigid_fit(self.targets, self.points)


def check_targets(targets: np.ndarray) -> None:
    """Raise ObservationError if the three target points are (nearly) collinear."""
    targets = np.asarray(targets, dtype=float)
    if not np.all(np.isfinite(targets)):
        raise ObservationError("targets contain non-finite values")
    area = 0.5 * np.linalg.norm(np.cross(targets[1] - targets[0], targets[2] - targets[0]))
    if area < MIN_TRIANGLE_AREA:
        raise ObservationError(
            f"the three targets are (nearly) collinear: triangle area {area:.3g} m² < {MIN_TRIANGLE_AREA} m²"
        )
