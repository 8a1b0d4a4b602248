"""ur-rtde interfaces in their own processes, so that no ur-rtde failure can hang or crash labcal.

Why: ur-rtde 1.6.5 hangs its constructor forever (holding the GIL) on a peer that accepts and never answers;
after the controller dies it keeps calling ``Reconnecting...`` for minutes inside a blocking ``moveJ``; and after
an RTDE connection drop its ``disconnect()`` / destructor can crash the interpreter with SIGSEGV. None of that can
be bounded from Python in the same process. Here each interface (receive or control) lives in a child process
(``python -m labcal.drivers.ur_process KIND HOST FREQUENCY VARIABLES``); :class:`RemoteInterface` forwards method
calls over a pipe and waits with a deadline. A call that misses its deadline, or a child that dies, kills the
child (SIGKILL: nothing of ur-rtde's runs in labcal's process) and raises ``RuntimeError`` — the error ur-rtde
itself raises — so :mod:`labcal.drivers.ur` maps it as before. The plumbing (:class:`ChildProcess` and the child's
:func:`serve`) is not ur-rtde's: the fake controller of :mod:`labcal_fakes.rtde_fake` runs on it too.

Example::

    rx = RemoteInterface("receive", "192.168.1.10", -1.0, ["timestamp", "actual_q"], start_timeout=5.0)
    rx.getActualQ()       # -> [q1, ..., q6], or RuntimeError within rx.call_timeout s
    rx.close()            # disconnect() with a deadline, then the child is gone
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, TextIO

log = logging.getLogger(__name__)

# How often a long call (a blocking moveJ) runs its watchdog while waiting for the child's answer, s.
WATCH_PERIOD = 0.05


class ChildProcess:
    """A Python module in a child process that answers JSON-line calls, every wait bounded.

    The child (see :func:`serve`) answers its start-up, then each ``[name, [args]]`` line, with ``["ok", value]``
    or ``["error", exception type name, message]``. ``started`` holds the start-up answer's value. Every call
    waits at most ``call_timeout`` s; a call given ``timeout=None`` (see :meth:`call`) waits as long as ``watch``
    (called every WATCH_PERIOD s while waiting) does not raise. Timeouts and a dead child raise RuntimeError and
    kill the child; later calls raise RuntimeError at once. label: what the child is, in every error message.
    log_stderr: the child's stderr goes to this module's log (debug) instead of the terminal.
    """

    def __init__(
        self,
        argv: Sequence[str],
        label: str,
        *,
        start_timeout: float,
        call_timeout: float,
        start_what: str = "starting",
        log_stderr: bool = True,
    ):
        self.label, self.call_timeout = label, float(call_timeout)
        self._lock = threading.Lock()
        self._replies: queue.Queue[bytes | None] = queue.Queue()
        self._dead: str | None = None
        self._process = subprocess.Popen(
            list(argv), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE if log_stderr else None
        )
        if log_stderr:
            threading.Thread(target=self._log_stderr, name=f"{label} log", daemon=True).start()
        threading.Thread(target=self._read_replies, name=f"{label} replies", daemon=True).start()
        try:
            self.started = self._decode(self._read_line(start_timeout, start_what, None))
        except BaseException:
            self._died(f"{start_what} was abandoned")  # as in call(); a start-up error answer ends the child too
            raise

    # -- calls -----------------------------------------------------------------------------------------------

    def call(
        self, name: str, *args: Any, timeout: float | str | None = "default", watch: Callable[[], None] | None = None
    ) -> Any:
        """Call ``name(*args)`` in the child. timeout: s, "default" (call_timeout), or None (``watch`` bounds it)."""
        with self._lock:
            if self._dead is not None:
                raise RuntimeError(f"the {self.label} is gone: {self._dead}")
            assert self._process.stdin is not None
            limit = self.call_timeout if timeout == "default" else timeout
            try:
                try:
                    self._process.stdin.write((json.dumps([name, list(args)]) + "\n").encode())
                    self._process.stdin.flush()
                except OSError as exc:
                    self._died(f"its process ended ({exc})")
                    raise RuntimeError(f"the {self.label} is gone: {self._dead}") from None
                line = self._read_line(limit, f"{name}()", watch)  # type: ignore[arg-type]
            except BaseException:
                # Whatever stopped the call once the request may have left (deadline, dead child, watchdog, Ctrl-C
                # even between sending and waiting), its answer may still come and would be taken for the next
                # call's: this child is done.
                self._died(f"{name}() was abandoned")
                raise
            return self._decode(line)

    @staticmethod
    def _decode(line: bytes) -> Any:
        reply = json.loads(line)
        if reply[0] == "ok":
            return reply[1]
        error = ValueError if reply[1] == "ValueError" else RuntimeError
        raise error(reply[2])

    def _read_line(self, timeout: float | None, what: str, watch: Callable[[], None] | None) -> bytes:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = WATCH_PERIOD if watch is not None else None
            if deadline is not None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._died(f"{what} got no answer within {timeout} s")
                    raise RuntimeError(f"{self.label}: {what} got no answer within {timeout} s")
                wait = remaining if wait is None else min(wait, remaining)
            try:
                line = self._replies.get(timeout=wait)
            except queue.Empty:
                if watch is not None:
                    watch()
                continue
            if line is None:
                code = self._process.wait()
                self._died(f"its process ended with code {code} during {what}")
                raise RuntimeError(f"the {self.label} is gone: {self._dead}")
            return line

    def _read_replies(self) -> None:
        # A thread rather than select(): pipes cannot be selected on Windows.
        assert self._process.stdout is not None
        with contextlib.suppress(OSError, ValueError):
            for line in self._process.stdout:
                self._replies.put(line)
        self._replies.put(None)

    # -- lifecycle -------------------------------------------------------------------------------------------

    @property
    def alive(self) -> bool:
        return self._dead is None and self._process.poll() is None

    def _died(self, why: str) -> None:
        if self._dead is None:
            self._dead = why
        self.kill()

    def kill(self) -> None:
        """SIGKILL the child (whatever it, ur-rtde say, is doing). Safe to repeat."""
        if self._dead is None:
            self._dead = "killed"
        with contextlib.suppress(OSError):
            if self._process.poll() is None:
                self._process.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._process.wait(2.0)
        for stream in (self._process.stdin, self._process.stdout):
            with contextlib.suppress(OSError):
                if stream is not None:
                    stream.close()

    def end(self, timeout: float) -> None:
        """Close the child's stdin (its :func:`serve` loop ends), give it ``timeout`` s to exit, then kill it."""
        if self.alive:
            with contextlib.suppress(OSError):
                assert self._process.stdin is not None
                self._process.stdin.close()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._process.wait(timeout)
        self.kill()

    def _log_stderr(self) -> None:
        assert self._process.stderr is not None
        for raw in self._process.stderr:  # ur-rtde's own chatter ("Reconnecting..."), kept out of the terminal
            log.debug("%s: %s", self.label, raw.decode("utf-8", "replace").rstrip())


