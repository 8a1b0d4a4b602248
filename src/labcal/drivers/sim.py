"""The simulated rig: a fake robot and a fake tracker sharing one simulated actual robot.

The robot reports the commanded joint values (its encoders are perfect; the errors are in the kinematics). The
tracker reports the *true* target positions of the actual robot at the current commanded configuration, in the
tracker frame of the actual robot, plus Gaussian noise (``ActualRobot.errors.tracker_noise``), averaged over the
requested samples with :func:`labcal.drivers.base.average_frames`. There may be any number m ≥ 1 of targets; each
can be lost at a measurement with its own drop-out probability (``dropout``), and comes back as a NaN row.
Repeatability noise, if the error model has
any, is drawn once per motion (the robot lands slightly differently each time it moves, not each time it is
looked at), so the true points are computed once per move and only the tracker noise is drawn per frame.

Controller joints: with a ``joint_map`` (the robot file's :class:`~labcal.robots.joint_map.JointMap`), the
simulated robot is a controller whose joints are not the model's: ``move_joints`` takes controller joints,
``joint_positions`` / ``state`` report them, and the actual robot moves to ``q_model = M q + b``. Joint limits stay
the model's (checked after conversion); speed and acceleration caps apply to the controller joints.

Seeded: the same actual robot, targets, seed, faults, drop-out and sequence of calls give the same measurements.
Faults and drop-outs draw from their own random streams, so switching them on does not change the noise of the
other frames.

Example::

    >>> from labcal.robots import load
    >>> from labcal.simulation import ErrorSpec, simulate
    >>> rig = SimRig(simulate(load("ur10"), ErrorSpec.none()), np.eye(3) * 0.1, seed=0)
    >>> with rig.robot() as robot, rig.tracker() as tracker:
    ...     robot.move_joints(np.full(6, 0.3), speed=0.5, acceleration=1.0)
    ...     m = tracker.measure(samples=3)
    >>> m.points.shape, m.samples
    ((3, 3), 3)
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from labcal.drivers.base import (
    ClosedOnExit,
    DriverError,
    DriverTimeout,
    Measurement,
    MeasurementRejected,
    ProtectiveStop,
    ProtocolError,
    RobotState,
    SafetyLimits,
    average_frames,
    move_time,
)
from labcal.robots.joint_map import JointMap
from labcal.simulation import ActualRobot

DROPOUT_MODES = ("nan", "reject")


@dataclass(frozen=True)
class SimFaults:
    """Faults to inject. ``*_at`` are 1-based call numbers (of ``tracker.measure`` or ``robot.move_joints``);
    ``*_probability`` apply to every call independently (seeded).

    dropout: one target is lost — with ``dropout_mode="nan"`` the measurement comes back with that target's
    coordinates NaN and a ``missing:tK`` quality flag, with ``"reject"`` the tracker raises MeasurementRejected.
    ``dropout_target``: which target (0-based index) is lost; None picks one at random. (Independent per-target
    drop-out, the common case of a lab, is :class:`SimRig`'s ``dropout``.)
    timeout: ``measure`` raises DriverTimeout. garbled: ``measure`` raises ProtocolError.
    protective_stop_at: the k-th accepted move stops halfway with ProtectiveStop and the robot stays in a
    protective stop until :meth:`SimRobot.clear_protective_stop`.
    """

    dropout_at: frozenset[int] = frozenset()
    dropout_probability: float = 0.0
    dropout_mode: str = "nan"
    dropout_target: int | None = None
    timeout_at: frozenset[int] = frozenset()
    timeout_probability: float = 0.0
    garbled_at: frozenset[int] = frozenset()
    garbled_probability: float = 0.0
    protective_stop_at: frozenset[int] = frozenset()

    def __post_init__(self) -> None:
        for name in ("dropout_at", "timeout_at", "garbled_at", "protective_stop_at"):
            calls = frozenset(int(v) for v in (getattr(self, name) or ()))
            if any(v < 1 for v in calls):
                raise ValueError(f"SimFaults.{name} counts calls from 1, got {sorted(calls)}")
            object.__setattr__(self, name, calls)
        for name in ("dropout_probability", "timeout_probability", "garbled_probability"):
            value = getattr(self, name)
            if not 0.0 <= float(value) <= 1.0:
                raise ValueError(f"SimFaults.{name} must be a probability in [0, 1], got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.dropout_mode not in DROPOUT_MODES:
            raise ValueError(f"SimFaults.dropout_mode must be one of {DROPOUT_MODES}, got {self.dropout_mode!r}")
        target = self.dropout_target
        if target is not None and (isinstance(target, bool) or not isinstance(target, int) or target < 0):
            raise ValueError(f"SimFaults.dropout_target must be a target index >= 0 or None, got {target!r}")


class SimRig:
    """One simulated actual robot shared by a :class:`SimRobot` and a :class:`SimTracker`.

    actual: the true robot; targets: (m, 3) m, target points in the tool frame (rows t1 … tm, m ≥ 1); seed:
    seeds the tracker noise, repeatability, random faults and drop-outs; dropout: probability that a target is
    not seen at a measurement, one float for all targets or (m,) one per target, drawn independently per target
    and per ``measure`` call (a call in which no target is seen raises MeasurementRejected); motion_time: seconds
    per move (float), or ``"realistic"`` for a trapezoidal-profile time of the slowest joint from its distance,
    the move's speed and acceleration; q0: (n,) initial joint values, controller joints (default: the model's
    zeros clipped into the limits); max_speed (rad/s) and max_acceleration (rad/s²): the robot's motion caps;
    joint_map: controller → model joints (None: the same), e.g. ``spec.joint_map`` of the robot file; serial: the
    simulated arm's serial number (what :meth:`SimRobot.device_identity` reports, hence the session's unit; the CLI
    gives ``sim-<seed of the simulated robot>``); None: the rig reports none.
    """

    def __init__(
        self,
        actual: ActualRobot,
        targets,
        *,
        seed: int,
        motion_time: float | str = 0.0,
        faults: SimFaults | None = None,
        q0=None,
        max_speed: float = 1.0,
        max_acceleration: float = 1.4,
        joint_map: JointMap | None = None,
        dropout=0.0,
        serial: str | None = None,
    ) -> None:
        targets = np.asarray(targets, dtype=float)
        if targets.ndim != 2 or targets.shape[1] != 3 or targets.shape[0] == 0 or not np.all(np.isfinite(targets)):
            raise ValueError(f"targets must be a finite (m, 3) array (m >= 1, metres, tool frame), got {targets.shape}")
        m = targets.shape[0]
        dropout = np.asarray(dropout, dtype=float)
        dropout = np.full(m, float(dropout)) if dropout.ndim == 0 else dropout
        if dropout.shape != (m,) or not np.all((dropout >= 0) & (dropout <= 1)):
            raise ValueError(
                f"dropout must be a probability in [0, 1], or {m} of them (one per target), got {dropout!r}"
            )
        if faults is not None and faults.dropout_target is not None and faults.dropout_target >= m:
            raise ValueError(
                f"SimFaults.dropout_target {faults.dropout_target} is not one of the {m} targets (0 … {m - 1})"
            )
        if not (motion_time == "realistic" or (isinstance(motion_time, int | float) and motion_time >= 0)):
            raise ValueError(f"motion_time must be seconds >= 0 or 'realistic', got {motion_time!r}")
        self.actual = actual
        self.serial = serial
        self.targets = targets
        self.dropout = dropout
        self.seed = int(seed)
        self.motion_time = motion_time
        self.faults = faults or SimFaults()
        model = actual.nominal
        if joint_map is not None and joint_map.n != model.n:
            raise ValueError(f"joint_map is for {joint_map.n} joints, the robot has {model.n}")
        # the identity map is no map: nothing is converted and the joints reported are exactly the ones commanded
        self.joint_map = None if joint_map is None or joint_map.is_identity else joint_map
        self.safety = SafetyLimits(
            np.array(model.limits), max_speed=max_speed, max_acceleration=max_acceleration, joint_map=self.joint_map
        )
        q = np.zeros(model.n) if q0 is None else self._to_model(np.asarray(q0, dtype=float))
        if q.shape != (model.n,):
            raise ValueError(f"q0 must have shape ({model.n},), got {q.shape}")
        self._q = np.clip(q, model.limits[:, 0], model.limits[:, 1])  # model joints: what the actual robot is at
        # the controller's own numbers, kept (not recomputed through the inverse map) so that it reports exactly
        # the joints it was commanded, as the unmapped rig does
        self._q_ctrl = self._q.copy() if self.joint_map is None else self.joint_map.to_controller(self._q)
        self._noise_rng, self._fault_rng, self._motion_rng, self._dropout_rng = (
            np.random.default_rng([self.seed, stream]) for stream in range(4)
        )
        self._lock = threading.RLock()
        self._true_points = self._draw_true_points()
        self.protective_stop = False
        self.moves = 0  # accepted move_joints calls
        self.measurements = 0  # measure calls
        self.stop_calls = 0
        self._t0 = time.monotonic()

    def robot(self) -> SimRobot:
        return SimRobot(self)

    def tracker(self) -> SimTracker:
        return SimTracker(self)

    @property
    def q(self) -> np.ndarray:
        """(n,) current joint values as the controller reports them (controller joints)."""
        with self._lock:
            return self._q_ctrl.copy()

    @property
    def q_model(self) -> np.ndarray:
        """(n,) current model joint values (what the actual robot's kinematics see)."""
        with self._lock:
            return self._q.copy()

    def _to_model(self, q: np.ndarray) -> np.ndarray:
        return q if self.joint_map is None else self.joint_map.to_model(q)

    def true_points(self) -> np.ndarray:
        """(m, 3) m: the targets' true positions in the base frame at the current pose."""
        with self._lock:
            return self._true_points.copy()

    def _draw_true_points(self) -> np.ndarray:
        return self.actual.true_points(self._q, self.targets, self._motion_rng)[0]

    def _clock(self) -> float:
        return time.monotonic() - self._t0

    def _move_duration(self, q: np.ndarray, speed: float, acceleration: float) -> float:
        """Seconds to move to the controller joints q (the motors' distance: controller joints)."""
        if self.motion_time != "realistic":
            return float(self.motion_time)
        return float(move_time(q - self.q, speed, acceleration).max(initial=0.0))


class SimRobot(ClosedOnExit):
    """The Robot port on a :class:`SimRig`. Context manager; ``close`` and ``stop`` are idempotent."""

    def __init__(self, rig: SimRig) -> None:
        self.rig = rig
        self.n_joints = rig.actual.n
        self.limits = rig.safety
        self._closed = False

    def identity(self) -> dict:
        """Who this robot is, for a session's start document."""
        return {"driver": "sim", "model": self.rig.actual.nominal.name, "seed": self.rig.seed}

    def device_identity(self) -> dict:
        """What the simulated controller tells about the arm: its model and (if the rig has one) serial number."""
        identity = {"model": self.rig.actual.nominal.name}
        if self.rig.serial is not None:
            identity["serial"] = self.rig.serial
        return identity

    def move_joints(self, q, speed: float, acceleration: float) -> None:
        """Move to q (n,) rad. Raises MotionRejected (limits/caps), ProtectiveStop, DriverError (closed)."""
        if self._closed:
            raise DriverError("the simulated robot is closed")
        q = self.limits.check_motion(q, speed, acceleration)
        rig = self.rig
        q_ctrl, q = q, rig._to_model(q)  # the actual robot moves in model joints
        with rig._lock:
            if rig.protective_stop:
                raise ProtectiveStop("the robot is in a protective stop; clear it before moving")
            rig.moves += 1
            k = rig.moves
            duration = rig._move_duration(q_ctrl, speed, acceleration)
        if duration > 0:
            time.sleep(duration)
        with rig._lock:
            if k in rig.faults.protective_stop_at:
                # Stopped halfway: the robot is somewhere between start and goal.
                rig._q = 0.5 * (rig._q + q)
                rig._q_ctrl = 0.5 * (rig._q_ctrl + q_ctrl)  # the map is linear: still the same configuration
                rig._true_points = rig._draw_true_points()
                rig.protective_stop = True
                raise ProtectiveStop(f"protective stop during move {k} (simulated)")
            rig._q, rig._q_ctrl = q.copy(), q_ctrl.copy()
            rig._true_points = rig._draw_true_points()

    def joint_positions(self) -> np.ndarray:
        if self._closed:
            raise DriverError("the simulated robot is closed")
        return self.rig.q

    def state(self) -> RobotState:
        if self._closed:
            raise DriverError("the simulated robot is closed")
        return RobotState(q=self.rig.q, timestamp=self.rig._clock(), protective_stop=self.rig.protective_stop)

    def clear_protective_stop(self) -> None:
        """What the operator does on the teach pendant after checking the cell."""
        with self.rig._lock:
            self.rig.protective_stop = False

    def stop(self) -> None:
        self.rig.stop_calls += 1

    def close(self) -> None:
        self._closed = True


class SimTracker(ClosedOnExit):
    """The Tracker port on a :class:`SimRig`: true target points in the tracker frame plus noise."""

    def __init__(self, rig: SimRig) -> None:
        self.rig = rig
        self._closed = False

    def identity(self) -> dict:
        identity = {"driver": "sim", "noise_m": self.rig.actual.errors.tracker_noise, "seed": self.rig.seed}
        if self.rig.dropout.any():  # only then: identities of rigs without drop-out read as before
            identity["dropout"] = self.rig.dropout.tolist()
        return identity

    def measure(self, samples: int = 1) -> Measurement:
        """Average ``samples`` frames: points (m, 3) m in the tracker frame (NaN rows: not seen), spread (m,) m.

        Raises MeasurementRejected, DriverTimeout or ProtocolError when a fault is injected.
        """
        if self._closed:
            raise DriverError("the simulated tracker is closed")
        if isinstance(samples, bool) or not isinstance(samples, int | np.integer) or samples < 1:
            raise ValueError(f"samples must be an integer >= 1, got {samples!r}")
        rig = self.rig
        faults = rig.faults
        with rig._lock:
            rig.measurements += 1
            k = rig.measurements
            # Always draw, so the fault stream does not depend on which faults fired before.
            u_timeout, u_garbled, u_dropout = rig._fault_rng.random(3)
            m = rig.targets.shape[0]
            lost = int(rig._fault_rng.integers(m)) if faults.dropout_target is None else faults.dropout_target
            seen = rig._dropout_rng.random(m) >= rig.dropout if rig.dropout.any() else np.ones(m, dtype=bool)
            if k in faults.timeout_at or u_timeout < faults.timeout_probability:
                raise DriverTimeout(f"simulated tracker did not answer measurement {k} in time")
            if k in faults.garbled_at or u_garbled < faults.garbled_probability:
                raise ProtocolError(f"simulated tracker sent a garbled reply to measurement {k}")
            T = rig.actual.T_tracker_base
            true = rig._true_points @ T[:3, :3].T + T[:3, 3]
            noise = rig.actual.errors.tracker_noise
            frames = np.array(
                [true + (rig._noise_rng.normal(0.0, noise, size=(m, 3)) if noise > 0 else 0.0) for _ in range(samples)]
            )
            now = rig._clock()
        if k in faults.dropout_at or u_dropout < faults.dropout_probability:
            if faults.dropout_mode == "reject":
                raise MeasurementRejected(f"target t{lost + 1} not visible in measurement {k} (simulated dropout)")
            seen[lost] = False
        if not seen.any():
            raise MeasurementRejected(f"none of the {m} target(s) visible in measurement {k} (simulated drop-out)")
        frames[:, ~seen] = np.nan
        return average_frames(list(frames), now)

    def close(self) -> None:
        self._closed = True
