"""Byte-exact tests of the configurable ASCII line protocol on a scripted transport."""

from __future__ import annotations

import numpy as np
import pytest
from serial_fixtures import TARGETS, ascii_line, ascii_profile, tool_to_tracker

from labcal.drivers.base import DriverTimeout, MeasurementRejected, ProtocolError
from labcal.drivers.serial.ascii import DeviceError
from labcal.drivers.serial_tracker import SerialTracker
from labcal.testing.fakes import ScriptedTransport

SEEN = tool_to_tracker()


def open_ascii(script, **ascii_overrides):
    t = ScriptedTransport(script)
    tracker = SerialTracker(ascii_profile(**ascii_overrides), TARGETS, transport=t, clock=t.clock, sleep=t.sleep)
    return tracker, t


def test_init_commands_then_polled_measurement():
    init = [{"command": "HELLO", "expect": "HI v\\d"}, {"command": "MODE 3"}]  # MODE 3 has no reply
    tracker, t = open_ascii([(b"HELLO\n", b"HI v2\n"), (b"MODE 3\n", b""), (b"M\n", ascii_line(SEEN))], init=init)
    m = tracker.measure()
    tracker.close()
    t.assert_done()
    np.testing.assert_allclose(m.points, SEEN, atol=1e-6)


def test_init_reply_that_does_not_match_fails_the_open_and_closes_the_port():
    t = ScriptedTransport([(b"HELLO\n", b"WHO?\n")])
    with pytest.raises(ProtocolError, match="'HELLO': reply 'WHO\\?' does not match"):
        SerialTracker(ascii_profile(init=[{"command": "HELLO", "expect": "HI.*"}]), TARGETS, transport=t, clock=t.clock)
    assert t.closed


def test_unit_and_axis_order_map_device_values_to_tracker_metres():
    # Device reports millimetres with its axes (a, b, c) = tracker (x, -z, y) ... i.e. tracker x = device x,
    # tracker y = device z, tracker z = -device y.
    device = np.column_stack([SEEN[:, 0], -SEEN[:, 2], SEEN[:, 1]])
    tracker, t = open_ascii([(b"M\n", ascii_line(device, scale=1e-3))], length_unit="mm", axes=["x", "z", "-y"])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-9)
    t.assert_done()


@pytest.mark.parametrize("unit,scale", [("m", 1.0), ("mm", 1e-3), ("um", 1e-6)])
def test_length_units(unit, scale):
    tracker, t = open_ascii([(b"M\n", ascii_line(SEEN, scale=scale))], length_unit=unit)
    np.testing.assert_allclose(tracker.measure().points, SEEN, rtol=1e-5, atol=1e-12)
    t.assert_done()


def test_garbled_then_timeout_is_retried_within_the_budget():
    tracker, t = open_ascii([(b"M\n", b"P 1 2\n"), (b"M\n", b""), (b"M\n", ascii_line(SEEN))], retries=2)
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-6)
    t.assert_done()


def test_retries_exhausted_raise_the_last_error():
    tracker, t = open_ascii([(b"M\n", b"P 1 2\n"), (b"M\n", b"")], retries=1)
    with pytest.raises(DriverTimeout):
        tracker.measure()
    t.assert_done()


def test_device_error_reply_is_raised_with_its_code_without_retry():
    tracker, t = open_ascii([(b"M\n", b"E42\n")])
    with pytest.raises(DeviceError, match="E42") as info:
        tracker.measure()
    assert info.value.code == "42"
    t.assert_done()


def test_empty_or_missing_marked_coordinates_reject_the_frame():
    line = ascii_line(SEEN).decode().split(" ")
    line[4:7] = ["", "", ""]  # t2 not seen
    tracker, t = open_ascii([(b"M\n", " ".join(line).encode())])
    with pytest.raises(MeasurementRejected, match="t2 not seen"):
        tracker.measure()
    line = ascii_line(SEEN).decode().split(" ")
    line[9] = "----\n"  # t3_z reported as dashes
    tracker2, t2 = open_ascii([(b"M\n", " ".join(line).encode())], missing="-+")
    with pytest.raises(MeasurementRejected, match="t3 not seen"):
        tracker2.measure()
    t.assert_done()
    t2.assert_done()


def test_unparseable_coordinate_is_garbled():
    line = ascii_line(SEEN).decode().replace(" ", " x", 1)
    tracker, t = open_ascii([(b"M\n", line.encode())], retries=0)
    with pytest.raises(ProtocolError, match=r"t1_x = 'x.*' is not a number"):
        tracker.measure()
    t.assert_done()


def test_nmea_checksum_good_bad_and_missing():
    body = ascii_line(SEEN).decode().strip()
    xor = 0
    for ch in body.encode():
        xor ^= ch
    good = f"${body}*{xor:02X}\n".encode()
    bad = f"${body}*{xor ^ 1:02X}\n".encode()
    unframed = body.encode() + b"\n"
    script = [(b"M\n", bad), (b"M\n", good), (b"M\n", unframed), (b"M\n", unframed)]
    tracker, t = open_ascii(script, checksum="nmea", retries=1)
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-6)  # the bad one was retried
    with pytest.raises(ProtocolError, match=r"not framed as \$body\*HH"):
        tracker.measure()
    t.assert_done()


def test_crc16_checksum_on_lines():
    from serial_fixtures import crc16_arc_bitwise

    body = ascii_line(SEEN).decode().strip()
    line = f"{body}{crc16_arc_bitwise(body.encode()):04X}\n".encode()
    tracker, t = open_ascii([(b"M\n", line)], checksum="crc16-arc")
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-6)
    t.assert_done()


def test_triangle_check_rejects_a_bent_triangle():
    bent = SEEN.copy()
    bent[2] += [0.0, 0.0, 0.01]
    tracker, t = open_ascii([(b"M\n", ascii_line(bent))], triangle_tolerance_mm=0.5)
    with pytest.raises(MeasurementRejected, match="disagrees with the targets"):
        tracker.measure()
    t.assert_done()


def test_stream_mode_skips_stale_input_and_the_first_partial_line():
    # Streaming device: the start command is an init step; lines then arrive unrequested.
    stale = b"P 9 9 9 9 9 9 9 9 9\nP 8 8"  # old full line + the head of the next, both before the request
    tail = b" 8 8 8 8 8 8 8\n"  # rest of the line under way when labcal flushed: must be skipped
    init = [{"command": "GO", "expect": "OK"}]
    t = ScriptedTransport([(b"GO\n", b"OK\n" + stale)])
    tracker = SerialTracker(
        ascii_profile(mode="stream", init=init, close_commands=["STOP"]),
        TARGETS,
        transport=t,
        clock=t.clock,
    )
    t.script.append((b"STOP\n", b""))
    t.feed(b"")  # nothing new yet; the flush at measure() drops `stale`
    original_flush = t.reset_input_buffer

    def flush_then_device_sends():
        original_flush()
        t.feed(tail + ascii_line(SEEN))

    t.reset_input_buffer = flush_then_device_sends
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-6)
    tracker.close()
    t.assert_done()
    assert ("flush", stale) in t.events
