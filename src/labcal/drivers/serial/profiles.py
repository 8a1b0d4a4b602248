"""Device profiles (TOML): serial settings and the protocol of one tracker model.

A profile file has a top-level ``protocol = "ascii" | "ndi"``, a ``[port]`` table and a table named after the
protocol. The shipped examples in the repository's ``drivers/`` folder document every field; the built-in
profiles (:data:`BUILTIN_PROFILES`, loadable by name) are complete files too. ``load_profile`` checks every field
against the schemas below (:mod:`labcal.tomlschema`) and names the bad one (``drivers/x.toml: ascii.reply ...``).
An ASCII reply regex names the coordinates of the k targets it carries, ``t1_x`` … ``tk_z``.

Lengths: profiles state device units at the edge (``length_unit``, ``*_mm`` fields); the loaded objects hold SI
units (metres, seconds).
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from labcal.tomlschema import Key, SchemaError, Table, fail, non_negative, positive, read_toml, validate

LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6}
AXES = ("x", "y", "z")


class ProfileError(SchemaError):
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
    """A line-based ASCII protocol whose reply names the coordinates of k targets with regex groups t1_x ... tk_z.

    axes: for tracker-frame x, y, z, which device axis (with optional '-') holds it, e.g. ("x", "-z", "y").
    length_scale: device length unit in metres. triangle_tolerance: m, or None to skip the check of the distances
    between the targets seen (it needs two of them). targets: k, the number of targets a reply names.
    identity_command / identity_reply: a query sent once when the session starts (before ``init``) and the regex
    whose named groups (``serial``, ``model``, ``firmware`` …) become the tracker's identity; identity: static
    (field, value) pairs the profile states for a device that cannot tell (``[ascii.identity] serial = "…"``).
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
    identity_command: str | None = None
    identity_reply: re.Pattern[str] | None = None
    identity: tuple[tuple[str, str], ...] = ()

    @property
    def targets(self) -> int:
        return reply_targets(self.reply, self.source)

    @property
    def length_scale(self) -> float:
        return LENGTH_UNITS[self.length_unit]


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
    write_terminator: ClassVar[bytes] = b"\r"  # the Combined API ends every command and reply with CR
    read_terminator: ClassVar[bytes] = b"\r"

    def __post_init__(self) -> None:
        # Profiles built in code (not loaded from TOML) must not fall back to TX on a typo.
        if self.reply not in NDI_REPLIES:
            raise ValueError(f"NDIProfile.reply must be one of {list(NDI_REPLIES)}, got {self.reply!r}")


Profile = AsciiProfile | NDIProfile

NDI_REPLIES = ("tx", "bx")

# NDI COMM baud codes (Combined API); 921600/1228739/230400 exist on newer units only.
NDI_BAUD_CODES = {9600: 0, 14400: 1, 19200: 2, 38400: 3, 57600: 4, 115200: 5, 921600: 6, 1228739: 7, 230400: 8}


def _regex(text: str) -> str | None:
    try:
        re.compile(text)
    except re.error as exc:
        return f"is not a valid regular expression ({exc}): {text!r}"
    return None


def _terminator(text: str) -> str | None:
    if not text:
        return "must not be empty"
    return None if text.isascii() else f"must be ASCII, got {text!r}"


def _axes(axes: list[str]) -> str | None:
    names = [a.lstrip("+-") for a in axes]
    if sorted(names) != list(AXES) or any(len(a) - len(n) > 1 for a, n in zip(axes, names, strict=True)):
        return f"must use each of x, y, z once, optionally signed, got {axes!r}"
    return None


