"""A fake Universal Robots controller that speaks RTDE (port 30004) on a loopback address, in its own process.

Why a separate process: the real ``rtde_receive.RTDEReceiveInterface`` constructor holds the GIL while it
connects, so a fake served by a thread of the same interpreter would never get to answer. Why its own loopback
address (127.0.x.y): the RTDE port is fixed at 30004 and several fakes (and several test runs) may be alive at
once.

The wire protocol follows UR's public RTDE guide (protocol versions 1 and 2): every package is a header (uint16
big-endian size including the 3-byte header, uint8 type) and a payload; ``V`` protocol version, ``v``
controller version (4 x uint32), ``O``/``I`` output/input recipe setup (recipe id + comma-separated types,
``NOT_FOUND`` for names it does not know, ``IN_USE`` for an input another client owns), ``S`` start, ``P`` pause
and ``U`` data packages (recipe id + values big-endian in recipe order; no recipe ids in version 1). It knows
every standard output field of the guide (constant idle values where the fake simulates nothing), the
registers in the guide's ranges, streams only the output recipe a client set up last, and paces it on absolute
deadlines with controller-tick timestamps (2 ms on e-Series, 8 ms on CB3), so 125 Hz is 125 packages a second
stamped 8 ms apart. Checked with ur-rtde 1.6.5 and with UR's own Python client (tests/drivers/test_rtde_fake.py).

The fake is backed by a simulated joint state: q (6,) in rad, safety flags and robot mode, set from the test
process through a pipe. With ``control=True`` it also emulates what ``rtde_control.RTDEControlInterface``
(ur-rtde 1.6.5) needs: the dashboard server (29999), the script port (30003) and ur-rtde's register protocol
(see :class:`ControlEmulator`), so a real ``moveJ`` moves the simulated joints.

Example::

    with FakeRTDEServer(q0=[0, -1.57, 1.57, 0, 0, 0]) as fake:
        recv = rtde_receive.RTDEReceiveInterface(fake.host, -1.0, ["timestamp", "actual_q"])
        fake.set_safety(protective=True)
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import operator
import os
import re
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from labcal.drivers.ur_process import ChildProcess, serve

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
HEADER = struct.Struct(">HB")

# RTDE type name -> struct format (big-endian added when packing).
TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

_VECTOR6D = (
    "target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
    "actual_current_window actual_current_as_torque joint_control_output actual_TCP_pose actual_TCP_speed "
    "actual_TCP_force target_TCP_pose target_TCP_speed joint_temperatures actual_joint_voltage ft_raw_wrench "
    "payload_inertia tcp_offset"
).split()
_DOUBLE = (
    "timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum actual_main_voltage "
    "actual_robot_voltage actual_robot_current standard_analog_input0 standard_analog_input1 "
    "standard_analog_output0 standard_analog_output1 io_current euromap67_24V_voltage euromap67_24V_current "
    "tool_analog_input0 tool_analog_input1 tool_output_current tool_temperature tcp_force_scalar payload "
    "joint_position_deviation_ratio collision_detection_ratio"
).split()
_UINT32 = (
    "runtime_state robot_status_bits safety_status_bits analog_io_types euromap67_input_bits "
    "euromap67_output_bits tool_mode tool_analog_input_types script_control_line output_bit_registers0_to_31 "
    "output_bit_registers32_to_63 input_bit_registers0_to_31 input_bit_registers32_to_63"
).split()
# The standard output fields of UR's RTDE guide (e-Series 5.x), besides the numbered registers.
_FIXED_TYPES: dict[str, str] = {
    **dict.fromkeys(_VECTOR6D, "VECTOR6D"),
    **dict.fromkeys(_DOUBLE, "DOUBLE"),
    **dict.fromkeys(_UINT32, "UINT32"),
    **dict.fromkeys(["tool_output_mode", "tool_digital_output0_mode", "tool_digital_output1_mode"], "UINT8"),
    **dict.fromkeys(["actual_tool_accelerometer", "payload_cog", "elbow_position", "elbow_velocity"], "VECTOR3D"),
    "actual_digital_input_bits": "UINT64",
    "actual_digital_output_bits": "UINT64",
    "robot_mode": "INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "tool_output_voltage": "INT32",
    "time_scale_source": "INT32",
    "joint_mode": "VECTOR6INT32",
}
# Inputs (what a client may write), besides input_{int,double,bit}_register_N.
_INPUT_TYPES: dict[str, str] = {
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "external_force_torque": "VECTOR6D",
}
_REGISTER = re.compile(r"^(input|output)_(int|double|bit)_register_(0|[1-9]\d*)$")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}
# Register numbers the RTDE guide names one by one: int and double 0..47 (0..23 shared with the fieldbus/PLC,
# 24..47 for RTDE clients); single bits 64..127 only (bits 0..63 are read and written as the two UINT32 words
# ``*_bit_registers0_to_31`` / ``*_bit_registers32_to_63``).
REGISTER_RANGES = {"int": range(48), "double": range(48), "bit": range(64, 128)}


# UR controller enumerations (RTDE guide): robot mode, safety mode, safety status bits, runtime state.
ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NORMAL = 1
SAFETY_MODE_PROTECTIVE_STOP = 3
SAFETY_MODE_ROBOT_EMERGENCY_STOP = 7
SAFETY_BIT_NORMAL = 1 << 0
SAFETY_BIT_PROTECTIVE_STOPPED = 1 << 2
SAFETY_BIT_EMERGENCY_STOPPED = (1 << 5) | (1 << 6) | (1 << 7)  # system, robot and combined e-stop bits
RUNTIME_STOPPED = 1
RUNTIME_PLAYING = 2


def rtde_type(name: str, direction: str = "output") -> str | None:
    """RTDE type of an output (or, with direction="input", input) name; None if unknown (NOT_FOUND).

    >>> rtde_type("output_bit_register_64"), rtde_type("output_bit_register_63"), rtde_type("actual_q")
    ('BOOL', None, 'VECTOR6D')
    """
    table = _FIXED_TYPES if direction == "output" else _INPUT_TYPES
    if name in table:
        return table[name]
    match = _REGISTER.match(name)
    if match is None or int(match.group(3)) not in REGISTER_RANGES[match.group(2)]:
        return None
    # both directions may read the input registers; only outputs may name output registers
    if direction == "output" or match.group(1) == "input":
        return _REGISTER_TYPES[match.group(2)]
    return None


def pack_package(kind: str, payload: bytes = b"") -> bytes:
    """One RTDE package: header (size incl. header, type byte) + payload."""
    return HEADER.pack(HEADER.size + len(payload), ord(kind)) + payload


def _vector_size(kind: str) -> int:
    """Number of values of an RTDE type: 3 or 6 for vectors, 0 for a scalar."""
    fmt = TYPE_FORMATS[kind]
    return int(fmt[0]) if fmt[0].isdigit() else 0


def pack_values(types: Sequence[str], values: Sequence[Any]) -> bytes:
    """Pack values big-endian in recipe order (no padding between them); vector values are sequences."""
    flat: list[Any] = []
    for kind, value in zip(types, values, strict=True):
        flat += value if _vector_size(kind) else [value]
    return struct.pack(">" + "".join(TYPE_FORMATS[k] for k in types), *flat)


def unpack_values(types: Sequence[str], data: bytes) -> list[Any]:
    """Inverse of :func:`pack_values`; raises struct.error if data has the wrong length."""
    flat = iter(struct.unpack(">" + "".join(TYPE_FORMATS[k] for k in types), data))
    sizes = [_vector_size(k) for k in types]
    return [[next(flat) for _ in range(size)] if size else next(flat) for size in sizes]


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Read exactly n bytes or raise ConnectionError when the peer closes."""
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("peer closed the connection")
        data += chunk
    return bytes(data)


