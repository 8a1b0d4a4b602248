"""CRC/checksums and the transport + framer layer (SerialLink)."""

from __future__ import annotations

import pytest
import serial
from hypothesis import given
from hypothesis import strategies as st
from scripted_transport import ScriptedTransport
from serial_fixtures import crc16_arc_bitwise

from labcal.drivers.base import ConnectionFailed, DriverTimeout, ProtocolError
from labcal.drivers.serial.crc import crc16_arc, xor8
from labcal.drivers.serial.link import SerialLink, open_serial
from labcal.drivers.serial.ndi import decode_reply, encode_command


def test_crc16_arc_check_value():
    assert crc16_arc(b"123456789") == 0xBB3D


@pytest.mark.parametrize(
    ("text", "crc"),
    [(b"INIT:", 0xE3A5), (b"OKAY", 0xA896), (b"RESET", 0xBE6F), (b"", 0x0000)],  # from the NDI API examples
)
def test_crc16_arc_known_ndi_frames(text, crc):
    assert crc16_arc(text) == crc


@given(st.binary(max_size=300))
def test_crc16_arc_agrees_with_a_bitwise_implementation_and_not_crc_hqx(data):
    assert crc16_arc(data) == crc16_arc_bitwise(data)


@given(st.binary(min_size=1, max_size=200))
def test_crc16_arc_residue_of_data_plus_its_little_endian_crc_is_zero(data):
    # A reflected CRC with no final XOR leaves a zero remainder when its own value is appended LSB first.
    assert crc16_arc(data + crc16_arc(data).to_bytes(2, "little")) == 0


def test_crc_hqx_is_a_different_crc():
    import binascii

    assert binascii.crc_hqx(b"123456789", 0) != crc16_arc(b"123456789")


def test_nmea_xor_of_a_published_sentence():
    assert xor8(b"GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") == 0x47


def test_encode_command_colon_form_gets_crc_space_form_does_not():
    assert encode_command("INIT:") == b"INIT:E3A5\r"
    assert encode_command("BEEP 1") == b"BEEP 1\r"


def test_decode_reply_checks_crc_and_length():
    assert decode_reply(b"OKAYA896") == "OKAY"
    with pytest.raises(ProtocolError, match="bad CRC"):
        decode_reply(b"OKAYA897")
    with pytest.raises(ProtocolError, match="too short"):
        decode_reply(b"A896")
    with pytest.raises(ProtocolError, match="garbled"):
        decode_reply(b"OKAYXYZW")


# -- framer ----------------------------------------------------------------------------------------------------


def link_for(data: bytes, terminator: bytes = b"\r\n", timeout: float = 0.2) -> tuple[SerialLink, ScriptedTransport]:
    t = ScriptedTransport([], pending_input=data, read_timeout=0.05)
    link = SerialLink(t, write_terminator=b"\n", read_terminator=terminator, timeout=timeout, clock=t.clock)
    return link, t


def test_read_line_returns_lines_without_terminator_one_at_a_time():
    link, t = link_for(b"first\r\nsecond\rstill second\r\n")
    assert link.read_line() == b"first"
    assert link.read_line() == b"second\rstill second"  # a lone CR is data when the terminator is CR LF
    t.assert_done()


def test_read_line_times_out_on_partial_line_and_reports_what_arrived():
    link, t = link_for(b"no terminator")
    with pytest.raises(DriverTimeout, match=r"0.2 s; partial reply b'no terminator'"):
        link.read_line()
    assert t.now == pytest.approx(0.2)  # the deadline, not one read timeout, bounded the wait


def test_read_line_times_out_on_silence():
    link, _ = link_for(b"")
    with pytest.raises(DriverTimeout, match=r"no complete reply within 0.2 s$"):
        link.read_line()


def test_overlong_line_is_a_protocol_error():
    link, _ = link_for(b"x" * 100)
    link.max_line = 50
    with pytest.raises(ProtocolError, match="longer than 50 bytes"):
        link.read_line()


@pytest.mark.parametrize("max_read", [None, 1])
def test_read_exact_returns_n_bytes_whatever_they_are_and_leaves_the_rest(max_read):
    link, t = link_for(b"\xc4\r\n\x00\r\xa5\nrest\r\n")
    t.max_read = max_read  # 1: the bytes trickle in one per read
    assert link.read_exact(6) == b"\xc4\r\n\x00\r\xa5"  # terminators are data in a counted read
    assert link.read_exact(0) == b""
    assert link.read_line() == b"\nrest"
    t.assert_done()


def test_read_exact_times_out_reporting_how_much_arrived():
    link, t = link_for(b"\xc4\xa5\x01")
    with pytest.raises(DriverTimeout, match=r"within 0.2 s: 3 of 8 bytes; partial reply b'\\xc4\\xa5\\x01'"):
        link.read_exact(8)
    assert t.now == pytest.approx(0.2)  # the deadline, not one read timeout, bounded the wait


def test_read_exact_times_out_on_silence():
    link, _ = link_for(b"")
    with pytest.raises(DriverTimeout, match=r"no complete reply within 0.05 s: 0 of 6 bytes$"):
        link.read_exact(6, timeout=0.05)


def test_read_exact_refuses_a_negative_count():
    link, _ = link_for(b"")
    with pytest.raises(ValueError, match="negative"):
        link.read_exact(-1)


def test_drain_reads_until_the_line_is_quiet_and_is_bounded():
    link, t = link_for(b"rest of a bad reply")
    assert link.drain() == b"rest of a bad reply"
    assert link.drain() == b""
    t.assert_done()
    link, t = link_for(b"x" * 100)
    link.max_line = 50
    assert link.drain() == b"x" * 51  # a streaming device cannot keep it reading forever


class ExplodingTransport(ScriptedTransport):
    def read(self, size: int = 1) -> bytes:
        raise serial.SerialException("device reports readiness to read but returned no data")

    def write(self, data: bytes) -> int:
        raise OSError(5, "Input/output error")


def test_library_errors_become_connection_failed():
    t = ExplodingTransport([])
    link = SerialLink(t, write_terminator=b"\r", read_terminator=b"\r", timeout=0.1, clock=t.clock)
    with pytest.raises(ConnectionFailed, match="serial read failed: device reports"):
        link.read_line()
    with pytest.raises(ConnectionFailed, match="serial read failed: device reports"):
        link.read_exact(8)
    with pytest.raises(ConnectionFailed, match=r"serial write failed.*Input/output error"):
        link.send_line("X")
    link.close()
    link.close()
    with pytest.raises(ConnectionFailed, match="closed"):
        link.send_line("X")


def test_opening_a_missing_port_is_connection_failed_naming_it():
    with pytest.raises(ConnectionFailed, match="/dev/does-not-exist-labcal"):
        open_serial("/dev/does-not-exist-labcal", baudrate=9600, bytesize=8, parity="N", stopbits=1, timeout=0.1)


def test_loop_url_round_trip_through_pyserial():
    port = open_serial("loop://", baudrate=9600, bytesize=8, parity="N", stopbits=1, timeout=0.2)
    link = SerialLink(port, write_terminator=b"\r", read_terminator=b"\r", timeout=0.2)
    try:
        link.write(encode_command("TX:1000") + b"\r")
        assert link.read_line() == b"TX:10003FDA"
        assert link.read_line(timeout=0.05) == b""  # the second CR: an empty line, not a timeout
        with pytest.raises(DriverTimeout):
            link.read_line(timeout=0.05)
    finally:
        link.close()