PORT_SCHEMA = Table(
    {
        "url": Key("str", doc="serial port or pyserial URL (socket://, loop://, a pty path)"),
        "baudrate": Key("int", default=9600, check=positive),
        "bytesize": Key("int", default=8, choices=(5, 6, 7, 8)),
        "parity": Key("str", default="N", choices=("N", "E", "O", "M", "S")),
        "stopbits": Key("number", default=1.0, choices=(1.0, 1.5, 2.0)),
        "timeout": Key("number", default=1.0, unit="s", check=positive, doc="wait for one reply line"),
    }
)
INIT_SCHEMA = Table({"command": Key("str", required=True), "expect": Key("str", check=_regex)})
IDENTITY_SCHEMA = Table(
    {
        "command": Key("str", doc="query sent once when the session starts, e.g. '*IDN?'"),
        "reply": Key("str", check=_regex, doc="full-match regex; named groups (serial, model, firmware) are kept"),
        "serial": Key("str", doc="stated serial number, for a device that cannot tell"),
        "model": Key("str"),
        "firmware": Key("str"),
    }
)
ASCII_SCHEMA = Table(
    {
        "mode": Key("str", default="poll", choices=("poll", "stream")),
        "measure_command": Key("str", doc='required when mode = "poll"'),
        "reply": Key("str", required=True, check=_regex, doc="full-match regex naming t1_x … tk_z"),
        "error_reply": Key("str", check=_regex),
        "missing": Key("str", check=_regex, doc="a coordinate matching this means the target was not seen"),
        "write_terminator": Key("str", default="\r\n", check=_terminator),
        "read_terminator": Key("str", default="\r\n", check=_terminator),
        "length_unit": Key("str", default="mm", choices=tuple(LENGTH_UNITS)),
        "axes": Key(
            "strings", shape=(3,), default=list(AXES), expect="three strings like ['x', '-z', 'y']", check=_axes
        ),
        "checksum": Key("str", default="none", choices=("none", "nmea", "crc16-arc")),
        "init": Key("tables", table=INIT_SCHEMA, default=[]),
        "close_commands": Key("strings", default=[]),
        "retries": Key("int", default=2, check=non_negative),
        "triangle_tolerance_mm": Key("number", unit="mm", check=positive, doc="pairwise-distance check"),
        "identity": Key("table", table=IDENTITY_SCHEMA, default={}, doc="who the tracker is (serial, model …)"),
    }
)
NDI_SCHEMA = Table(
    {
        "reply": Key("str", default="tx", choices=NDI_REPLIES),
        "baudrate": Key("int", default=115200, choices=tuple(NDI_BAUD_CODES)),
        "handshake": Key("bool", default=False),
        "switch_delay": Key("number", default=0.15, unit="s", check=non_negative),
        "init_timeout": Key("number", default=5.0, unit="s", check=positive),
        "match_tolerance_mm": Key("number", default=0.5, unit="mm", check=positive),
        "retries": Key("int", default=2, check=non_negative),
        "reset_on_failure": Key("bool", default=True),
    }
)


PLACEMENT_SCHEMA = Table(
    {
        "position_mm": Key(
            "vector", shape=(3,), required=True, unit="mm, robot base frame", doc="the tracker's origin (line of sight)"
        )
    }
)


def load_placement(path: str | Path) -> tuple[float, float, float] | None:
    """The tracker's origin in the robot base frame, m, from the profile's ``[placement] position_mm``; None when
    the profile has no placement. The whole profile is checked first (:func:`load_profile`)."""
    load_profile(path)
    if str(path) in BUILTIN_PROFILES and not Path(path).is_file():
        return None  # the built-in profiles describe devices, not a cell
    placement = read_toml(path, ProfileError, "device profile").get("placement")
    if not placement:
        return None
    x, y, z = (float(v) / 1000.0 for v in placement["position_mm"])
    return (x, y, z)


def _profile_schema(protocol: str) -> Table:
    keys = {
        "protocol": Key("str", required=True, choices=("ascii", "ndi")),
        "name": Key("str"),
        "description": Key("str"),
        "port": Key("table", table=PORT_SCHEMA, default={}),
        "placement": Key("table", table=PLACEMENT_SCHEMA, doc="where the tracker stands in the robot cell"),
    }
    if protocol == "ndi":
        keys["ndi"] = Key("table", table=NDI_SCHEMA, default={})
    else:
        keys["ascii"] = Key("table", table=ASCII_SCHEMA, required=True)
    return Table(keys, name="device profile")


def _fail(source: str, path: str, message: str) -> ProfileError:
    return fail(source, path, message, ProfileError)


def reply_targets(reply: re.Pattern[str], source: str = "<profile>") -> int:
    """The number of targets k a reply regex names (groups t1_x … tk_z, all of them); ProfileError otherwise."""
    found = [int(m.group(1)) for g in reply.groupindex if (m := re.fullmatch(r"t([1-9][0-9]*)_[xyz]", g))]
    k = max(found, default=1)
    missing = [f"t{i}_{a}" for i in range(1, k + 1) for a in AXES if f"t{i}_{a}" not in reply.groupindex]
    if missing:
        raise _fail(
            source,
            "ascii.reply",
            f"regex lacks named group(s) {missing} (name every coordinate: (?P<t1_x>...) ... (?P<t{k}_z>...))",
        )
    return k


