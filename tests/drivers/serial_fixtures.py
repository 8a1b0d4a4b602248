"""Shared helpers for the serial tracker tests (imported by tests/drivers/test_serial_*, test_ndi*, ...).

Expected wire bytes are written out here once. The NDI command constants are checked against what the real
``ndicapy`` client sends in test_ndi_ndicapy.py, and the CRC below is an independent bit-by-bit implementation,
so the byte-exact tests do not just compare the driver with itself.
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any

import numpy as np
from scripted_transport import ScriptedTransport

from labcal.drivers.serial.profiles import NDIProfile, PortSettings, parse_profile
from labcal.drivers.serial.tracker import SerialTracker

# Targets in the tool frame (m): a clearly scalene triangle, sides 100 mm, 70 mm, ~122.07 mm.
TARGETS = np.array([[0.0, 0.0, 0.0], [0.100, 0.0, 0.0], [0.0, 0.070, 0.0]])

# NDI commands exactly as the Combined API wants them (CRC16 in hex, CR).
INIT = b"INIT:E3A5\r"
COMM_115200 = b"COMM:500000048\r"
TSTART = b"TSTART:5423\r"
TX = b"TX:10003FDA\r"
BX = b"BX:1000FEAD\r"
TSTOP = b"TSTOP:2C14\r"
COMM_9600 = b"COMM:000000084\r"
OKAY = b"OKAYA896\r"
RESET = b"RESETBE6F\r"


def crc16_arc_bitwise(data: bytes) -> int:
    """CRC-16/ARC the slow way: reflected polynomial 0xA001, init 0, one bit at a time."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xA001 if crc & 1 else 0)
    return crc


def ndi_reply(body: str) -> bytes:
    """A device reply: body + CRC16 (4 uppercase hex) + CR."""
    data = body.encode("ascii")
    return data + f"{crc16_arc_bitwise(data):04X}\r".encode("ascii")


def coord(value_m: float) -> str:
    """One TX coordinate: sign + 6 digits, units of 0.01 mm."""
    hundredths = round(value_m * 1e5)
    return ("+" if hundredths >= 0 else "-") + f"{abs(hundredths):06d}"


def tx_body(strays: np.ndarray, oov_flags: str | None = None, status: str = "0000") -> str:
    """A TX:1000 body with no tool handles and the given strays (N, 3) m."""
    strays = np.asarray(strays, dtype=float).reshape(-1, 3)
    n = len(strays)
    flags = oov_flags if oov_flags is not None else "0" * (-(-n // 4))
    return "00" + f"{n:02X}" + flags + "".join(coord(v) for v in strays.ravel()) + status


def bx_frame(body: bytes) -> bytes:
    """Wrap a BX body in its binary framing: C4 A5, uint16 LE length, header CRC, body, body CRC (LE)."""
    header = bytes([0xC4, 0xA5, len(body) & 0xFF, len(body) >> 8])
    return (
        header + crc16_arc_bitwise(header).to_bytes(2, "little") + body + crc16_arc_bitwise(body).to_bytes(2, "little")
    )


def bx_body(
    strays: np.ndarray, oov: list[bool] | None = None, status: int = 0, handles: tuple[tuple[int, int], ...] = ()
) -> bytes:
    """A BX:1000 body: handles (id, status), strays (N, 3) m as float32 mm, out-of-volume bits, status."""
    strays = np.asarray(strays, dtype=float).reshape(-1, 3)
    n = len(strays)
    flags = bytearray(-(-n // 8))
    for j, out in enumerate(oov or []):
        if out:
            flags[j // 8] |= 1 << (j % 8)
    body = bytes([len(handles)]) + b"".join(struct.pack("<BB", h, st) for h, st in handles)
    body += bytes([n]) + bytes(flags)
    for x, y, z in strays:
        body += struct.pack("<fff", x * 1000.0, y * 1000.0, z * 1000.0)
    return body + struct.pack("<H", status)


def bx_reply(strays: np.ndarray, **kw: Any) -> bytes:
    """A whole binary reply to BX:1000 (see ``bx_body`` for the keywords)."""
    return bx_frame(bx_body(strays, **kw))


def tool_to_tracker(targets: np.ndarray = TARGETS) -> np.ndarray:
    """The targets seen by a tracker 1.5 m away, rotated about z by 30 degrees (m)."""
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return targets @ R.T + np.array([0.05, -0.02, -1.5])


def ndi_profile(**overrides: Any) -> NDIProfile:
    base = NDIProfile(name="test", port=PortSettings(url=None, timeout=0.2), switch_delay=0.1, init_timeout=1.0)
    return dataclasses.replace(base, **overrides)


OPEN_NDI = [(INIT, OKAY), (COMM_115200, OKAY), (TSTART, OKAY)]
CLOSE_NDI = [(TSTOP, OKAY), (COMM_9600, OKAY)]


def scripted_ndi(script: list[tuple[bytes, bytes]], **profile: Any) -> tuple[SerialTracker, ScriptedTransport]:
    """An NDI SerialTracker on a scripted transport (the script must include the opening exchanges)."""
    t = ScriptedTransport(script)
    tracker = SerialTracker(ndi_profile(**profile), TARGETS, transport=t, clock=t.clock, sleep=t.sleep)
    return tracker, t


ASCII_PROFILE: dict[str, Any] = {
    "protocol": "ascii",
    "name": "scripted ascii",
    "port": {"timeout": 0.2},
    "ascii": {
        "write_terminator": "\n",
        "read_terminator": "\n",
        "mode": "poll",
        "measure_command": "M",
        "reply": (
            r"P (?P<t1_x>\S*) (?P<t1_y>\S*) (?P<t1_z>\S*) (?P<t2_x>\S*) (?P<t2_y>\S*) (?P<t2_z>\S*)"
            r" (?P<t3_x>\S*) (?P<t3_y>\S*) (?P<t3_z>\S*)"
        ),
        "error_reply": r"E(?P<code>\d+)",
        "length_unit": "m",
        "retries": 1,
    },
}


def ascii_profile(**ascii_overrides: Any):
    data = {**ASCII_PROFILE, "ascii": {**ASCII_PROFILE["ascii"], **ascii_overrides}}
    return parse_profile(data, "test-ascii")


def ascii_line(points_m: np.ndarray, scale: float = 1.0) -> bytes:
    """'P x1 y1 z1 ... z3\\n' with coordinates divided by ``scale`` (device unit in m)."""
    values = np.asarray(points_m, dtype=float).ravel() / scale
    return ("P " + " ".join(f"{v:.6f}" for v in values) + "\n").encode("ascii")
