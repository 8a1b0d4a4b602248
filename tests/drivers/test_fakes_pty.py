"""End to end over a real pseudo-terminal: pyserial + labcal's driver against the fake devices' threads."""

from __future__ import annotations

import dataclasses
import itertools
import time
from pathlib import Path

import numpy as np
import pytest
from ascii_fake import FakeASCIIDevice
from serial_fixtures import TARGETS, bx_reply, tool_to_tracker

from labcal.drivers.base import ConnectionFailed, MeasurementRejected
from labcal.drivers.serial.ascii import DeviceError
from labcal.drivers.serial.ndi import NDIError
from labcal.drivers.serial.profiles import load_profile
from labcal.drivers.serial.tracker import SerialTracker, open_tracker
from labcal_fakes.devices import FakeNDIDevice

pytestmark = [pytest.mark.integration, pytest.mark.timeout(30)]

REPO = Path(__file__).resolve().parents[2]
SEEN = tool_to_tracker()  # true target positions in the tracker frame, m
ATOL = {"tx": 5e-6, "bx": 1e-7}  # m: TX has 0.01 mm digits, BX float32 millimetres
REPLIES = ["tx", "bx"]


def ndi_tracker(dev: FakeNDIDevice, **overrides) -> SerialTracker:
    profile = load_profile(REPO / "drivers" / "ndi-polaris.toml")
    profile = dataclasses.replace(profile, switch_delay=0.0, init_timeout=0.5, **overrides)
    profile = dataclasses.replace(profile, port=dataclasses.replace(profile.port, timeout=0.2))
    return SerialTracker(profile, TARGETS, url=dev.port)


