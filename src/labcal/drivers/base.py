"""Driver ports: what a session needs from a robot and a tracker, labcal's own driver errors, and the time a joint
move takes (:func:`move_time`: the sim rig waits it, the planner orders poses by it).

Sessions talk to these Protocols only; the CLI picks the concrete driver (sim, serial tracker, UR). Every
concrete driver is a context manager whose ``close()`` is safe to call twice.

Units: metres, radians, seconds everywhere here. Devices that speak millimetres or degrees convert at the
driver's edge.

Example::

    with SimRig(...).robot() as robot, SimRig(...).tracker() as tracker:
        limits.check_motion(q, speed=0.5, acceleration=1.0)
        robot.move_joints(q, speed=0.5, acceleration=1.0)
        m = tracker.measure(samples=5)   # m.points: (m, 3) metres, rows t1 … tm, NaN rows where not seen
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Self, runtime_checkable

import numpy as np

from labcal.robots.joint_map import JointMap

# --------------------------------------------------------------------------------------------------------------
# Errors. Library exceptions (RuntimeError from ur-rtde, SerialException from pyserial) never escape a driver.


class DriverError(Exception):
    """Base class of every error a driver raises."""


class ConnectionFailed(DriverError):
    """The device could not be reached or the connection was lost."""


class DriverTimeout(DriverError):
    """The device did not answer in time."""


class ProtocolError(DriverError):
    """The device answered something the protocol does not allow (garbled reply, bad CRC, ERRORxx)."""


class StaleData(DriverError):
    """The device keeps answering, but its timestamp stopped advancing."""


class MotionRejected(DriverError):
    """A motion was refused before it started (joint limit, speed or acceleration cap, robot not ready)."""


class MotionFailed(DriverError):
    """The robot accepted a motion but did not complete it (controller returned failure)."""


class ProtectiveStop(DriverError):
    """The robot entered a protective stop; the session pauses and can be resumed after it is cleared."""


class EmergencyStop(ProtectiveStop):
    """The robot is emergency-stopped."""


class MeasurementRejected(DriverError):
    """A tracker frame was received but is unusable (missing target, inconsistent triangle, out of volume)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


# --------------------------------------------------------------------------------------------------------------
# Value types.


@dataclass(frozen=True)
class RobotState:
    """A snapshot of the robot controller.

    q: (n,) actual joint positions, rad (m for prismatic joints); timestamp: controller time, s.
    """

    q: np.ndarray
    timestamp: float
    protective_stop: bool = False
    emergency_stop: bool = False
    ready: bool = True


@dataclass(frozen=True)
class Measurement:
    """One (possibly averaged) tracker reading of the session's m targets (m ≥ 1).

    points: (m, 3) target positions in the tracker frame, metres, rows in target order t1 … tm; a row of NaN is a
    target the tracker did not see. A row is either wholly finite or wholly NaN, and at least one is seen.
    spread: (m,) per-target RMS distance of the averaged samples from their mean, metres (0 for one sample, NaN
    where the target was not seen); default: 0 for every seen target.
    timestamp: time of the last sample, s (device clock if it has one, else host monotonic clock).
    quality: free-form flags from the device, e.g. ("out_of_volume:t2", "missing:t3"); empty when all is well.

    >>> m = Measurement(np.array([[0.1, 0.2, 1.5], [np.nan] * 3]), timestamp=0.0)
    >>> m.seen.tolist(), m.spread.tolist()
    ([True, False], [0.0, nan])
    """

    points: np.ndarray
    timestamp: float
    spread: np.ndarray | None = None
    samples: int = 1
    quality: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise ValueError(f"Measurement.points must be (m, 3) with m >= 1 targets, got shape {points.shape}")
        finite = np.isfinite(points)
        partial = np.flatnonzero(finite.any(axis=1) & ~finite.all(axis=1))
        if partial.size:
            i = int(partial[0])
            raise ValueError(
                f"Measurement.points: target t{i + 1} is partly missing {points[i].tolist()}: a target is either "
                "seen (3 finite coordinates) or not (3 NaN)"
            )
        seen = finite.all(axis=1)
        if not seen.any():
            raise ValueError("Measurement.points: no target seen (every row NaN); that is not a measurement")
        if self.spread is None:
            spread = np.where(seen, 0.0, np.nan)
        else:
            spread = np.asarray(self.spread, dtype=float)
            if spread.shape != (points.shape[0],):
                raise ValueError(f"Measurement.spread must be ({points.shape[0]},), got shape {spread.shape}")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "spread", spread)

    @property
    def seen(self) -> np.ndarray:
        """(m,) bool: True where the target was seen."""
        return np.isfinite(self.points).all(axis=1)

    @property
    def m(self) -> int:
        """Number of targets (seen or not)."""
        return int(self.points.shape[0])


