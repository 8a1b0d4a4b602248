"""Byte-exact NDI Combined API tests on a scripted transport: every exchange written out, all consumed."""

from __future__ import annotations

import numpy as np
import pytest
from scripted_transport import BREAK, ScriptedTransport
from serial_fixtures import (
    CLOSE_NDI,
    COMM_9600,
    COMM_115200,
    INIT,
    OKAY,
    OPEN_NDI,
    RESET,
    TARGETS,
    TSTART,
    TSTOP,
    TX,
    ndi_profile,
    ndi_reply,
    scripted_ndi,
    tool_to_tracker,
    tx_body,
)

from labcal.drivers.base import (
    ConnectionFailed,
    DriverTimeout,
    MeasurementRejected,
    ProtocolError,
    Tracker,
)
from labcal.drivers.serial.ndi import NDIError, parse_tx_strays
from labcal.drivers.serial.tracker import SerialTracker

SEEN = tool_to_tracker()  # (3, 3) m, what the tracker should report, rows t1, t2, t3


def frame(strays=SEEN, **kw) -> bytes:
    return ndi_reply(tx_body(strays, **kw))


def test_open_measure_close_is_byte_exact_and_switches_baud_after_comm_okay():
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, frame()), *CLOSE_NDI])
    assert isinstance(tracker, Tracker)
    m = tracker.measure()
    tracker.close()
    tracker.close()  # second close is a no-op
    t.assert_done()
    np.testing.assert_allclose(m.points, SEEN, atol=5e-6)  # 0.01 mm resolution on the wire
    assert m.samples == 1 and m.quality == ()
    kinds = [e[0] for e in t.events]
    # The host changes its rate only after reading OKAY to COMM and waiting the switch delay, before TSTART.
    comm = t.events.index(("write", COMM_115200))
    assert t.events[comm + 1 :][:3] == [("sleep", 0.1), ("baud", 115200), ("flush", b"")]
    assert t.events.index(("write", TSTART)) > comm + 2
    # On close: TSTOP, then COMM back to 9600 and the host follows, so the next session's INIT is understood.
    assert t.events[-4:] == [("write", COMM_9600), ("sleep", 0.1), ("baud", 9600), ("close", None)]
    assert kinds.count("close") == 1


def test_no_comm_when_the_profile_keeps_9600():
    tracker, t = scripted_ndi([(INIT, OKAY), (TSTART, OKAY), (TSTOP, OKAY)], baudrate=9600)
    tracker.close()
    t.assert_done()
    assert not [e for e in t.events if e[0] == "baud"]


def test_strays_in_any_order_with_an_extra_reflection_are_labelled_as_t1_t2_t3():
    spurious = SEEN.mean(axis=0) + np.array([0.2, -0.13, 0.05])
    shuffled = np.array([SEEN[2], spurious, SEEN[0], SEEN[1]])
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, frame(shuffled))])
    m = tracker.measure()
    t.assert_done()
    np.testing.assert_allclose(m.points, SEEN, atol=5e-6)


@pytest.mark.parametrize(
    ("strays", "reason"),
    [
        (SEEN[:2], "only 2 marker"),
        (np.zeros((0, 3)), "no marker visible"),
        (SEEN + np.array([[0, 0, 0], [0, 0, 0], [0.002, 0, 0]]), "mismatch"),  # t3 moved 2 mm: bent triangle
    ],
)
def test_missing_or_inconsistent_markers_reject_the_frame(strays, reason):
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, frame(strays))])
    with pytest.raises(MeasurementRejected, match=reason) as info:
        tracker.measure()
    t.assert_done()
    assert reason in info.value.reason


def test_out_of_volume_flag_on_a_matched_marker_rejects_the_frame():
    # Four strays: flag bit 3 (the last stray, a matched target) set; bit 0 (spurious) set too.
    spurious = SEEN[0] + np.array([0.3, 0.3, 0.3])
    strays = np.array([spurious, SEEN[0], SEEN[1], SEEN[2]])
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, frame(strays, oov_flags="9"))])
    with pytest.raises(MeasurementRejected, match="t3 out of the characterised volume"):
        tracker.measure()
    t.assert_done()


def test_out_of_volume_flag_on_a_spurious_marker_only_is_fine():
    spurious = SEEN[0] + np.array([0.3, 0.3, 0.3])
    strays = np.array([spurious, SEEN[0], SEEN[1], SEEN[2]])
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, frame(strays, oov_flags="1"))])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)
    t.assert_done()


