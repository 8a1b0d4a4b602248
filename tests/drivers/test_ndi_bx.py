"""Binary ``BX:1000`` replies: byte-exact sessions on a scripted transport, the parser's checks, round trips.

Expected replies are built by ``serial_fixtures.bx_reply`` (struct + a bitwise CRC), independently of both the
driver's parser and the fake device's encoder; test_ndi_ndicapy.py checks the fake against NDI's own client.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scripted_transport import BREAK, ScriptedTransport
from serial_fixtures import (
    BX,
    CLOSE_NDI,
    OPEN_NDI,
    RESET,
    TARGETS,
    bx_body,
    bx_frame,
    bx_reply,
    ndi_profile,
    ndi_reply,
    scripted_ndi,
    tool_to_tracker,
)

from labcal.drivers.base import DriverTimeout, MeasurementRejected, ProtocolError
from labcal.drivers.serial.ndi import NDIError, StrayFrame, parse_bx_body, split_bx_reply
from labcal.drivers.serial.tracker import SerialTracker
from labcal_fakes.devices import encode_bx_reply

SEEN = tool_to_tracker()  # (3, 3) m, rows t1, t2, t3
F32 = 1e-7  # m: float32 millimetres near 1.5 m resolve about 0.12 um


def bx_session(script, **profile):
    return scripted_ndi(script, reply="bx", **profile)


# -- sessions on a scripted transport --------------------------------------------------------------------------


@pytest.mark.parametrize("max_read", [None, 1])
def test_bx_session_is_byte_exact_and_reads_replies_containing_cr_bytes(max_read):
    # Status 0x0D0D puts two CR bytes into the reply: a line reader would stop there, a counted read must not,
    # also when the reply trickles in one byte per read.
    first = bx_reply(SEEN, status=0x0D0D)
    assert b"\r" in first[:-3]
    second = bx_reply(SEEN + np.array([0.0002, 0.0, 0.0]))
    t = ScriptedTransport([*OPEN_NDI, (BX, first), (BX, second), *CLOSE_NDI], max_read=max_read)
    tracker = SerialTracker(ndi_profile(reply="bx"), TARGETS, transport=t, clock=t.clock, sleep=t.sleep)
    m = tracker.measure(samples=2)
    tracker.close()
    t.assert_done()
    np.testing.assert_allclose(m.points, SEEN + np.array([0.0001, 0.0, 0.0]), atol=F32)
    assert m.samples == 2
    assert m.quality == ("system_status:0x0D0D",)
    assert [e[1] for e in t.events if e[0] == "write"].count(BX) == 2


def test_bx_strays_in_any_order_with_handles_and_an_extra_reflection_are_labelled():
    spurious = SEEN.mean(axis=0) + np.array([0.2, -0.13, 0.05])
    shuffled = np.array([SEEN[2], spurious, SEEN[0], SEEN[1]])
    handles = ((0x01, 0x01), (0x02, 0x04))  # a seen handle and a disabled one: neither carries data here
    tracker, t = bx_session([*OPEN_NDI, (BX, bx_reply(shuffled, handles=handles))])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()


def test_bx_out_of_volume_on_a_matched_marker_rejects_the_frame_and_on_a_spurious_one_does_not():
    spurious = SEEN[0] + np.array([0.3, 0.3, 0.3])
    strays = np.array([spurious, SEEN[0], SEEN[1], SEEN[2]])
    script = [
        *OPEN_NDI,
        (BX, bx_reply(strays, oov=[False, False, False, True])),
        (BX, bx_reply(strays, oov=[True, False, False, False])),
    ]
    tracker, t = bx_session(script)
    with pytest.raises(MeasurementRejected, match="t3 out of the characterised volume"):
        tracker.measure()
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()


def test_bx_missing_marker_rejects_the_frame():
    tracker, t = bx_session([*OPEN_NDI, (BX, bx_reply(SEEN[:2]))])
    with pytest.raises(MeasurementRejected, match="only 2 marker"):
        tracker.measure()
    t.assert_done()


def test_bx_bad_body_crc_is_retried_then_accepted():
    good = bx_reply(SEEN)
    bad = good[:-2] + bytes([good[-2] ^ 0xFF, good[-1]])
    tracker, t = bx_session([*OPEN_NDI, (BX, bad), (BX, good)])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()


@pytest.mark.parametrize(
    "spoil",
    [
        pytest.param(lambda r: b"\x00#" + r[2:], id="bad start sequence"),
        pytest.param(lambda r: r[:4] + bytes([r[4] ^ 0x10]) + r[5:], id="bad header CRC"),
    ],
)
def test_bx_untrustworthy_header_drains_the_rest_of_the_reply_and_retries(spoil):
    good = bx_reply(SEEN)
    tracker, t = bx_session([*OPEN_NDI, (BX, spoil(good)), (BX, good)])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()
    # The rest of the spoilt reply was read off the line before the retry, so the flush found nothing left.
    flushes = [e[1] for e in t.events if e[0] == "flush"]
    assert flushes[-2:] == [b"", b""]


def test_bx_truncated_reply_is_a_timeout_naming_the_announced_length():
    tracker, t = bx_session([*OPEN_NDI, (BX, bx_reply(SEEN)[:-5])], retries=0, reset_on_failure=False)
    with pytest.raises(DriverTimeout, match=r"truncated BX reply to 'BX:1000' \(header announces 41 body bytes\)"):
        tracker.measure()
    t.assert_done()


def test_bx_truncated_reply_and_silence_are_retried():
    good = bx_reply(SEEN)
    tracker, t = bx_session([*OPEN_NDI, (BX, good[:-5]), (BX, b""), (BX, good)])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()


def test_bx_persistent_timeouts_trigger_a_break_reset_and_full_restart():
    script = [*OPEN_NDI, (BX, b""), (BX, b""), (BREAK, RESET), *OPEN_NDI, (BX, bx_reply(SEEN))]
    tracker, t = bx_session(script, retries=1)
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()
    assert tracker.protocol.resets == 1


def test_bx_reset_announced_by_the_device_reinitialises_without_a_break():
    tracker, t = bx_session([*OPEN_NDI, (BX, RESET), *OPEN_NDI, (BX, bx_reply(SEEN))])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()
    assert not [e for e in t.events if e[0] == "break"]


def test_bx_ascii_error_reply_raises_with_code_and_is_not_retried():
    tracker, t = bx_session([*OPEN_NDI, (BX, ndi_reply("ERROR0C"))])
    with pytest.raises(NDIError, match=r"'BX:1000' failed: ERROR0C") as info:
        tracker.measure()
    t.assert_done()
    assert info.value.code == 0x0C


def test_bx_error04_is_retried():
    tracker, t = bx_session([*OPEN_NDI, (BX, ndi_reply("ERROR04")), (BX, bx_reply(SEEN))])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()


def test_bx_corrupted_ascii_error_reply_is_read_to_its_cr_and_retried():
    tracker, t = bx_session([*OPEN_NDI, (BX, b"ERROR0C0000\r"), (BX, bx_reply(SEEN))])
    np.testing.assert_allclose(tracker.measure().points, SEEN, atol=F32)
    t.assert_done()
    assert [e[1] for e in t.events if e[0] == "flush"][-2:] == [b"", b""]


def test_bx_ascii_line_that_is_neither_error_nor_reset_is_a_protocol_error():
    tracker, t = bx_session([*OPEN_NDI, (BX, ndi_reply("RESET!"))], retries=0, reset_on_failure=False)
    with pytest.raises(ProtocolError, match="expected a binary reply to 'BX:1000', got 'RESET!'"):
        tracker.measure()
    t.assert_done()


def test_bx_well_framed_but_malformed_body_raises_without_retrying():
    body = bx_body(SEEN)
    body = body[:2] + body[3:]  # stray count 3, but the out-of-volume byte is missing
    tracker, t = bx_session([*OPEN_NDI, (BX, bx_frame(body))])
    with pytest.raises(ProtocolError, match="BX reply"):
        tracker.measure()
    t.assert_done()


# -- the parser ------------------------------------------------------------------------------------------------


def test_parse_bx_reads_handles_count_bits_coordinates_and_status():
    strays = np.arange(30, dtype=float).reshape(10, 3) * 0.25e-3 - 1.5  # exact in float32 mm
    oov = [j in (0, 8, 9) for j in range(10)]  # bits in both out-of-volume bytes
    reply = bx_reply(strays, oov=oov, status=0x0102, handles=((0x0A, 0x01), (0x0B, 0x04)))
    frame = parse_bx_body(split_bx_reply(reply))
    assert isinstance(frame, StrayFrame)
    np.testing.assert_allclose(frame.strays, strays, rtol=0, atol=1e-15)  # metres, not millimetres
    assert frame.out_of_volume.tolist() == oov
    assert frame.system_status == 0x0102


def test_parse_bx_with_no_strays():
    frame = parse_bx_body(split_bx_reply(bx_reply(np.zeros((0, 3)))))
    assert frame.strays.shape == (0, 3) and frame.out_of_volume.shape == (0,)


GOOD = bx_reply(SEEN)  # 41-byte body: 1 + 1 + 1 + 36 + 2
NAN = bx_frame(bx_body(np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]])))
INF = bx_frame(bx_body(np.array([[0.0, np.inf, 0.0]])))


def _short_body() -> bytes:
    body = bx_body(SEEN)
    return bx_frame(body[:-14])  # three strays announced, the last one and the status cut off


@pytest.mark.parametrize(
    ("reply", "message"),
    [
        pytest.param(b"\xc5" + GOOD[1:], r"bad start sequence C5 A5, expected C4 A5", id="start"),
        pytest.param(GOOD[:4] + bytes([GOOD[4] ^ 1]) + GOOD[5:], r"bad header CRC: got", id="header-crc"),
        pytest.param(GOOD[:-1] + bytes([GOOD[-1] ^ 1]), r"bad body CRC: got", id="body-crc"),
        pytest.param(GOOD[:20] + bytes([GOOD[20] ^ 1]) + GOOD[21:], r"bad body CRC", id="body-bit"),
        pytest.param(
            GOOD + b"\x00", r"length mismatch: header announces 41 body bytes \(49 in all\), got 50", id="long"
        ),
        pytest.param(GOOD[:-1], r"length mismatch: .*got 48", id="short"),
        pytest.param(GOOD[:5], r"shorter than its header", id="no-header"),
        pytest.param(
            _short_body(), r"body truncated: 3 stray position\(s\) needs bytes 3 to 38, the body has 27", id="truncated"
        ),
        pytest.param(bx_frame(bx_body(SEEN) + b"\x00"), r"length mismatch: body is 42 bytes but", id="trailing"),
        pytest.param(bx_frame(b"\x02\x01\x01"), r"body truncated: 2 handle id/status pair", id="handles"),
        pytest.param(bx_frame(b""), r"body truncated: handle count", id="empty-body"),
        pytest.param(NAN, r"stray 1 has a non-finite coordinate: \(nan, 0.0, 0.0\) mm", id="nan"),
        pytest.param(INF, r"stray 0 has a non-finite coordinate: \(0.0, inf, 0.0\) mm", id="inf"),
    ],
)
def test_parse_bx_names_what_is_wrong(reply, message):
    with pytest.raises(ProtocolError, match=message):
        parse_bx_body(split_bx_reply(reply))


def test_parse_bx_raises_the_ascii_error_reply_as_ndi_error():
    with pytest.raises(NDIError, match="ERROR0C"):
        parse_bx_body(split_bx_reply(ndi_reply("ERROR0C")))


# -- round trips and corruption --------------------------------------------------------------------------------

mm_float32 = st.floats(-3000.0, 3000.0, width=32, allow_nan=False)


@st.composite
def scenes(draw):
    m = draw(st.integers(0, 40))
    mm = np.array(draw(st.lists(mm_float32, min_size=3 * m, max_size=3 * m)), dtype=float).reshape(m, 3)
    oov = draw(st.lists(st.booleans(), min_size=m, max_size=m))
    status = draw(st.integers(0, 0xFFFF))
    handles = tuple(draw(st.lists(st.tuples(st.integers(0, 255), st.integers(0, 255)), max_size=4)))
    return mm, oov, status, handles


@given(scenes())
def test_fake_encoder_round_trips_through_the_parser_and_matches_the_independent_encoder(scene):
    mm, oov, status, handles = scene
    metres = mm * 1e-3
    reply = encode_bx_reply(metres, oov, status, handles)
    assert reply == bx_reply(metres, oov=oov, status=status, handles=handles)
    frame = parse_bx_body(split_bx_reply(reply))
    np.testing.assert_array_equal(frame.strays, mm * 1e-3)  # float32 mm survive the trip exactly
    assert frame.out_of_volume.tolist() == oov
    assert frame.system_status == status


@given(scenes(), st.data())
def test_every_single_byte_corruption_is_rejected(scene, data):
    mm, oov, status, handles = scene
    reply = encode_bx_reply(mm * 1e-3, oov, status, handles)
    i = data.draw(st.integers(0, len(reply) - 1), label="byte")
    flip = data.draw(st.integers(1, 255), label="xor")
    spoilt = reply[:i] + bytes([reply[i] ^ flip]) + reply[i + 1 :]
    with pytest.raises(ProtocolError):
        parse_bx_body(split_bx_reply(spoilt))


@given(st.binary(max_size=200))
def test_arbitrary_bytes_give_a_frame_or_a_protocol_error_never_another_exception(data):
    try:
        parse_bx_body(split_bx_reply(data))
    except ProtocolError:
        pass


def test_fake_encoder_checks_flag_count():
    with pytest.raises(ValueError, match="2 out-of-volume flags for 3 strays"):
        encode_bx_reply(SEEN, [False, True])


def test_header_crc_makes_the_whole_reply_crc_equal_the_body_crc():
    # Why clients that run one CRC over header + body (ndicapi does) accept replies framed as specified:
    # a CRC-16/ARC over data followed by its own CRC is zero, so the header leaves the running CRC at zero.
    from labcal.drivers.serial.crc import crc16_arc

    n = struct.unpack_from("<H", GOOD, 2)[0]
    assert crc16_arc(GOOD[:6]) == 0
    assert crc16_arc(GOOD[: 6 + n]) == crc16_arc(GOOD[6 : 6 + n]) == struct.unpack_from("<H", GOOD, 6 + n)[0]
