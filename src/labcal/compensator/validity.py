"""The validity region of a compensator: the neighbourhood of the configurations its data measured.

A calibration is measured where its data are. The per-joint box of the data's ranges is not that region: data
taken in a small cube at one orientation move the wrist joints together with the arm joints, and the box lets every
joint vary on its own, so most of its volume is configurations no pose resembled (the narrow series of issue 27:
large corrections at 15 % of the box). The region is therefore the union of balls of radius ``radius`` around the
fitted configurations (``centres``) in a scaled joint space: each joint divided by its spread in the data (standard
deviation, at least :data:`MIN_SPREAD`). A joint the data swept is measured in units of that sweep; a joint the
data barely moved (joint 5 of a series at one tool axis) keeps the region within a few of its tiny spreads of
where it was, so nothing the data did not see is extrapolated along it.

``radius`` is twice the median distance from a fitted configuration to its nearest neighbour, at least
:data:`MIN_RADIUS`: the spacing of the data themselves, so the balls of a well-spread series overlap into one
region, while a corner of the box that no configuration came near stays outside. The floor is what keeps
configurations like the data's inside as the data grow denser: with 0.5 spreads, a local-POE fit on 1,500 of the
real UR10's random poses refused 10 % of the other 1,273; with 1.5 spreads it refuses 0.1 % (97 % inside with 150
fitted poses, 99.6 % with 500), and a joint the data barely moved still stays within 1.5 of its tiny spreads.
The file keeps at most
:data:`MAX_CENTRES` configurations (a farthest-point subsample, deterministic; the radius grows to the largest
distance of a dropped configuration to the kept ones, so every fitted configuration stays inside): bounded size
(at most 512 × n numbers) whatever the session's length.

Example::

    >>> q = np.array([[0.0, 1.0], [0.2, 1.0], [0.4, 1.0]])            # joint 2 never moved
    >>> region = ValidityRegion.from_configurations(q)
    >>> region.weights.round(3).tolist()                               # 1 / spread (joint 2: 1 / MIN_SPREAD)
    [6.124, 1000.0]
    >>> bool(region.inside(np.array([[0.3, 1.0]]))[0]), bool(region.inside(np.array([[0.3, 1.01]]))[0])
    (True, False)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_CENTRES = 512  # configurations kept in a compensator file
MIN_SPREAD = 1e-3  # rad (m): the least spread a joint is scaled by (a joint that never moved: 1 mrad)
MIN_RADIUS = 1.5  # spreads: the least radius (see the module docstring: data-like configurations must be inside)
RADIUS_FACTOR = 2.0  # radius = factor × median nearest-neighbour distance of the data


@dataclass(frozen=True, eq=False)
class ValidityRegion:
    """centres (c, n) in scaled joint units, radius (same units), weights (n,) the factors that turn joint values
    (rad, m) into those units: 1 / the joint's spread in the data."""

    centres: np.ndarray
    radius: float
    weights: np.ndarray

    @classmethod
    def from_configurations(cls, q: np.ndarray, weights: np.ndarray | None = None) -> ValidityRegion:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        w = 1.0 / np.maximum(q.std(axis=0), MIN_SPREAD) if weights is None else np.asarray(weights, dtype=float)
        x = np.unique(q * w, axis=0)
        if len(x) > 1:
            nearest = _nearest(x, x, exclude_self=True)
            radius = max(MIN_RADIUS, RADIUS_FACTOR * float(np.median(nearest)))
        else:
            radius = MIN_RADIUS
        if len(x) > MAX_CENTRES:
            keep = _farthest_points(x, MAX_CENTRES)
            radius = max(radius, float(_nearest(x, x[keep]).max()))
            x = x[keep]
        return cls(centres=x, radius=radius, weights=w)

    def distance(self, q2: np.ndarray) -> np.ndarray:
        """(k,) scaled distance from each configuration (k, n) to the nearest centre."""
        return _nearest(np.atleast_2d(q2) * self.weights, self.centres)

    def reach(self) -> np.ndarray:
        """(n, 2) the least and greatest value of each joint inside the region (model joint units)."""
        half = self.radius / self.weights
        return np.stack(
            [self.centres.min(axis=0) / self.weights - half, self.centres.max(axis=0) / self.weights + half], axis=1
        )

    def inside(self, q2: np.ndarray) -> np.ndarray:
        """(k,) whether each configuration (k, n) is inside (within the radius of a centre)."""
        return self.distance(q2) <= self.radius

    def sample(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """(count, n) configurations drawn uniformly in the balls around random centres (model joint units)."""
        n = self.centres.shape[1]
        c = self.centres[rng.integers(0, len(self.centres), size=count)]
        u = rng.normal(size=(count, n))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        r = self.radius * rng.uniform(0, 1, size=(count, 1)) ** (1.0 / n)
        return (c + u * r) / self.weights

    def as_dict(self) -> dict:
        return {"centres": self.centres.tolist(), "radius": float(self.radius), "joint_scale": self.weights.tolist()}

    @classmethod
    def from_dict(cls, d: dict, n: int) -> ValidityRegion:
        centres = np.asarray(d["centres"], dtype=float).reshape(-1, n)
        weights = np.asarray(d["joint_scale"], dtype=float).reshape(n)
        radius = float(d["radius"])
        if not (len(centres) and np.isfinite(centres).all() and np.isfinite(weights).all() and weights.min() > 0):
            raise ValueError("validity: centres and weights must be finite numbers (weights > 0), at least one centre")
        if not (np.isfinite(radius) and radius > 0) or len(centres) > MAX_CENTRES:
            raise ValueError(f"validity: radius must be > 0 and at most {MAX_CENTRES} centres")
        return cls(centres=centres, radius=radius, weights=weights)


def _nearest(x: np.ndarray, centres: np.ndarray, exclude_self: bool = False) -> np.ndarray:
    """(k,) Euclidean distance from each row of x to the nearest row of centres (in blocks: bounded memory)."""
    out = np.empty(len(x))
    for start in range(0, len(x), 256):
        block = x[start : start + 256]
        d2 = (
            np.einsum("ka,ka->k", block, block)[:, None]
            - 2.0 * block @ centres.T
            + np.einsum("ca,ca->c", centres, centres)[None]
        )
        if exclude_self:
            d2[np.arange(len(block)), np.arange(start, start + len(block))] = np.inf
        out[start : start + 256] = np.sqrt(np.clip(d2.min(axis=1), 0.0, None))
    return out


def _farthest_points(x: np.ndarray, count: int) -> np.ndarray:
    """Indices of a greedy farthest-point subsample, starting at row 0 (deterministic)."""
    chosen = [0]
    d = np.linalg.norm(x - x[0], axis=1)
    for _ in range(count - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(x - x[i], axis=1))
    return np.array(sorted(chosen))