def read_package(sock: socket.socket) -> tuple[str, bytes]:
    """Read one RTDE package, returning (type letter, payload)."""
    size, kind = HEADER.unpack(recv_exact(sock, HEADER.size))
    if size < HEADER.size:
        raise ConnectionError(f"RTDE package size {size} is smaller than its header")
    return chr(kind), recv_exact(sock, size - HEADER.size)


# Standard outputs the fake keeps constant, at values a powered, idle arm on a bench reports (volts, amperes of the
# arm, degC, m/s^2; tool and joint modes 253 = running; I/O and tool currents are left at 0: nothing is wired).
_IDLE_OUTPUTS: dict[str, Any] = {
    "actual_main_voltage": 48.0,
    "actual_robot_voltage": 48.0,
    "actual_robot_current": 0.6,
    "actual_joint_voltage": [47.8] * 6,
    "joint_temperatures": [31.0, 32.5, 33.0, 30.5, 30.0, 29.5],
    "tool_temperature": 30.0,
    "actual_tool_accelerometer": [0.0, 0.0, 9.81],
    "actual_execution_time": 0.35,  # ms of the 2 ms control period
    "tool_mode": 253,
    "tool_output_voltage": 24,
    "tool_output_current": 0.0,
    "payload": 1.0,
    "payload_inertia": [0.0] * 6,
}

