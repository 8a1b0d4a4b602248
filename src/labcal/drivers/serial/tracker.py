"""SerialTracker: the ``Tracker`` port on top of transport -> framer -> protocol profile.

Example::

    targets = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.07, 0.0]])   # tool frame, m
    with open_tracker("drivers/ndi-polaris.toml", targets, url="/dev/ttyUSB0") as tracker:
        m = tracker.measure(samples=5)   # m.points (3, 3) m in the tracker frame (NaN rows: unseen), m.spread (3,)

    with open_tracker("ascii-single-smr", [[0.0, 0.0, 0.045]], url="/dev/ttyUSB0") as tracker:
        m = tracker.measure()            # m.points (1, 3): the one reflector
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from labcal.drivers.base import ClosedOnExit, DriverError, Measurement, average_frames
from labcal.drivers.serial.ascii import AsciiProtocol
from labcal.drivers.serial.link import SerialLink, Transport, open_serial
from labcal.drivers.serial.matching import check_targets
from labcal.drivers.serial.ndi import NDIProtocol
from labcal.drivers.serial.profiles import AsciiProfile, NDIProfile, Profile, load_profile


class SerialTracker(ClosedOnExit):
    """A tracker of the session's m targets on a serial line, described by a profile (``load_profile``).

    targets: (m, 3) nominal target points in the tool frame, m (rows t1 … tm); an ASCII profile's reply must name
    exactly m targets, and the NDI profile uses the distances between them to label unordered markers (one
    target, or three or more; see :func:`~labcal.drivers.serial.matching.check_targets`). transport: an open
    ``serial.Serial``-like object (tests pass a
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
        if targets.ndim != 2 or targets.shape[1] != 3 or len(targets) == 0 or not np.all(np.isfinite(targets)):
            raise ValueError(f"targets must be a finite (m, 3) array in metres (m >= 1), got shape {targets.shape}")
        if isinstance(profile, NDIProfile):
            check_targets(targets, profile.match_tolerance)
        elif not isinstance(profile, AsciiProfile):
            raise TypeError(f"profile must be an AsciiProfile or NDIProfile, got {type(profile).__name__}")
        elif profile.targets != len(targets):
            raise ValueError(
                f"{profile.source}: the reply names {profile.targets} target(s) (t1 … t{profile.targets}), the "
                f"session has {len(targets)}: use a profile whose reply matches the targets file"
            )
        self.profile = profile
        self.targets = targets
        self._clock = clock
        self._closed = False
        self._identity: dict[str, Any] | None = None
        if transport is None:
            target_url = url or profile.port.url
            if not target_url:
                raise ValueError(f"{profile.source}: no serial port: set [port].url or pass url=")
            transport = open_serial(**{**dataclasses.asdict(profile.port), "url": target_url})
        self.link = SerialLink(
            transport,
            write_terminator=profile.write_terminator,
            read_terminator=profile.read_terminator,
            timeout=profile.port.timeout,
            clock=clock,
            sleep=sleep,
        )
        self.protocol: NDIProtocol | AsciiProtocol = (
            AsciiProtocol(profile, targets, self.link)
            if isinstance(profile, AsciiProfile)
            else NDIProtocol(profile, targets, self.link)
        )
        try:
            self.protocol.start()
        except BaseException:
            self.link.close()
            self._closed = True
            raise

    def device_identity(self) -> dict[str, Any]:
        """What the tracker told about itself (serial, model, firmware …, ``notes`` for what it did not tell).

        NDI: asked once, here (``VER:4``, ``APIREV:``); ASCII: what the profile's ``[ascii.identity]`` gave when
        the session started (its command's reply, and the static fields). Never raises for a silent device."""
        if self._identity is None:
            if self._closed:
                raise DriverError("device_identity() on a closed tracker")
            self._identity = self.protocol.identify()
        return dict(self._identity)

    def measure(self, samples: int = 1) -> Measurement:
        """Average ``samples`` frames into one Measurement (points (m, 3) m with NaN rows for targets not seen,
        spread (m,) m, host timestamp s), each target over the frames that saw it.

        Raises MeasurementRejected (no target seen, a target out of volume, markers that cannot be labelled),
        DriverTimeout, ProtocolError (after bounded retries), ConnectionFailed.
        """
        if self._closed:
            raise DriverError("measure() on a closed tracker")
        if isinstance(samples, bool) or not isinstance(samples, int | np.integer) or samples < 1:
            raise ValueError(f"samples must be a positive int, got {samples!r}")
        labelled = self.protocol.read_frames(int(samples))
        frames = [points for points, _ in labelled]
        # "missing" flags are the averaged measurement's to give: a target seen in some frame was not missing.
        quality = [f for _, flags in labelled for f in flags if not f.startswith("missing:")]
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


def open_tracker(profile_path: str | Path, targets: Any, url: str | None = None, **kwargs: Any) -> SerialTracker:
    """Load the profile at ``profile_path`` and open the tracker; ``url`` overrides the profile's port.

    ``profile_path`` may also name a built-in profile (``ascii-single-smr``). targets: (m, 3) array in metres, or
    the path of a targets TOML file (``unit``, ``points``).
    """
    profile = load_profile(profile_path)
    if isinstance(targets, str | Path):
        from labcal.datasets.targets import load_targets

        targets = load_targets(targets)
    return SerialTracker(profile, targets, url=url, **kwargs)
