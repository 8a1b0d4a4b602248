"""NDI Combined API (Polaris family optical trackers) tracking passive stray markers.

Commands are ASCII ``CMD:params`` followed by the CRC-16/ARC of everything before it (4 uppercase hex) and CR;
replies are a body, the CRC of the body and CR. The session is ``INIT:`` (at 9600 8N1) -> ``COMM:`` (faster
rate, the host follows after a short delay) -> ``TSTART:`` -> ``TX:1000`` per frame -> ``TSTOP:`` ->
``COMM:00000`` (back to 9600, where the next session starts). After a serial break the device resets to
9600 8N1 and answers ``RESETBE6F``.

A ``TX:1000`` body (reply option 0x1000, passive stray markers) is::

    HH                      number of port handles (labcal loads no tools: 00; any handle blocks are skipped)
    NN                      number of strays N, hex
    F...F                   ceil(N/4) hex chars of out-of-volume flags (bit i, counted from the least
                            significant bit of the whole field, is stray i)
    N x (±dddddd ±dddddd ±dddddd)   X, Y, Z in units of 0.01 mm
    SSSS                    system status, hex

``BX:1000`` asks for the same data as a binary reply (profile option ``reply = "bx"``); it has no CR and every
field is little-endian::

    C4 A5                   start sequence 0xA5C4
    uint16 N                body length (the whole reply is N + 8 bytes)
    uint16                  CRC-16/ARC of the four bytes above
    body (N bytes):
        uint8 H                 number of port handles, then H x (uint8 handle, uint8 status); option 0x1000
                                alone adds no per-handle data
        uint8 M                 number of strays
        ceil(M/8) bytes         out-of-volume bits (bit j of the byte stream, LSB first, is stray j)
        M x float32 x, y, z     millimetres
        uint16                  system status
    uint16                  CRC-16/ARC of the body

Errors (``ERRORxx``) and ``RESETBE6F`` stay ASCII lines in binary mode.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from labcal.drivers.base import ConnectionFailed, DriverTimeout, MeasurementRejected, ProtocolError, average_frames
from labcal.drivers.serial.crc import crc16_arc
from labcal.drivers.serial.link import SerialLink, retried
from labcal.drivers.serial.matching import match_targets
from labcal.drivers.serial.profiles import NDI_BAUD_CODES, NDIProfile

# Meanings of ERRORxx codes (NDI Combined API); unknown codes are reported by number.
ERROR_CODES = {
    0x01: "Invalid command",
    0x02: "Command too long",
    0x03: "Command too short",
    0x04: "Invalid CRC calculated for command",
    0x05: "Time-out on command execution",
    0x06: "Unable to set up new communication parameters",
    0x07: "Incorrect number of command parameters",
    0x08: "Invalid port handle selected",
    0x09: "Invalid tracking priority selected",
    0x0A: "Invalid LED selected",
    0x0B: "Invalid LED state selected",
    0x0C: "Command is invalid while in the current mode",
    0x0D: "No tool assigned to the selected port handle",
    0x0E: "Selected port handle not initialized",
    0x0F: "Selected port handle not enabled",
    0x10: "System not initialized",
    0x11: "Unable to stop tracking",
    0x12: "Unable to start tracking",
    0x13: "Unable to initialize Tool-in-Port",
    0x14: "Invalid Position Sensor or Field Generator characterization parameters",
    0x15: "Unable to initialize the Measurement System",
    0x16: "Unable to start diagnostic mode",
    0x17: "Unable to stop diagnostic mode",
}

RESET_REPLY = b"RESETBE6F"
STRAY_CHARS = 21  # three coordinates of sign + 6 digits

BX_START = b"\xc4\xa5"  # 0xA5C4, little-endian like every binary field
BX_HEADER_SIZE = 6  # start sequence, body length, header CRC
BX_STRAY_SIZE = 12  # three float32

T = TypeVar("T")


class NDIError(ProtocolError):
    """The device answered ERRORxx. ``code`` is the int error code, ``meaning`` its description."""

    def __init__(self, command: str, code: int):
        self.command = command
        self.code = code
        self.meaning = ERROR_CODES.get(code, "unknown error code")
        super().__init__(f"{command!r} failed: ERROR{code:02X} ({self.meaning})")


class DeviceReset(ProtocolError):
    """The device sent RESETBE6F instead of a reply: it power-cycled or was reset and lost its state."""


def encode_command(command: str) -> bytes:
    """Bytes to send for ``command``: colon form gets its CRC, space form goes as is; CR terminated.

    >>> encode_command("INIT:")
    b'INIT:E3A5\\r'
    """
    data = command.encode("ascii")
    if ":" in command:
        data += f"{crc16_arc(data):04X}".encode("ascii")
    return data + b"\r"


def decode_reply(line: bytes, command: str = "") -> str:
    """Check the CRC of one reply line (without CR) and return its body. ERRORxx raises NDIError, RESETBE6F
    DeviceReset."""
    if line == RESET_REPLY:
        raise DeviceReset(f"device reset (RESETBE6F) while waiting for the reply to {command!r}")
    if len(line) < 5:
        raise ProtocolError(f"reply to {command!r} too short for a body and CRC: {line!r}")
    body, crc_text = line[:-4], line[-4:]
    try:
        text = body.decode("ascii")
        crc = int(crc_text.decode("ascii"), 16)
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError(f"garbled reply to {command!r}: {line!r}") from exc
    if crc != crc16_arc(body):
        raise ProtocolError(f"bad CRC in reply to {command!r}: got {crc:04X}, body gives {crc16_arc(body):04X}")
    if text.startswith("ERROR"):
        try:
            code = int(text[5:7], 16)
        except ValueError as exc:
            raise ProtocolError(f"garbled error reply to {command!r}: {text!r}") from exc
        raise NDIError(command, code)
    return text


@dataclass(frozen=True)
class StrayFrame:
    """A parsed TX:1000 or BX:1000 body. strays: (N, 3) m; out_of_volume: (N,) bool; system_status: int flags."""

    strays: np.ndarray
    out_of_volume: np.ndarray
    system_status: int


def _hex(body: str, start: int, width: int, what: str) -> tuple[int, int]:
    """The hex field of ``width`` chars at ``start`` and where the next field starts."""
    field = body[start : start + width]
    if len(field) != width or any(c not in "0123456789ABCDEFabcdef" for c in field):
        raise ProtocolError(f"TX reply: {what} at char {start} is not {width} hex digits: {field!r}")
    return int(field, 16), start + width


def _coordinate(body: str, start: int) -> float:
    field = body[start : start + 7]
    if len(field) != 7 or field[0] not in "+-" or not field[1:].isdigit():
        raise ProtocolError(f"TX reply: coordinate at char {start} is not sign + 6 digits: {field!r}")
    return int(field) * 1e-5  # 0.01 mm -> m


def parse_tx_strays(body: str) -> StrayFrame:
    """Parse a ``TX:1000`` reply body (CRC already removed). Raises ProtocolError on any malformation."""
    handles, pos = _hex(body, 0, 2, "handle count")
    for k in range(handles):  # tool blocks are not used by labcal; each ends with a line feed
        end = body.find("\n", pos)
        if end < 0:
            raise ProtocolError(f"TX reply: handle block {k + 1} of {handles} has no line feed")
        pos = end + 1
    n, pos = _hex(body, pos, 2, "stray count")
    n_flags = math.ceil(n / 4)
    flags, pos = _hex(body, pos, n_flags, "out-of-volume flags") if n_flags else (0, pos)
    expected = pos + n * STRAY_CHARS + 4
    if len(body) != expected:
        raise ProtocolError(f"TX reply with {n} strays should be {expected} chars, got {len(body)}: {body!r}")
    strays = np.array([_coordinate(body, pos + 7 * j) for j in range(3 * n)], dtype=float).reshape(n, 3)
    status, _ = _hex(body, expected - 4, 4, "system status")
    oov = np.array([bool(flags >> i & 1) for i in range(n)], dtype=bool)
    return StrayFrame(strays=strays, out_of_volume=oov, system_status=status)


def bx_body_length(header: bytes, command: str = "BX:1000") -> int:
    """Check the 6-byte header of a binary reply (start sequence, header CRC); return the body length N.

    The header is checked on its own so a reader knows how many more bytes to wait for, and never waits for a
    length it cannot trust.
    """
    if len(header) < BX_HEADER_SIZE:
        raise ProtocolError(f"BX reply to {command!r} truncated: {len(header)} bytes, shorter than its header")
    if header[:2] != BX_START:
        raise ProtocolError(
            f"BX reply to {command!r}: bad start sequence {header[:2].hex(' ').upper()}, expected C4 A5"
        )
    length, crc = struct.unpack_from("<HH", header, 2)
    expected = crc16_arc(header[:4])
    if crc != expected:
        raise ProtocolError(f"BX reply to {command!r}: bad header CRC: got {crc:04X}, header gives {expected:04X}")
    return int(length)


def split_bx_reply(reply: bytes, command: str = "BX:1000") -> bytes:
    """Check the framing of one whole binary reply (header, length, body CRC) and return its body.

    An ASCII ``ERRORxx`` reply (CR optional) raises NDIError, as through ``decode_reply``.
    """
    if reply.startswith(b"ERROR"):
        decode_reply(reply.removesuffix(b"\r"), command)  # raises NDIError, or ProtocolError on a bad CRC
    n = bx_body_length(reply[:BX_HEADER_SIZE], command)
    if len(reply) != BX_HEADER_SIZE + n + 2:
        raise ProtocolError(
            f"BX reply to {command!r}: length mismatch: header announces {n} body bytes ({n + 8} in all), "
            f"got {len(reply)}"
        )
    body = reply[BX_HEADER_SIZE : BX_HEADER_SIZE + n]
    (crc,) = struct.unpack_from("<H", reply, BX_HEADER_SIZE + n)
    if crc != crc16_arc(body):
        raise ProtocolError(f"BX reply to {command!r}: bad body CRC: got {crc:04X}, body gives {crc16_arc(body):04X}")
    return body


def _take(body: bytes, pos: int, size: int, what: str) -> tuple[bytes, int]:
    """The ``size`` bytes at ``pos`` and where the next field starts."""
    if pos + size > len(body):
        raise ProtocolError(
            f"BX reply body truncated: {what} needs bytes {pos} to {pos + size - 1}, the body has {len(body)}"
        )
    return body[pos : pos + size], pos + size


def parse_bx_body(body: bytes) -> StrayFrame:
    """Parse a ``BX:1000`` reply body (framing already checked by ``split_bx_reply``) into metres.

    Raises ProtocolError when the content does not fill the body exactly or a coordinate is NaN or infinite.
    """
    (handles,), pos = _take(body, 0, 1, "handle count")
    # Only option 0x1000 is requested, so every handle (disabled, missing or seen) is just id + status.
    _, pos = _take(body, pos, 2 * handles, f"{handles} handle id/status pair(s)")
    (m,), pos = _take(body, pos, 1, "stray count")
    flags, pos = _take(body, pos, math.ceil(m / 8), "out-of-volume bits")
    coords, pos = _take(body, pos, m * BX_STRAY_SIZE, f"{m} stray position(s)")
    status, pos = _take(body, pos, 2, "system status")
    if pos != len(body):
        raise ProtocolError(
            f"BX reply: length mismatch: body is {len(body)} bytes but its content ({m} strays) ends at byte {pos}"
        )
    mm = np.frombuffer(coords, dtype="<f4").astype(float).reshape(m, 3)
    finite = np.isfinite(mm).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise ProtocolError(f"BX reply: stray {i} has a non-finite coordinate: {tuple(mm[i].tolist())} mm")
    oov = np.array([bool(flags[j // 8] >> (j % 8) & 1) for j in range(m)], dtype=bool)
    return StrayFrame(strays=mm * 1e-3, out_of_volume=oov, system_status=int.from_bytes(status, "little"))


_VERSION_NUMBER = re.compile(r"(\d+(?:\.\d+)+)\s*$")


def parse_ver(text: str) -> dict[str, str]:
    """Serial number, model and firmware from a ``VER:4`` reply body (lines separated by LF).

    The reply is text: a first line naming the device, then ``Key: value`` lines, e.g.::

        Polaris Vega Control Firmware
        NDI S/N: P9-00384
        Freeze Tag: Polaris Vega 001.004

    gives {"model": "Polaris Vega", "serial": "P9-00384", "firmware": "001.004"}. A line labcal does not know is
    ignored; a field not found is simply absent.
    """
    lines = [line.strip() for line in text.replace("\r", "\n").split("\n") if line.strip()]
    identity: dict[str, str] = {}
    for line in lines:
        key, sep, value = line.partition(":")
        key, value = key.strip().lower(), value.strip()
        if not sep and line == lines[0]:  # the first line names the device
            model = re.sub(r"\s+(control\s+)?firmware$", "", line, flags=re.IGNORECASE).strip()
            if model:
                identity["model"] = model
        elif value and ("s/n" in key or "serial" in key):
            identity.setdefault("serial", value)
        elif value and ("freeze tag" in key or "firmware revision" in key):
            found = _VERSION_NUMBER.search(value)
            identity.setdefault("firmware", found.group(1) if found else value)
    return identity


class NDIProtocol:
    """The NDI session on a SerialLink: start (INIT, COMM, TSTART), read_strays (TX:1000 or BX:1000) and label them
    as the targets, stop (TSTOP)."""

    def __init__(self, profile: NDIProfile, targets: np.ndarray, link: SerialLink):
        self.profile = profile
        self.targets = np.asarray(targets, dtype=float)
        self.link = link
        self.tracking = False
        self.resets = 0  # hard resets (break) performed, for diagnostics

    # -- one exchange --------------------------------------------------------------------------------------

    def command(self, command: str, *, timeout: float | None = None, retries: int | None = None) -> str:
        """Send ``command`` and return the reply body; retry on timeouts, bad CRC, garbage and ERROR04."""
        return self._exchange(command, self._ascii_reply, timeout, retries)

    def _ascii_reply(self, command: str, timeout: float | None) -> str:
        return decode_reply(self.link.read_line(timeout), command)

    def _binary_reply(self, command: str, timeout: float | None) -> bytes:
        wait = self.link.timeout if timeout is None else timeout
        deadline = self.link.clock() + wait
        head = self.link.read_exact(BX_HEADER_SIZE, wait)
        if head[:5] in (b"ERROR", b"RESET"):
            # Errors and the reset announcement stay ASCII lines; both are longer than a binary header.
            line = head + self.link.read_line(max(deadline - self.link.clock(), 0.0))
            text = decode_reply(line, command)  # raises for ERRORxx, RESETBE6F and a bad CRC
            raise ProtocolError(f"expected a binary reply to {command!r}, got {text!r}")
        try:
            n = bx_body_length(head, command)
        except ProtocolError:
            self.link.drain()  # the rest of this reply has no length we can trust: let it go by
            raise
        try:
            rest = self.link.read_exact(n + 2, max(deadline - self.link.clock(), 0.0))
        except DriverTimeout as exc:
            raise DriverTimeout(f"truncated BX reply to {command!r} (header announces {n} body bytes): {exc}") from exc
        return split_bx_reply(head + rest, command)

    def _exchange(
        self, command: str, read: Callable[[str, float | None], T], timeout: float | None, retries: int | None
    ) -> T:
        def attempt() -> T:
            self.link.flush_input()
            self.link.write(encode_command(command))
            return read(command, timeout)

        def final(error: Exception) -> bool:  # a reset, or an ERRORxx other than a corrupted command (ERROR04)
            return isinstance(error, DeviceReset) or (isinstance(error, NDIError) and error.code != 0x04)

        return retried((self.profile.retries if retries is None else retries) + 1, attempt, final)

    def _expect_okay(self, command: str, **kw: float | int | None) -> None:
        body = self.command(command, **kw)  # type: ignore[arg-type]
        if body != "OKAY" and not body.startswith("WARNING"):
            raise ProtocolError(f"expected OKAY to {command!r}, got {body!r}")

    # -- session -------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Initialise (resetting with a break if the device does not answer INIT), switch baud, start tracking."""
        try:
            self._expect_okay("INIT:", timeout=self.profile.init_timeout, retries=0)
        except (DriverTimeout, ProtocolError):
            # A device left at another baud rate, or tracking, or mid-command, does not take INIT: reset it.
            if not self.profile.reset_on_failure:
                raise
            self.recover(hard=True)
        else:
            self._switch_baud_and_track()

    def _switch_baud_and_track(self) -> None:
        if self.profile.baudrate != 9600:
            code = NDI_BAUD_CODES[self.profile.baudrate]
            self._expect_okay(f"COMM:{code}000{int(self.profile.handshake)}")
            # The device changes rate after sending OKAY; follow once it has.
            self.link.sleep(self.profile.switch_delay)
            self.link.set_baudrate(self.profile.baudrate)
        self._expect_okay("TSTART:")
        self.tracking = True

    def recover(self, *, hard: bool) -> None:
        """Bring the device back to tracking: with a serial break first (hard: the device must answer RESETBE6F at
        9600, else ConnectionFailed) or, after a RESET it sent, without."""
        self.tracking = False
        self.link.set_baudrate(9600)
        if hard:
            self.resets += 1
            self.link.flush_input()
            self.link.send_break()
            try:
                line = self.link.read_line(self.profile.init_timeout)
            except DriverTimeout as exc:
                raise ConnectionFailed(f"no RESET reply after a serial break: {exc}") from exc
            if line != RESET_REPLY:
                raise ConnectionFailed(f"expected RESETBE6F after a serial break, got {line!r}")
        self._expect_okay("INIT:", timeout=self.profile.init_timeout)
        self._switch_baud_and_track()

    def _with_recovery(self, exchange: Callable[[], T]) -> T:
        """Run a measurement exchange; after a device reset or spent retries, set the session up again once."""
        try:
            return exchange()
        except DeviceReset:
            self.recover(hard=False)
        except NDIError:
            raise
        except (DriverTimeout, ProtocolError):
            if not self.profile.reset_on_failure:
                raise
            self.recover(hard=True)
        return exchange()

    def read_strays(self) -> StrayFrame:
        """One TX:1000 or BX:1000 exchange (with recovery): the unlabelled markers of one frame."""
        if self.profile.reply == "bx":
            return parse_bx_body(self._with_recovery(lambda: self._exchange("BX:1000", self._binary_reply, None, None)))
        return parse_tx_strays(self._with_recovery(lambda: self.command("TX:1000")))

    def label(self, frame: StrayFrame, reference: np.ndarray | None = None) -> tuple[np.ndarray, tuple[str, ...]]:
        """Label a frame's markers as the targets: ((m, 3) m, NaN rows for targets not seen; quality flags).

        reference: (m, 3) m, where the targets were in other frames of the same measurement (see
        :func:`~labcal.drivers.serial.matching.match_targets`). Raises MeasurementRejected when no marker can be
        labelled, or a labelled one is out of the characterised volume.
        """
        match = match_targets(frame.strays, self.targets, self.profile.match_tolerance, reference)
        out = [f"t{k + 1}" for k, i in enumerate(match.indices) if i >= 0 and frame.out_of_volume[i]]
        if out:
            raise MeasurementRejected(f"target(s) {', '.join(out)} out of the characterised volume")
        quality: tuple[str, ...] = (f"system_status:0x{frame.system_status:04X}",) if frame.system_status else ()
        quality += tuple(f"missing:t{k + 1}" for k, i in enumerate(match.indices) if i < 0)
        return match.points, quality

    def read_frames(self, samples: int) -> list[tuple[np.ndarray, tuple[str, ...]]]:
        """``samples`` frames, each labelled (see :meth:`label`); frames too sparse to label alone are labelled from
        where the others saw the targets (the robot stands still during one measurement)."""
        raw = [self.read_strays() for _ in range(samples)]
        labelled: list = []
        first: MeasurementRejected | None = None
        for frame in raw:
            try:
                labelled.append(self.label(frame))
            except MeasurementRejected as exc:
                labelled.append(None)
                first = first or exc
        if first is None:
            return labelled
        done = [item[0] for item in labelled if item is not None]
        if not done:
            raise first
        reference = average_frames(done, timestamp=0.0).points  # each target over the frames that saw it
        return [item or self.label(frame, reference) for item, frame in zip(labelled, raw, strict=True)]

    def identify(self) -> dict[str, object]:
        """Ask the device who it is (``VER:4``, ``APIREV:``): serial, model, firmware, api_revision, and ``notes``
        for what it would not tell. Never raises a protocol error: a session can be recorded without them."""
        identity: dict[str, object] = {}
        notes = []
        # Its combined firmware description and its API revision, each with what labcal keeps of the reply.
        for command, parse in (("VER:4", parse_ver), ("APIREV:", lambda body: {"api_revision": body.strip()})):
            try:
                body = self.command(command, retries=0)
            except (DriverTimeout, ProtocolError) as exc:  # NDIError (ERRORxx) included
                notes.append(f"{command} not answered: {exc}")
                continue
            identity.update(parse(body))
            if command == "VER:4" and "serial" not in identity:
                notes.append(f"no serial number in the VER:4 reply {body[:120]!r}")
        if notes:
            identity["notes"] = notes
        return identity

    def stop(self) -> None:
        """Stop tracking and put the device back to 9600 baud, where the next session's INIT expects it.

        Without the COMM back to 9600 the next session would need a serial break and a full reset (seconds).
        """
        if self.tracking:
            self.tracking = False
            self._expect_okay("TSTOP:", retries=0)
        if self.link.transport.baudrate != 9600:
            self._expect_okay("COMM:00000", retries=0)
            self.link.sleep(self.profile.switch_delay)
            self.link.set_baudrate(9600)
