"""Fake serial tracker devices for tests and the simulated rig.

``FakeNDIDevice`` runs on the master side of a pseudo-terminal in a background thread (:class:`PtyDevice`, the
base of any such fake line device: the tests' fake ASCII tracker is another); pyserial (or the real ``ndicapy``
client) opens ``.port``, the slave path, exactly as it would open a real device. It reads target positions from
``points_provider() -> (m, 3)`` metres in the tracker frame (any number of targets; a NaN row is a target the
camera cannot see at the moment), so a simulator can feed it the true target positions plus noise, and hide
targets.

Limits of a pty: bytes flow whatever the baud rate, and a serial break does not reach the master side. The fake
NDI device therefore keeps an *emulated* rate (9600 after reset, then what COMM set) and compares it with the
rate the client configured on the pty (termios settings are shared by both ends' view of the slave): at a
mismatch it ignores the command, as a real device seeing framing errors would. ``reset()`` emulates what a
break (or power cycle) does; the host-side break path itself is tested with a scripted transport
(tests/drivers/scripted_transport.py).

Fault injection (one-shot, in order, applied to the next measurement request, ``TX`` or ``BX``)::

    with FakeNDIDevice(provider, seed=1) as dev:
        dev.inject("bad_crc")        # also: "no_reply", "garbled", "truncated", "drop_target", "extra_stray",
        ...                          # "out_of_volume", "reset", "error:0C" (any hex code)
"""

from __future__ import annotations

import collections
import contextlib
import math
import os
import select
import struct
import termios
import threading
import time
import tty
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from labcal.drivers.serial.crc import crc16_arc

PointsProvider = Callable[[], np.ndarray]

_TERMIOS_SPEEDS = {
    getattr(termios, f"B{rate}"): rate
    for rate in (9600, 19200, 38400, 57600, 115200, 230400, 921600)
    if hasattr(termios, f"B{rate}")
}

# A scalene triangle (sides 100, 70, ~122 mm) about 1.5 m in front of a tracker: a sensible default scene.
DEFAULT_TRACKER_POINTS = np.array([[0.10, -0.05, -1.50], [0.20, -0.05, -1.50], [0.10, 0.02, -1.50]])


class PtyDevice:
    """A line-oriented fake device on a pty master, served by a daemon thread.

    The fake keeps its own handle on the slave open, so clients may open and close the port repeatedly without
    the master seeing a hang-up; an EIO on the master is still tolerated (the loop waits and carries on).
    """

    terminator = b"\r"
    FAULTS: tuple[str, ...] = ()

    def __init__(self, points_provider: PointsProvider | None, seed: int):
        self.points_provider = points_provider or DEFAULT_TRACKER_POINTS.copy
        self.rng = np.random.default_rng(seed)
        self.received: list[str] = []  # every command line, as received (CRC included)
        self.faults: collections.deque[str] = collections.deque()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no CR->LF translation before a client configures the port
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._run, name=f"{type(self).__name__}:{self.port}", daemon=True)

    # -- lifecycle -----------------------------------------------------------------------------------------

    def start(self) -> PtyDevice:
        if self._thread.ident is None:  # not started yet
            self._thread.start()
        return self

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> Any:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- faults --------------------------------------------------------------------------------------------

    def inject(self, fault: str, count: int = 1) -> None:
        """Queue ``fault`` for the next ``count`` measurement requests (see the class's FAULTS)."""
        kind = fault.split(":", 1)[0]
        if kind not in self.FAULTS:
            raise ValueError(f"unknown fault {fault!r}; known: {list(self.FAULTS)}")
        with self._lock:
            self.faults.extend([fault] * count)

    def _next_fault(self) -> str | None:
        with self._lock:
            return self.faults.popleft() if self.faults else None

    # -- I/O -----------------------------------------------------------------------------------------------

    def send(self, data: bytes, timeout: float = 1.0) -> bool:
        """Write ``data`` to the client; return False (data dropped) if the client does not drain it in time."""
        view = memoryview(data)
        deadline = time.monotonic() + timeout
        while view:
            try:
                view = view[os.write(self._master, view) :]
            except BlockingIOError:  # the client has not read what came before: wait (up to the deadline)
                left = deadline - time.monotonic()
                if left <= 0 or self._stop.is_set():
                    return False
                select.select([], [self._master], [], min(left, 0.05))
            except OSError:
                return False  # EIO: no client; a real device talking to an unplugged cable loses the bytes
        return True

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.01)
            except (OSError, ValueError):
                return  # the fds were closed under us
            if ready:
                try:
                    chunk = os.read(self._master, 4096)
                except BlockingIOError:
                    chunk = b""
                except OSError:
                    # EIO: the last client closed the slave. Wait for the next one.
                    time.sleep(0.01)
                    continue
                buf += chunk
                while self.terminator in buf:
                    line, buf = buf.split(self.terminator, 1)
                    text = line.decode("ascii", errors="replace")
                    self.received.append(text)
                    reply = self.handle(text)
                    if reply:
                        self.send(reply)
            self.tick()

    def host_baudrate(self) -> int | None:
        """The baud rate the client set on the pty (None if unknown)."""
        try:
            speed = termios.tcgetattr(self._slave)[5]  # ospeed
        except (termios.error, OSError):
            return None
        return _TERMIOS_SPEEDS.get(speed)

    def handle(self, line: str) -> bytes | None:  # pragma: no cover - abstract
        raise NotImplementedError

    def tick(self) -> None:
        """Called about every 10 ms from the device thread (streaming devices send here)."""