def _ascii(t: dict, port: PortSettings, name: str, source: str) -> AsciiProfile:
    if t["mode"] == "poll" and not t.get("measure_command"):
        raise _fail(source, "ascii.measure_command", 'is required when mode = "poll"')
    reply = re.compile(t["reply"])
    targets = reply_targets(reply, source)
    tol_mm = t.get("triangle_tolerance_mm")
    if tol_mm is not None and targets < 2:
        raise _fail(source, "ascii.triangle_tolerance_mm", "needs at least two targets in the reply to compare")
    plain: dict[str, Any] = {
        key: t.get(key) for key in ("mode", "measure_command", "length_unit", "checksum", "retries")
    }
    optional: dict[str, Any] = {key: re.compile(t[key]) if key in t else None for key in ("error_reply", "missing")}
    ident = t["identity"]
    if ("command" in ident) != ("reply" in ident):
        given, other = ("command", "reply") if "command" in ident else ("reply", "command")
        raise _fail(source, f"ascii.identity.{other}", f"is required with ascii.identity.{given}")
    return AsciiProfile(
        name=name,
        port=port,
        reply=reply,
        **plain,
        **optional,
        write_terminator=t["write_terminator"].encode("ascii"),
        read_terminator=t["read_terminator"].encode("ascii"),
        axes=tuple(t["axes"]),
        init=tuple(InitStep(s["command"], re.compile(s["expect"]) if "expect" in s else None) for s in t["init"]),
        close_commands=tuple(t["close_commands"]),
        triangle_tolerance=None if tol_mm is None else tol_mm * 1e-3,
        source=source,
        identity_command=ident.get("command"),
        identity_reply=re.compile(ident["reply"]) if "reply" in ident else None,
        identity=tuple((k, ident[k]) for k in ("serial", "model", "firmware") if k in ident),
    )


def _ndi(t: dict, port: PortSettings, name: str, source: str) -> NDIProfile:
    if port.baudrate != 9600 or port.bytesize != 8 or port.parity != "N" or port.stopbits != 1:
        raise _fail(
            source, "port", "is wrong for NDI: an NDI device starts at 9600 8N1; set the target rate in [ndi].baudrate"
        )
    given = {k: v for k, v in t.items() if k != "match_tolerance_mm"}  # the schema's keys are the fields
    return NDIProfile(name=name, port=port, match_tolerance=t["match_tolerance_mm"] * 1e-3, source=source, **given)


def parse_profile(data: dict[str, Any], source: str = "<profile>") -> Profile:
    """Build a profile from an already-parsed TOML document (``source`` names it in error messages)."""
    protocol = data.get("protocol") if isinstance(data, dict) else None
    doc = validate(data, _profile_schema(protocol if protocol == "ndi" else "ascii"), source=source, error=ProfileError)
    pt = doc["port"]
    stopbits = int(pt["stopbits"]) if pt["stopbits"] == int(pt["stopbits"]) else pt["stopbits"]
    port = PortSettings(pt.get("url"), pt["baudrate"], pt["bytesize"], pt["parity"], stopbits, pt["timeout"])
    name = doc.get("name", Path(source).stem)
    if doc["protocol"] == "ascii":
        return _ascii(doc["ascii"], port, name, source)
    return _ndi(doc["ndi"], port, name, source)


def load_profile(path: str | Path) -> Profile:
    """Read a device profile TOML file, or a built-in profile by name (:data:`BUILTIN_PROFILES`).

    Raises ProfileError naming the file and the bad field.
    """
    if str(path) in BUILTIN_PROFILES and not Path(path).is_file():
        return parse_profile(tomllib.loads(BUILTIN_PROFILES[str(path)]), f"built-in profile {path}")
    return parse_profile(read_toml(path, ProfileError, "device profile"), str(path))


#: Profiles that ship inside labcal, loadable by name (``--tracker-profile ascii-single-smr``); print one to start a
#: profile of your own. A file of the same name in the working directory wins.
BUILTIN_PROFILES = {
    "ascii-single-smr": """\
# One spherically mounted retroreflector (SMR) per pose: a laser tracker (or the lab PC relaying it) that
# answers each poll with one point.  host "MEAS?\\r\\n" -> device "$PTS,x,y,z*HH\\r\\n" in millimetres, HH the
# NMEA-style checksum; a lost beam comes back as empty fields or "nan". The session's targets file has one point.
name = "Single-reflector ASCII tracker"
protocol = "ascii"

[port]
baudrate = 115200
timeout = 1.0

[ascii]
mode = "poll"
measure_command = "MEAS?"
reply = 'PTS,(?P<t1_x>[^,]*),(?P<t1_y>[^,]*),(?P<t1_z>[^,]*)'
error_reply = 'ERR,(?P<code>\\d+)'
missing = 'nan|NaN|-+'
length_unit = "mm"
checksum = "nmea"

[[ascii.init]]
command = "UNITS MM"
expect = "OK"
""",
}
