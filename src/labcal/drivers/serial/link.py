"""Transport and framer: bytes in and out of a serial port, one terminated line (or counted block) at a time.

The transport is anything shaped like ``serial.Serial`` (``write``, ``read``, ``reset_input_buffer``,
``send_break``, ``close`` and a settable ``baudrate``): a real port from ``serial.serial_for_url`` (device path,
pty path, ``socket://``, ``loop://``) or a scripted fake in tests. ``SerialLink`` turns every library error into
a labcal driver error and reads lines, or blocks of a known length for binary replies, against an overall
deadline, because pyserial's ``readline`` and ``read`` return partial data (or ``b''``) on timeout without
saying so.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

from labcal.drivers.base import ConnectionFailed, DriverTimeout, ProtocolError

T = TypeVar("T")


def retried(attempts: int, attempt: Callable[[], T], final: Callable[[Exception], bool]) -> T:
    """``attempt()`` up to ``attempts`` (>= 1) times: a DriverTimeout or ProtocolError (a reply lost or garbled on
    the line) is tried again unless ``final(error)``; the last attempt's error is raised."""
    for _ in range(attempts - 1):
        try:
            return attempt()
        except (DriverTimeout, ProtocolError) as exc:
            if final(exc):
                raise
    return attempt()


class Transport(Protocol):
    """The part of the ``serial.Serial`` API the serial tracker uses."""

    baudrate: int

    def write(self, data: bytes) -> int | None: ...

    def read(self, size: int = 1) -> bytes: ...

    def reset_input_buffer(self) -> None: ...

    def send_break(self, duration: float = 0.25) -> None: ...

    def close(self) -> None: ...


def open_serial(url: str, *, baudrate: int, bytesize: int, parity: str, stopbits: float, timeout: float) -> Any:
    """Open ``url`` with pyserial; raise ConnectionFailed (naming the url) instead of pyserial's errors.

    ``timeout`` (s) is the overall reply timeout; pyserial gets a shorter per-read timeout so the framer's
    deadline, not the number of bytes that trickle in, bounds each wait.
    """
    import serial  # lazily: the math layers and `labcal --help` never need pyserial

    try:
        return serial.serial_for_url(
            url,
            baudrate=baudrate,
            bytesize=bytesize,
            parity=parity,
            stopbits=stopbits,
            timeout=min(timeout, 0.05),
            write_timeout=max(timeout, 1.0),
        )  # and pyserial's defaults: no software or hardware flow control
    except (serial.SerialException, OSError, ValueError) as exc:
        raise ConnectionFailed(f"cannot open serial port {url!r}: {exc}") from exc


def _library_errors() -> tuple[type[BaseException], ...]:
    """Exceptions a serial port can raise: pyserial's own, OS errors, and termios.error (not an OSError!)."""
    import serial  # a dependency; imported here, lazily, as in open_serial

    errors: list[type[BaseException]] = [OSError, serial.SerialException]
    try:
        import termios

        errors.append(termios.error)
    except ImportError:  # pragma: no cover - Windows has no termios
        pass
    return tuple(errors)


class SerialLink:
    """A transport plus line framing, with labcal exceptions only.

    read_terminator: non-empty (the profile loader checks an ASCII profile's; NDI's is CR).

    clock: monotonic time source in s (injected so scripted tests can simulate timeouts instantly).
    sleep: delay function in s (injected for the same reason).
    """

    max_line = 8192  # bytes: the longest reply, so a device sending garbage without terminators cannot fill memory

    def __init__(
        self,
        transport: Transport,
        *,
        write_terminator: bytes,
        read_terminator: bytes,
        timeout: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.transport = transport
        self.write_terminator = write_terminator
        self.read_terminator = read_terminator
        self.timeout = float(timeout)
        self.clock = clock
        self.sleep = sleep
        self._errors = _library_errors()
        self.closed = False

    # -- raw operations, errors translated -------------------------------------------------------------------

    def _call(self, what: str, fn: Callable[..., Any], *args: Any) -> Any:
        if self.closed:
            raise ConnectionFailed(f"serial link is closed (during {what})")
        try:
            return fn(*args)
        except self._errors as exc:
            raise ConnectionFailed(f"serial {what} failed: {exc}") from exc

    def flush_input(self) -> None:
        """Discard stale input (left over from an earlier failed exchange or a streaming device)."""
        self._call("input flush", self.transport.reset_input_buffer)

    def write(self, data: bytes) -> None:
        written = self._call("write", self.transport.write, data)
        if written is not None and written != len(data):
            raise DriverTimeout(f"wrote only {written} of {len(data)} bytes")

    def send_line(self, text: str) -> None:
        self.write(text.encode("ascii") + self.write_terminator)

    def send_break(self, duration: float = 0.25) -> None:
        self._call("break", self.transport.send_break, duration)

    def set_baudrate(self, baudrate: int) -> None:
        self._call("baud rate change", setattr, self.transport, "baudrate", int(baudrate))

    def read_line(self, timeout: float | None = None) -> bytes:
        """Read up to and including the read terminator; return the line without it.

        Raises DriverTimeout (with whatever partial bytes arrived) when the terminator does not arrive within
        ``timeout`` s (default: the link timeout), ProtocolError when the line exceeds ``max_line`` bytes.
        """
        wait = self.timeout if timeout is None else timeout
        deadline = self.clock() + wait
        buf = bytearray()
        term = self.read_terminator
        while True:
            chunk = self._call("read", self.transport.read, 1)
            if chunk:
                buf += chunk
                if buf.endswith(term):
                    return bytes(buf[: -len(term)])
                if len(buf) > self.max_line:
                    raise ProtocolError(f"reply longer than {self.max_line} bytes without terminator {term!r}")
            elif self.clock() >= deadline:
                detail = f"; partial reply {bytes(buf)!r}" if buf else ""
                raise DriverTimeout(f"no complete reply within {wait:.3g} s{detail}")

    def read_exact(self, n: int, timeout: float | None = None) -> bytes:
        """Read exactly ``n`` bytes (binary replies carry their length instead of a terminator).

        Raises DriverTimeout (with whatever partial bytes arrived) when fewer than ``n`` bytes arrive within
        ``timeout`` s (default: the link timeout).
        """
        if n < 0:
            raise ValueError(f"cannot read a negative number of bytes ({n})")
        wait = self.timeout if timeout is None else timeout
        deadline = self.clock() + wait
        buf = bytearray()
        while len(buf) < n:
            chunk = self._call("read", self.transport.read, n - len(buf))
            if chunk:
                buf += chunk
            elif self.clock() >= deadline:
                detail = f"; partial reply {bytes(buf)!r}" if buf else ""
                raise DriverTimeout(f"no complete reply within {wait:.3g} s: {len(buf)} of {n} bytes{detail}")
        return bytes(buf)

    def drain(self) -> bytes:
        """Read until one read comes back empty (the line went quiet) and return what was discarded.

        After a binary reply whose header cannot be trusted, the rest of it is still arriving and has no
        terminator to read up to; the flush before the next request would miss bytes still on the wire.
        Bounded by ``max_line`` so a streaming device cannot keep this going forever.
        """
        buf = bytearray()
        while len(buf) <= self.max_line:
            chunk = self._call("read", self.transport.read, self.max_line + 1 - len(buf))
            if not chunk:
                break
            buf += chunk
        return bytes(buf)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.transport.close()
        except self._errors:
            pass  # closing a port that already vanished is not an error worth reporting
