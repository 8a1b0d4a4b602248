"""SerialTracker: the ``Tracker`` port on top of transport -> framer -> protocol profile.

Example::

    targets = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.07, 0.0]])   # tool frame, m
    with open_tracker("drivers/ndi-polaris.toml", targets, url="/dev/ttyUSB0") as tracker:
        m = tracker.measure(samples=5)   # m.points (3, 3) m in the tracker frame, m.spread (3,) m
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from labcal.drivers.base import DriverError, Measurement, average_frames
from labcal.drivers.serial.ascii import AsciiProtocol
from labcal.drivers.serial.link import SerialLink, Transport, open_serial
from labcal.drivers.serial.matching import check_scalene
from labcal.drivers.serial.ndi import NDIProtocol
from labcal.drivers.serial.profiles import AsciiProfile, NDIProfile, Profile, load_profile


class SerialTracker:
    """A three-target tracker on a serial line, described by a profile (``load_profile``).

    targets: (3, 3) nominal target points in the tool frame, m (rows t1, t2, t3); the NDI profile uses their
    triangle to label unordered markers. transport: an open ``serial.Serial``-like object (tests pass a
    scripted one); otherwise ``url`` (or the profile's ``[port].url``) is opened with ``serial_for_url``.
    clock/sleep: time source and delay in s, injected so scripted tests run instantly.
    """

    def __init__(
        self,
        profile: Profile,
        targets: Any,
        *,
        transport: Transport | None = None,
        url: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        targets = np.asarray(targets, dtype=float)
        if targets.shape != (3, 3) or not np.all(np.isfinite(targets)):
            raise ValueError(f"targets must be a finite (3, 3) array in metres, got shape {targets.shape}")
        if isinstance(profile, NDIProfile):
            check_scalene(targets, profile.match_tolerance)
        elif not isinstance(profile, AsciiProfile):
            raise TypeError(f"profile must be an AsciiProfile or NDIProfile, got {type(profile).__name__}")
        self.profile = profile
        self.targets = targets
        self._clock = clock
        self._closed = False
        if transport is None:
            target_url = url or profile.port.url
            if not target_url:
                raise ValueError(f"{profile.source}: no serial port: set [port].url or pass url=")
            port = profile.port
            transport = open_serial(
                target_url,
                baudrate=port.baudrate,
                bytesize=port.bytesize,
                parity=port.parity,
                stopbits=port.stopbits,
                timeout=port.timeout,
            )
        if isinstance(profile, NDIProfile):
            terminators = (b"\r", b"\r")
        else:
            terminators = (profile.write_terminator, profile.read_terminator)
        self.link = SerialLink(
            transport,
            write_terminator=terminators[0],
            read_terminator=terminators[1],
            timeout=profile.port.timeout,
            clock=clock,
            sleep=sleep,
        )
        self.protocol: NDIProtocol | AsciiProtocol
        if isinstance(profile, NDIProfile):
            self.protocol = NDIProtocol(profile, targets, self.link, sleep)
        else:
            self.protocol = AsciiProtocol(profile, targets, self.link)
        try:
            self.protocol.start()
        except BaseException:
            self.link.close()
            self._closed = True
            raise

    def measure(self, samples: int = 1) -> Measurement:
        """Average ``samples`` frames into one Measurement (points (3, 3) m, spread (3,) m, host timestamp s).

        Raises MeasurementRejected (a target missing, out of volume or mislabelled), DriverTimeout,
        ProtocolError (after bounded retries), ConnectionFailed.
        """
        if self._closed:
            raise DriverError("measure() on a closed tracker")
        if isinstance(samples, bool) or not isinstance(samples, int | np.integer) or samples < 1:
            raise ValueError(f"samples must be a positive int, got {samples!r}")
        frames = []
        quality: list[str] = []
        for _ in range(int(samples)):
            points, flags = self.protocol.read_frame()
            frames.append(points)
            quality.extend(flags)
        return average_frames(frames, timestamp=self._clock(), quality=tuple(dict.fromkeys(quality)))

    def close(self) -> None:
        """Stop the device (best effort) and close the port. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            self.protocol.stop()
        except DriverError:
            pass  # the port may be gone already; closing must not fail because of it
        finally:
            self.link.close()

    def __enter__(self) -> SerialTracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_tracker(profile_path: str | Path, targets: Any, url: str | None = None, **kwargs: Any) -> SerialTracker:
    """Load the profile at ``profile_path`` and open the tracker; ``url`` overrides the profile's port.

    targets: (3, 3) array in metres, or the path of a targets TOML file (``unit``, ``points``).
    """
    profile = load_profile(profile_path)
    if isinstance(targets, str | Path):
        from labcal.datasets.targets import load_targets

        targets = load_targets(targets)
    return SerialTracker(profile, targets, url=url, **kwargs)
