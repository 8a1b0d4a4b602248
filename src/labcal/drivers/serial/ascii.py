"""A configurable ASCII line protocol: one request (or one streamed line) gives the k targets of the session.

The reply regex names the coordinates ``t1_x ... tk_z`` in the *device's* axes and unit (k = 1 for a tracker
that follows one reflector); the profile's ``axes`` and ``length_unit`` map them to the tracker frame in metres.
An empty coordinate, or one matching the profile's ``missing`` regex, means that target was not seen: its row
comes back NaN with a ``missing:tK`` flag, and a line that saw no target at all is rejected (MeasurementRejected).
Optional checksums apply to measurement lines: ``nmea`` (``$body*HH``, XOR of the body bytes) or ``crc16-arc``
(body + 4 hex digits).
"""

from __future__ import annotations

import numpy as np

from labcal.datasets.targets import pair_distances
from labcal.drivers.base import DriverTimeout, MeasurementRejected, ProtocolError
from labcal.drivers.serial.crc import crc16_arc, xor8
from labcal.drivers.serial.link import SerialLink, retried
from labcal.drivers.serial.profiles import AXES, AsciiProfile


class DeviceError(ProtocolError):
    """The device answered with its error reply (``error_reply`` regex); ``code`` is its code group or ''."""

    def __init__(self, message: str, code: str = ""):
        super().__init__(message)
        self.code = code


def strip_checksum(line: str, kind: str) -> str:
    """Verify and remove a line checksum; raise ProtocolError when it is missing or wrong."""
    if kind == "none":
        return line
    if kind == "nmea":
        if not line.startswith("$") or len(line) < 4 or line[-3] != "*":
            raise ProtocolError(f"line is not framed as $body*HH: {line!r}")
        body, text = line[1:-3], line[-2:]
        value = xor8(body.encode("ascii"))
    else:  # "crc16-arc", the only other kind the profile loader accepts
        body, text = line[:-4], line[-4:]
        value = crc16_arc(body.encode("ascii"))
    try:
        got = int(text, 16)
    except ValueError as exc:
        raise ProtocolError(f"checksum field {text!r} is not hex in {line!r}") from exc
    if got != value:
        raise ProtocolError(f"bad {kind} checksum in {line!r}: got {got:X}, body gives {value:X}")
    return body


