"""The example ASCII tracker of drivers/ascii-example.toml as a fake device on a pty (test_fakes_pty.py)."""

from __future__ import annotations

import time

import numpy as np

from labcal.drivers.serial.crc import xor8
from labcal_fakes.devices import PointsProvider, PtyDevice


class FakeASCIIDevice(PtyDevice):
    """The example ASCII tracker of ``drivers/ascii-example.toml`` (CR LF lines, mm, NMEA-style checksum).

    Commands: ``*IDN?`` -> ``LABCAL,FAKE-3T,FK-0001,1.0`` (maker, model ``FAKE-<m>T`` for m targets, ``serial``,
    firmware); ``UNITS MM`` -> ``OK``;
    ``MEAS?`` -> ``$PTS,x1,y1,z1,...,zm*HH`` (m = the rows of ``points_provider()``: one for the built-in
    ``ascii-single-smr`` profile); ``STREAM ON``/``STREAM OFF`` -> ``OK`` (while on, a measurement line every
    1/stream_hz s); anything else -> ``ERR,01``. A target the device cannot see (a NaN row, or the
    ``drop_target`` fault) has empty fields.
    """

    terminator = b"\r\n"
    FAULTS = ("no_reply", "bad_checksum", "garbled", "drop_target", "error")

    def __init__(
        self,
        points_provider: PointsProvider | None = None,
        *,
        seed: int = 0,
        noise: float = 0.0,
        stream_hz: float = 100.0,
    ):
        super().__init__(points_provider, seed)
        self.serial = "FK-0001"
        self.noise = float(noise)
        self.stream_hz = float(stream_hz)
        self.streaming = False
        self._next_stream = 0.0

    def _line(self, text: str) -> bytes:
        return text.encode("ascii") + b"\r\n"

    def measurement_line(self, fault: str | None = None) -> bytes | None:
        points = np.array(self.points_provider(), dtype=float).reshape(-1, 3)
        if self.noise:
            points = points + self.rng.normal(0.0, self.noise, size=points.shape)
        if fault == "no_reply":
            return None
        if fault is not None and fault.startswith("error"):
            return self._line("ERR," + (fault.partition(":")[2] or "05"))
        fields = ["" if not np.isfinite(v) else f"{v * 1e3:.4f}" for v in points.ravel()]
        if fault == "drop_target":
            k = int(self.rng.integers(len(points)))
            fields[3 * k : 3 * k + 3] = ["", "", ""]
        body = "PTS," + ",".join(fields)
        checksum = xor8(body.encode("ascii")) ^ (0x5A if fault == "bad_checksum" else 0)
        line = f"${body}*{checksum:02X}"
        if fault == "garbled":
            line = line[:10] + "?!" + line[14:]
        return self._line(line)

    def handle(self, line: str) -> bytes | None:
        command = line.strip().upper()
        if command == "*IDN?":
            m = len(np.asarray(self.points_provider()).reshape(-1, 3))
            return self._line(f"LABCAL,FAKE-{m}T,{self.serial},1.0")
        if command == "UNITS MM":
            return self._line("OK")
        if command == "MEAS?":
            return self.measurement_line(self._next_fault())
        if command in ("STREAM ON", "STREAM OFF"):
            self.streaming = command == "STREAM ON"
            self._next_stream = time.monotonic()
            return self._line("OK")
        return self._line("ERR,01")

    def tick(self) -> None:
        if self.streaming and time.monotonic() >= self._next_stream:
            self._next_stream += 1.0 / self.stream_hz
            line = self.measurement_line(self._next_fault())
            if line:
                # A real streaming device loses lines nobody reads; so does this one (short send timeout).
                self.send(line, timeout=0.001)
