"""Byte-exact tests of the configurable ASCII line protocol on a scripted transport."""

from __future__ import annotations

import numpy as np
import pytest
from scripted_transport import ScriptedTransport
from serial_fixtures import TARGETS, ascii_line, ascii_profile, tool_to_tracker

from labcal.drivers.base import DriverTimeout, MeasurementRejected, ProtocolError
from labcal.drivers.serial.ascii import DeviceError
from labcal.drivers.serial.crc import xor8
from labcal.drivers.serial.profiles import load_profile
from labcal.drivers.serial.tracker import SerialTracker

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


def test_empty_or_missing_marked_coordinates_are_targets_not_seen():
    line = ascii_line(SEEN).decode().split(" ")
    line[4:7] = ["", "", ""]  # t2 not seen
    tracker, t = open_ascii([(b"M\n", " ".join(line).encode())])
    m = tracker.measure()
    assert m.seen.tolist() == [True, False, True] and m.quality == ("missing:t2",)
    np.testing.assert_allclose(m.points[[0, 2]], SEEN[[0, 2]], atol=1e-6)
    line = ascii_line(SEEN).decode().split(" ")
    line[7:10] = ["--", "-", "----\n"]  # t3 reported as dashes
    tracker2, t2 = open_ascii([(b"M\n", " ".join(line).encode())], missing="-+")
    assert tracker2.measure().seen.tolist() == [True, True, False]
    t.assert_done()
    t2.assert_done()


def test_a_line_that_saw_no_target_is_rejected():
    blank = ("P" + " " * 9 + "\n").encode()
    tracker, t = open_ascii([(b"M\n", blank)])
    with pytest.raises(MeasurementRejected, match="none of the 3 target"):
        tracker.measure()
    t.assert_done()


def test_a_partly_given_point_is_garbled_not_unseen():
    line = ascii_line(SEEN).decode().split(" ")
    line[5] = ""  # t2_y alone is empty: the line is damaged, the target was not lost
    tracker, t = open_ascii([(b"M\n", " ".join(line).encode())], retries=0)
    with pytest.raises(ProtocolError, match="t2 is only partly given"):
        tracker.measure()
    t.assert_done()


def test_each_target_is_averaged_over_the_frames_that_saw_it():
    lost = ascii_line(SEEN).decode().split(" ")
    lost[1:4] = ["", "", ""]  # t1 not seen in the second frame
    shifted = SEEN + np.array([0.001, 0.0, 0.0])
    script = [(b"M\n", ascii_line(SEEN)), (b"M\n", " ".join(lost).encode()), (b"M\n", ascii_line(shifted))]
    tracker, t = open_ascii(script)
    m = tracker.measure(samples=3)
    t.assert_done()
    # the line carries micrometres: compare at that resolution
    np.testing.assert_allclose(m.points[0], SEEN[0] + [0.0005, 0.0, 0.0], atol=1e-6)  # frames 1 and 3 only
    np.testing.assert_allclose(m.points[1], SEEN[1] + [0.001 / 3, 0.0, 0.0], atol=1e-6)
    assert abs(m.points[0, 0] - SEEN[0, 0] - 0.0005) < abs(m.points[0, 0] - SEEN[0, 0] - 0.001 / 3) - 1e-4
    assert m.quality == () and m.samples == 3  # t1 was seen in some frame: not missing


def test_the_triangle_check_compares_only_targets_that_were_seen():
    line = ascii_line(SEEN).decode().split(" ")
    line[7:10] = ["", "", "\n"]
    bent = SEEN.copy()
    bent[1] += 0.003 * (SEEN[1] - SEEN[0]) / np.linalg.norm(SEEN[1] - SEEN[0])  # t1-t2 grows by 3 mm
    tracker, t = open_ascii([(b"M\n", " ".join(line).encode()), (b"M\n", ascii_line(bent))], triangle_tolerance_mm=1.0)
    assert tracker.measure().seen.tolist() == [True, True, False]
    with pytest.raises(MeasurementRejected, match=r"disagrees with the targets by 3\.000 mm > 1\.000 mm"):
        tracker.measure()
    t.assert_done()


# -- a tracker that follows one reflector (the built-in ascii-single-smr profile) -----------------------------


def smr_line(point_mm: str) -> bytes:
    body = f"PTS,{point_mm}"
    return f"${body}*{xor8(body.encode()):02X}\r\n".encode()


def test_single_reflector_profile_byte_exact():
    smr = np.array([[0.0, 0.0, 0.045]])  # one target, 45 mm in front of the flange
    script = [
        (b"UNITS MM\r\n", b"OK\r\n"),
        (b"MEAS?\r\n", smr_line("100.5,-20.25,1500")),
        (b"MEAS?\r\n", smr_line("nan,nan,nan")),
        (b"MEAS?\r\n", b"ERR,07\r\n"),
    ]
    t = ScriptedTransport(script)
    tracker = SerialTracker(load_profile("ascii-single-smr"), smr, transport=t, clock=t.clock, sleep=t.sleep)
    m = tracker.measure()
    np.testing.assert_allclose(m.points, [[0.1005, -0.02025, 1.5]])
    assert m.points.shape == (1, 3) and m.spread.tolist() == [0.0]
    with pytest.raises(MeasurementRejected, match="none of the 1 target"):
        tracker.measure()
    with pytest.raises(DeviceError, match="ERR,07"):
        tracker.measure()
    tracker.close()
    t.assert_done()


def test_the_profile_must_name_as_many_targets_as_the_session_has():
    t = ScriptedTransport([])
    with pytest.raises(ValueError, match=r"the reply names 1 target\(s\) \(t1 … t1\), the session has 3"):
        SerialTracker(load_profile("ascii-single-smr"), TARGETS, transport=t, clock=t.clock)


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