def wait_for(predicate, timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


# -- NDI ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("reply", REPLIES)
def test_ndi_session_over_pty_labels_shuffled_strays_and_leaves_the_device_stopped(reply):
    with FakeNDIDevice(lambda: SEEN, seed=3, extra_stray=True) as dev:
        with ndi_tracker(dev, reply=reply) as tracker:
            m = tracker.measure(samples=4)
            assert dev.state == "tracking" and dev.baudrate == 115200
        np.testing.assert_allclose(m.points, SEEN, atol=ATOL[reply])
        assert m.samples == 4
        assert wait_for(lambda: dev.state == "setup" and dev.baudrate == 9600)  # TSTOP, COMM:00000 on close
        names = [c.split(":")[0] for c in dev.received]
        frame = reply.upper()
        assert names == ["INIT", "COMM", "TSTART", frame, frame, frame, frame, "TSTOP", "COMM"]


def test_ndi_averaging_over_pty_reports_the_spread_of_the_samples():
    offsets = itertools.cycle([np.array([0.0002, 0.0, 0.0]), np.array([-0.0002, 0.0, 0.0])])
    with FakeNDIDevice(lambda: SEEN + next(offsets), seed=0) as dev, ndi_tracker(dev) as tracker:
        m = tracker.measure(samples=2)
    np.testing.assert_allclose(m.points, SEEN, atol=5e-6)
    np.testing.assert_allclose(m.spread, np.full(3, 0.0002), atol=1e-8)


@pytest.mark.parametrize("reply", REPLIES)
@pytest.mark.parametrize("fault", ["bad_crc", "garbled", "truncated", "no_reply"])
def test_ndi_transient_faults_are_retried(fault, reply):
    with FakeNDIDevice(lambda: SEEN, seed=1) as dev, ndi_tracker(dev, reply=reply) as tracker:
        dev.inject(fault)
        np.testing.assert_allclose(tracker.measure().points, SEEN, atol=ATOL[reply])
        # the faulty frame and its retry
        assert [c.split(":")[0] for c in dev.received].count(reply.upper()) == 2


@pytest.mark.parametrize("reply", REPLIES)
def test_ndi_device_reset_mid_session_is_recovered_by_reinitialising(reply):
    with FakeNDIDevice(lambda: SEEN, seed=1) as dev, ndi_tracker(dev, reply=reply) as tracker:
        dev.inject("reset")
        np.testing.assert_allclose(tracker.measure().points, SEEN, atol=ATOL[reply])
        names = [c.split(":")[0] for c in dev.received]
        frame = reply.upper()
        assert names == ["INIT", "COMM", "TSTART", frame, "INIT", "COMM", "TSTART", frame]


@pytest.mark.parametrize(
    ("fault", "error", "match"),
    [
        ("drop_target", MeasurementRejected, "only 2 marker"),
        ("out_of_volume", MeasurementRejected, "out of the characterised volume"),
        ("error:0C", NDIError, "ERROR0C"),
    ],
)
@pytest.mark.parametrize("reply", REPLIES)
def test_ndi_unusable_frames_raise_and_the_next_frame_is_fine(fault, error, match, reply):
    with FakeNDIDevice(lambda: SEEN, seed=2) as dev, ndi_tracker(dev, reply=reply) as tracker:
        dev.inject(fault)
        with pytest.raises(error, match=match):
            tracker.measure()
        np.testing.assert_allclose(tracker.measure().points, SEEN, atol=ATOL[reply])


def test_fake_rejects_a_command_with_a_bad_crc_with_error04():
    import serial

    with FakeNDIDevice(lambda: SEEN) as dev:
        port = serial.serial_for_url(dev.port, timeout=1.0)
        try:
            port.write(b"INIT:0000\r")
            assert port.read_until(b"\r") == b"ERROR04" + b"%04X" % _crc(b"ERROR04") + b"\r"
            port.write(b"BOGUS:1234\r")
            assert port.read_until(b"\r").startswith(b"ERROR0")
        finally:
            port.close()


def test_fake_ignores_commands_sent_at_the_wrong_baud_rate():
    import serial

    with FakeNDIDevice(lambda: SEEN) as dev:
        for baud, expect in ((115200, b""), (9600, b"OKAY")):
            port = serial.serial_for_url(dev.port, baudrate=baud, timeout=0.2)
            try:
                port.write(b"INIT:E3A5\r")
                assert port.read_until(b"\r")[:4] == expect
            finally:
                port.close()
        assert dev.ignored == ["INIT:E3A5"]


def _crc(data: bytes) -> int:
    from serial_fixtures import crc16_arc_bitwise

    return crc16_arc_bitwise(data)


def test_fake_answers_bx_with_the_binary_reply_of_its_markers():
    import serial

    with FakeNDIDevice(lambda: SEEN, shuffle=False, strict_baud=False) as dev:
        dev.system_status = 0x0102
        port = serial.serial_for_url(dev.port, timeout=1.0)
        try:
            port.write(b"BX:1000FEAD\r")
            assert port.read_until(b"\r") == b"ERROR10" + b"%04X" % _crc(b"ERROR10") + b"\r"  # not initialised
            for command in (b"INIT:E3A5\r", b"TSTART:5423\r"):
                port.write(command)
                assert port.read_until(b"\r")[:4] == b"OKAY"
            port.write(b"BX:1000FEAD\r")
            expected = bx_reply(SEEN, status=0x0102)  # the independent encoder of the scripted tests
            assert port.read(len(expected)) == expected
            port.timeout = 0.1
            assert port.read(1) == b""  # no CR or anything else after a binary reply
        finally:
            port.close()


def test_port_can_be_reopened_after_a_client_closes_it():
    with FakeNDIDevice(lambda: SEEN) as dev:
        for _ in range(2):
            with ndi_tracker(dev) as tracker:
                np.testing.assert_allclose(tracker.measure().points, SEEN, atol=5e-6)


def test_device_going_away_gives_a_driver_error_not_a_pyserial_one():
    dev = FakeNDIDevice(lambda: SEEN).start()
    tracker = ndi_tracker(dev, retries=0, reset_on_failure=False)
    try:
        dev.close()
        with pytest.raises(ConnectionFailed, match="serial input flush failed"):
            tracker.measure()
    finally:
        tracker.close()  # must not raise although the device is gone
        dev.close()


# -- ASCII ----------------------------------------------------------------------------------------------------


def test_ascii_example_profile_end_to_end_with_faults():
    with FakeASCIIDevice(lambda: SEEN, seed=4) as dev:
        with open_tracker(REPO / "drivers" / "ascii-example.toml", TARGETS, url=dev.port) as tracker:
            identity = {"maker": "LABCAL", "model": "FAKE-3T", "serial": "FK-0001", "firmware": "1.0"}
            assert tracker.device_identity() == identity  # the profile's [ascii.identity] query, asked at start
            np.testing.assert_allclose(tracker.measure(samples=2).points, SEEN, atol=1e-7)
            for fault in ("bad_checksum", "garbled"):
                dev.inject(fault)
                np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-7)
            dev.inject("drop_target")
            m = tracker.measure()
            assert m.seen.sum() == 2 and m.quality == (f"missing:t{int(np.flatnonzero(~m.seen)[0]) + 1}",)
            np.testing.assert_allclose(m.points[m.seen], SEEN[m.seen], atol=1e-7)
            dev.inject("error:07")
            with pytest.raises(DeviceError, match="ERR,07"):
                tracker.measure()
        assert dev.received[:3] == ["*IDN?", "*IDN?", "UNITS MM"]  # the identity query, then the init steps
        assert dev.received.count("MEAS?") == 2 + 2 * 2 + 1 + 1