# ----------------------------------------------------------------------------------------------------------
# NDI Combined API


_NDI_BAUDS = {0: 9600, 1: 14400, 2: 19200, 3: 38400, 4: 57600, 5: 115200, 6: 921600, 7: 1228739, 8: 230400}
# The commands that only move the device between its states: command -> ({state: ERRORxx code refusing it in that
# state}, state after OKAY). INIT is refused while tracking, TSTART before INIT, TSTOP unless tracking.
_NDI_TRANSITIONS = {
    "INIT": ({"tracking": 0x0C}, "setup"),
    "TSTART": ({"reset": 0x10, "tracking": 0x0C}, "tracking"),
    "TSTOP": ({"reset": 0x0C, "setup": 0x0C}, "setup"),
}


def _ndi_frame(body: str) -> bytes:
    data = body.encode("ascii")
    return data + f"{crc16_arc(data):04X}\r".encode("ascii")


# How the reply-spoiling faults change a whole reply: TX (body, 4 hex CRC digits, CR) and BX (binary, body CRC last).
_SPOIL_TX = {
    "bad_crc": lambda r: r[:-5] + f"{(int(r[-5:-1], 16) + 1) & 0xFFFF:04X}\r".encode("ascii"),
    "garbled": lambda r: r[: len(r) // 2] + b"\x00#~" + r[len(r) // 2 + 3 :],
    "truncated": lambda r: r[:-5],
}
_SPOIL_BX = {
    "bad_crc": lambda r: r[:-2] + bytes([r[-2] ^ 0x01, r[-1]]),
    "garbled": lambda r: b"\x00#~" + r[3:],
    "truncated": lambda r: r[:-5],
}


def encode_bx_reply(
    strays: Any,
    out_of_volume: Sequence[bool] | None = None,
    system_status: int = 0,
    handles: Sequence[tuple[int, int]] = (),
) -> bytes:
    """A whole binary reply to ``BX:1000``, as a Polaris sends it (header, body, body CRC; no CR).

    strays: (M, 3) m, sent as float32 millimetres. out_of_volume: M flags (default none). handles: (handle id,
    status) pairs, which option 0x1000 reports without any per-handle data.
    """
    mm = np.asarray(strays, dtype=float).reshape(-1, 3) * 1e3
    m = len(mm)
    oov = [False] * m if out_of_volume is None else [bool(f) for f in out_of_volume]
    if len(oov) != m:
        raise ValueError(f"{len(oov)} out-of-volume flags for {m} strays")
    bits = sum(1 << j for j, flag in enumerate(oov) if flag)
    body = bytes([len(handles)]) + b"".join(bytes([h, st]) for h, st in handles)
    body += bytes([m]) + bits.to_bytes(math.ceil(m / 8), "little")
    body += mm.astype("<f4").tobytes() + struct.pack("<H", system_status)
    header = b"\xc4\xa5" + struct.pack("<H", len(body))
    return header + struct.pack("<H", crc16_arc(header)) + body + struct.pack("<H", crc16_arc(body))


class FakeNDIDevice(PtyDevice):
    """A Polaris-like NDI Combined API device reporting the targets as passive stray markers.

    points_provider: () -> (m, 3) m, true target positions in the tracker frame (rows t1 … tm; a NaN row is not
    seen: no marker for it).
    shuffle: report strays in a random order (as a real tracker does). extra_stray: always add one spurious
    reflection. noise: Gaussian noise per coordinate, m (on top of whatever the provider adds). seed: RNG seed.
    strict_baud: ignore commands while the client's pty rate differs from the emulated device rate.

    State: ``state`` is "reset" (after power-up/reset), "setup" (after INIT) or "tracking"; ``baudrate`` is the
    emulated rate set by COMM. Replies follow the API: body + CRC16 + CR; ERRORxx for bad commands; ``BX``
    answers in binary (``encode_bx_reply``) from the same simulated markers as ``TX``; ``VER`` answers
    ``version_text`` (serial P9-00384) and ``APIREV`` ``api_revision``, in any state.

    Faults on a BX reply: "bad_crc" spoils the body CRC, "garbled" the start sequence, "truncated" drops the
    last bytes (a TX reply loses its CR and CRC); the others act as on TX.
    """

    FAULTS = ("no_reply", *_SPOIL_TX, "drop_target", "extra_stray", "out_of_volume", "reset", "error")

    def __init__(
        self,
        points_provider: PointsProvider | None = None,
        *,
        seed: int = 0,
        shuffle: bool = True,
        extra_stray: bool = False,
        noise: float = 0.0,
        strict_baud: bool = True,
    ):
        super().__init__(points_provider, seed)
        self.strict_baud = strict_baud
        self.ignored: list[str] = []  # commands dropped because of a baud-rate mismatch
        self.shuffle = shuffle
        self.extra_stray = extra_stray
        self.noise = float(noise)
        self.state = "reset"
        self.baudrate = 9600
        self.system_status = 0
        # What VER answers (lines separated by LF, as a Polaris does) and APIREV; tests may change either.
        self.version_text = "Polaris Vega Control Firmware\nNDI S/N: P9-00384\nFreeze Tag: Polaris Vega 001.004"
        self.api_revision = "G.001.005"

    # -- reset emulation -----------------------------------------------------------------------------------

    def reset(self, announce: bool = True) -> None:
        """Do what a serial break or power cycle does: lose all state, go back to 9600, say RESETBE6F."""
        self.state = "reset"
        self.baudrate = 9600
        if announce:
            self.send(_ndi_frame("RESET"))

    # -- commands ------------------------------------------------------------------------------------------

    def handle(self, line: str) -> bytes | None:
        if self.strict_baud:
            host = self.host_baudrate()
            if host is not None and host != self.baudrate:
                self.ignored.append(line)
                return None
        if ":" in line:
            name, _, rest = line.partition(":")
            if len(rest) < 4:
                return _ndi_frame("ERROR03")
            params, crc_text = rest[:-4], rest[-4:]
            if crc_text.upper() != f"{crc16_arc(line[:-4].encode('ascii', errors='replace')):04X}":
                return _ndi_frame("ERROR04")
        else:
            name, _, params = line.partition(" ")
        name, params = name.strip().upper(), params.strip()
        if name in _NDI_TRANSITIONS:
            refused, after = _NDI_TRANSITIONS[name]
            if self.state in refused:
                return _ndi_frame(f"ERROR{refused[self.state]:02X}")
            self.state = after
            return _ndi_frame("OKAY")
        if name in ("TX", "BX"):
            return self._measure(params, binary=name == "BX")
        if name == "COMM":
            return self._comm(params)
        if name == "VER":  # any of the firmware descriptions a Polaris gives: the same text here
            return _ndi_frame(self.version_text if params in ("0", "3", "4", "5") else "ERROR07")
        return _ndi_frame(self.api_revision if name == "APIREV" else "ERROR01")

    def _comm(self, params: str) -> bytes:
        if len(params) != 5 or not params.isdigit() or int(params[0]) not in _NDI_BAUDS:
            return _ndi_frame("ERROR06")
        if params[1:4] != "000":
            return _ndi_frame("ERROR06")  # only 8N1 is emulated
        # OKAY goes out at the old rate; the device then switches (no-op on a pty, recorded for tests).
        self.baudrate = _NDI_BAUDS[int(params[0])]
        return _ndi_frame("OKAY")

    def _measure(self, params: str, binary: bool) -> bytes | None:
        """TX or BX: a frame of the markers the camera sees, as the next queued fault (if any) spoils it."""
        if self.state != "tracking":
            return _ndi_frame("ERROR10" if self.state == "reset" else "ERROR0C")
        try:
            option = int(params or "0001", 16)
        except ValueError:
            return _ndi_frame("ERROR07")
        fault = self._next_fault()
        kind, _, code = (fault or "").partition(":")
        if kind == "no_reply":
            return None
        if kind == "reset":
            self.reset(announce=False)
            return _ndi_frame("RESET")
        if kind == "error":
            return _ndi_frame(f"ERROR{int(code or '0C', 16):02X}")
        if binary and option != 0x1000:
            return _ndi_frame("ERROR07")  # only passive strays are emulated in binary
        if binary:
            reply = encode_bx_reply(*self._stray_scene(fault), system_status=self.system_status)
        else:  # no tool handles; the strays only when option 0x1000 asks for them
            reply = _ndi_frame(f"00{self._strays(fault) if option & 0x1000 else ''}{self.system_status:04X}")
        spoil = (_SPOIL_BX if binary else _SPOIL_TX).get(kind)
        return spoil(reply) if spoil else reply

    def _stray_scene(self, fault: str | None) -> tuple[np.ndarray, list[bool]]:
        """The markers the camera sees: (N, 3) m in report order and their out-of-volume flags."""
        points = np.array(self.points_provider(), dtype=float).reshape(-1, 3)
        if self.noise:
            points = points + self.rng.normal(0.0, self.noise, size=points.shape)
        points = points[np.isfinite(points).all(axis=1)]  # hidden targets send no marker
        oov = [False] * len(points)
        if fault == "drop_target" and len(points):
            keep = np.delete(np.arange(len(points)), self.rng.integers(len(points)))
            points, oov = points[keep], oov[1:]
        if fault == "out_of_volume" and oov:
            oov[int(self.rng.integers(len(oov)))] = True
        if self.extra_stray or fault == "extra_stray":
            spurious = points.mean(axis=0) + self.rng.uniform(0.15, 0.3, size=3) * self.rng.choice([-1, 1], 3)
            points = np.vstack([points, spurious])
            oov.append(False)
        order = self.rng.permutation(len(points)) if self.shuffle else np.arange(len(points))
        return points[order], [oov[i] for i in order]

    def _strays(self, fault: str | None) -> str:
        points, oov = self._stray_scene(fault)
        units = np.rint(points * 1e5).astype(np.int64)  # 0.01 mm
        out = np.array(oov, dtype=bool) | (np.abs(units) > 999_999).any(axis=1)  # beyond 6 digits: out of volume
        n = len(points)
        flags = sum(1 << int(i) for i in np.flatnonzero(out))
        text = f"{n:02X}" + (f"{flags:0{math.ceil(n / 4)}X}" if n else "")
        return text + "".join(f"{v:+07d}" for v in np.clip(units, -999_999, 999_999).ravel())