def test_nonzero_system_status_is_reported_as_quality():
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, frame(status="0002"))])
    assert tracker.measure().quality == ("system_status:0x0002",)
    t.assert_done()


def test_averaging_returns_the_mean_and_per_target_rms_spread():
    offsets = [np.zeros(3), np.array([0.0001, 0.0, 0.0]), np.array([-0.0001, 0.0, 0.0])]
    script = [*OPEN_NDI] + [(TX, frame(SEEN + d)) for d in offsets]
    tracker, t = scripted_ndi(script)
    m = tracker.measure(samples=3)
    t.assert_done()
    assert m.samples == 3
    np.testing.assert_allclose(m.points, SEEN, atol=5e-6)
    # RMS distance from the mean of 0, +0.1 mm, -0.1 mm is 0.1 * sqrt(2/3) mm for every target.
    np.testing.assert_allclose(m.spread, np.full(3, 1e-4 * np.sqrt(2 / 3)), rtol=1e-6)


@pytest.mark.parametrize("samples", [0, -1, 1.5, True])
def test_bad_sample_counts_are_refused(samples):
    tracker, _ = scripted_ndi(list(OPEN_NDI))
    with pytest.raises(ValueError, match="samples"):
        tracker.measure(samples=samples)


def test_bad_reply_crc_is_retried_then_accepted():
    good = frame()
    bad = good[:-5] + (b"0000" if good[-5:-1] != b"0000" else b"FFFF") + b"\r"
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, bad), (TX, good)])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)
    t.assert_done()


def test_garbled_reply_and_timeout_are_retried_with_input_flushed_before_each_request():
    good = frame()
    garbled = good[:7] + b"\xff\x00" + good[9:]
    # Timeout: the device answers nothing, then a late partial line arrives that must be flushed.
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, garbled), (TX, b""), (TX, good)])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)
    t.assert_done()


def test_stale_bytes_left_by_an_earlier_exchange_are_discarded():
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, frame())])
    t.feed(b"OKAY\rnoise-from-before")
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)
    t.assert_done()
    assert ("flush", b"OKAY\rnoise-from-before") in t.events


def test_error_reply_raises_with_code_and_meaning_and_is_not_retried():
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, ndi_reply("ERROR0C"))])
    with pytest.raises(NDIError, match=r"ERROR0C.*invalid while in the current mode") as info:
        tracker.measure()
    t.assert_done()
    assert info.value.code == 0x0C
    assert isinstance(info.value, ProtocolError)


def test_error04_command_crc_is_retried():
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, ndi_reply("ERROR04")), (TX, frame())])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)
    t.assert_done()


def test_persistent_timeouts_trigger_a_break_reset_and_full_restart():
    # retries=1: two silent TX, then break -> RESETBE6F at 9600 -> INIT -> COMM -> TSTART -> TX works.
    script = [*OPEN_NDI, (TX, b""), (TX, b""), (BREAK, RESET), *OPEN_NDI, (TX, frame())]
    tracker, t = scripted_ndi(script, retries=1)
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)
    t.assert_done()
    assert tracker.protocol.resets == 1
    bauds = [e[1] for e in t.events if e[0] == "baud"]
    assert bauds == [115200, 9600, 115200]  # back to 9600 for the break, up again after COMM
    brk = next(i for i, e in enumerate(t.events) if e[0] == "break")
    assert t.events[brk - 2 : brk] == [("baud", 9600), ("flush", b"")]


def test_timeouts_without_reset_raise_driver_timeout():
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, b""), (TX, b"")], retries=1, reset_on_failure=False)
    with pytest.raises(DriverTimeout, match="no complete reply"):
        tracker.measure()
    t.assert_done()


def test_partial_reply_without_terminator_is_a_timeout_not_a_frame():
    partial = frame()[:-1]  # everything but the CR
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, partial)], retries=0, reset_on_failure=False)
    with pytest.raises(DriverTimeout, match="partial reply"):
        tracker.measure()
    t.assert_done()


def test_break_without_reset_reply_is_a_connection_failure():
    script = [*OPEN_NDI, (TX, b""), (BREAK, b"")]
    tracker, t = scripted_ndi(script, retries=0)
    with pytest.raises(ConnectionFailed, match="no RESET reply after a serial break"):
        tracker.measure()
    t.assert_done()


