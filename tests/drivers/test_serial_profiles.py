"""Device profile TOML loading: the shipped profiles load, and every bad field is named."""

from __future__ import annotations

from pathlib import Path

import pytest

from labcal.drivers.serial.profiles import AsciiProfile, NDIProfile, PortSettings, ProfileError, load_profile

REPO = Path(__file__).resolve().parents[2]


def test_shipped_ndi_profile():
    p = load_profile(REPO / "drivers" / "ndi-polaris.toml")
    assert isinstance(p, NDIProfile)
    assert (p.port.baudrate, p.port.bytesize, p.port.parity, p.port.stopbits) == (9600, 8, "N", 1)
    assert p.baudrate == 115200
    assert p.reply == "tx"
    assert p.match_tolerance == pytest.approx(0.5e-3)  # given in mm, held in m


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
        (('protocol = "ascii"', 'protocol = "modbus"'), r"protocol must be one of 'ascii', 'ndi', got 'modbus'"),
        (("timeout = 0.5", "timeout = -1"), r"port\.timeout must be > 0, got -1"),
        (("timeout = 0.5", 'timeout = "fast"'), r"port\.timeout must be a finite number \(s\), got 'fast'"),
        (("timeout = 0.5", "parity = 'X'"), r"port\.parity must be one of 'N', 'E', 'O', 'M', 'S', got 'X'"),
        (("timeout = 0.5", "baud = 9600"), r"port: unknown key 'baud' \(did you mean 'baudrate'\?\)"),
        (('measure_command = "M"', ""), r"ascii\.measure_command is required when mode = \"poll\""),
        (("(?P<t2_y>.*)", "(?P<t2_Y>.*)"), r"ascii\.reply regex lacks named group\(s\) \['t2_y'\]"),
        (("(?P<t1_x>.*)", "(?P<t1_x>.*"), r"ascii\.reply is not a valid regular expression"),
        (
            ('measure_command = "M"', 'measure_command = "M"\nlength_unit = "inch"'),
            r"length_unit must be one of 'm', 'mm', 'um', got",
        ),
        (('measure_command = "M"', 'measure_command = "M"\naxes = ["x", "x", "z"]'), r"ascii\.axes must use each"),
        (('measure_command = "M"', 'measure_command = "M"\naxes = ["x", "y"]'), r"ascii\.axes must be three strings"),
        (
            ('measure_command = "M"', 'measure_command = "M"\nchecksum = "md5"'),
            r"checksum must be one of 'none', 'nmea', 'crc16-arc'",
        ),
        (('measure_command = "M"', 'measure_command = "M"\nretries = -1'), r"ascii\.retries must be >= 0, got -1"),
        (
            ('measure_command = "M"', 'measure_command = "M"\nread_terminator = ""'),
            r"read_terminator must not be empty",
        ),
        (("[ascii]", '[[ascii.init]]\nexpect = "OK"\n[ascii]'), r"ascii\.init\[1\]\.command is missing \(required\)"),
        (('measure_command = "M"', 'measure_command = "M"\ntimeout = 1'), r"ascii: unknown key 'timeout'"),
        (("[ascii]", "[asci]"), r"device profile: unknown key 'asci' \(did you mean 'ascii'\?\)"),
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
        ('protocol = "ndi"\n[ndi]\nbaudrate = 100000', r"ndi\.baudrate must be one of 9600, .*, got 100000"),
        ('protocol = "ndi"\n[ndi]\nmatch_tolerance_mm = 0', r"ndi\.match_tolerance_mm must be > 0, got 0"),
        (
            'protocol = "ndi"\n[ndi]\nreset_on_failure = "yes"',
            r"ndi\.reset_on_failure must be true or false, got",
        ),
        ('protocol = "ndi"\n[ndi]\nretries = true', r"ndi\.retries must be an integer, got True"),
        ('protocol = "ndi"\n[port]\nbaudrate = 115200', r"starts at 9600 8N1"),
        ('protocol = "ndi"\n[ndi]\nreply = "binary"', r"ndi\.reply must be one of 'tx', 'bx', got 'binary'"),
        ('protocol = "ndi"\n[ndi]\nreply = "BX"', r"ndi\.reply must be one of 'tx', 'bx', got 'BX'"),
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


def test_an_ascii_profile_without_its_table_names_it(tmp_path):
    with pytest.raises(ProfileError, match=r"device\.toml: ascii is missing \(required\)"):
        load_profile(write(tmp_path, 'protocol = "ascii"\n'))


ONE_POINT = GOOD_ASCII.replace(
    """reply = '''(?x)(?P<t1_x>.*),(?P<t1_y>.*),(?P<t1_z>.*),
  (?P<t2_x>.*),(?P<t2_y>.*),(?P<t2_z>.*),(?P<t3_x>.*),(?P<t3_y>.*),(?P<t3_z>.*)'''""",
    "reply = '(?P<t1_x>.*),(?P<t1_y>.*),(?P<t1_z>.*)'",
)


def test_the_reply_regex_says_how_many_targets_a_reply_carries(tmp_path):
    assert load_profile(write(tmp_path, GOOD_ASCII)).targets == 3
    assert load_profile(write(tmp_path, ONE_POINT)).targets == 1
    four = GOOD_ASCII.replace("(?P<t3_z>.*)", "(?P<t3_z>.*),(?P<t4_x>.*),(?P<t4_y>.*),(?P<t4_z>.*)")
    assert load_profile(write(tmp_path, four)).targets == 4
    gap = GOOD_ASCII.replace("(?P<t3_z>.*)", "(?P<t3_z>.*),(?P<t5_x>.*),(?P<t5_y>.*),(?P<t5_z>.*)")
    with pytest.raises(ProfileError, match=r"lacks named group\(s\) \['t4_x', 't4_y', 't4_z'\]"):
        load_profile(write(tmp_path, gap))


def test_a_distance_check_needs_two_targets(tmp_path):
    text = ONE_POINT.replace('measure_command = "M"', 'measure_command = "M"\ntriangle_tolerance_mm = 1.0')
    with pytest.raises(ProfileError, match=r"ascii\.triangle_tolerance_mm needs at least two targets"):
        load_profile(write(tmp_path, text))


def test_the_single_reflector_profile_is_built_in(tmp_path, monkeypatch):
    from labcal.drivers.serial.profiles import BUILTIN_PROFILES

    p = load_profile("ascii-single-smr")
    assert isinstance(p, AsciiProfile) and p.targets == 1 and p.checksum == "nmea" and p.length_scale == 1e-3
    assert p.reply.fullmatch("PTS,1.5,-2,3").group("t1_y") == "-2" and p.source == "built-in profile ascii-single-smr"
    # its text is a profile file to copy: the same profile when written out and loaded from a file
    copy = load_profile(write(tmp_path, BUILTIN_PROFILES["ascii-single-smr"]))
    assert copy.reply.pattern == p.reply.pattern and copy.init == p.init and copy.targets == 1
    # a file of that name in the working directory wins over the built-in
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ascii-single-smr").write_text(GOOD_ASCII)
    assert load_profile("ascii-single-smr").targets == 3