# Denavit-Hartenberg d1, a2, a3, d4, d5, d6 (m) of UR arms (UR's published DH tables); alpha is
# (pi/2, 0, 0, pi/2, -pi/2, 0) and a1 = a4 = a5 = a6 = 0 on all of them.
_UR_DH = {
    "UR3": (0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819),
    "UR5": (0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
    "UR10": (0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922),
    "UR3e": (0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921),
    "UR5e": (0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "UR10e": (0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
    "UR16e": (0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655),
}
_UR_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)


def _ur_frames(q: Sequence[float], model: str) -> list[Any]:
    """The base-frame transforms (4, 4) after each of the 6 joints of a UR arm at q (rad)."""
    from labcal.kinematics.conversions import dh_transform  # lazy: only the pose outputs need numpy

    d1, a2, a3, d4, d5, d6 = _UR_DH.get(model, _UR_DH["UR10"])
    rows = zip(q, (0.0, a2, a3, 0.0, 0.0, 0.0), (d1, 0.0, 0.0, d4, d5, d6), _UR_ALPHA, strict=True)
    return list(
        itertools.accumulate((dh_transform(a, alpha, d, theta) for theta, a, d, alpha in rows), operator.matmul)
    )


def tcp_pose(q: Sequence[float], model: str = "UR10") -> list[float]:
    """The flange pose [x, y, z (m), rx, ry, rz (rotation vector, rad)] in the base frame at q (6,) rad (no TCP
    offset), as ``actual_TCP_pose`` reports it."""
    from labcal.kinematics.se3 import log_so3  # axis * angle, angle in [0, pi]: how UR reports the orientation

    T = _ur_frames(q, model)[-1]
    return [*T[:3, 3].tolist(), *log_so3(T[:3, :3]).tolist()]


def elbow_position(q: Sequence[float], model: str = "UR10") -> list[float]:
    """Base-frame position (m) of the elbow (the origin after joint 2's link), from q (6,) rad.

    >>> [round(v, 4) + 0.0 for v in elbow_position([0, 0, 0, 0, 0, 0])]
    [-0.612, 0.0, 0.1273]
    """
    return _ur_frames(q, model)[1][:3, 3].tolist()


# --------------------------------------------------------------------------------------------------------------
# The simulated controller (lives in the child process).


class SimController:
    """Joint state, safety state and RTDE registers of the fake controller. All access under ``lock``."""

    def __init__(self, q0: Sequence[float], controller_version: Sequence[int]):
        self.lock = threading.Lock()
        self.q = [float(v) for v in q0]
        self.target_q = list(self.q)
        self.qd = [0.0] * 6
        self.protective = False
        self.emergency = False
        self.robot_mode = ROBOT_MODE_RUNNING
        self.program_running = False
        self.controller_version = tuple(int(v) for v in controller_version)
        self.t0 = time.monotonic()
        self.frozen_at: float | None = None
        self.registers: dict[str, Any] = {}
        self.log: list[tuple[str, Any]] = []  # control-side events (script uploads, commands) for tests
        self.serial: str | None = "20185500001"  # None: a controller too old to know "get serial number"
        self.robot_model = "UR10"
        # input field -> the RTDE session whose recipe claimed it; another client asking for it gets IN_USE
        self.input_owners: dict[str, object] = {}

    def timestamp(self) -> float:
        """Controller time, s since the fake started (stops advancing while frozen)."""
        if self.frozen_at is not None:
            return self.frozen_at
        return time.monotonic() - self.t0

    def safety_mode(self) -> int:
        if self.emergency:
            return SAFETY_MODE_ROBOT_EMERGENCY_STOP
        return SAFETY_MODE_PROTECTIVE_STOP if self.protective else SAFETY_MODE_NORMAL

    def safety_bits(self) -> int:
        protective = SAFETY_BIT_PROTECTIVE_STOPPED if self.protective else 0
        return protective | (SAFETY_BIT_EMERGENCY_STOPPED if self.emergency else 0) or SAFETY_BIT_NORMAL

    def value(self, name: str, kind: str, timestamp: float | None = None) -> Any:
        """Current value of an output variable (caller holds the lock).

        timestamp: the controller time of the sample being packed (s); None for now.
        """
        simple = {
            "timestamp": lambda: self.timestamp() if timestamp is None else timestamp,
            "actual_q": lambda: self.q,
            "target_q": lambda: self.target_q,
            "actual_qd": lambda: self.qd,
            "target_qd": lambda: self.qd,
            "robot_mode": lambda: self.robot_mode,
            "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode,
            "safety_status_bits": self.safety_bits,
            "runtime_state": lambda: RUNTIME_PLAYING if self.program_running else RUNTIME_STOPPED,
            # bit 0 power on, bit 1 program running
            "robot_status_bits": lambda: 1 | (2 if self.program_running else 0),
            "speed_scaling": lambda: 1.0,
            "target_speed_fraction": lambda: 1.0,
            "joint_mode": lambda: [253] * 6,  # 253 = JOINT_RUNNING_MODE
            "elbow_position": lambda: elbow_position(self.q, self.robot_model),
            "actual_TCP_pose": lambda: tcp_pose(self.q, self.robot_model),
            "target_TCP_pose": lambda: tcp_pose(self.target_q, self.robot_model),
            "elbow_velocity": self._elbow_velocity,
            "input_bit_registers0_to_31": lambda: self.registers.get("input_bit_registers0_to_31", 0),
            "input_bit_registers32_to_63": lambda: self.registers.get("input_bit_registers32_to_63", 0),
        }
        if name in simple:
            return simple[name]()
        if name in self.registers:
            return self.registers[name]
        if name in _IDLE_OUTPUTS:
            return _IDLE_OUTPUTS[name]
        zero: Any = False if kind == "BOOL" else 0.0 if "d" in TYPE_FORMATS[kind] else 0
        return [zero] * _vector_size(kind) if _vector_size(kind) else zero

    def _elbow_velocity(self) -> list[float]:
        """Finite difference of the elbow position over 1 ms at the current joint speeds, m/s."""
        dt = 1e-3
        ahead = elbow_position([q + v * dt for q, v in zip(self.q, self.qd, strict=True)], self.robot_model)
        here = elbow_position(self.q, self.robot_model)
        return [(a - h) / dt for a, h in zip(ahead, here, strict=True)]


def control_period(controller_version: Sequence[int]) -> float:
    """The controller's control period, s: 2 ms on e-Series (PolyScope 5 and later), 8 ms on CB3 (3.x)."""
    return 0.008 if int(controller_version[0]) < 5 else 0.002


def output_decimation(frequency: float, tick: float) -> int:
    """Control periods between two output packages: the controller sends every floor(f_control / f)-th sample.

    >>> output_decimation(125.0, 0.002), output_decimation(500.0, 0.002), output_decimation(10.0, 0.008)
    (4, 1, 12)
    """
    if not frequency > 0:
        return round(1.0 / tick)  # nonsense frequency: 1 Hz
    return max(1, math.floor(1.0 / (tick * frequency) + 1e-9))


def paced(
    period: float,
    start: float,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    max_lag: float = 0.25,
) -> Iterator[float]:
    """Yield the deadlines start + n * period (s, on ``clock``), each once it is due, sleeping until then.

    Absolute deadlines: a late wake-up delays one package, never the ones after it (sleeping one period after
    each package drifts by the overshoot: 119 packages/s for 125 Hz). Late by less than ``max_lag``, the
    overdue deadlines follow at once; later than that (a stalled process), it skips to the latest due one, as
    the controller drops the packages it could not send.
    """
    n = 0
    while True:
        deadline = start + n * period
        now = clock()
        if now - deadline > max_lag:
            n = math.floor((now - start) / period + 1e-9)
            deadline = start + n * period
        elif deadline > now:
            sleep(deadline - now)
        yield deadline
        n += 1


class _RTDESession:
    """One client connection on port 30004.

    Protocol version 1 until the client negotiates 2: in version 1 the output setup carries no frequency (the
    controller streams at 125 Hz) and neither its answer nor the data packages carry a recipe id. The
    controller keeps one output recipe per client: a later output setup replaces the earlier one, so only the
    recipe the client set up last is streamed, under its own id. Input fields belong to the first client whose
    recipe names them until it disconnects; another client's recipe naming one gets ``IN_USE`` (and id 0). One
    client may name a field in several of its own input recipes (ur-rtde's control interface does).
    """

    def __init__(self, sock: socket.socket, sim: SimController, unknown: Sequence[str] = ()):
        self.sock = sock
        self.unknown = set(unknown)  # names answered NOT_FOUND, like an older PolyScope
        self.sim = sim
        self.send_lock = threading.Lock()
        self.protocol = 1
        self.tick = control_period(sim.controller_version)
        self.output: tuple[int, float, list[str], list[str]] | None = None  # recipe id, Hz, names, types
        self.output_setups = 0
        self.inputs: dict[int, tuple[list[str], list[str]]] = {}
        self.streaming = threading.Event()
        self.closed = threading.Event()

    def send(self, kind: str, payload: bytes = b"") -> None:
        with self.send_lock:
            self.sock.sendall(pack_package(kind, payload))

    def gone(self) -> bool:
        """Whether the client has closed the connection (a peek: the reader thread may not have seen it yet).

        A client killed and restarted (a reconnecting driver) must get its input fields back at once, as a real
        controller, which learns of the close from the kernel, gives them."""
        if self.closed.is_set():
            return True
        try:
            return self.sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except BlockingIOError:
            return False  # open, nothing to read
        except OSError:
            return True  # reset or closed

    def run(self) -> None:
        threading.Thread(target=self._stream, daemon=True).start()
        try:
            while True:
                kind, payload = read_package(self.sock)
                self._handle(kind, payload)
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            self.closed.set()
            self.streaming.clear()
            with self.sim.lock:  # a client that went away frees its input fields
                for name in [n for n, owner in self.sim.input_owners.items() if owner is self]:
                    del self.sim.input_owners[name]
            with contextlib.suppress(OSError):
                self.sock.close()

    def _handle(self, kind: str, payload: bytes) -> None:
        if kind == "V":
            (version,) = struct.unpack(">H", payload)
            accepted = version in (1, 2)
            if accepted:
                self.protocol = version
            self.send("V", struct.pack(">?", accepted))
        elif kind == "v":
            self.send("v", struct.pack(">4I", *self.sim.controller_version))
        elif kind == "O":
            self._setup_outputs(payload)
        elif kind == "I":
            self._setup_inputs(payload)
        elif kind == "S":
            self.send("S", struct.pack(">?", self.output is not None or bool(self.inputs)))
            if self.output is not None:
                self.streaming.set()
        elif kind == "P":
            with self.send_lock:  # no data package may follow the pause answer
                self.streaming.clear()
                self.sock.sendall(pack_package("P", struct.pack(">?", True)))
        elif kind == "U":
            recipe = payload[0]
            if recipe in self.inputs:  # the emulated program polls the registers every control tick
                names, types = self.inputs[recipe]
                values = unpack_values(types, payload[1:])
                with self.sim.lock:
                    self.sim.registers.update(zip(names, values, strict=True))
        else:
            text = f"fake controller: unsupported package type {kind!r}".encode("ascii")
            # 'M' text message, level 1 = error. Version 2: uint8 length, text, uint8 source length, source, level;
            # version 1: level, text.
            if self.protocol >= 2:
                self.send("M", struct.pack(">B", len(text)) + text + b"\x04fake\x01")
            else:
                self.send("M", b"\x01" + text)

    def _setup_outputs(self, payload: bytes) -> None:
        if self.protocol >= 2:
            (frequency,) = struct.unpack(">d", payload[:8])
            payload = payload[8:]
        else:
            frequency = 125.0
        names = [n for n in payload.decode("ascii").split(",") if n]
        types = [("NOT_FOUND" if n in self.unknown else rtde_type(n)) or "NOT_FOUND" for n in names]
        self._log_not_found("O", names, types)
        recipe = 0
        if names and "NOT_FOUND" not in types:
            self.output_setups += 1
            recipe = self.output_setups
            self.output = (recipe, float(frequency), names, types)
        with self.sim.lock:
            self.sim.log.append(("setup_outputs", {"recipe": recipe, "names": names, "protocol": self.protocol}))
        answer = ",".join(types).encode("ascii")
        self.send("O", (struct.pack(">B", recipe) + answer) if self.protocol >= 2 else answer)

    def _setup_inputs(self, payload: bytes) -> None:
        names = [n for n in payload.decode("ascii").split(",") if n]
        with self.sim.lock:
            types = []
            for name in names:
                owner = self.sim.input_owners.get(name)
                if isinstance(owner, _RTDESession) and owner is not self and owner.gone():
                    del self.sim.input_owners[name]  # closed, but its reader thread has not noticed yet
                    owner = None
                kind = rtde_type(name, "input")
                types.append("NOT_FOUND" if kind is None else "IN_USE" if owner not in (None, self) else kind)
            recipe = 0 if not names or {"NOT_FOUND", "IN_USE"} & set(types) else len(self.inputs) + 1
            if recipe:
                self.sim.input_owners.update(dict.fromkeys(names, self))
                self.inputs[recipe] = (names, types)
            taken = [n for n, t in zip(names, types, strict=True) if t == "IN_USE"]
            if taken:
                self.sim.log.append(("in_use", {"names": taken}))
        self._log_not_found("I", names, types)
        self.send("I", struct.pack(">B", recipe) + ",".join(types).encode("ascii"))

    def _log_not_found(self, kind: str, names: list[str], types: list[str]) -> None:
        missing = [n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND"]
        if missing:
            with self.sim.lock:
                self.sim.log.append(("not_found", {"recipe": kind, "names": missing}))

    def _stream(self) -> None:
        while not self.closed.is_set():
            output = self.output
            if not self.streaming.wait(0.05) or output is None:
                continue
            recipe, frequency, names, types = output
            period = self.tick * output_decimation(frequency, self.tick)
            with self.sim.lock:
                t0 = self.sim.t0
            # first package on the next control tick; the stamps are control ticks, so they step by one period
            start = t0 + math.ceil((time.monotonic() - t0) / self.tick) * self.tick
            for deadline in paced(period, start):
                if self.closed.is_set() or not self.streaming.is_set() or self.output is not output:
                    break  # paused, gone, or a new recipe: start a new schedule
                with self.sim.lock:
                    if self.sim.frozen_at is not None:
                        stamp = self.sim.frozen_at
                    else:
                        stamp = round((deadline - self.sim.t0) / self.tick) * self.tick
                    values = [self.sim.value(n, k, stamp) for n, k in zip(names, types, strict=True)]
                body = pack_values(types, values)
                package = pack_package("U", (struct.pack(">B", recipe) + body) if self.protocol >= 2 else body)
                try:
                    with self.send_lock:
                        if self.streaming.is_set():
                            self.sock.sendall(package)
                except OSError:
                    return


class ControlEmulator:
    """What ur-rtde 1.6.5's RTDEControlInterface needs from a controller, on top of RTDE.

    - Dashboard server (29999): a greeting line, then one answer line per command line.
    - Script port (30003): streams a few bytes on connect (like the real-time interface); an uploaded script
      containing ur-rtde's control loop marker "starts the program".
    - The program: ur-rtde's register protocol. input_int_register_0 holds a command id (1 MOVEJ, 34 STOPJ,
      255 stop script; 0 idle); input_int_register_1 = 1 for asynchronous moves; input_double_register_0..5
      the target q (rad), 6 the speed (rad/s), 7 the acceleration (rad/s²). output_int_register_0 answers 1
      (ready, when the command is 0) or 2 (done with the command).

    Moves are linear in joint space at the commanded speed of the leading axis (acceleration ignored), in real
    time. A protective/emergency stop set while moving halts the joints where they are and stops the program,
    as a real controller does. ``fault`` = ("protective", fraction) triggers that stop part-way into the next move.
    """

    MOVEJ, STOPJ, STOP_SCRIPT = 1, 34, 255
    TICK = 0.002  # s, the e-Series control period

    def __init__(self, sim: SimController):
        self.sim = sim
        self.fault: tuple[str, float] | None = None
        self._abort = threading.Event()

    def _reg(self, name: str, default: Any = 0) -> Any:
        return self.sim.registers.get(name, default)

    def _start_program(self) -> None:
        with self.sim.lock:
            if self.sim.program_running:
                return
            self.sim.program_running = True
            self.sim.registers["output_int_register_0"] = 1
            self.sim.log.append(("program", "started"))
        threading.Thread(target=self._run_program, daemon=True).start()

    def _run_program(self) -> None:
        executing = False
        while True:
            with self.sim.lock:
                if not self.sim.program_running:
                    return
                cmd = int(self._reg("input_int_register_0"))
                if cmd == 0:
                    executing = False
                    self.sim.registers["output_int_register_0"] = 1
            if cmd != 0 and not executing:
                executing = True
                keep_running = self._process(cmd)
                with self.sim.lock:
                    if not keep_running:
                        self.sim.program_running = False
                        self.sim.log.append(("program", "stopped"))
                        return
                    if self.sim.program_running:
                        self.sim.registers["output_int_register_0"] = 2
            time.sleep(self.TICK)

    def _process(self, cmd: int) -> bool:
        """Run one command of the register protocol; False when it ends the program."""
        with self.sim.lock:
            self.sim.log.append(("command", cmd))
            if cmd not in (self.MOVEJ, self.STOPJ, self.STOP_SCRIPT):
                self.sim.log.append(("unsupported", cmd))
            if cmd == self.MOVEJ:
                goal = [float(self._reg(f"input_double_register_{i}", 0.0)) for i in range(6)]
                speed = float(self._reg("input_double_register_6", 0.0))
                asynchronous = int(self._reg("input_int_register_1")) == 1
                self.sim.log.append(("movej", {"q": goal, "speed": speed, "async": asynchronous}))
        if cmd == self.MOVEJ:
            self._abort.clear()
            if asynchronous:
                threading.Thread(target=self._move, args=(goal, speed), daemon=True).start()
            else:
                self._move(goal, speed)
            return True
        if cmd == self.STOPJ:
            self._abort.set()
            return True
        return cmd != self.STOP_SCRIPT  # an unsupported command is logged and ignored

    def _move(self, goal: list[float], speed: float) -> None:
        with self.sim.lock:
            start = list(self.sim.q)
            self.sim.target_q = list(goal)
            fault, self.fault = self.fault, None
        distance = max(abs(g - s) for g, s in zip(goal, start, strict=True))
        duration = min(distance / speed, 30.0) if speed > 0 else 0.0
        t0 = time.monotonic()
        while True:
            fraction = 1.0 if duration <= 0 else min((time.monotonic() - t0) / duration, 1.0)
            with self.sim.lock:
                if fault is not None and fraction >= fault[1]:
                    setattr(self.sim, fault[0], True)  # the flag named by the fault: "protective" or "emergency"
                if self.sim.protective or self.sim.emergency:
                    self.sim.program_running = False  # a safety stop halts the program where it is
                    self.sim.log.append(("program", "halted by safety stop"))
                    return
                if self._abort.is_set():
                    return
                self.sim.q = [s + (g - s) * fraction for s, g in zip(start, goal, strict=True)]
                self.sim.qd = [
                    (g - s) / duration if 0 < fraction < 1 else 0.0 for s, g in zip(start, goal, strict=True)
                ]
            if fraction >= 1.0:
                return
            time.sleep(self.TICK)

    def serve_dashboard(self, sock: socket.socket) -> None:
        with contextlib.closing(sock), sock.makefile("rwb") as stream:
            stream.write(b"Connected: Universal Robots Dashboard Server\n")
            stream.flush()
            for raw in stream:
                line = raw.decode("ascii", "replace").strip()
                with self.sim.lock:
                    self.sim.log.append(("dashboard", line))
                    answer = self.dashboard_answer(line)
                stream.write(answer.encode("ascii") + b"\n")
                stream.flush()

    def dashboard_answer(self, line: str) -> str:
        """The dashboard server's reply to one command line (caller holds the sim lock)."""
        sim = self.sim
        if line == "unlock protective stop":
            sim.protective = False
        elif line == "stop":
            sim.program_running = False
        safety = "ROBOT_EMERGENCY_STOP" if sim.emergency else "PROTECTIVE_STOP" if sim.protective else "NORMAL"
        answers = {
            "PolyscopeVersion": "URSoftware {}.{}.{}.{} (fake)".format(*sim.controller_version),
            "get serial number": sim.serial,  # None: a controller too old to know the command
            "get robot model": sim.robot_model,
            "is in remote control": "true",
            "robotmode": "Robotmode: RUNNING"
            if sim.robot_mode == ROBOT_MODE_RUNNING
            else f"Robotmode: {sim.robot_mode}",
            "safetystatus": f"Safetystatus: {safety}",
            "safetymode": f"Safetystatus: {safety}",
            "running": f"Program running: {str(sim.program_running).lower()}",
            "programState": "PLAYING" if sim.program_running else "STOPPED",
            "unlock protective stop": "Protective stop releasing",
            "close safety popup": "closing safety popup",
            "stop": "Stopped",
            "play": "Failed to execute: play",  # no .urp programs here: ur-rtde uploads its script instead
        }
        answer = answers.get(line)
        return f"could not understand: '{line}'" if answer is None else answer

    def serve_script(self, sock: socket.socket) -> None:
        with contextlib.closing(sock):
            sock.sendall(struct.pack(">IB", 5, 16))  # a minimal packet: the real port streams state at once
            data = b""
            while True:
                try:
                    chunk = sock.recv(65536)
                except OSError:
                    break
                if not chunk:
                    break
                data += chunk
                if b"# NODE_CONTROL_LOOP_ENDS" in data and data.rstrip().endswith(b"end"):
                    with self.sim.lock:
                        self.sim.log.append(("script", len(data)))
                    self._start_program()
                    data = b""


def _listen(host: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    # SO_REUSEADDR lets a new fake reuse an address whose old connections sit in TIME_WAIT; Linux still refuses
    # the bind while another socket is listening there, which is what tells the fakes apart.
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
        sock.listen(8)
    except OSError:
        sock.close()
        raise
    return sock


def _accept_loop(listener: socket.socket, handler: Any) -> None:
    while True:
        try:
            conn, _ = listener.accept()
        except OSError:
            return
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=handler, args=(conn,), daemon=True).start()


def candidate_hosts(start: int, count: int = 400) -> list[str]:
    """Loopback addresses 127.0.x.y (x, y in 1..254, skipping 127.0.0.1) beginning at index ``start``."""
    indices = ((start + i) % (254 * 254) for i in range(count))
    hosts = (f"127.0.{k // 254}.{k % 254 + 1}" for k in indices)
    return [host for host in hosts if host != "127.0.0.1"]


def _child_main(options: dict[str, Any], commands: Any, replies: Any) -> None:
    """Body of the fake's process: bind, report the host, then serve until stdin closes (see
    :func:`labcal.drivers.ur_process.serve`). commands/replies: text streams of JSON lines (stdin and stdout)."""
    sim = SimController(options["q0"], options["controller_version"])
    sim.serial, sim.robot_model = options.get("serial", sim.serial), options.get("robot_model", sim.robot_model)
    ports = [RTDE_PORT] + ([DASHBOARD_PORT, SCRIPT_PORT] if options["control"] else [])
    listeners: dict[int, socket.socket] = {}
    sessions: list[_RTDESession] = []

    def start() -> tuple[Callable[..., Any], str]:
        for host in options["hosts"]:
            try:
                for port in ports:
                    listeners[port] = _listen(host, port)
                break
            except OSError:
                for sock in listeners.values():
                    sock.close()
                listeners.clear()
        else:
            raise RuntimeError(
                f"fake RTDE server failed to start: no free loopback address among {len(options['hosts'])} candidates"
            )
        control = ControlEmulator(sim) if options["control"] else None

        def serve_rtde(sock: socket.socket) -> None:
            session = _RTDESession(sock, sim, options["unknown_variables"])
            sessions.append(session)
            session.run()

        threading.Thread(target=_accept_loop, args=(listeners[RTDE_PORT], serve_rtde), daemon=True).start()
        if control is not None:
            for port, handler in ((DASHBOARD_PORT, control.serve_dashboard), (SCRIPT_PORT, control.serve_script)):
                threading.Thread(target=_accept_loop, args=(listeners[port], handler), daemon=True).start()
        return (lambda command, args=None: _apply(sim, sessions, control, command, args)), host

    serve(start, commands, replies)  # until stdin closes: stop() closes it, and so does the parent's end
    for sock in listeners.values():
        with contextlib.suppress(OSError):
            sock.close()
    for session in sessions:
        with contextlib.suppress(OSError):
            session.sock.shutdown(socket.SHUT_RDWR)


def _apply(
    sim: SimController, sessions: list[_RTDESession], control: ControlEmulator | None, command: str, args: Any
) -> Any:
    with sim.lock:
        if command == "set_q":
            if len(args) != 6:
                raise ValueError(f"q needs 6 values, got {len(args)}")
            sim.q = [float(v) for v in args]
            sim.target_q = list(sim.q)
        elif command == "set_safety":
            sim.protective, sim.emergency = bool(args[0]), bool(args[1])
        elif command == "set_robot_mode":
            sim.robot_mode = int(args)
        elif command == "freeze":
            if args and sim.frozen_at is None:
                sim.frozen_at = sim.timestamp()
            elif not args and sim.frozen_at is not None:
                # resume from the frozen value so controller time never runs backwards
                sim.t0 = time.monotonic() - sim.frozen_at
                sim.frozen_at = None
        elif command == "fault":
            if control is None:
                raise ValueError("faults need a fake started with control=True")
            control.fault = (str(args[0]), float(args[1]))
        elif command == "drop_clients":
            for session in sessions:
                with contextlib.suppress(OSError):
                    session.sock.shutdown(socket.SHUT_RDWR)
        elif command == "snapshot":
            return {
                "q": list(sim.q),
                "timestamp": sim.timestamp(),
                "registers": dict(sim.registers),
                "log": list(sim.log),
                "clients": sum(not s.closed.is_set() for s in sessions),
            }
        else:
            raise ValueError(f"unknown command {command!r}")
    return None


# --------------------------------------------------------------------------------------------------------------
# The handle used by tests (parent process).


class FakeRTDEServer:
    """Start a fake UR controller in a child process (``python -m labcal_fakes.rtde_fake``); a context manager.

    q0: (6,) initial joint positions, rad. control: also serve dashboard/script ports and emulate ur-rtde's
    control registers. controller_version: answered to ``v`` (major, minor, bugfix, build).
    unknown_variables: output names to answer NOT_FOUND (an older controller). serial / robot_model:
    the dashboard's answers to ``get serial number`` / ``get robot model`` (serial None: the controller does not
    understand the command, as PolyScope before 3.10/5.4).
    A plain subprocess (not multiprocessing) so scripts using the fake need no ``if __name__ == "__main__"``.
    """

    def __init__(
        self,
        q0: Sequence[float] = (0.0, -1.5708, 1.5708, 0.0, 1.5708, 0.0),
        *,
        control: bool = False,
        controller_version: Sequence[int] = (5, 11, 0, 0),
        unknown_variables: Sequence[str] = (),
        serial: str | None = "20185500001",
        robot_model: str = "UR10",
    ):
        if len(q0) != 6:
            raise ValueError(f"q0 needs 6 joint values, got {len(q0)}")
        self._options = {
            "q0": [float(v) for v in q0],
            "control": control,
            "controller_version": [int(v) for v in controller_version],
            "unknown_variables": list(unknown_variables),
            "serial": serial,
            "robot_model": robot_model,
            # Spread start addresses by pid so parallel test runs rarely try the same address first.
            "hosts": candidate_hosts((os.getpid() * 37) % 60000),
        }
        self._child: ChildProcess | None = None
        self.host = ""

    def __enter__(self) -> FakeRTDEServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        argv = [sys.executable, "-m", "labcal_fakes.rtde_fake", json.dumps(self._options)]
        # 20 s to start (binding may try many addresses on a loaded machine), 5 s per command
        self._child = ChildProcess(argv, "fake RTDE server", start_timeout=20.0, call_timeout=5.0, log_stderr=False)
        self.host = self._child.started

    def _call(self, command: str, *args: Any) -> Any:
        if self._child is None:
            raise RuntimeError("fake RTDE server is not running")
        return self._child.call(command, *args)

    def set_q(self, q: Sequence[float]) -> None:
        """Set the simulated actual (and target) joint positions, (6,) rad."""
        self._call("set_q", [float(v) for v in q])

    def set_safety(self, protective: bool = False, emergency: bool = False) -> None:
        """Set protective-stop / emergency-stop flags (safety mode and safety status bits follow)."""
        self._call("set_safety", [bool(protective), bool(emergency)])

    def set_robot_mode(self, mode: int) -> None:
        """Set the robot mode reported in ``robot_mode`` (7 = RUNNING)."""
        self._call("set_robot_mode", int(mode))

    def freeze_timestamp(self, frozen: bool = True) -> None:
        """Keep streaming packages, but with a timestamp (and data time) that no longer advances."""
        self._call("freeze", bool(frozen))

    def inject_stop_during_next_move(self, kind: str = "protective", fraction: float = 0.5) -> None:
        """control=True only: the next MOVEJ hits a protective (or "emergency") stop ``fraction`` of the way."""
        if kind not in ("protective", "emergency") or not 0 <= fraction <= 1:
            raise ValueError(f"kind must be 'protective' or 'emergency' and fraction in [0, 1], got {kind}, {fraction}")
        self._call("fault", [kind, float(fraction)])

    def drop_clients(self) -> None:
        """Shut down every client connection (the server keeps listening)."""
        self._call("drop_clients")

    def snapshot(self) -> dict[str, Any]:
        """q, timestamp, RTDE registers, control log and number of connected RTDE clients."""
        return self._call("snapshot")

    def kill(self) -> None:
        """Kill the process abruptly (the kernel closes its sockets): a controller that died. Safe to repeat."""
        child, self._child = self._child, None
        if child is not None:
            child.kill()

    def stop(self) -> None:
        """Stop the process politely (closing its stdin), killing it if it does not exit in time. Safe to call twice."""
        if self._child is not None:
            self._child.end(3.0)
        self.kill()

    @property
    def alive(self) -> bool:
        return self._child is not None and self._child.alive


if __name__ == "__main__":
    # Ctrl-C in a terminal reaches the whole process group; the owner of the fake stops it (closing stdin), as the
    # UR interfaces' children leave stopping to labcal.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _child_main(json.loads(sys.argv[1]), sys.stdin, sys.stdout)
