"""Stand-ins for ur-rtde's interfaces and helpers shared by the UR driver tests.

The stubs define exactly the methods labcal.drivers.ur calls (``RECEIVE_METHODS`` / ``CONTROL_METHODS``
below) with the parameter names of the real pybind11 methods; test_ur_contract.py checks both.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import numpy as np

from labcal.drivers.base import SafetyLimits
from labcal.drivers.ur import URProfile

HOME = np.array([0.0, -1.5708, 1.5708, 0.0, 1.5708, 0.0])

# The ur-rtde methods labcal.drivers.ur calls, per interface.
RECEIVE_METHODS: Sequence[str] = (
    "getTimestamp",
    "getActualQ",
    "isProtectiveStopped",
    "isEmergencyStopped",
    "getRobotMode",
    "isConnected",
    "disconnect",
)
CONTROL_METHODS: Sequence[str] = (
    "moveJ",
    "stopJ",
    "isProgramRunning",
    "reuploadScript",
    "isConnected",
    "disconnect",
)


def make_profile(host: str = "127.0.0.1", **overrides: object) -> URProfile:
    """A profile with ±π joint limits, speed cap 0.5 rad/s, acceleration cap 1.0 rad/s², no settle wait."""
    fields: dict[str, object] = {
        "name": "test",
        "model": "ur10",
        "host": host,
        "limits": SafetyLimits(joint_limits=np.tile([-np.pi, np.pi], (6, 1)), max_speed=0.5, max_acceleration=1.0),
        "settle_time": 0.0,
        "position_tolerance": 1e-3,
        "connect_timeout": 1.0,
        "stale_timeout": 0.2,
    }
    fields.update(overrides)
    return URProfile(**fields)  # type: ignore[arg-type]


class StubReceive:
    """RTDEReceiveInterface stand-in: a controller clock that advances 2 ms per getTimestamp call."""

    def __init__(self, q: np.ndarray = HOME):
        self.q = [float(v) for v in q]
        self.t = 0.0
        self.frozen = False
        self.connected = True
        self.protective = False
        self.emergency = False
        self.mode = 7
        self.disconnects = 0
        self.fail_with: Exception | None = None  # raised by every getter, like ur-rtde after a failure

    def _check(self) -> None:
        if self.fail_with is not None:
            raise self.fail_with

    def getTimestamp(self) -> float:
        self._check()
        if not self.frozen:
            self.t += 0.002
        return self.t

    def getActualQ(self) -> list[float]:
        self._check()
        return list(self.q)

    def isProtectiveStopped(self) -> bool:
        self._check()
        return self.protective

    def isEmergencyStopped(self) -> bool:
        self._check()
        return self.emergency

    def getRobotMode(self) -> int:
        self._check()
        return self.mode

    def isConnected(self) -> bool:
        return self.connected

    def disconnect(self) -> None:
        self.disconnects += 1
        self.connected = False


class StubControl:
    """RTDEControlInterface stand-in that moves the StubReceive's joints; ``outcome`` scripts moveJ results.

    outcome: "ok" (move there), "false" (return False), "protective" (stop halfway, flag, return False),
    "short" (stop 0.01 rad short, return True), or an exception instance to raise.
    """

    def __init__(self, receive: StubReceive):
        self.receive = receive
        self.outcome: object = "ok"
        self.moves: list[tuple[list[float], float, float, bool]] = []
        self.stops: list[tuple[float, bool]] = []
        self.stop_error: Exception | None = None
        self.program_running = True  # ur-rtde's control script; a safety stop halts it
        self.reuploads = 0
        self.connected = True
        self.disconnects = 0

    def moveJ(self, q: list[float], speed: float = 1.05, acceleration: float = 1.4, asynchronous: bool = False) -> bool:
        # Same range checks as ur-rtde 1.6.5 (ValueError), so a bypassed labcal check would be seen.
        if not 0 <= speed <= 3.14 or not 0 <= acceleration <= 40:
            raise ValueError("speed or acceleration out of range")
        self.moves.append((list(q), speed, acceleration, asynchronous))
        if isinstance(self.outcome, Exception):
            raise self.outcome
        start = np.asarray(self.receive.q)
        goal = np.asarray(q, dtype=float)
        if self.outcome == "ok":
            self.receive.q = goal.tolist()
            return True
        if self.outcome == "short":
            self.receive.q = (goal - 0.01 * np.sign(goal - start + 1e-12)).tolist()
            return True
        if self.outcome == "protective":
            self.receive.q = ((start + goal) / 2).tolist()
            self.receive.protective = True
            self.program_running = False
        return False

    def stopJ(self, a: float = 2.0, asynchronous: bool = False) -> None:
        self.stops.append((a, asynchronous))
        if self.stop_error is not None:
            raise self.stop_error

    def isProgramRunning(self) -> bool:
        return self.program_running

    def reuploadScript(self) -> bool:
        self.reuploads += 1
        self.program_running = True
        return True

    def isConnected(self) -> bool:
        return self.connected

    def disconnect(self) -> None:
        self.disconnects += 1
        self.connected = False


@contextmanager
def silent_listener(first: int = 200) -> Iterator[str]:
    """A TCP listener on 127.0.x.y:30004 that completes the handshake (kernel backlog) but never answers."""
    from labcal_fakes.rtde_fake import candidate_hosts

    for host in candidate_hosts(first + (os.getpid() * 53) % 50000, count=200):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, 30004))
        except OSError:
            sock.close()
            continue
        sock.listen(4)
        try:
            yield host
        finally:
            sock.close()
        return
    raise RuntimeError("no free loopback address for the silent listener")
