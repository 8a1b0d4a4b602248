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
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from labcal.drivers.base import ConnectionFailed, DriverTimeout, MeasurementRejected, ProtocolError
from labcal.drivers.serial.crc import crc16_arc
from labcal.drivers.serial.link import SerialLink
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
    """Check the CRC of one reply line (without CR) and return its body. ERRORxx raises NDIError."""
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
    """A parsed TX:1000 body. strays: (N, 3) m; out_of_volume: (N,) bool; system_status: int flags."""

    strays: np.ndarray
    out_of_volume: np.ndarray
    system_status: int


def _hex(body: str, start: int, width: int, what: str) -> int:
    field = body[start : start + width]
    if len(field) != width or any(c not in "0123456789ABCDEFabcdef" for c in field):
        raise ProtocolError(f"TX reply: {what} at char {start} is not {width} hex digits: {field!r}")
    return int(field, 16)


def _coordinate(body: str, start: int) -> float:
    field = body[start : start + 7]
    if len(field) != 7 or field[0] not in "+-" or not field[1:].isdigit():
        raise ProtocolError(f"TX reply: coordinate at char {start} is not sign + 6 digits: {field!r}")
    return int(field) * 1e-5  # 0.01 mm -> m


def parse_tx_strays(body: str) -> StrayFrame:
    """Parse a ``TX:1000`` reply body (CRC already removed). Raises ProtocolError on any malformation."""
    handles = _hex(body, 0, 2, "handle count")
    pos = 2
    for k in range(handles):  # tool blocks are not used by labcal; each ends with a line feed
        end = body.find("\n", pos)
        if end < 0:
            raise ProtocolError(f"TX reply: handle block {k + 1} of {handles} has no line feed")
        pos = end + 1
    n = _hex(body, pos, 2, "stray count")
    pos += 2
    n_flags = math.ceil(n / 4)
    flags = _hex(body, pos, n_flags, "out-of-volume flags") if n_flags else 0
    pos += n_flags
    expected = pos + n * STRAY_CHARS + 4
    if len(body) != expected:
        raise ProtocolError(f"TX reply with {n} strays should be {expected} chars, got {len(body)}: {body!r}")
    strays = np.array(
        [[_coordinate(body, pos + i * STRAY_CHARS + 7 * a) for a in range(3)] for i in range(n)], dtype=float
    ).reshape(n, 3)
    status = _hex(body, expected - 4, 4, "system status")
    oov = np.array([bool(flags >> i & 1) for i in range(n)], dtype=bool)
    return StrayFrame(strays=strays, out_of_volume=oov, system_status=status)


class NDIProtocol:
    """The NDI session on a SerialLink: start (INIT, COMM, TSTART), read_frame (TX:1000), stop (TSTOP)."""

    def __init__(
        self,
        profile: NDIProfile,
        targets: np.ndarray,
        link: SerialLink,
        sleep: Callable[[float], None],
    ):
        self.profile = profile
        self.targets = np.asarray(targets, dtype=float)
        self.link = link
        self.sleep = sleep
        self.tracking = False
        self.resets = 0  # hard resets (break) performed, for diagnostics

    # -- one exchange --------------------------------------------------------------------------------------

    def command(self, command: str, *, timeout: float | None = None, retries: int | None = None) -> str:
        """Send ``command`` and return the reply body; retry on timeouts, bad CRC, garbage and ERROR04."""
        tries = (self.profile.retries if retries is None else retries) + 1
        last: Exception | None = None
        for _ in range(tries):
            self.link.flush_input()
            self.link.write(encode_command(command))
            try:
                line = self.link.read_line(timeout)
                if line == RESET_REPLY:
                    raise DeviceReset(f"device reset (RESETBE6F) while waiting for the reply to {command!r}")
                return decode_reply(line, command)
            except DeviceReset:
                raise
            except NDIError as exc:
                if exc.code != 0x04:  # only a corrupted command is worth sending again
                    raise
                last = exc
            except (DriverTimeout, ProtocolError) as exc:
                last = exc
        assert last is not None
        raise last

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
            self._break_reset()
            self._expect_okay("INIT:", timeout=self.profile.init_timeout)
        self._switch_baud_and_track()

    def _switch_baud_and_track(self) -> None:
        if self.profile.baudrate != 9600:
            code = NDI_BAUD_CODES[self.profile.baudrate]
            self._expect_okay(f"COMM:{code}000{int(self.profile.handshake)}")
            # The device changes rate after sending OKAY; follow once it has.
            self.sleep(self.profile.switch_delay)
            self.link.set_baudrate(self.profile.baudrate)
        self._expect_okay("TSTART:")
        self.tracking = True

    def _break_reset(self) -> None:
        """Serial break -> RESETBE6F at 9600 (raises ConnectionFailed if the device does not reset)."""
        self.tracking = False
        self.resets += 1
        self.link.set_baudrate(9600)
        self.link.flush_input()
        self.link.send_break()
        try:
            line = self.link.read_line(self.profile.init_timeout)
        except DriverTimeout as exc:
            raise ConnectionFailed(f"no RESET reply after a serial break: {exc}") from exc
        if line != RESET_REPLY:
            raise ConnectionFailed(f"expected RESETBE6F after a serial break, got {line!r}")

    def recover(self, *, hard: bool) -> None:
        """Bring the device back to tracking: with a break first (hard) or, after a RESET it sent, without."""
        self.tracking = False
        if hard:
            self._break_reset()
        else:
            self.link.set_baudrate(9600)
        self._expect_okay("INIT:", timeout=self.profile.init_timeout)
        self._switch_baud_and_track()

    def _tx(self) -> str:
        try:
            return self.command("TX:1000")
        except DeviceReset:
            self.recover(hard=False)
        except NDIError:
            raise
        except (DriverTimeout, ProtocolError):
            if not self.profile.reset_on_failure:
                raise
            self.recover(hard=True)
        return self.command("TX:1000")

    def read_frame(self) -> tuple[np.ndarray, tuple[str, ...]]:
        """One frame: (3, 3) target positions in the tracker frame, m, and quality flags."""
        frame = parse_tx_strays(self._tx())
        match = match_targets(frame.strays, self.targets, self.profile.match_tolerance)
        out = [f"t{k + 1}" for k, i in enumerate(match.indices) if frame.out_of_volume[i]]
        if out:
            raise MeasurementRejected(f"target(s) {', '.join(out)} out of the characterised volume")
        quality = (f"system_status:0x{frame.system_status:04X}",) if frame.system_status else ()
        return match.points, quality

    def stop(self) -> None:
        """Stop tracking and put the device back to 9600 baud, where the next session's INIT expects it.

        Without the COMM back to 9600 the next session would need a serial break and a full reset (seconds).
        """
        if self.tracking:
            self.tracking = False
            self._expect_okay("TSTOP:", retries=0)
        if self.link.transport.baudrate != 9600:
            self._expect_okay("COMM:00000", retries=0)
            self.sleep(self.profile.switch_delay)
            self.link.set_baudrate(9600)