def test_reset_announced_by_the_device_reinitialises_without_a_break():
    script = [*OPEN_NDI, (TX, RESET), *OPEN_NDI, (TX, frame())]
    tracker, t = scripted_ndi(script)
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)
    t.assert_done()
    assert not [e for e in t.events if e[0] == "break"]
    assert tracker.protocol.resets == 0


def test_init_without_answer_on_open_resets_the_device_first():
    # A device left at 115200 by an earlier session does not understand INIT at 9600.
    script = [(INIT, b""), (BREAK, RESET), *OPEN_NDI, *CLOSE_NDI]
    tracker, t = scripted_ndi(script)
    tracker.close()
    t.assert_done()


def test_failed_open_closes_the_port_and_raises_a_driver_error():
    t = ScriptedTransport([(INIT, b""), (BREAK, RESET), (INIT, ndi_reply("ERROR15"))])
    with pytest.raises(NDIError, match="Unable to initialize the Measurement System"):
        SerialTracker(ndi_profile(), TARGETS, transport=t, clock=t.clock, sleep=t.sleep)
    t.assert_done()
    assert t.closed


def test_comm_error_raises_protocol_error_naming_the_command():
    script = [(INIT, OKAY), (COMM_115200, ndi_reply("ERROR06"))]
    with pytest.raises(NDIError, match=r"COMM:50000.*ERROR06"):
        scripted_ndi(script)


def test_close_survives_a_dead_port():
    tracker, t = scripted_ndi(list(OPEN_NDI))
    t.closed = True  # the USB adapter was unplugged
    tracker.close()
    with pytest.raises(Exception, match="closed tracker"):
        tracker.measure()


def test_non_scalene_targets_are_refused_before_opening():
    iso = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.05, 0.08, 0.0]])  # t1-t3 == t2-t3
    t = ScriptedTransport([])
    with pytest.raises(ValueError, match="not scalene enough"):
        SerialTracker(ndi_profile(), iso, transport=t, clock=t.clock, sleep=t.sleep)
    t.assert_done()  # nothing was sent


# -- TX body parsing -------------------------------------------------------------------------------------------


def test_parse_tx_reads_count_flags_coordinates_and_status():
    body = "0005" + "12" + "+001234-000001+100000" * 5 + "0100"
    f = parse_tx_strays(body)
    assert f.strays.shape == (5, 3)
    np.testing.assert_allclose(f.strays[0], [0.01234, -0.00001, 1.0])
    assert f.out_of_volume.tolist() == [False, True, False, False, True]  # 0x12 = bits 1 and 4
    assert f.system_status == 0x0100


def test_parse_tx_skips_tool_handle_blocks():
    body = "01" + "0AMISSING0000000000000000\n" + "01" + "0" + "+000100+000200+000300" + "0000"
    np.testing.assert_allclose(parse_tx_strays(body).strays, [[0.001, 0.002, 0.003]])


@pytest.mark.parametrize(
    ("body", "what"),
    [
        ("0003" + "0" + "+000000" * 8 + "0000", "should be"),  # three strays announced, one coordinate short
        ("0001" + "0" + "+0000x0+000000+000000" + "0000", "not sign \\+ 6 digits"),
        ("0001" + "G" + "+000000+000000+000000" + "0000", "out-of-volume flags"),
        ("0001" + "0" + "+000000+000000+000000" + "00Z0", "system status"),
        ("zz", "handle count"),
        ("01" + "0A" + "0000", "no line feed"),
    ],
)
def test_parse_tx_rejects_malformed_bodies(body, what):
    with pytest.raises(ProtocolError, match=what):
        parse_tx_strays(body)


def test_well_formed_but_malformed_tx_raises_protocol_error_through_measure():
    tracker, t = scripted_ndi([*OPEN_NDI, (TX, ndi_reply("0001"))])
    with pytest.raises(ProtocolError, match="TX reply"):
        tracker.measure()
    t.assert_done()


def test_targets_constant_is_scalene():
    sides = sorted(np.linalg.norm(TARGETS[i] - TARGETS[j]) for i, j in [(0, 1), (0, 2), (1, 2)])
    assert np.min(np.diff(sides)) > 0.01
