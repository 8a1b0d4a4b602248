"""Accuracy metrics: one definition used by fits, reports, benchmarks and the CLI.

Position error: distance between predicted and measured tool origins (m). Orientation error: the angle of
``R_measured R_predictedᵀ`` (rad), measured on the manifold. The measured pose is the rigid fit of the targets to
the measured points (:func:`labcal.calibration.observations.rigid_fit`), so it exists only in rows that see three
non-collinear targets (:meth:`~labcal.calibration.observations.Observations.pose_rows`); elsewhere the pose
errors are NaN and the summaries count only the rows that have one.

Point error: distance between each predicted target point and its measured position (m), per configuration and
target (:func:`point_errors`). The pose error hides a targets file that does not match the data (the rigid fit
absorbs it); the point error does not, so both are reported side by side.

**Primary metric.** Point errors are what every fit minimises and what any tracker measures. Pose errors are the
primary figure only when every row fixes a pose; whenever some row sees fewer than three (non-collinear) targets
the per-target point errors are (``split_table``'s ``"primary"``, :func:`primary_error`), and
:func:`observability` says what orientation accuracy the data can support.

Example::

    >>> s = summarize(np.array([1e-3, 2e-3]), np.array([1e-4, 3e-4]))
    >>> round(s["pos_mean"] * 1e3, 6), round(s["ori_max"] * 1e3, 6)
    (1.5, 0.3)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypedDict

import numpy as np

from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3

STATS = ("mean", "rms", "p95", "max", "std")


class FitWarning(TypedDict):
    """A blocking finding of a fit (``FitResult.warnings``; :mod:`labcal.calibration.fit` lists the codes)."""

    code: str
    message: str


class PointStats(TypedDict):
    """Count (finite distances), mean, p95 and max (m) of target-point distances."""

    count: float
    mean: float
    p95: float
    max: float


class PointSummary(PointStats):
    """:func:`summarize_points`: over every target point, then per target."""

    per_target: list[PointStats]


class BeforeAfter(TypedDict):
    before: PointSummary
    after: PointSummary


class SplitEntry(TypedDict):
    """One split of :func:`split_table`; "before"/"after" are :func:`summarize` (count, pos_mean … ori_std)."""

    before: dict[str, float]
    after: dict[str, float]
    points: BeforeAfter
    primary: str


class Observability(TypedDict):
    """:func:`observability`'s record (saved with a fit)."""

    targets: int
    geometry: str
    rows: int
    rows_with_pose: int
    orientation: str
    unobservable: list[str]
    claim: str


def summarize(pos: np.ndarray, ori: np.ndarray) -> dict[str, float]:
    """Mean, RMS, 95th percentile, max and std of position (m) and orientation (rad) errors.

    NaN entries (rows without a measured pose) are skipped; ``count`` is the number of rows summarised."""
    pos, ori = np.asarray(pos, float), np.asarray(ori, float)
    defined = np.isfinite(pos) & np.isfinite(ori)  # NaN: rows without a measured pose
    pos, ori = pos[defined], ori[defined]
    out: dict[str, float] = {"count": float(len(pos))}
    for name, e in (("pos", pos), ("ori", ori)):
        out.update({f"{name}_{s}": value for s, value in statistics(e, STATS).items()})
    return out


_STATISTICS: dict[str, Callable[[np.ndarray], Any]] = {
    "mean": np.mean,
    "rms": lambda e: np.sqrt(np.mean(e * e)),
    "p95": lambda e: np.percentile(e, 95),
    "max": np.max,
    "min": np.min,
    "median": np.median,
    "std": np.std,
}


def statistics(e: np.ndarray, names: tuple[str, ...]) -> dict[str, float]:
    """{name: that statistic of the errors e} for names among mean, rms, p95, max, min, median, std; NaN each when
    e is empty."""
    return {name: float(_STATISTICS[name](e)) if e.size else float("nan") for name in names}


