"""Device profiles (TOML): serial settings and the protocol of one tracker model.

A profile file has a top-level ``protocol = "ascii" | "ndi"``, a ``[port]`` table and a table named after the
protocol. The shipped examples in the repository's ``drivers/`` folder document every field. ``load_profile``
checks every field and names the bad one (``drivers/x.toml: [ascii].reply: ...``).

Lengths: profiles state device units at the edge (``length_unit``, ``*_mm`` fields); the loaded objects hold SI
units (metres, seconds).
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6}
AXES = ("x", "y", "z")
COORD_GROUPS = tuple(f"t{i}_{a}" for i in (1, 2, 3) for a in AXES)
CHECKSUMS = ("none", "nmea", "crc16-arc")
PARITIES = ("N", "E", "O", "M", "S")


class ProfileError(ValueError):
    """A device profile is missing a field or has a bad value; the message names file and field."""


@dataclass(frozen=True)
class PortSettings:
    """Serial port settings. timeout: overall wait for one reply line, s."""

    url: str | None = None
    baudrate: int = 9600
    bytesize: int = 8
    parity: str = "N"
    stopbits: float = 1
    timeout: float = 1.0


@dataclass(frozen=True)
class InitStep:
    """A command sent once after opening; ``expect`` (regex, full match) checks its reply, None: no reply."""

    command: str
    expect: re.Pattern[str] | None = None


@dataclass(frozen=True)
class AsciiProfile:
    """A line-based ASCII protocol whose reply names the nine coordinates with regex groups t1_x ... t3_z.

    axes: for tracker-frame x, y, z, which device axis (with optional '-') holds it, e.g. ("x", "-z", "y").
    length_scale: device length unit in metres. triangle_tolerance: m, or None to skip the side-length check.
    """

    name: str
    port: PortSettings
    reply: re.Pattern[str]
    mode: str = "poll"
    measure_command: str | None = None
    write_terminator: bytes = b"\r\n"
    read_terminator: bytes = b"\r\n"
    error_reply: re.Pattern[str] | None = None
    missing: re.Pattern[str] | None = None
    length_unit: str = "mm"
    axes: tuple[str, str, str] = AXES
    checksum: str = "none"
    init: tuple[InitStep, ...] = ()
    close_commands: tuple[str, ...] = ()
    retries: int = 2
    triangle_tolerance: float | None = None
    source: str = "<profile>"
    protocol: str = "ascii"

    @property
    def length_scale(self) -> float:
        return LENGTH_UNITS[self.length_unit]

    def with_url(self, url: str) -> AsciiProfile:
        return dataclasses.replace(self, port=dataclasses.replace(self.port, url=url))


@dataclass(frozen=True)
class NDIProfile:
    """NDI Combined API (Polaris family) tracking passive stray markers with ``TX:1000`` or ``BX:1000``.

    reply: "tx" (ASCII replies) or "bx" (binary replies: float32 coordinates instead of 0.01 mm digits).
    baudrate: rate switched to with COMM after INIT (the port opens at ``port.baudrate``, 9600 on power-up).
    switch_delay: s between the COMM reply and the host's own baud change. init_timeout: s, INIT is slow.
    match_tolerance: m, worst allowed difference between a measured and a nominal triangle side.
    """

    name: str
    port: PortSettings
    baudrate: int = 115200
    handshake: bool = False
    switch_delay: float = 0.15
    init_timeout: float = 5.0
    match_tolerance: float = 0.5e-3
    retries: int = 2
    reset_on_failure: bool = True
    source: str = "<profile>"
    protocol: str = "ndi"
    reply: str = "tx"  # last, so positional construction keeps its meaning

    def __post_init__(self) -> None:
        # Profiles built in code (not loaded from TOML) must not fall back to TX on a typo.
        if self.reply not in NDI_REPLIES:
            raise ValueError(f"NDIProfile.reply must be one of {list(NDI_REPLIES)}, got {self.reply!r}")

    def with_url(self, url: str) -> NDIProfile:
        return dataclasses.replace(self, port=dataclasses.replace(self.port, url=url))


Profile = AsciiProfile | NDIProfile

NDI_REPLIES = ("tx", "bx")

# NDI COMM baud codes (Combined API); 921600/1228739/230400 exist on newer units only.
NDI_BAUD_CODES = {9600: 0, 14400: 1, 19200: 2, 38400: 3, 57600: 4, 115200: 5, 921600: 6, 1228739: 7, 230400: 8}


class _Table:
    """Typed, path-aware access to one TOML table; unknown keys are errors (they are usually typos)."""

    def __init__(self, data: Any, where: str, source: str):
        if not isinstance(data, dict):
            raise ProfileError(f"{source}: {where} must be a table, got {type(data).__name__}")
        self.data = dict(data)
        self.where = where
        self.source = source
        self.used: set[str] = set()

    def fail(self, key: str, message: str) -> ProfileError:
        return ProfileError(f"{self.source}: {self.where}.{key}: {message}")

    def get(self, key: str, kind: type | tuple[type, ...], default: Any = ..., *, choices: Any = None) -> Any:
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                raise self.fail(key, "required field is missing")
            return default
        value = self.data[key]
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if isinstance(value, bool) and bool not in kinds:
            raise self.fail(key, f"expected {'/'.join(k.__name__ for k in kinds)}, got {value!r}")
        if float in kinds and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kinds):
            raise self.fail(key, f"expected {'/'.join(k.__name__ for k in kinds)}, got {value!r}")
        if choices is not None and value not in choices:
            raise self.fail(key, f"{value!r} is not one of {list(choices)}")
        return value

    def positive(self, key: str, default: Any = ..., *, allow_zero: bool = False) -> float:
        value = self.get(key, float, default)
        if value is None:
            return value
        if not (value > 0 or (allow_zero and value == 0)) or value != value or value == float("inf"):
            raise self.fail(key, f"must be {'>= 0' if allow_zero else '> 0'} and finite, got {value!r}")
        return value

    def regex(self, key: str, default: Any = ...) -> re.Pattern[str] | None:
        text = self.get(key, str, default)
        if text is None:
            return None
        try:
            return re.compile(text)
        except re.error as exc:
            raise self.fail(key, f"invalid regular expression {text!r}: {exc}") from exc

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            raise ProfileError(f"{self.source}: {self.where}: unknown field(s) {unknown}")


def _terminator(table: _Table, key: str, default: str) -> bytes:
    text = table.get(key, str, default)
    if not text:
        raise table.fail(key, "must not be empty")
    try:
        return text.encode("ascii")
    except UnicodeEncodeError as exc:
        raise table.fail(key, f"must be ASCII, got {text!r}") from exc


def _stopbits(t: _Table) -> float:
    value = t.get("stopbits", (int, float), 1, choices=(1, 1.5, 2))
    return int(value) if value == int(value) else value


def _port(data: Any, source: str) -> PortSettings:
    t = _Table(data, "[port]", source)
    port = PortSettings(
        url=t.get("url", str, None),
        baudrate=int(t.get("baudrate", int, 9600)),
        bytesize=t.get("bytesize", int, 8, choices=(5, 6, 7, 8)),
        parity=t.get("parity", str, "N", choices=PARITIES),
        stopbits=_stopbits(t),
        timeout=t.positive("timeout", 1.0),
    )
    if port.baudrate <= 0:
        raise t.fail("baudrate", f"must be > 0, got {port.baudrate}")
    t.finish()
    return port


def _axes(t: _Table) -> tuple[str, str, str]:
    axes = t.get("axes", list, list(AXES))
    if len(axes) != 3 or not all(isinstance(a, str) for a in axes):
        raise t.fail("axes", f"expected three strings like ['x', '-z', 'y'], got {axes!r}")
    names = [a.lstrip("+-") for a in axes]
    if sorted(names) != list(AXES) or any(len(a) - len(n) > 1 for a, n in zip(axes, names, strict=True)):
        raise t.fail("axes", f"must use each of x, y, z once, optionally signed, got {axes!r}")
    return (axes[0], axes[1], axes[2])


def _ascii(data: Any, port: PortSettings, name: str, source: str) -> AsciiProfile:
    t = _Table(data, "[ascii]", source)
    mode = t.get("mode", str, "poll", choices=("poll", "stream"))
    measure_command = t.get("measure_command", str, None)
    if mode == "poll" and not measure_command:
        raise t.fail("measure_command", 'required when mode = "poll"')
    reply = t.regex("reply")
    assert reply is not None
    missing_groups = [g for g in COORD_GROUPS if g not in reply.groupindex]
    if missing_groups:
        raise t.fail("reply", f"regex lacks named group(s) {missing_groups} (use (?P<t1_x>...) ... (?P<t3_z>...))")
    error_reply = t.regex("error_reply", None)
    missing = t.regex("missing", None)
    init_steps = []
    for k, step in enumerate(t.get("init", list, [])):
        st = _Table(step, f"[ascii].init[{k}]", source)
        init_steps.append(InitStep(command=st.get("command", str), expect=st.regex("expect", None)))
        st.finish()
    close_commands = t.get("close_commands", list, [])
    if not all(isinstance(c, str) for c in close_commands):
        raise t.fail("close_commands", f"expected a list of strings, got {close_commands!r}")
    retries = t.get("retries", int, 2)
    if retries < 0:
        raise t.fail("retries", f"must be >= 0, got {retries}")
    tol_mm = t.positive("triangle_tolerance_mm", None)
    profile = AsciiProfile(
        name=name,
        port=port,
        reply=reply,
        mode=mode,
        measure_command=measure_command,
        write_terminator=_terminator(t, "write_terminator", "\r\n"),
        read_terminator=_terminator(t, "read_terminator", "\r\n"),
        error_reply=error_reply,
        missing=missing,
        length_unit=t.get("length_unit", str, "mm", choices=tuple(LENGTH_UNITS)),
        axes=_axes(t),
        checksum=t.get("checksum", str, "none", choices=CHECKSUMS),
        init=tuple(init_steps),
        close_commands=tuple(close_commands),
        retries=retries,
        triangle_tolerance=None if tol_mm is None else tol_mm * 1e-3,
        source=source,
    )
    t.finish()
    return profile


def _ndi(data: Any, port: PortSettings, name: str, source: str) -> NDIProfile:
    t = _Table(data, "[ndi]", source)
    baudrate = t.get("baudrate", int, 115200, choices=tuple(NDI_BAUD_CODES))
    retries = t.get("retries", int, 2)
    if retries < 0:
        raise t.fail("retries", f"must be >= 0, got {retries}")
    profile = NDIProfile(
        name=name,
        port=port,
        reply=t.get("reply", str, "tx", choices=NDI_REPLIES),
        baudrate=baudrate,
        handshake=t.get("handshake", bool, False),
        switch_delay=t.positive("switch_delay", 0.15, allow_zero=True),
        init_timeout=t.positive("init_timeout", 5.0),
        match_tolerance=t.positive("match_tolerance_mm", 0.5) * 1e-3,
        retries=retries,
        reset_on_failure=t.get("reset_on_failure", bool, True),
        source=source,
    )
    if port.baudrate != 9600 or port.bytesize != 8 or port.parity != "N" or port.stopbits != 1:
        raise ProfileError(f"{source}: [port]: an NDI device starts at 9600 8N1; set the target rate in [ndi].baudrate")
    t.finish()
    return profile


def parse_profile(data: dict[str, Any], source: str = "<profile>") -> Profile:
    """Build a profile from an already-parsed TOML document (``source`` names it in error messages)."""
    top = _Table(data, "(top level)", source)
    protocol = top.get("protocol", str, choices=("ascii", "ndi"))
    name = top.get("name", str, Path(source).stem)
    port = _port(top.get("port", dict, {}), source)
    if protocol == "ascii":
        profile: Profile = _ascii(top.get("ascii", dict), port, name, source)
    else:
        profile = _ndi(top.get("ndi", dict, {}), port, name, source)
    top.finish()
    return profile


def load_profile(path: str | Path) -> Profile:
    """Read a device profile TOML file. Raises ProfileError naming the file and the bad field."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read device profile: {exc}") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{path}: not valid TOML: {exc}") from exc
    return parse_profile(data, str(path))