class RemoteInterface(ChildProcess):
    """A ur-rtde ``RTDEReceiveInterface`` ("receive") or ``RTDEControlInterface`` ("control") in a child process.

    Any method name is forwarded: ``iface.getActualQ()``, bounded as :class:`ChildProcess` calls are; after the
    child is gone ``isConnected()`` answers False.
    """

    def __init__(
        self,
        kind: str,
        host: str,
        frequency: float,
        variables: Sequence[str] = (),
        *,
        start_timeout: float = 10.0,
        call_timeout: float = 2.0,
    ):
        if kind not in ("receive", "control"):
            raise ValueError(f"kind must be 'receive' or 'control', got {kind!r}")
        self.kind, self.host = kind, host
        argv = [sys.executable, "-m", "labcal.drivers.ur_process", kind, host, repr(float(frequency))]
        super().__init__(
            [*argv, json.dumps(list(variables))],
            f"ur-rtde {kind} interface",
            start_timeout=start_timeout,
            call_timeout=call_timeout,
            start_what=f"connecting the RTDE {kind} interface to {host}",
        )

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args: self.call(name, *args)

    def call(self, name: str, *args: Any, **kw: Any) -> Any:
        if name == "isConnected" and self._dead is not None:
            return False
        return super().call(name, *args, **kw)

    def close(self, timeout: float = 1.0) -> None:
        """``disconnect()`` within ``timeout`` s (a healthy link is told goodbye), then the child goes."""
        if self._dead is None:
            with contextlib.suppress(Exception):
                self.call("disconnect", timeout=timeout)
        self.kill()


# --------------------------------------------------------------------------------------------------------------
# The child.


def serve(start: Callable[[], tuple[Callable[..., Any], Any]], requests: Iterable[str], replies: TextIO) -> None:
    """The child's side of :class:`ChildProcess`: ``start()`` gives (handler, start-up value) or raises (answered
    as an error); then each ``[name, [args]]`` line of ``requests`` is answered with ``handler(name, *args)``, until
    ``requests`` ends (EOF when the parent goes away: a child never outlives it)."""

    def reply(*values: Any) -> None:
        replies.write(json.dumps(list(values)) + "\n")
        replies.flush()

    try:
        handler, started = start()
    except Exception as exc:
        reply("error", type(exc).__name__, str(exc))
        return
    reply("ok", started)
    for line in requests:
        name, args = json.loads(line)
        try:
            value = handler(name, *args)
        except Exception as exc:
            reply("error", type(exc).__name__, str(exc))
        else:
            reply("ok", value)


def _child(kind: str, host: str, frequency: float, variables: list[str]) -> None:
    # Ctrl-C in a terminal reaches the whole process group: labcal decides how to stop, through this process.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The protocol keeps the original stdout; ur-rtde's C++ prints (std::cout) go to stderr, away from it.
    replies = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)

    def start() -> tuple[Callable[..., Any], None]:
        if kind == "receive":
            import rtde_receive

            iface = rtde_receive.RTDEReceiveInterface(host, frequency, variables)
        else:
            import rtde_control

            iface = rtde_control.RTDEControlInterface(host, frequency)
        return (lambda name, *args: getattr(iface, name)(*args)), None

    serve(start, sys.stdin, replies)
    # No disconnect here: after a dropped link it is what crashes; the parent asks for it while the link is up.
    os._exit(0)


if __name__ == "__main__":
    _child(sys.argv[1], sys.argv[2], float(sys.argv[3]), json.loads(sys.argv[4]))