class AsciiProtocol:
    """The ASCII session on a SerialLink: start (init commands), read_frame, stop (close commands)."""

    def __init__(self, profile: AsciiProfile, targets: np.ndarray, link: SerialLink):
        self.profile = profile
        self.link = link
        self.targets = np.asarray(targets, dtype=float)
        self.nominal_distances = pair_distances(self.targets)
        # tracker-frame axis i is device axis _index[i], times _sign[i]
        self._index = [AXES.index(a.lstrip("+-")) for a in profile.axes]
        self._sign = np.array([-1.0 if a.startswith("-") else 1.0 for a in profile.axes])
        self.identity: dict[str, object] = {}  # filled by start()

    def _read_text(self) -> str:
        line = self.link.read_line()
        try:
            return line.decode("ascii")
        except UnicodeDecodeError as exc:
            raise ProtocolError(f"non-ASCII reply {line!r}") from exc

    def start(self) -> None:
        self.identity = self._ask_identity()
        for step in self.profile.init:
            self.link.flush_input()
            self.link.send_line(step.command)
            if step.expect is None:
                continue
            text = self._read_text()
            if not step.expect.fullmatch(text):
                raise ProtocolError(
                    f"init command {step.command!r}: reply {text!r} does not match {step.expect.pattern!r}"
                )

    def _ask_identity(self) -> dict[str, object]:
        """The profile's static identity fields, completed by the device's answer to its identity command (the
        device's word wins); an unanswered or unmatched query is a note, not an error."""
        p = self.profile
        identity: dict[str, object] = dict(p.identity)
        if p.identity_command is None or p.identity_reply is None:
            return identity
        try:
            self.link.flush_input()
            self.link.send_line(p.identity_command)
            text = self._read_text()
        except (DriverTimeout, ProtocolError) as exc:
            identity["notes"] = [f"identity command {p.identity_command!r} not answered: {exc}"]
            return identity
        m = p.identity_reply.fullmatch(text)
        if m is None:
            identity["notes"] = [f"identity reply {text[:120]!r} does not match {p.identity_reply.pattern!r}"]
        else:
            identity.update({k: v.strip() for k, v in m.groupdict().items() if v and v.strip()})
        return identity

    def identify(self) -> dict[str, object]:
        """What :meth:`start` learnt about the device (see :meth:`_ask_identity`)."""
        return dict(self.identity)

    def _fetch_line(self) -> str:
        self.link.flush_input()
        if self.profile.mode == "poll":
            assert self.profile.measure_command is not None
            self.link.send_line(self.profile.measure_command)
        else:
            # After the flush the next bytes may be the tail of a line already under way: skip to a boundary.
            self.link.read_line()
        return self._read_text()

    def _parse(self, text: str) -> tuple[np.ndarray, tuple[str, ...]]:
        p = self.profile
        err = p.error_reply.fullmatch(text) if p.error_reply is not None else None
        if err is not None:
            raise DeviceError(f"device error reply {text!r}", code=err.groupdict().get("code") or "")
        body = strip_checksum(text, p.checksum)
        m = p.reply.fullmatch(body)
        if m is None:
            raise ProtocolError(f"garbled reply {text!r} does not match {p.reply.pattern!r}")
        k = len(self.targets)
        device = np.full((k, 3), np.nan)
        missing = []
        for t in range(k):
            values = [(m.group(f"t{t + 1}_{axis}") or "").strip() for axis in AXES]
            blank = [not v or (p.missing is not None and p.missing.fullmatch(v) is not None) for v in values]
            if all(blank):
                missing.append(t)
                continue
            if any(blank):
                # Part of a point is no point: the device garbled it, it did not lose the target.
                raise ProtocolError(f"target t{t + 1} is only partly given in {text!r}")
            for a, (axis, value) in enumerate(zip(AXES, values, strict=True)):
                try:
                    device[t, a] = float(value)
                except ValueError as exc:
                    raise ProtocolError(f"t{t + 1}_{axis} = {value!r} is not a number in {text!r}") from exc
        if len(missing) == k:
            raise MeasurementRejected(f"none of the {k} target(s) seen by the tracker in {text!r}")
        if not np.all(np.isfinite(np.delete(device, missing, axis=0))):
            raise MeasurementRejected(f"non-finite coordinate in {text!r}")
        flags = tuple(f"missing:t{t + 1}" for t in missing)
        return device[:, self._index] * self._sign * p.length_scale, flags

    def read_frame(self) -> tuple[np.ndarray, tuple[str, ...]]:
        """One frame: (k, 3) target positions in the tracker frame, m (NaN rows: not seen), and quality flags.

        Retries garbled lines and timeouts.
        """
        points, flags = retried(
            self.profile.retries + 1,
            lambda: self._parse(self._fetch_line()),
            lambda error: isinstance(error, DeviceError),  # the device's own error reply: asking again cannot help
        )
        tol = self.profile.triangle_tolerance
        if tol is not None:
            # Only distances between two seen targets can be compared (NaN otherwise).
            error = np.abs(pair_distances(points) - self.nominal_distances)
            if np.any(error > tol):
                raise MeasurementRejected(
                    f"measured triangle disagrees with the targets by {np.nanmax(error) * 1e3:.3f} mm > "
                    f"{tol * 1e3:.3f} mm"
                )
        return points, flags

    def read_frames(self, samples: int) -> list[tuple[np.ndarray, tuple[str, ...]]]:
        """``samples`` frames (see :meth:`read_frame`)."""
        return [self.read_frame() for _ in range(samples)]

    def stop(self) -> None:
        for command in self.profile.close_commands:
            self.link.send_line(command)
