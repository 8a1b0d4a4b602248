"""Label unordered marker positions as the three nominal targets by their triangle side lengths.

A tracker that reports stray markers (NDI ``TX:1000``) gives them in no particular order, sometimes with extra
reflections. Distances between markers do not depend on where the tool is, so the ordered triple of markers
whose pairwise distances best reproduce the nominal triangle (targets in the tool frame) is the assignment.
This only works if the nominal triangle is clearly scalene; ``check_scalene`` says so at configuration time.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from labcal.drivers.base import MeasurementRejected

_PAIRS = ((0, 1), (0, 2), (1, 2))


def side_lengths(points: np.ndarray) -> np.ndarray:
    """Side lengths (3,) of the triangle of ``points`` (3, 3), ordered |p1-p2|, |p1-p3|, |p2-p3|, same unit."""
    p = np.asarray(points, dtype=float)
    return np.array([np.linalg.norm(p[i] - p[j]) for i, j in _PAIRS])


def check_scalene(targets: np.ndarray, tolerance: float) -> np.ndarray:
    """Validate nominal targets (3, 3) m and return them as floats.

    Raises ValueError when two sides differ by less than 2 x ``tolerance`` (m): such a triangle cannot be
    labelled from distances within that tolerance.
    """
    t = np.asarray(targets, dtype=float)
    if t.shape != (3, 3) or not np.all(np.isfinite(t)):
        raise ValueError(f"targets must be a finite (3, 3) array in metres, got shape {t.shape}")
    sides = side_lengths(t)
    names = ("t1-t2", "t1-t3", "t2-t3")
    if np.min(sides) < 4 * tolerance:
        raise ValueError(f"targets are (nearly) coincident: side lengths {np.round(sides * 1e3, 3)} mm")
    for a, b in itertools.combinations(range(3), 2):
        if abs(sides[a] - sides[b]) < 2 * tolerance:
            raise ValueError(
                f"target triangle is not scalene enough to label markers: sides {names[a]} "
                f"({sides[a] * 1e3:.3f} mm) and {names[b]} ({sides[b] * 1e3:.3f} mm) differ by less than "
                f"2 x tolerance ({2 * tolerance * 1e3:.3f} mm)"
            )
    return t


@dataclass(frozen=True)
class Match:
    """indices: stray index for t1, t2, t3; mismatch: worst side-length error, m; points: (3, 3) m."""

    indices: tuple[int, int, int]
    mismatch: float
    points: np.ndarray


def match_targets(strays: np.ndarray, targets: np.ndarray, tolerance: float) -> Match:
    """Pick the ordered triple of ``strays`` (N, 3) m that best fits the nominal ``targets`` (3, 3) m.

    The score of a triple is its worst side-length error; the best triple must be within ``tolerance`` (m) and
    the runner-up (a different set or order) must not, otherwise the frame is ambiguous. Raises
    MeasurementRejected with the reason.
    """
    p = np.asarray(strays, dtype=float).reshape(-1, 3)
    n = p.shape[0]
    if n < 3:
        raise MeasurementRejected(f"only {n} marker(s) visible, need 3")
    nominal = side_lengths(targets)
    dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
    perms = np.array(list(itertools.permutations(range(n), 3)))
    measured = np.stack([dist[perms[:, i], perms[:, j]] for i, j in _PAIRS], axis=1)
    score = np.max(np.abs(measured - nominal), axis=1)
    order = np.argsort(score, kind="stable")
    best = int(order[0])
    if score[best] > tolerance:
        raise MeasurementRejected(
            f"no 3 of {n} markers match the target triangle: best side-length mismatch "
            f"{score[best] * 1e3:.3f} mm > tolerance {tolerance * 1e3:.3f} mm"
        )
    if len(order) > 1 and score[order[1]] <= tolerance:
        raise MeasurementRejected(
            f"ambiguous marker assignment: two triples of the {n} markers match the target triangle within "
            f"{tolerance * 1e3:.3f} mm"
        )
    idx = tuple(int(i) for i in perms[best])
    return Match(indices=(idx[0], idx[1], idx[2]), mismatch=float(score[best]), points=p[list(idx)])
