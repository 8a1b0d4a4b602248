"""A ``serial.Serial`` stand-in for byte-exact protocol tests: a script of (expected bytes written, reply bytes)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

BREAK = b"<serial break>"


class ScriptedTransport:
    """A ``serial.Serial`` stand-in that plays a script of (expected bytes written, reply bytes).

    When the bytes written so far equal the next expected chunk, its reply becomes readable; writing anything
    else fails the test at once (AssertionError naming the step). ``BREAK`` as the expected chunk means a serial
    break. ``read`` returns b'' when nothing is buffered (a timeout) and advances the fake clock by
    ``read_timeout`` s, so timeouts cost no real time; pass ``clock=t.clock, sleep=t.sleep`` to the driver.
    ``events`` logs writes, breaks, baud changes, sleeps and flushes in order. Call ``assert_done()`` at the end.
    ``max_read`` caps the bytes one ``read`` returns, as a slow line delivers a reply in pieces.
    """

    def __init__(
        self,
        script: Sequence[tuple[bytes, bytes]],
        *,
        baudrate: int = 9600,
        read_timeout: float = 0.05,
        pending_input: bytes = b"",
        max_read: int | None = None,
    ):
        self.script = list(script)
        self.step = 0
        self._written = b""
        self._input = bytearray(pending_input)
        self._baudrate = baudrate
        self.read_timeout = read_timeout
        self.max_read = max_read
        self.now = 0.0
        self.events: list[tuple[str, Any]] = []
        self.closed = False

    # -- the serial.Serial surface -------------------------------------------------------------------------

    @property
    def baudrate(self) -> int:
        return self._baudrate

    @baudrate.setter
    def baudrate(self, value: int) -> None:
        self._baudrate = value
        self.events.append(("baud", value))

    def _expected(self, what: str) -> bytes:
        if self.closed:
            raise OSError(f"{what} on a closed port")
        if self.step >= len(self.script):
            raise AssertionError(f"script exhausted after {self.step} steps, but the driver did a {what}")
        return self.script[self.step][0]

    def _advance(self) -> None:
        self._input += self.script[self.step][1]
        self.step += 1
        self._written = b""

    def write(self, data: bytes) -> int:
        expected = self._expected(f"write of {bytes(data)!r}")
        self.events.append(("write", bytes(data)))
        self._written += bytes(data)
        if expected == BREAK or not expected.startswith(self._written):
            raise AssertionError(f"script step {self.step}: expected {expected!r}, driver wrote {self._written!r}")
        if self._written == expected:
            self._advance()
        return len(data)

    def send_break(self, duration: float = 0.25) -> None:
        expected = self._expected("serial break")
        self.events.append(("break", duration))
        if expected != BREAK or self._written:
            raise AssertionError(f"script step {self.step}: expected {expected!r}, driver sent a serial break")
        self._advance()

    def read(self, size: int = 1) -> bytes:
        if self.closed:
            raise OSError("read on a closed port")
        if not self._input:
            self.now += self.read_timeout
            return b""
        size = size if self.max_read is None else min(size, self.max_read)
        data = bytes(self._input[:size])
        del self._input[:size]
        return data

    def reset_input_buffer(self) -> None:
        self.events.append(("flush", bytes(self._input)))
        self._input.clear()

    def close(self) -> None:
        self.closed = True
        self.events.append(("close", None))

    # -- test helpers --------------------------------------------------------------------------------------

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.events.append(("sleep", seconds))
        self.now += seconds

    def feed(self, data: bytes) -> None:
        """Make ``data`` readable now (unsolicited device output)."""
        self._input += data

    def assert_done(self) -> None:
        """Every scripted exchange happened and every reply byte was read (or deliberately flushed)."""
        problems = []
        if self.step != len(self.script):
            problems.append(f"{len(self.script) - self.step} step(s) unused, next {self.script[self.step]!r}")
        if self._written:
            problems.append(f"partial write {self._written!r}")
        if self._input:
            problems.append(f"unread reply bytes {bytes(self._input)!r}")
        if problems:
            raise AssertionError("scripted transport: " + "; ".join(problems))
