"""Tracker identity (issue 17.1): the NDI driver asks ``VER:4`` and ``APIREV:`` (byte-exact on a scripted
transport, and against the fake device on a pty); an ASCII profile names an identity query and regex, or states
fields statically. A device that does not tell gives notes, never a failed session."""

from __future__ import annotations

import numpy as np
import pytest
from scripted_transport import ScriptedTransport
from serial_fixtures import (
    CLOSE_NDI,
    OPEN_NDI,
    TARGETS,
    TX,
    ascii_line,
    ascii_profile,
    crc16_arc_bitwise,
    ndi_reply,
    scripted_ndi,
    tool_to_tracker,
    tx_body,
)

from labcal.drivers.serial.ndi import parse_ver
from labcal.drivers.serial.tracker import SerialTracker
from labcal.tomlschema import SchemaError
from labcal_fakes.devices import FakeNDIDevice

# The commands exactly as they go on the wire (CRC16 of "VER:4" and "APIREV:", written out; checked below).
VER4 = b"VER:4A6EF\r"
APIREV = b"APIREV:443E\r"
VER_TEXT = "Polaris Vega Control Firmware\nNDI S/N: P9-00384\nFreeze Tag: Polaris Vega 001.004"
# The same reply as the device's bytes: LF-separated lines, then the CRC of all of them, then CR.
VER_REPLY = b"Polaris Vega Control Firmware\nNDI S/N: P9-00384\nFreeze Tag: Polaris Vega 001.0046A97\r"


def test_the_written_out_bytes_carry_the_right_crcs():
    assert VER4 == b"VER:4" + f"{crc16_arc_bitwise(b'VER:4'):04X}\r".encode()
    assert APIREV == b"APIREV:" + f"{crc16_arc_bitwise(b'APIREV:'):04X}\r".encode()
    assert VER_REPLY == ndi_reply(VER_TEXT)


def test_ndi_identity_is_asked_once_byte_exact_after_tracking_started():
    seen = tool_to_tracker()
    script = [*OPEN_NDI, (VER4, VER_REPLY), (APIREV, b"G.001.0056001\r"), (TX, ndi_reply(tx_body(seen))), *CLOSE_NDI]
    tracker, t = scripted_ndi(script)
    expected = {"model": "Polaris Vega", "serial": "P9-00384", "firmware": "001.004", "api_revision": "G.001.005"}
    assert tracker.device_identity() == expected
    assert tracker.device_identity() == expected  # cached: nothing more on the wire
    np.testing.assert_allclose(tracker.measure().points, seen, atol=5e-6)  # the session goes on as before
    tracker.close()
    t.assert_done()


def test_an_ndi_device_that_refuses_ver_gives_notes_and_keeps_tracking():
    # ERROR01 (invalid command) to VER, nothing at all to APIREV (a timeout): notes, no exception, no retry.
    tracker, t = scripted_ndi([*OPEN_NDI, (VER4, ndi_reply("ERROR01")), (APIREV, b""), *CLOSE_NDI])
    identity = tracker.device_identity()
    assert set(identity) == {"notes"}
    assert identity["notes"][0].startswith("VER:4 not answered: ") and "Invalid command" in identity["notes"][0]
    assert identity["notes"][1].startswith("APIREV: not answered: ")
    tracker.close()
    t.assert_done()


@pytest.mark.parametrize(
    "text,expected",
    [
        (VER_TEXT, {"model": "Polaris Vega", "serial": "P9-00384", "firmware": "001.004"}),
        (
            "Polaris Spectra\r\nSerial Number: P6-01234\r\nCombined Firmware Revision: 024",
            {"model": "Polaris Spectra", "serial": "P6-01234", "firmware": "024"},
        ),
        ("024", {"model": "024"}),  # a bare revision: nothing that looks like a serial
    ],
)
def test_ver_replies_are_parsed_line_by_line(text, expected):
    assert parse_ver(text) == expected


@pytest.mark.integration
@pytest.mark.timeout(30)
def test_the_fake_ndi_device_on_a_pty_tells_who_it_is():
    from labcal.drivers.serial.profiles import NDIProfile, PortSettings

    with FakeNDIDevice(lambda: tool_to_tracker()) as device:
        profile = NDIProfile(name="pty", port=PortSettings(url=device.port, timeout=1.0), switch_delay=0.05)
        with SerialTracker(profile, TARGETS) as tracker:
            assert tracker.device_identity() == {
                "model": "Polaris Vega",
                "serial": "P9-00384",
                "firmware": "001.004",
                "api_revision": "G.001.005",
            }
            assert np.isfinite(tracker.measure().points).all()


IDN = {"command": "ID?", "reply": r"(?P<vendor>[^,]*),(?P<model>[^,]*),(?P<serial>[^,]*),(?P<firmware>.*)"}


def _ascii_tracker(script, **identity):
    t = ScriptedTransport(script)
    profile = ascii_profile(identity=identity)
    return SerialTracker(profile, TARGETS, transport=t, clock=t.clock, sleep=t.sleep), t


def test_an_ascii_identity_query_is_sent_once_when_the_session_starts():
    seen = tool_to_tracker()
    tracker, t = _ascii_tracker([(b"ID?\n", b"ACME,LT-9,SN 0042,2.1\n"), (b"M\n", ascii_line(seen))], **IDN)
    assert tracker.device_identity() == {"vendor": "ACME", "model": "LT-9", "serial": "SN 0042", "firmware": "2.1"}
    np.testing.assert_allclose(tracker.measure().points, seen, atol=1e-6)  # 6 decimals on the wire
    tracker.close()
    t.assert_done()


def test_static_ascii_identity_fills_what_the_device_does_not_tell():
    tracker, _ = _ascii_tracker([], serial="LT-0007", model="Tracker 3")
    assert tracker.device_identity() == {"serial": "LT-0007", "model": "Tracker 3"}
    tracker, _ = _ascii_tracker([(b"ID?\n", b"garbage\n")], serial="LT-0007", **IDN)
    identity = tracker.device_identity()
    assert identity["serial"] == "LT-0007" and "does not match" in identity["notes"][0]


def test_an_identity_command_needs_its_reply_regex():
    with pytest.raises(SchemaError, match=r"ascii\.identity\.reply is required with ascii\.identity\.command"):
        ascii_profile(identity={"command": "ID?"})
    with pytest.raises(SchemaError, match=r"ascii\.identity.*unknown key 'serail'"):
        ascii_profile(identity={"serail": "x"})
