"""Universal Robots driver: the ``Robot`` port over ur-rtde 1.6.5 (``rtde_receive`` / ``rtde_control``).

Four ur-rtde behaviours shape this module:

- A controller that accepts the TCP connection but never answers makes the interface constructors hang forever
  *while holding the GIL*. So :meth:`URRobot.connect` first probes each port with a socket timeout and checks
  the peer really answers (an RTDE protocol-version request on 30004, the greeting line of the dashboard on
  29999, streamed bytes on 30003) before a real interface is built.
- ``moveJ`` returns False on failure instead of raising: the result is checked and the safety state read to
  tell a protective/emergency stop from another failure.
- Getters keep returning the last values after the connection died. Health is judged by the controller
  ``timestamp`` advancing (:class:`~labcal.drivers.base.StaleData`), and ``isConnected()`` going False.
- After the controller dies a blocking ``moveJ`` keeps ``Reconnecting...`` for about ten minutes, and after a
  dropped RTDE connection ur-rtde can crash the interpreter (SIGSEGV). So :meth:`URRobot.connect` runs each
  interface in its own process (:mod:`labcal.drivers.ur_process`): every call has a deadline, a move is watched
  (the controller timestamp must advance at least every ``watchdog_timeout`` s), and a failed interface is killed,
  never waited for. A fault ends a move within ``watchdog_timeout`` + ``call_timeout`` s.

ur-rtde's RuntimeError/ValueError never escape: they become labcal's :mod:`labcal.drivers.base` errors.

Example::

    profile = load_ur_profile("drivers/ur10-lab.toml")
    with URRobot.connect(profile) as robot:
        robot.move_joints(q, speed=0.3, acceleration=0.5)   # q: (6,) rad
        print(robot.state())
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import re
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from labcal.drivers.base import (
    ClosedOnExit,
    ConnectionFailed,
    DriverError,
    DriverTimeout,
    EmergencyStop,
    MotionFailed,
    MotionRejected,
    ProtectiveStop,
    ProtocolError,
    RobotState,
    SafetyLimits,
    StaleData,
)
from labcal.drivers.ur_process import RemoteInterface
from labcal.drivers.workspace import WORKSPACE_SCHEMA, Workspace, parse_workspace
from labcal.tomlschema import Key, SchemaError, Table, read_toml, validate

log = logging.getLogger(__name__)

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
ROBOT_MODE_RUNNING = 7
N_JOINTS = 6
# ur-rtde 1.6.5 raises ValueError outside these ranges; profile caps must stay inside them.
UR_RTDE_MAX_SPEED = 3.14  # rad/s
UR_RTDE_MAX_ACCELERATION = 40.0  # rad/s²
# ur-rtde's control and receive interfaces read separate RTDE streams, so the sample in hand may predate an
# event the control side already saw (end of a move, a safety stop). Fresh samples are watched this long, s.
STREAM_SKEW_WINDOW = 0.1
# How long resume() waits for a re-uploaded control script to run (ur-rtde's constructor also waits 5 s), s.
SCRIPT_START_TIMEOUT = 5.0
# What labcal asks the controller to stream (everything the getters below need, nothing more).
RECEIVE_VARIABLES = ["timestamp", "actual_q", "robot_mode", "safety_mode", "safety_status_bits", "runtime_state"]


class ProbeTimeout(ConnectionFailed, DriverTimeout):
    """A port accepted the TCP connection but the peer did not answer in time (it would hang ur-rtde)."""


# --------------------------------------------------------------------------------------------------------------
# Profile.


@dataclass(frozen=True)
class URProfile:
    """A UR robot as the lab set it up.

    limits: joint limits (6, 2) rad and speed/acceleration caps (rad/s, rad/s²).
    settle_time: wait after a move before the final position is read, s.
    position_tolerance: max |q_actual - q_target| after a move, rad.
    stale_timeout: how long a controller timestamp may stay unchanged before data counts as stale, s.
    frequency: RTDE output rate, Hz (-1: controller default, 125 Hz on CB3, 500 Hz on e-Series).
    watchdog_timeout: during a move, how long the controller timestamp may stay unchanged before the move is
    abandoned (controller dead, network down), s. call_timeout: the longest any other ur-rtde call may take, s.
    No ports: ur-rtde 1.6.5 connects to UR's standard ones only (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT), so the
    probes use those too (a profile's ``[ports]`` may only restate them).
    """

    name: str
    model: str  # robot model name/file whose joint limits bound the profile's ("" if none)
    host: str
    limits: SafetyLimits
    settle_time: float = 0.2
    position_tolerance: float = 1e-3
    stop_acceleration: float = 2.0
    connect_timeout: float = 2.0
    stale_timeout: float = 0.5
    frequency: float = -1.0
    workspace: Workspace | None = None  # the cell's allowed/keep-out boxes and tracker position, for the planner
    watchdog_timeout: float = 1.0
    call_timeout: float = 2.0

    def with_host(self, host: str) -> URProfile:
        """The same profile pointed at another controller (e.g. a fake on a loopback address)."""
        return URProfile(**{**self.__dict__, "host": host})


_STANDARD_PORTS = {"rtde": RTDE_PORT, "dashboard": DASHBOARD_PORT, "script": SCRIPT_PORT}


def _within(lo: float, hi: float) -> Callable[[float], str | None]:
    return lambda v: None if lo <= v <= hi else f"must be within [{lo}, {hi}], got {v}"


def _standard_port(standard: int) -> Callable[[int], str | None]:
    why = f"must be {standard}: ur-rtde 1.6.5 always connects to port {standard}, so another port cannot be honoured"
    return lambda v: None if v == standard else f"{why} (got {v})"


def _non_empty(text: str) -> str | None:
    return None if text else "must not be empty"


def _frequency_ok(value: float) -> str | None:
    ok = value == -1 or 1 <= value <= 500
    return None if ok else f"must be -1 (controller default) or in [1, 500], got {value}"


_DEG6 = {"shape": (N_JOINTS,), "unit": "degrees", "required": True}
UR_PROFILE_SCHEMA = Table(
    {
        "name": Key("str", required=True, check=_non_empty),
        "driver": Key("str", default="ur", choices=("ur",), doc="this loader reads only UR profiles"),
        "model": Key("str", default="", doc="labcal robot model whose joint limits bound the profile's"),
        "host": Key("str", required=True, check=_non_empty, doc="controller IP"),
        "ports": Key(
            "table",
            default={},
            table=Table({k: Key("int", default=v, check=_standard_port(v)) for k, v in _STANDARD_PORTS.items()}),
        ),
        "motion": Key(
            "table",
            default={},
            table=Table(
                {
                    "max_speed_rad_s": Key("number", default=0.5, unit="rad/s", check=_within(1e-6, UR_RTDE_MAX_SPEED)),
                    "max_acceleration_rad_s2": Key(
                        "number", default=1.0, unit="rad/s²", check=_within(1e-6, UR_RTDE_MAX_ACCELERATION)
                    ),
                    "stop_acceleration_rad_s2": Key(
                        "number", default=2.0, unit="rad/s²", check=_within(0.1, UR_RTDE_MAX_ACCELERATION)
                    ),
                    "settle_time_s": Key("number", default=0.2, unit="s", check=_within(0.0, 10.0)),
                    "position_tolerance_rad": Key("number", default=1e-3, unit="rad", check=_within(1e-6, 0.1)),
                }
            ),
        ),
        "joint_limits_deg": Key(
            "table", table=Table({"lower": Key("vector", **_DEG6), "upper": Key("vector", **_DEG6)})
        ),
        "workspace": Key("table", table=WORKSPACE_SCHEMA, doc="the cell: allowed/keep-out boxes, tracker position"),
        "timing": Key(
            "table",
            default={},
            table=Table(
                {
                    "connect_timeout_s": Key("number", default=2.0, unit="s", check=_within(0.01, 60.0)),
                    "stale_timeout_s": Key("number", default=0.5, unit="s", check=_within(0.01, 10.0)),
                    "frequency_hz": Key("number", default=-1.0, unit="Hz", check=_frequency_ok),
                    "watchdog_timeout_s": Key("number", default=1.0, unit="s", check=_within(0.05, 4.0)),
                    "call_timeout_s": Key("number", default=2.0, unit="s", check=_within(0.1, 4.0)),
                }
            ),
        ),
    },
    name="robot profile",
)


class URProfileError(SchemaError):
    """A UR robot profile has a bad key or value; the message names the file and the key."""


def load_ur_profile(path: str | Path) -> URProfile:
    """Read a robot profile TOML (see drivers/ur10-lab.toml). Raises URProfileError (a ValueError) naming the key."""
    return parse_ur_profile(read_toml(path, URProfileError, "robot profile"), source=str(path))


def parse_ur_profile(data: dict[str, Any], source: str = "<profile>") -> URProfile:
    """Build a URProfile from parsed TOML data (mm/deg named in keys, converted to SI here)."""

    def fail(message: str) -> ValueError:
        return URProfileError(f"{source}: {message}", source)

    doc = validate(data, UR_PROFILE_SCHEMA, source=source, error=URProfileError)
    motion, timing = doc["motion"], doc["timing"]
    model_limits = _model_limits(doc["model"], fail)
    limits_table = doc.get("joint_limits_deg", {})
    if not limits_table and model_limits is None:
        raise fail("give [joint_limits_deg] or a 'model' whose robot file carries joint limits")
    if limits_table:
        joint_limits = np.radians(np.column_stack([limits_table["lower"], limits_table["upper"]]).astype(float))
    else:
        joint_limits = np.array(model_limits)
    if model_limits is not None:
        # The model's limits are the hard bound: a profile may only narrow them.
        outside = (joint_limits[:, 0] < model_limits[:, 0] - 1e-9) | (joint_limits[:, 1] > model_limits[:, 1] + 1e-9)
        for j in np.flatnonzero(outside):
            raise fail(
                f"[joint_limits_deg] joint {j + 1}: [{math.degrees(joint_limits[j, 0]):.3f}, "
                f"{math.degrees(joint_limits[j, 1]):.3f}] deg goes beyond model {data['model']!r} limits "
                f"[{math.degrees(model_limits[j, 0]):.3f}, {math.degrees(model_limits[j, 1]):.3f}] deg"
            )
    for j, (lo, hi) in enumerate(joint_limits):
        if not lo < hi:
            raise fail(f"[joint_limits_deg] joint {j + 1}: lower {math.degrees(lo)} is not below upper")
        if lo < -2 * math.pi - 1e-9 or hi > 2 * math.pi + 1e-9:
            raise fail(f"[joint_limits_deg] joint {j + 1}: UR joints cannot go beyond ±360 deg")

    limits = SafetyLimits(
        joint_limits=joint_limits,
        max_speed=motion["max_speed_rad_s"],
        max_acceleration=motion["max_acceleration_rad_s2"],
    )
    return URProfile(
        name=doc["name"],
        model=doc["model"],
        host=doc["host"],
        limits=limits,
        settle_time=motion["settle_time_s"],
        position_tolerance=motion["position_tolerance_rad"],
        stop_acceleration=motion["stop_acceleration_rad_s2"],
        connect_timeout=timing["connect_timeout_s"],
        stale_timeout=timing["stale_timeout_s"],
        frequency=timing["frequency_hz"],
        workspace=parse_workspace(doc["workspace"], source, URProfileError) if "workspace" in doc else None,
        watchdog_timeout=timing["watchdog_timeout_s"],
        call_timeout=timing["call_timeout_s"],
    )


def _model_limits(model: str, fail: Callable[[str], ValueError]) -> np.ndarray | None:
    """Joint limits (6, 2) rad of the named robot model (built-in name or robot file path), or None for ""
    (the schema has made sure ``model`` is a string)."""
    if not model:
        return None
    from labcal.robots import RobotFileError, load  # lazy: the profile loader is usable without it

    try:
        spec = load(model)
    except RobotFileError as exc:
        raise fail(f"'model' = {model!r}: {exc}") from exc
    limits = np.asarray(spec.model.limits, dtype=float)
    if limits.shape != (N_JOINTS, 2):
        raise fail(f"'model' = {model!r} has {limits.shape[0]} joints; a UR arm has {N_JOINTS}")
    return limits


# --------------------------------------------------------------------------------------------------------------
# Probes: never hand a silent peer to ur-rtde.


def _open(host: str, port: int, timeout: float) -> socket.socket:
    try:
        return socket.create_connection((host, port), timeout=timeout)
    except TimeoutError as exc:
        raise ConnectionFailed(f"{host}:{port} did not accept a connection within {timeout} s") from exc
    except OSError as exc:
        raise ConnectionFailed(f"cannot connect to {host}:{port}: {exc.strerror or exc}") from exc


def _recv_exact(sock: socket.socket, n: int, deadline: float, what: str) -> bytes:
    data = bytearray()
    while len(data) < n:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise ProbeTimeout(f"{what}: connection accepted, but no (complete) answer in time")
        sock.settimeout(remaining)
        try:
            chunk = sock.recv(n - len(data))
        except TimeoutError as exc:
            raise ProbeTimeout(f"{what}: connection accepted, but no (complete) answer in time") from exc
        except OSError as exc:
            raise ConnectionFailed(f"{what}: connection lost while waiting for the answer: {exc}") from exc
        if not chunk:
            raise ConnectionFailed(f"{what}: the peer closed the connection without answering")
        data += chunk
    return bytes(data)


def _rtde_request(sock: socket.socket, kind: str, payload: bytes, deadline: float, what: str) -> bytes:
    sock.sendall(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)
    while True:
        size, reply = struct.unpack(">HB", _recv_exact(sock, 3, deadline, what))
        if size < 3:
            raise ProtocolError(f"{what}: RTDE header announces {size} bytes, less than the header itself")
        body = _recv_exact(sock, size - 3, deadline, what)
        if chr(reply) == kind:
            return body
        if chr(reply) != "M":  # text messages may come in between; anything else is not RTDE
            raise ProtocolError(f"{what}: expected an RTDE {kind!r} reply, got package type {reply}")


def probe_rtde(host: str, port: int = RTDE_PORT, timeout: float = 2.0) -> tuple[int, int, int, int]:
    """Check that an RTDE server answers; return its controller version (major, minor, bugfix, build).

    Sends a protocol-version request (version 2) and a controller-version request, each answer awaited with
    ``timeout`` s in total. Raises ConnectionFailed (nothing there), ProbeTimeout (accepts, never answers) or
    ProtocolError (answers something that is not RTDE, or refuses protocol 2).
    """
    what = f"RTDE probe of {host}:{port}"
    deadline = time.monotonic() + timeout
    with contextlib.closing(_open(host, port, timeout)) as sock:
        accepted = _rtde_request(sock, "V", struct.pack(">H", 2), deadline, what)
        if accepted[:1] != b"\x01":
            raise ProtocolError(f"{what}: controller refused RTDE protocol version 2 (answer {accepted!r})")
        body = _rtde_request(sock, "v", b"", deadline, what)
        if len(body) != 16:
            raise ProtocolError(f"{what}: controller version answer has {len(body)} bytes, expected 16")
        major, minor, bugfix, build = struct.unpack(">4I", body)
        return major, minor, bugfix, build


def probe_dashboard(host: str, port: int = DASHBOARD_PORT, timeout: float = 2.0) -> str:
    """Check that the dashboard server greets us with a line within ``timeout`` s; return that line."""
    return _ask_dashboard(host, port, timeout, f"dashboard probe of {host}:{port}", (), {})


def _ask_dashboard(host: str, port: int, timeout: float, what: str, commands: Sequence[str], answers: dict) -> str:
    """Send each command line to the dashboard server after its greeting, all within ``timeout`` s; return the
    greeting. ``answers`` ({command: answer line}) fills as they come, so a caller keeps them when a later one fails."""
    deadline = time.monotonic() + timeout
    with contextlib.closing(_open(host, port, timeout)) as sock:
        greeting = _read_line(sock, deadline, what)
        for command in commands:
            sock.sendall(command.encode("ascii") + b"\n")
            answers[command] = _read_line(sock, deadline, what)
    return greeting


# What labcal asks the dashboard server about the arm, and the identity key each answer goes to.
IDENTITY_COMMANDS = (("get serial number", "serial"), ("get robot model", "model"), ("PolyscopeVersion", "software"))
# The dashboard answers a command it does not know (older PolyScope) with a sentence, not an error code.
_DASHBOARD_REFUSALS = ("could not understand", "failed", "error", "unknown")
_SOFTWARE_VERSION = re.compile(r"(\d+\.\d+\.\d+(?:\.\d+)?)")
_IDENTITY_TOKEN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")


def parse_dashboard_identity(answers: dict[str, str]) -> dict[str, Any]:
    """The identity in the dashboard's answers ({command: answer line}): serial, model, software (+ notes).

    >>> parse_dashboard_identity({"get serial number": "20185500001", "get robot model": "UR10",
    ...                           "PolyscopeVersion": "URSoftware 5.11.0.108249 (Sep 15 2021)"})
    {'serial': '20185500001', 'model': 'UR10', 'software': '5.11.0.108249'}

    An answer that is missing, a refusal ("could not understand: …") or not an identifier becomes a note instead.
    """
    identity: dict[str, Any] = {}
    notes = []
    for command, key in IDENTITY_COMMANDS:
        answer = answers.get(command)
        if answer is None:
            notes.append(f"the dashboard server did not answer {command!r}")
            continue
        text = answer.strip()
        if key == "software":
            found = _SOFTWARE_VERSION.search(text)
            value = found.group(1) if found and not text.lower().startswith(_DASHBOARD_REFUSALS) else None
        else:
            ok = _IDENTITY_TOKEN.fullmatch(text) and not text.lower().startswith(_DASHBOARD_REFUSALS)
            value = text if ok else None
        if value is None:
            notes.append(f"the dashboard server answered {command!r} with {text[:80]!r}")
        else:
            identity[key] = value
    if notes:
        identity["notes"] = notes
    return identity


def read_dashboard_identity(host: str, port: int = DASHBOARD_PORT, timeout: float = 2.0) -> dict[str, Any]:
    """Ask the dashboard server who the arm is (:data:`IDENTITY_COMMANDS`); never raises.

    A controller that cannot be reached or stops answering gives what it told so far plus a note: a session can
    be recorded without the serial number (the operator then names the unit with ``--unit``).
    """
    what = f"dashboard identity query of {host}:{port}"
    answers: dict[str, str] = {}
    try:
        _ask_dashboard(host, port, timeout, what, [command for command, _ in IDENTITY_COMMANDS], answers)
    except (ConnectionFailed, ProtocolError, OSError) as exc:
        identity = parse_dashboard_identity(answers)
        asked = [c for c, _ in IDENTITY_COMMANDS if c not in answers]
        notes = [n for n in identity.pop("notes", []) if not any(repr(c) in n for c in asked)]
        identity["notes"] = [*notes, f"{what} failed ({exc}); not known: {', '.join(asked)}"]
        return identity
    return parse_dashboard_identity(answers)


def _read_line(sock: socket.socket, deadline: float, what: str) -> str:
    line = b""
    while not line.endswith(b"\n"):
        line += _recv_exact(sock, 1, deadline, what)
        if len(line) > 4096:
            raise ProtocolError(f"{what}: a line longer than 4096 bytes without a newline")
    return line.decode("utf-8", "replace").strip()


def probe_script_port(host: str, port: int = SCRIPT_PORT, timeout: float = 2.0) -> None:
    """Check that the script/real-time port streams bytes after connecting (it does so at 125-500 Hz)."""
    deadline = time.monotonic() + timeout
    with contextlib.closing(_open(host, port, timeout)) as sock:
        _recv_exact(sock, 1, deadline, f"script port probe of {host}:{port}")


# --------------------------------------------------------------------------------------------------------------
# The robot.


# How long an interface may take to connect: ur-rtde's control constructor alone waits up to 5 s for its script, s.
CONSTRUCT_TIMEOUT = 10.0


class URRobot(ClosedOnExit):
    """The ``Robot`` port for a UR arm. A context manager; ``close()`` is safe to call twice.

    receive: an ``rtde_receive.RTDEReceiveInterface`` (or a stand-in with the same methods).
    control: an ``rtde_control.RTDEControlInterface``, or None for a read-only robot (move_joints refuses).
    Use :meth:`connect` to probe and build the real interfaces; pass stand-ins directly in tests.
    identity: what the controller told about itself (:func:`read_dashboard_identity`), None if it was not asked.
    """

    n_joints = N_JOINTS

    def __init__(
        self,
        profile: URProfile,
        receive: Any,
        control: Any | None = None,
        *,
        identity: dict[str, Any] | None = None,
    ):
        self.profile = profile
        self.identity_read = None if identity is None else dict(identity)
        self.limits = profile.limits
        self._receive = receive
        self._control = control
        self._last_timestamp: float | None = None
        self._closed = False

    @classmethod
    def connect(
        cls,
        profile: URProfile,
        *,
        read_only: bool = False,
        probe: bool = True,
        receive_factory: Callable[[str, float], Any] | None = None,
        control_factory: Callable[[str, float], Any] | None = None,
    ) -> URRobot:
        """Probe the controller's ports, then build the interfaces (control only unless ``read_only``).

        The probe also asks the dashboard server for the arm's serial number, model and software version
        (:meth:`device_identity`); a controller that does not tell leaves a note, never an error.

        Raises ConnectionFailed (ProbeTimeout for a silent peer) or ProtocolError; never hangs on a peer that
        fails the probe. ``receive_factory`` / ``control_factory`` (``(host, frequency) -> interface``; tests pass
        stand-ins): by default each ur-rtde interface runs in its own process, so a peer that answers the probe
        and then goes silent costs at most CONSTRUCT_TIMEOUT s, never a hang.
        """
        host, timeout = profile.host, profile.connect_timeout
        identity = None
        if probe:
            version = probe_rtde(host, RTDE_PORT, timeout)
            log.info("UR controller at %s answers RTDE, version %s", host, ".".join(map(str, version)))
            if not read_only:
                probe_dashboard(host, DASHBOARD_PORT, timeout)
                probe_script_port(host, SCRIPT_PORT, timeout)
            identity = read_dashboard_identity(host, DASHBOARD_PORT, timeout)
            log.info("UR controller at %s: %s", host, identity)
        # by default each ur-rtde interface in its own process (see labcal.drivers.ur_process)
        remote = functools.partial(RemoteInterface, start_timeout=CONSTRUCT_TIMEOUT, call_timeout=profile.call_timeout)
        receive_factory = receive_factory or functools.partial(remote, "receive", variables=RECEIVE_VARIABLES)
        control_factory = control_factory or functools.partial(remote, "control")
        receive = _construct(receive_factory, host, profile.frequency, "RTDE receive interface")
        control = None
        if not read_only:
            try:
                control = _construct(control_factory, host, profile.frequency, "RTDE control interface")
            except BaseException:
                cls(profile, receive).close()  # never raises; ends a RemoteInterface's process too, not only its link
                raise
        return cls(profile, receive, control, identity=identity)

    def device_identity(self) -> dict[str, Any]:
        """What the controller told about itself: ``serial``, ``model``, ``software`` (PolyScope version), and
        ``notes`` for what it did not tell; {} if it was not asked (built from stand-ins without ``identity``)."""
        return dict(self.identity_read or {})

    # -- context manager -------------------------------------------------------------------------------------

    def __exit__(self, *exc: object) -> None:
        try:
            if exc and exc[0] is not None:
                self.stop()  # leaving because of an error: make sure nothing keeps moving
        finally:
            self.close()  # also when a second Ctrl-C lands during the stop

    def close(self) -> None:
        """Disconnect both interfaces. Safe to call twice; never raises."""
        if self._closed:
            return
        self._closed = True
        remote = [i for i in (self._control, self._receive) if isinstance(i, RemoteInterface)]
        # ur-rtde's disconnect() takes ~0.5 s per interface: both at once; a dead link is killed, not waited for
        closers = [threading.Thread(target=i.close, args=(min(1.0, self.profile.call_timeout),)) for i in remote]
        for thread in closers:
            thread.start()
        for iface in (self._control, self._receive):
            if iface is not None and iface not in remote:
                with contextlib.suppress(Exception):
                    iface.disconnect()
        for thread in closers:
            thread.join()

    # -- reading ---------------------------------------------------------------------------------------------

    def _rx(self) -> Any:
        if self._closed:
            raise ConnectionFailed("the UR robot connection is closed")
        return self._receive

    def _call_rx(self, name: str, *args: Any) -> Any:
        rx = self._rx()
        try:
            return getattr(rx, name)(*args)
        except (RuntimeError, ValueError) as exc:
            if not self._connected(rx):
                raise ConnectionFailed(f"lost the RTDE connection to {self.profile.host}: {exc}") from exc
            raise ProtocolError(f"RTDE receive {name}() failed: {exc}") from exc

    @staticmethod
    def _connected(rx: Any) -> bool:
        try:
            return bool(rx.isConnected())
        except Exception:
            return False

    def _fresh_timestamp(self) -> float:
        """Wait (at most stale_timeout) for a controller timestamp newer than the last one seen."""
        rx = self._rx()
        deadline = time.monotonic() + self.profile.stale_timeout
        current = self._call_rx("getTimestamp")
        previous = self._last_timestamp if self._last_timestamp is not None else current
        while True:
            if not self._connected(rx):
                raise ConnectionFailed(f"the RTDE connection to {self.profile.host} is down")
            if current > previous:
                break
            if time.monotonic() >= deadline:
                raise StaleData(
                    f"controller timestamp stuck at {current:.6f} s for {self.profile.stale_timeout} s "
                    f"({self.profile.host})"
                )
            time.sleep(0.001)
            current = self._call_rx("getTimestamp")
        self._last_timestamp = current
        return current

    def state(self) -> RobotState:
        """A fresh controller snapshot: q (6,) rad, controller timestamp s, safety flags, ready."""
        timestamp = self._fresh_timestamp()
        q = np.asarray(self._call_rx("getActualQ"), dtype=float)
        if q.shape != (N_JOINTS,):
            raise ProtocolError(f"controller reported {q.shape} joint values, expected ({N_JOINTS},)")
        protective = bool(self._call_rx("isProtectiveStopped"))
        emergency = bool(self._call_rx("isEmergencyStopped"))
        mode = int(self._call_rx("getRobotMode"))
        return RobotState(
            q=q,
            timestamp=timestamp,
            protective_stop=protective,
            emergency_stop=emergency,
            ready=mode == ROBOT_MODE_RUNNING and not protective and not emergency,
        )

    def robot_mode(self) -> int:
        """Controller robot mode (7 = RUNNING)."""
        return int(self._call_rx("getRobotMode"))

    def joint_positions(self) -> np.ndarray:
        """Actual joint positions (6,), rad, from a fresh controller sample."""
        return self.state().q

    # -- moving ----------------------------------------------------------------------------------------------

    @property
    def _control_lost(self) -> bool:
        """The control interface's process is gone (a stand-in interface in this process never is)."""
        return isinstance(self._control, RemoteInterface) and not self._control.alive

    def _call_control(self, name: str, *args: Any, **bounds: Any) -> Any:
        """ur-rtde control ``name(*args)``: in its process within ``bounds`` (``timeout``, ``watch``: see
        :meth:`~labcal.drivers.ur_process.ChildProcess.call`); a stand-in in this process is called directly."""
        if isinstance(self._control, RemoteInterface):
            return self._control.call(name, *args, **bounds)
        return getattr(self._control, name)(*args)

    def _sample(self, done: Callable[[RobotState], bool]) -> RobotState:
        """Fresh states until ``done(state)`` or STREAM_SKEW_WINDOW has passed: ur-rtde's control and receive
        interfaces read separate streams, so the sample in hand may predate an event the control side saw."""
        deadline = time.monotonic() + STREAM_SKEW_WINDOW
        state = self.state()
        while not done(state) and time.monotonic() < deadline:
            state = self.state()
        return state

    def _raise_if_stopped(self, state: RobotState, when: str) -> None:
        where = np.array2string(state.q, precision=4)
        if state.emergency_stop:
            raise EmergencyStop(f"robot is emergency-stopped {when} (q = {where} rad)")
        if state.protective_stop:
            raise ProtectiveStop(f"robot is protective-stopped {when} (q = {where} rad)")

    def move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        """Move to q (6,) rad with joint speed (rad/s) and acceleration (rad/s²); block until it ends.

        Checks limits and robot state first (MotionRejected, ProtectiveStop, EmergencyStop), then checks the
        controller's answer and the final position (MotionFailed, ProtectiveStop).
        """
        if self._control is None:
            raise MotionRejected("this UR robot was opened read-only (no control interface)")
        target = self.limits.check_motion(q, speed, acceleration)
        if self._control_lost:
            raise ConnectionFailed(f"the control interface to {self.profile.host} was lost; resume the session")
        before = self.state()
        self._raise_if_stopped(before, "before the move")
        mode = self.robot_mode()
        if mode != ROBOT_MODE_RUNNING:
            raise MotionRejected(f"robot mode is {mode}, not RUNNING ({ROBOT_MODE_RUNNING}); refusing to move")
        try:
            ok = self._move_watched(target, float(speed), float(acceleration), before)
        except ValueError as exc:
            raise MotionRejected(f"ur-rtde refused the move: {exc}") from exc
        except RuntimeError as exc:
            if self._control_lost:
                raise ConnectionFailed(f"lost the control interface to {self.profile.host}: {exc}") from exc
            self._raise_stop_or(MotionFailed(f"moveJ raised: {exc}"), exc)
        if not ok:
            self._raise_stop_or(MotionFailed(f"controller reported moveJ to {target.tolist()} failed"), None)
        if self.profile.settle_time > 0:
            time.sleep(self.profile.settle_time)
        tolerance = self.profile.position_tolerance
        after = self._sample(lambda s: _stopped(s) or float(np.max(np.abs(s.q - target))) <= tolerance)
        self._raise_if_stopped(after, "after the move")
        error = float(np.max(np.abs(after.q - target)))
        if error > tolerance:
            raise MotionFailed(
                f"robot ended {error:.6f} rad from the target (tolerance {tolerance} rad): q = {after.q.tolist()}"
            )

    def _move_watched(self, target: np.ndarray, speed: float, acceleration: float, before: RobotState) -> bool:
        """moveJ, blocking; in a process of its own it is watched: the controller timestamp must advance at least
        every ``watchdog_timeout`` s and the move must end within twice its planned time (+ 10 s). Otherwise the
        control interface is killed and StaleData (timestamp stuck) or ConnectionFailed (link down, move too long)
        raised; the caller's stop() then halts the program through the dashboard."""
        args = (target.tolist(), speed, acceleration, False)
        distance = float(np.max(np.abs(target - before.q)))
        planned = distance / speed + speed / acceleration
        budget = 2.0 * planned + 10.0
        deadline = time.monotonic() + budget
        last = {"timestamp": before.timestamp, "at": time.monotonic()}

        def watch() -> None:
            now = time.monotonic()
            if now > deadline:
                raise ConnectionFailed(
                    f"moveJ on {self.profile.host} did not end within {budget:.1f} s (planned {planned:.1f} s)"
                )
            timestamp = self._call_rx("getTimestamp")
            if not self._connected(self._rx()):
                raise ConnectionFailed(f"the RTDE connection to {self.profile.host} is down during a move")
            if timestamp > last["timestamp"]:
                last.update(timestamp=timestamp, at=now)
            elif now - last["at"] > self.profile.watchdog_timeout:
                raise StaleData(
                    f"controller {self.profile.host} silent during a move: its timestamp stuck at {timestamp:.6f} s "
                    f"for {now - last['at']:.1f} s (controller down or network lost; watchdog "
                    f"{self.profile.watchdog_timeout} s)"
                )

        return bool(self._call_control("moveJ", *args, timeout=None, watch=watch))

    def _halt_from_dashboard(self) -> None:
        """Stop the program through the dashboard server (independent of RTDE): the best left when the control
        interface is gone. Never raises; bounded by a short timeout (a dead controller refuses or times out)."""
        what = f"dashboard stop on {self.profile.host}:{DASHBOARD_PORT}"
        timeout, answers = min(0.5, self.profile.connect_timeout), dict[str, str]()
        try:
            _ask_dashboard(self.profile.host, DASHBOARD_PORT, timeout, what, ["stop"], answers)
            log.warning("%s: %s", what, answers["stop"])
        except (DriverError, OSError) as exc:
            log.info("%s failed: %s", what, exc)

    def _raise_stop_or(self, error: MotionFailed, cause: BaseException | None) -> None:
        """After a failed move: raise the stop that caused it if the safety state shows one, else ``error``.

        The sample in hand may predate the stop that ended the move (see STREAM_SKEW_WINDOW).
        """
        try:
            state = self._sample(_stopped)
        except StaleData as exc:
            raise MotionFailed(f"{error}; and the controller data went stale: {exc}") from cause
        except ConnectionFailed as exc:
            raise ConnectionFailed(f"{error}; and the connection is lost: {exc}") from cause
        self._raise_if_stopped(state, "after a failed move")
        raise error from cause

    def resume(self) -> None:
        """Continue after a protective stop an operator has cleared (labcal never unlocks a stop itself).

        A safety stop halts ur-rtde's control script on the controller; this re-uploads it. Raises
        ProtectiveStop/EmergencyStop if the stop is still active, MotionRejected if read-only or not RUNNING,
        ConnectionFailed if the script cannot be restarted.
        """
        if self._control is None:
            raise MotionRejected("this UR robot was opened read-only (no control interface)")
        state = self._sample(lambda s: not _stopped(s))  # the sample may predate the operator's clearing of the stop
        self._raise_if_stopped(state, "— clear it on the teach pendant first")
        mode = self.robot_mode()
        if mode != ROBOT_MODE_RUNNING:
            raise MotionRejected(f"robot mode is {mode}, not RUNNING ({ROBOT_MODE_RUNNING}); cannot resume")
        if self._program_running():
            return
        try:  # uploading waits for the controller: a longer deadline than other calls
            restarted = self._call_control("reuploadScript", timeout=SCRIPT_START_TIMEOUT + self.profile.call_timeout)
        except RuntimeError as exc:
            raise ConnectionFailed(f"could not restart the control script on {self.profile.host}: {exc}") from exc
        if not restarted:
            raise ConnectionFailed(f"the control script on {self.profile.host} could not be uploaded")
        # reuploadScript() returns once the script is sent, before the controller runs it
        deadline = time.monotonic() + SCRIPT_START_TIMEOUT
        while not self._program_running():
            if time.monotonic() >= deadline:
                raise ConnectionFailed(
                    f"the control script on {self.profile.host} did not start within {SCRIPT_START_TIMEOUT} s"
                )
            time.sleep(0.01)

    def _program_running(self) -> bool:
        try:
            return bool(self._call_control("isProgramRunning"))
        except RuntimeError as exc:
            raise ConnectionFailed(f"lost the control connection to {self.profile.host}: {exc}") from exc

    def stop(self) -> None:
        """Decelerate any joint motion (stopJ). Always safe: never raises, also after close or an error."""
        if self._control is None or self._closed:
            return
        if self._control_lost:
            self._halt_from_dashboard()  # the control interface is gone: the dashboard is what is left
            return
        try:
            self._control.stopJ(self.profile.stop_acceleration, False)
        except Exception as exc:  # stop() is called on error paths; it must not mask the original error
            log.warning("stopJ on %s failed: %s", self.profile.host, exc)


def _stopped(state: RobotState) -> bool:
    return state.protective_stop or state.emergency_stop


def _construct(factory: Callable[[str, float], Any], host: str, frequency: float, what: str) -> Any:
    try:
        return factory(host, frequency)
    except ValueError as exc:
        raise ProtocolError(f"{what} for {host}: {exc}") from exc
    except RuntimeError as exc:
        # ur-rtde reports every setup failure as RuntimeError; only its wording tells a controller that lacks
        # a variable (wrong PolyScope version: a protocol problem) from one that cannot be reached.
        if "not found" in str(exc).lower():
            raise ProtocolError(f"{what} for {host}: {exc}") from exc
        raise ConnectionFailed(f"{what} for {host} could not be set up: {exc}") from exc