def prediction_errors(robot: CalibratedRobot, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """Per-configuration (position m, orientation rad) error of the robot's predicted pose vs the measured one.

    Tracker-frame data are compared in the tracker frame through the robot's T_tracker_base. NaN in rows that do
    not see three non-collinear targets (no measured pose).
    """
    if obs.k == 0:
        return np.zeros(0), np.zeros(0)
    T_pred = robot.T_tracker_base @ robot.predict_pose(obs.q, tcp=robot.measurement_tool)  # the fixture measured
    has = obs.pose_rows()
    pos, ori = np.full(obs.k, np.nan), np.full(obs.k, np.nan)
    if has.any():
        pos[has], ori[has] = se3.pose_distance(obs.measured_poses()[has], T_pred[has])
    return pos, ori


def point_residuals(robot: CalibratedRobot, obs: Observations) -> np.ndarray:
    """(k, m, 3) measured minus predicted target points (m), observation frame; NaN where a target was not seen."""
    pred = robot.predict_points(obs.q, obs.targets)
    R, t = robot.T_tracker_base[:3, :3], robot.T_tracker_base[:3, 3]
    return obs.points - (np.einsum("ab,kmb->kma", R, pred) + t)


def point_errors(robot: CalibratedRobot, obs: Observations) -> np.ndarray:
    """(k, m) distance (m) between each predicted target point and the measured one, per configuration and target.

    Unlike :func:`prediction_errors` this does not go through the pose fitted to the measured points, so a targets
    file that does not match the data (swapped, mis-measured targets) shows up here as large residuals even when
    the pose error is small. Tracker-frame data are compared in the tracker frame. A measured point that is NaN
    (a target the tracker did not see) gives NaN for that target only; the summaries skip it. The norms of
    :func:`point_residuals`; a row's mean over its seen targets is :func:`labcal.calibration.cv.row_errors`.
    """
    if obs.k == 0:
        return np.zeros((0, obs.m))
    return np.linalg.norm(point_residuals(robot, obs), axis=-1)


def summarize_points(d: np.ndarray) -> PointSummary:
    """Mean / p95 / max (m) of (k, m) point distances: over every target point, and per target (``per_target``).

    NaN entries (missing targets) are skipped; ``count`` is the number of finite distances.
    """
    d = np.asarray(d, dtype=float)
    d = d.reshape(d.shape[0], -1) if d.ndim == 2 else d.reshape(0, 3)

    def stats(e: np.ndarray) -> PointStats:
        e = e[np.isfinite(e)]
        mean, p95, top = statistics(e, ("mean", "p95", "max")).values()
        return {"count": float(e.size), "mean": mean, "p95": p95, "max": top}

    return {**stats(d.ravel()), "per_target": [stats(d[:, i]) for i in range(d.shape[1])]}


def primary_error(robot: CalibratedRobot, obs: Observations) -> tuple[float, str]:
    """(mean error m, "pose" | "points"): the tool origin's position error when every row fixes a pose, else the
    mean target-point error over the seen targets (module docstring). NaN for no rows."""
    if obs.k == 0 or obs.pose_rows().all():
        return float(np.mean(prediction_errors(robot, obs)[0])) if obs.k else float("nan"), "pose"
    d = point_errors(robot, obs)
    return float(np.mean(d[np.isfinite(d)])), "points"


def validation_error(robot: CalibratedRobot, obs: Observations) -> float:
    """Mean position error (m) of the robot's prediction on the validation rows (NaN when there are none); the
    mean target-point error when those rows do not all fix a pose (:func:`primary_error`)."""
    mask = obs.split == "val"
    if not mask.any():
        return float("nan")
    return primary_error(robot, obs.subset(mask))[0]


def split_table(before: CalibratedRobot, after: CalibratedRobot, obs: Observations) -> dict[str, SplitEntry]:
    """{split: {"before": summary, "after": summary, "points": {"before": …, "after": …}, "primary": "pose" |
    "points"}} per split present (and "all").

    "before"/"after": :func:`summarize` of the pose errors (rows with a measured pose only: ``count`` says how
    many; NaN statistics when none has one); "points": :func:`summarize_points` of the per-target point errors
    (:func:`point_errors`); "primary": which of the two is the figure to quote (module docstring). Absent splits
    are skipped before selecting rows.
    """
    table: dict[str, SplitEntry] = {}
    for split in ("train", "val", "test", "all"):
        mask = np.ones(obs.k, bool) if split == "all" else np.asarray(obs.split == split, dtype=bool)
        if not mask.any():
            continue
        part = obs if split == "all" else obs.subset(mask)
        table[split] = {
            "before": summarize(*prediction_errors(before, part)),
            "after": summarize(*prediction_errors(after, part)),
            "points": {
                "before": summarize_points(point_errors(before, part)),
                "after": summarize_points(point_errors(after, part)),
            },
            "primary": "pose" if part.pose_rows().all() else "points",
        }
    return table


def observability(obs: Observations, unobservable: list[str] | None = None) -> Observability:
    """What the targets of ``obs`` let a fit claim about orientation (JSON-ready).

    ``{"targets": m, "geometry": "point" | "line" | "plane" (the targets seen in at least one row), "rows",
    "rows_with_pose", "orientation": "measured" | "partial" | "none", "unobservable": [words], "claim": text}``.
    "measured": every row fixes a pose, orientation errors are measured and reported; "partial": the targets
    span a plane over the rows but only some rows fix a pose (or the tool is fixed only up to a rotation about a
    line): orientation is calibrated and reported on the rows that have a pose, or only partly; "none": one
    target point — positions only. ``unobservable``: the directions a fit could not identify, in words (from
    the local-POE info), else those of the target geometry.
    """
    from labcal.calibration.local_poe import target_null

    rows = np.ones(obs.k, bool)
    null = target_null(obs, rows, 0, 6)
    kind = null["geometry"]
    with_pose = int(obs.pose_rows().sum()) if obs.k else 0
    words = list(unobservable) if unobservable is not None else list(null["words"])
    names = ", ".join(f"t{i + 1}" for i in np.flatnonzero(obs.seen.any(axis=0))) if obs.k else ""
    if kind == "point":
        level = "none"
        claim = (
            f"Only target point {names} was measured: the calibration and its errors are point positions; no "
            "orientation accuracy can be claimed (the tool's orientation is the nominal one, unmeasured), and "
            f"points of the tool away from {names} inherit that orientation's error."
        )
    elif kind == "line":
        level = "partial"
        claim = (
            f"The targets {names} lie on a line: the tool's rotation about that line is not measured, so only the "
            "orientation of that line can be claimed, not the rotation about it; errors are point errors."
        )
    elif with_pose == obs.k:
        level = "measured"
        claim = "Every pose saw three non-collinear targets: position and orientation errors are both measured."
    else:
        level = "partial"
        claim = (
            f"{with_pose} of {obs.k} poses saw three non-collinear targets: orientation errors are measured on "
            "those poses only; the primary figures are the per-target point errors."
        )
    return {
        "targets": int(obs.m),
        "geometry": kind,
        "rows": int(obs.k),
        "rows_with_pose": with_pose,
        "orientation": level,
        "unobservable": words,
        "claim": claim,
    }


def reduction(before: float, after: float) -> float:
    """Percentage reduction of an error statistic (the paper's figure of merit)."""
    return 100.0 * (1.0 - after / before) if before > 0 else float("nan")


# The pose is fitted to the measured points, so a wrong targets file (swapped or mis-measured targets) leaves the pose
# error small while the points themselves are far off; calibration error moves both alike (ratio ~1-3 with targets
# ~0.1 m from the tool origin). Below POINT_FLOOR (m) the residuals are within a hand-measured targets file's ~1 mm.
POINT_RATIO = 10.0
POINT_FLOOR = 2e-3


def point_residual_warning(entry: SplitEntry | None) -> FitWarning | None:
    """{"code": "point-residuals", "message"} when a split-table entry's points are far off while its pose fits.

    entry: one split of :func:`split_table` ({"after": …, "points": {"after": …}}); None when the points agree.
    """
    if not entry or "points" not in entry:
        return None
    pose, pts = entry["after"].get("pos_mean"), entry["points"]["after"].get("mean")
    # NaN pose (no row fixes a pose: fewer than three targets) compares False: no pose to contrast the points with
    if pose is None or pts is None or not (pts > POINT_FLOOR and pts > POINT_RATIO * pose):
        return None
    per = entry["points"]["after"].get("per_target") or []
    each = ", ".join(f"t{i + 1} {t['mean'] * 1e3:.3f}" for i, t in enumerate(per) if t.get("mean") is not None)
    return {
        "code": "point-residuals",
        "message": f"the measured target points are {pts * 1e3:.3f} mm from their predictions on average (per "
        f"target mm: {each}) while the pose error is {pose * 1e3:.4f} mm: the targets file does not match the data "
        "(targets swapped, mis-measured or in the wrong unit)",
    }