def test_ascii_no_reply_is_retried_over_pty():
    with FakeASCIIDevice(lambda: SEEN) as dev:
        profile = load_profile(REPO / "drivers" / "ascii-example.toml")
        profile = dataclasses.replace(profile, port=dataclasses.replace(profile.port, timeout=0.1))
        with SerialTracker(profile, TARGETS, url=dev.port) as tracker:
            dev.inject("no_reply")
            np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-7)
        assert dev.received.count("MEAS?") == 2


def test_ascii_streaming_device_over_pty():
    from labcal.drivers.serial.profiles import InitStep

    with FakeASCIIDevice(lambda: SEEN, stream_hz=200.0) as dev:
        profile = load_profile(REPO / "drivers" / "ascii-example.toml")
        profile = dataclasses.replace(
            profile,
            mode="stream",
            measure_command=None,
            init=(*profile.init, InitStep("STREAM ON", None)),
            close_commands=("STREAM OFF",),
        )
        with SerialTracker(profile, TARGETS, url=dev.port) as tracker:
            m = tracker.measure(samples=3)
        np.testing.assert_allclose(m.points, SEEN, atol=1e-7)
        assert "MEAS?" not in dev.received
        assert wait_for(lambda: not dev.streaming)  # STREAM OFF sent on close


def test_fake_fault_names_are_checked():
    with FakeNDIDevice() as dev, pytest.raises(ValueError, match="unknown fault 'explode'"):
        dev.inject("explode")


def test_open_tracker_accepts_a_targets_file(tmp_path):
    path = tmp_path / "targets.toml"
    mm = TARGETS * 1e3
    path.write_text(f'unit = "mm"\npoints = {mm.tolist()}\n')
    with FakeASCIIDevice(lambda: SEEN) as dev:
        with open_tracker(REPO / "drivers" / "ascii-example.toml", path, url=dev.port) as tracker:
            np.testing.assert_allclose(tracker.targets, TARGETS, atol=1e-12)
            np.testing.assert_allclose(tracker.measure().points, SEEN, atol=1e-7)


def test_single_reflector_profile_end_to_end_over_pty():
    smr = SEEN[:1]
    visible = [True]
    with FakeASCIIDevice(lambda: smr if visible[0] else np.full((1, 3), np.nan), seed=2) as dev:
        with open_tracker("ascii-single-smr", TARGETS[:1], url=dev.port) as tracker:
            m = tracker.measure(samples=2)
            assert m.points.shape == (1, 3)
            np.testing.assert_allclose(m.points, smr, atol=1e-7)
            visible[0] = False  # the beam is broken: nothing to average
            with pytest.raises(MeasurementRejected, match="none of the 1 target"):
                tracker.measure()
        assert dev.received[:2] == ["UNITS MM", "MEAS?"]
