"""Device profile TOML loading: the shipped profiles load, and every bad field is named."""

from __future__ import annotations

from pathlib import Path

import pytest

from labcal.drivers.serial_tracker import AsciiProfile, NDIProfile, PortSettings, ProfileError, load_profile

REPO = Path(__file__).resolve().parents[2]


def test_shipped_ndi_profile():
    p = load_profile(REPO / "drivers" / "ndi-polaris.toml")
    assert isinstance(p, NDIProfile)
    assert (p.port.baudrate, p.port.bytesize, p.port.parity, p.port.stopbits) == (9600, 8, "N", 1)
    assert p.baudrate == 115200
    assert p.reply == "tx"
    assert p.match_tolerance == pytest.approx(0.5e-3)  # given in mm, held in m
    assert p.with_url("/dev/pts/9").port.url == "/dev/pts/9"


def test_shipped_ascii_profile():
    p = load_profile(REPO / "drivers" / "ascii-example.toml")
    assert isinstance(p, AsciiProfile)
    assert p.write_terminator == b"\r\n" and p.read_terminator == b"\r\n"
    assert p.length_scale == 1e-3
    assert p.checksum == "nmea"
    assert [s.command for s in p.init] == ["*IDN?", "UNITS MM"]
    m = p.reply.fullmatch("PTS,1,2,3,4,5,6,7,8,9")
    assert m is not None and m.group("t3_z") == "9"
    assert p.triangle_tolerance == pytest.approx(1e-3)


GOOD_ASCII = """
protocol = "ascii"
[port]
timeout = 0.5
[ascii]
measure_command = "M"
reply = '''(?x)(?P<t1_x>.*),(?P<t1_y>.*),(?P<t1_z>.*),
  (?P<t2_x>.*),(?P<t2_y>.*),(?P<t2_z>.*),(?P<t3_x>.*),(?P<t3_y>.*),(?P<t3_z>.*)'''
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "device.toml"
    path.write_text(text)
    return path


def test_minimal_ascii_profile_gets_defaults_and_its_name_from_the_file(tmp_path):
    p = load_profile(write(tmp_path, GOOD_ASCII))
    assert p.name == "device" and p.mode == "poll" and p.axes == ("x", "y", "z") and p.checksum == "none"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (('protocol = "ascii"', 'protocol = "modbus"'), r"\(top level\)\.protocol: 'modbus' is not one of"),
        (("timeout = 0.5", "timeout = -1"), r"\[port\]\.timeout: must be > 0"),
        (("timeout = 0.5", 'timeout = "fast"'), r"\[port\]\.timeout: expected float"),
        (("timeout = 0.5", "parity = 'X'"), r"\[port\]\.parity: 'X' is not one of"),
        (("timeout = 0.5", "baud = 9600"), r"\[port\]: unknown field\(s\) \['baud'\]"),
        (('measure_command = "M"', ""), r"\[ascii\]\.measure_command: required when mode = \"poll\""),
        (("(?P<t2_y>.*)", "(?P<t2_Y>.*)"), r"\[ascii\]\.reply: regex lacks named group\(s\) \['t2_y'\]"),
        (("(?P<t1_x>.*)", "(?P<t1_x>.*"), r"\[ascii\]\.reply: invalid regular expression"),
        (('measure_command = "M"', 'measure_command = "M"\nlength_unit = "inch"'), r"length_unit: 'inch'"),
        (('measure_command = "M"', 'measure_command = "M"\naxes = ["x", "x", "z"]'), r"axes: must use each"),
        (('measure_command = "M"', 'measure_command = "M"\naxes = ["x", "y"]'), r"axes: expected three"),
        (('measure_command = "M"', 'measure_command = "M"\nchecksum = "md5"'), r"checksum: 'md5'"),
        (('measure_command = "M"', 'measure_command = "M"\nretries = -1'), r"retries: must be >= 0"),
        (('measure_command = "M"', 'measure_command = "M"\nread_terminator = ""'), r"read_terminator: must not"),
        (("[ascii]", '[[ascii.init]]\nexpect = "OK"\n[ascii]'), r"\[ascii\]\.init\[0\]\.command: required"),
        (('measure_command = "M"', 'measure_command = "M"\ntimeout = 1'), r"\[ascii\]: unknown field"),
        (("[ascii]", "[asci]"), r"\(top level\)\.ascii: required field is missing"),
    ],
)
def test_bad_ascii_fields_are_named(tmp_path, change, message):
    old, new = change
    assert old in GOOD_ASCII
    path = write(tmp_path, GOOD_ASCII.replace(old, new, 1))
    with pytest.raises(ProfileError, match=message) as info:
        load_profile(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('protocol = "ndi"\n[ndi]\nbaudrate = 100000', r"\[ndi\]\.baudrate: 100000 is not one of"),
        ('protocol = "ndi"\n[ndi]\nmatch_tolerance_mm = 0', r"\[ndi\]\.match_tolerance_mm: must be > 0"),
        ('protocol = "ndi"\n[ndi]\nreset_on_failure = "yes"', r"reset_on_failure: expected bool"),
        ('protocol = "ndi"\n[ndi]\nretries = true', r"retries: expected int, got True"),
        ('protocol = "ndi"\n[port]\nbaudrate = 115200', r"starts at 9600 8N1"),
        ('protocol = "ndi"\n[ndi]\nreply = "binary"', r"\[ndi\]\.reply: 'binary' is not one of \['tx', 'bx'\]"),
        ('protocol = "ndi"\n[ndi]\nreply = "BX"', r"\[ndi\]\.reply: 'BX' is not one of"),
        ("protocol = ", r"not valid TOML"),
    ],
)
def test_bad_ndi_fields_are_named(tmp_path, text, message):
    with pytest.raises(ProfileError, match=message):
        load_profile(write(tmp_path, text))


def test_ndi_reply_bx_is_selected_in_the_profile(tmp_path):
    p = load_profile(write(tmp_path, 'protocol = "ndi"\n[ndi]\nreply = "bx"\n'))
    assert isinstance(p, NDIProfile) and p.reply == "bx"
    assert load_profile(write(tmp_path, 'protocol = "ndi"\n')).reply == "tx"


def test_ndi_profile_built_in_code_refuses_an_unknown_reply():
    with pytest.raises(ValueError, match=r"NDIProfile.reply must be one of \['tx', 'bx'\], got 'TX'"):
        NDIProfile(name="x", port=PortSettings(), reply="TX")


def test_missing_file_is_a_profile_error(tmp_path):
    with pytest.raises(ProfileError, match="cannot read device profile"):
        load_profile(tmp_path / "nope.toml")
