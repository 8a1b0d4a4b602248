"""Label unordered marker positions as the session's targets by the distances between them.

A tracker that reports stray markers (NDI ``TX:1000``) gives them in no particular order, sometimes with extra
reflections and sometimes without a target it could not see. Distances between markers do not depend on where
the tool is, so a set of markers whose pairwise distances reproduce those of some targets (in the tool frame) is
those targets. This needs three markers at least: two markers at the right distance fit either way round, and one
marker fits anywhere. So:

- three or more markers matching a clearly scalene triangle of targets label themselves, and every further target
  is the one marker at the right distance from all of those (``check_targets`` makes sure at configuration time
  that the target distances can be told apart);
- fewer markers are labelled only when there is nothing to choose: a single target and a single marker, or a
  ``reference`` (the targets' positions in the tracker frame from other frames of the same measurement, robot
  standing still) that each marker sits on;
- a target that cannot be labelled stays NaN, and a frame is rejected only when no marker can be labelled
  unambiguously.

Example: three targets, t3 hidden, and the positions of a frame that saw all three as the reference::

    >>> T = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.07, 0.0]])
    >>> m = match_targets(T[[1, 0]] + 1.0, T, 0.5e-3, reference=T + 1.0)
    >>> m.indices, np.isnan(m.points[2]).all()
    ((1, 0, -1), np.True_)
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from labcal.datasets.targets import pair_distances, target_pairs
from labcal.drivers.base import MeasurementRejected


def check_targets(targets: np.ndarray, tolerance: float) -> np.ndarray:
    """Validate m nominal targets (m, 3) m for labelling stray markers; return them as floats.

    One target is fine (a lone marker is it). Two are refused: their one distance reads the same both ways
    round, so no frame could ever be labelled. Three or more must have all pairwise distances at least
    4 x ``tolerance`` and differing from each other by at least 2 x ``tolerance`` (three: a clearly scalene
    triangle).
    """
    t = np.asarray(targets, dtype=float)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0 or not np.all(np.isfinite(t)):
        raise ValueError(f"targets must be a finite (m, 3) array in metres (m >= 1), got shape {t.shape}")
    m = len(t)
    if m == 1:
        return t
    if m == 2:
        raise ValueError(
            "two targets cannot be told apart as stray markers (the one distance between them reads the same both "
            "ways round): use one target, or three or more"
        )
    pairs = target_pairs(m)
    d = pair_distances(t)
    if np.min(d) < 4 * tolerance:
        i, j = pairs[int(np.argmin(d))]
        raise ValueError(f"targets t{i + 1} and t{j + 1} are (nearly) coincident: {d.min() * 1e3:.3f} mm apart")
    order = np.argsort(d, kind="stable")
    gaps = np.diff(d[order])
    if gaps.size and np.min(gaps) < 2 * tolerance:
        k = int(np.argmin(gaps))
        (a, b), (c, e) = pairs[order[k]], pairs[order[k + 1]]
        raise ValueError(
            f"target distances t{a + 1}-t{b + 1} ({d[order[k]] * 1e3:.3f} mm) and t{c + 1}-t{e + 1} "
            f"({d[order[k + 1]] * 1e3:.3f} mm) differ by less than 2 x tolerance ({2 * tolerance * 1e3:.3f} mm): "
            "the targets are not scalene enough to label markers"
        )
    return t


@dataclass(frozen=True)
class Match:
    """indices: stray index for t1 … tm, -1 where the target is not labelled; mismatch: worst distance error, m
    (0 for a match made without distances); points: (m, 3) m, NaN rows where not labelled."""

    indices: tuple[int, ...]
    mismatch: float
    points: np.ndarray


def _match(p: np.ndarray, assignment: dict[int, int], m: int, mismatch: float) -> Match:
    indices = tuple(assignment.get(t, -1) for t in range(m))
    points = np.where(np.array(indices)[:, None] >= 0, p[list(indices)], np.nan)  # (m, 3), NaN rows: not labelled
    return Match(indices=indices, mismatch=float(mismatch), points=points)


def _by_distances(p: np.ndarray, targets: np.ndarray, tolerance: float) -> tuple[list, float]:
    """Every labelling grown from a matching triangle: ([(score, assignment)], best triangle score seen)."""
    n, m = len(p), len(targets)
    dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
    nominal_all = np.linalg.norm(targets[:, None, :] - targets[None, :, :], axis=2)
    perms = np.array(list(itertools.permutations(range(n), 3)))
    measured = pair_distances(p[perms])  # (P, 3): |ab|, |ac|, |bc| of every ordered triple of markers
    found: dict[tuple, tuple[float, dict[int, int]]] = {}
    best = np.inf
    for triple in itertools.combinations(range(m), 3):
        nominal = pair_distances(targets[list(triple)])
        score = np.max(np.abs(measured - nominal), axis=1)
        best = min(best, float(score.min()))
        for k in np.flatnonzero(score <= tolerance):
            assignment = dict(zip(triple, (int(s) for s in perms[k]), strict=True))
            if any(assignment.items() <= dict(key).items() for key in found):
                continue  # a triangle of a labelling already grown: growing it again gives the same labelling
            worst = float(score[k])
            # Grow the triangle: a further target is the one unused marker at the right distance from all labelled.
            for target in range(m):
                if target in assignment:
                    continue
                labelled, markers = list(assignment), list(assignment.values())
                errors = np.max(np.abs(dist[:, markers] - nominal_all[target, labelled]), axis=1)  # (n,) m
                errors[markers] = np.inf  # a marker labels one target
                fits = np.flatnonzero(errors <= tolerance)
                if len(fits) == 1:
                    assignment[target] = int(fits[0])
                    worst = max(worst, float(errors[fits[0]]))
            key = tuple(sorted(assignment.items()))
            if key not in found or worst < found[key][0]:
                found[key] = (worst, assignment)
    return sorted(found.values(), key=lambda c: (-len(c[1]), c[0])), best


def _by_reference(p: np.ndarray, reference: np.ndarray, tolerance: float) -> dict[int, int]:
    """Markers lying on a reference position (within ``tolerance``, one candidate each way): {target: marker}."""
    gap = np.linalg.norm(p[:, None, :] - reference[None, :, :], axis=2)  # (n, m), NaN for unseen references
    near = np.nan_to_num(gap, nan=np.inf) <= tolerance
    # A marker near exactly one reference that no other marker is near.
    unique = near & (near.sum(axis=0) == 1)[None, :] & (near.sum(axis=1) == 1)[:, None]
    return {int(t): int(s) for t, s in zip(*np.nonzero(unique.T), strict=True)}


def match_targets(
    strays: np.ndarray, targets: np.ndarray, tolerance: float, reference: np.ndarray | None = None
) -> Match:
    """Label ``strays`` (N, 3) m as the nominal ``targets`` (m, 3) m; targets left unlabelled come back NaN.

    With three or more targets, the labelling that explains the most targets by distances within ``tolerance``
    (m) wins, and another labelling of as many targets that also fits makes the frame ambiguous. With fewer than
    three markers (or no matching triangle) markers are labelled from ``reference`` (m, 3) m, NaN rows allowed,
    or, for a single target, when exactly one marker is seen. Raises MeasurementRejected with the reason when no
    target can be labelled unambiguously.
    """
    p = np.asarray(strays, dtype=float).reshape(-1, 3)
    t = np.asarray(targets, dtype=float)
    n, m = len(p), len(t)
    if n == 0:
        raise MeasurementRejected("no marker visible")
    best = np.inf
    if m >= 3 and n >= 3:
        candidates, best = _by_distances(p, t, tolerance)
        if candidates:
            worst, assignment = candidates[0]
            if len(candidates) > 1 and len(candidates[1][1]) == len(assignment):
                raise MeasurementRejected(
                    f"ambiguous marker assignment: two labellings of the {n} markers match the target "
                    f"{'triangle' if m == 3 else 'distances'} within {tolerance * 1e3:.3f} mm"
                )
            return _match(p, assignment, m, worst)
    if reference is not None:
        ref = np.asarray(reference, dtype=float).reshape(m, 3)
        assignment = _by_reference(p, ref, tolerance)
        if assignment:
            labelled = sorted(assignment)
            got = pair_distances(p[[assignment[k] for k in labelled]])
            want = pair_distances(t[labelled])
            worst = float(np.max(np.abs(got - want))) if got.size else 0.0
            if worst <= tolerance:
                return _match(p, assignment, m, worst)
    if m == 1 and n == 1:
        return _match(p, {0: 0}, 1, 0.0)
    if np.isfinite(best):
        raise MeasurementRejected(
            f"no 3 of {n} markers match the target triangle: best side-length mismatch "
            f"{best * 1e3:.3f} mm > tolerance {tolerance * 1e3:.3f} mm"
        )
    if m == 1:
        raise MeasurementRejected(f"{n} markers visible for the one target: cannot tell which one it is")
    raise MeasurementRejected(
        f"only {n} marker(s) visible: fewer than three markers cannot be told apart by their distances, and no "
        "complete frame of this measurement shows where the targets are"
    )