@dataclass(frozen=True)
class SafetyLimits:
    """Joint limits and motion caps, checked before any motion is sent to a robot.

    joint_limits: (n, 2) [lo, hi] per joint (rad or m); max_speed in rad/s; max_acceleration in rad/s².
    joint_map: when set, the robot is commanded in controller joints while ``joint_limits`` are the robot file's
    (model joints): a target is converted (q_model = M q + b) and the model joints are checked, so a coupled joint's
    limit is the model's, not a box in controller joints.
    """

    joint_limits: np.ndarray
    max_speed: float = 1.0
    max_acceleration: float = 1.4
    joint_map: JointMap | None = None

    def within(self, q: np.ndarray) -> np.ndarray:
        """(k, n) commanded joints → (k,) bool: every joint inside ``joint_limits`` (through the joint map).

        The one definition of "inside the limits": :meth:`check_motion` refuses exactly the targets this calls
        False, and the planner keeps exactly the ones it calls True.

        >>> SafetyLimits(np.array([[-1.0, 1.0], [0.0, 2.0]])).within(np.array([[0.5, 2.0], [0.5, 2.1]])).tolist()
        [True, False]
        """
        return np.all(self._inside(np.asarray(q, dtype=float))[1], axis=-1)

    def _inside(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joints checked (model joints through the joint map, else q) and (..., n) bool: each inside its limits."""
        limits = np.asarray(self.joint_limits, dtype=float)
        checked = q if self.joint_map is None or self.joint_map.is_identity else self.joint_map.to_model(q)
        return checked, (checked >= limits[:, 0]) & (checked <= limits[:, 1])

    def check_motion(self, q: np.ndarray, speed: float, acceleration: float) -> np.ndarray:
        """Return q as a float array if the motion is allowed, else raise MotionRejected naming the cause."""
        q = np.asarray(q, dtype=float)
        limits = np.asarray(self.joint_limits, dtype=float)
        if q.shape != (limits.shape[0],):
            raise MotionRejected(f"target has {q.shape} joint values, the robot has {limits.shape[0]} joints")
        if not np.all(np.isfinite(q)):
            raise MotionRejected(f"target contains non-finite joint values: {q.tolist()}")
        checked, inside = self._inside(q)
        mapped = checked is not q  # converted through the joint map
        what = "model joint" if mapped else "joint"
        if not inside.all():
            j = int(np.flatnonzero(~inside)[0])
            value, (lo, hi) = checked[j], limits[j]
            raise MotionRejected(
                f"{what} {j + 1} target {value:.6f} is outside its limits [{lo:.6f}, {hi:.6f}]"
                + (f" (controller joints {np.round(q, 6).tolist()} through the joint map)" if mapped else "")
            )
        if not (np.isfinite(speed) and 0 < speed <= self.max_speed):
            raise MotionRejected(f"speed {speed} rad/s is outside (0, {self.max_speed}] rad/s")
        if not (np.isfinite(acceleration) and 0 < acceleration <= self.max_acceleration):
            raise MotionRejected(f"acceleration {acceleration} rad/s² is outside (0, {self.max_acceleration}] rad/s²")
        return q


def move_time(distance, speed, acceleration) -> np.ndarray:
    """Seconds of a trapezoidal joint move over ``distance`` (rad, any shape) at ``speed`` rad/s and ``acceleration``
    rad/s² (same shape or broadcast); a move too short to reach ``speed`` is triangular.

    A joint move of a UR arm (moveJ) is led by the joint that has the farthest to go; the others are slowed to end
    with it, so a move takes the longest of its joints' times (:func:`labcal.sessions.plans.motion_time`).

    >>> move_time([0.0, 0.1, 2.0], 0.5, 1.0).round(3).tolist()
    [0.0, 0.632, 4.5]
    """
    d = np.abs(np.asarray(distance, dtype=float))
    v, a = np.asarray(speed, dtype=float), np.asarray(acceleration, dtype=float)
    full = d > v**2 / a
    return np.where(full, d / v + v / a, 2.0 * np.sqrt(d / a))


class ClosedOnExit:
    """The ``with`` block of every concrete driver: leaving it closes the driver (``close()`` is safe twice)."""

    def close(self) -> None:  # pragma: no cover - every driver defines its own
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------------------------------
# Ports.


class _Device(Protocol):
    """What every port is: a context manager whose ``close()`` is safe to call twice."""

    def close(self) -> None: ...

    def __enter__(self) -> Self: ...

    def __exit__(self, *exc: object) -> None: ...


@runtime_checkable
class Robot(_Device, Protocol):
    """A joint-space positioned robot. ``move_joints`` blocks until the motion ends."""

    n_joints: int
    limits: SafetyLimits

    def move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        """Move to q (n,), checking ``limits`` first. Raises MotionRejected, MotionFailed, ProtectiveStop."""
        ...

    def joint_positions(self) -> np.ndarray:
        """Actual joint positions (n,)."""
        ...

    def state(self) -> RobotState:
        """Controller snapshot including safety state."""
        ...

    def stop(self) -> None:
        """Stop any motion. Always safe to call, also after close or after an error."""
        ...


@runtime_checkable
class Tracker(_Device, Protocol):
    """A 3D tracker that measures the session's m targets on the end effector (any of them may be unseen)."""

    def measure(self, samples: int = 1) -> Measurement:
        """Average ``samples`` frames. Raises MeasurementRejected, DriverTimeout, ProtocolError."""
        ...


def average_frames(frames: list[np.ndarray], timestamp: float, quality: tuple[str, ...] = ()) -> Measurement:
    """Average frames of (m, 3) points into one Measurement: each target over the frames that saw it.

    A frame's NaN row is a target it did not see. The spread of a target is the RMS distance of its samples from
    their mean. A target seen in no frame stays NaN and gets a ``missing:tK`` quality flag. Raises
    MeasurementRejected for a frame that saw no target, a partly missing point, or frames of different shapes.

    >>> m = average_frames([np.zeros((3, 3)), np.ones((3, 3)) * 2e-6], timestamp=1.0)
    >>> float(m.points[0, 0]), round(float(m.spread[0]) * 1e6, 3)
    (1e-06, 1.732)
    >>> lost = np.array([[1.0, 2.0, 3.0], [np.nan] * 3])
    >>> m = average_frames([lost, lost + [[0.002, 0, 0], [0, 0, 0]]], timestamp=1.0)
    >>> m.points[0].tolist(), m.points[1].tolist(), round(float(m.spread[0]), 6), m.quality
    ([1.001, 2.0, 3.0], [nan, nan, nan], 0.001, ('missing:t2',))
    """
    try:
        stack = np.asarray(frames, dtype=float)
    except ValueError as exc:  # ragged: frames with different numbers of targets
        raise MeasurementRejected(f"frames of different shapes cannot be averaged: {exc}") from exc
    if stack.ndim != 3 or stack.shape[2] != 3 or stack.shape[0] == 0 or stack.shape[1] == 0:
        raise MeasurementRejected(f"expected k frames of m targets x 3 coordinates, got shape {stack.shape}")
    finite = np.isfinite(stack)
    seen = finite.all(axis=2)  # (k, m)
    partial = np.argwhere(finite.any(axis=2) & ~seen)
    if partial.size:
        f, t = (int(v) for v in partial[0])
        raise MeasurementRejected(
            f"frame {f + 1}: target t{t + 1} has a missing (non-finite) coordinate: {stack[f, t].tolist()}"
        )
    blank = np.flatnonzero(~seen.any(axis=1))
    if blank.size:
        raise MeasurementRejected(
            f"frame {int(blank[0]) + 1} of {stack.shape[0]} saw none of the {stack.shape[1]} targets"
        )
    count = seen.sum(axis=0)  # (m,) frames that saw each target
    # With every target in every frame these are the very operations of stack.mean(axis=0) and its spread.
    filled = np.where(seen[:, :, None], stack, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = filled.sum(axis=0) / count[:, None]
        dev = np.where(seen, np.sum((np.where(seen[:, :, None], stack, mean) - mean) ** 2, axis=2), 0.0)
        spread = np.sqrt(dev.sum(axis=0) / count)
    mean[count == 0] = np.nan
    spread[count == 0] = np.nan
    flags = tuple(dict.fromkeys((*quality, *(f"missing:t{i + 1}" for i in np.flatnonzero(count == 0)))))
    return Measurement(points=mean, timestamp=timestamp, spread=spread, samples=stack.shape[0], quality=flags)
