"""Cross-check with the real NDI client library: ``ndicapy`` (PyPI ndicapi 3.7.6) against FakeNDIDevice.

If NDI's own client parses the fake's replies into the same markers, the fake speaks the protocol, and labcal's
driver reading the same markers from the same fake is independent evidence that the driver does too. The
command bytes ndicapy sends also pin down the constants used by the byte-exact scripted tests.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from serial_fixtures import BX, COMM_9600, COMM_115200, INIT, TARGETS, TSTART, TSTOP, TX, tool_to_tracker

from labcal.drivers.serial.ndi import ERROR_CODES, encode_command
from labcal.drivers.serial.profiles import load_profile
from labcal.drivers.serial.tracker import SerialTracker
from labcal_fakes.devices import FakeNDIDevice

ndicapy = pytest.importorskip("ndicapy")

pytestmark = [pytest.mark.integration, pytest.mark.timeout(30)]

REPO = Path(__file__).resolve().parents[2]
SEEN = tool_to_tracker()


def ndicapy_strays(port: str) -> tuple[np.ndarray, int]:
    """Run an NDI session with ndicapy; return the strays of one TX:1000 frame (N, 3) m and the status."""
    device = ndicapy.ndiOpen(port)
    assert device, f"ndicapy could not open {port}"
    try:
        for command in ("INIT:", "COMM:50000", "TSTART:"):
            reply = ndicapy.ndiCommand(device, command)
            assert ndicapy.ndiGetError(device) == ndicapy.NDI_OKAY, ndicapy.ndiErrorString(ndicapy.ndiGetError(device))
            assert reply == "OKAY", (command, reply)
        ndicapy.ndiCommand(device, "TX:1000")
        assert ndicapy.ndiGetError(device) == ndicapy.NDI_OKAY
        n = ndicapy.ndiGetTXNumberOfPassiveStrays(device)
        strays = np.array([ndicapy.ndiGetTXPassiveStray(device, i) for i in range(n)], dtype=float) * 1e-3  # mm->m
        status = ndicapy.ndiGetTXSystemStatus(device)
        assert ndicapy.ndiCommand(device, "TSTOP:") == "OKAY"
        # Leave the device at 9600 as found, so the next client's INIT is understood.
        assert ndicapy.ndiCommand(device, "COMM:00000") == "OKAY"
        return strays.reshape(n, 3), status
    finally:
        ndicapy.ndiClose(device)


def test_ndicapy_reads_the_fake_and_agrees_with_labcal():
    with FakeNDIDevice(lambda: SEEN, seed=11, extra_stray=True) as dev:
        reference, status = ndicapy_strays(dev.port)
        assert status == 0
        # ndicapy framed its commands exactly like the constants the scripted tests expect labcal to send.
        sent = (INIT, COMM_115200, TSTART, TX, TSTOP, COMM_9600)
        assert dev.received == [c[:-1].decode() for c in sent]
        for command in ("INIT:", "COMM:50000", "TSTART:", "TX:1000", "TSTOP:", "COMM:00000"):
            assert encode_command(command)[:-1].decode() in dev.received

        profile = load_profile(REPO / "drivers" / "ndi-polaris.toml")
        with SerialTracker(dataclasses.replace(profile, switch_delay=0.0), TARGETS, url=dev.port) as tracker:
            ours = tracker.measure().points

    assert reference.shape == (4, 3)  # three targets + the spurious reflection, in the fake's shuffled order
    # Every point labcal reports is one ndicapy saw, and labcal labelled them in target order.
    nearest = np.array([np.min(np.linalg.norm(reference - p, axis=1)) for p in ours])
    assert np.all(nearest < 1e-9)
    np.testing.assert_allclose(ours, SEEN, atol=5e-6)
    # ndicapy's spurious stray is the one labcal left out.
    leftover = [r for r in reference if np.min(np.linalg.norm(ours - r, axis=1)) > 1e-9]
    assert len(leftover) == 1


def test_ndicapy_sees_the_faults_the_driver_must_handle():
    with FakeNDIDevice(lambda: SEEN, seed=5) as dev:
        device = ndicapy.ndiOpen(dev.port)
        try:
            for command in ("INIT:", "TSTART:"):
                ndicapy.ndiCommand(device, command)
            # ndicapy's Python wrapper raises OSError for a failed command.
            dev.inject("bad_crc")
            with pytest.raises(OSError, match="Bad CRC on reply"):
                ndicapy.ndiCommand(device, "TX:1000")
            assert ndicapy.ndiGetError(device) == ndicapy.NDI_BAD_CRC
            dev.inject("error:0C")
            with pytest.raises(OSError, match="Command is invalid while in the current mode"):
                ndicapy.ndiCommand(device, "TX:1000")
            assert ndicapy.ndiGetError(device) == 0x0C
            ndicapy.ndiCommand(device, "TX:1000")
            assert ndicapy.ndiGetError(device) == ndicapy.NDI_OKAY
            assert ndicapy.ndiGetTXNumberOfPassiveStrays(device) == 3
        finally:
            ndicapy.ndiClose(device)


def test_error_code_meanings_agree_with_ndicapy():
    for code, meaning in ERROR_CODES.items():
        assert ndicapy.ndiErrorString(code).startswith(meaning), hex(code)


# -- binary BX replies ---------------------------------------------------------------------------------------


def ndicapy_bx_and_tx(port: str) -> tuple[np.ndarray, np.ndarray, int]:
    """One session with ndicapy: strays of a BX:1000 and of a TX:1000 frame, (N, 3) m each, and the BX status."""
    device = ndicapy.ndiOpen(port)
    assert device, f"ndicapy could not open {port}"
    try:
        for command in ("INIT:", "COMM:50000", "TSTART:"):
            assert ndicapy.ndiCommand(device, command) == "OKAY", command
        # ndiBX takes the reply option as an int and formats it itself ("BX:%04X").
        ndicapy.ndiBX(device, 0x1000)
        assert ndicapy.ndiGetError(device) == ndicapy.NDI_OKAY, ndicapy.ndiErrorString(ndicapy.ndiGetError(device))
        n = ndicapy.ndiGetBXNumberOfPassiveStrays(device)
        bx = np.array([ndicapy.ndiGetBXPassiveStray(device, i) for i in range(n)], dtype=float) * 1e-3  # mm -> m
        status = ndicapy.ndiGetBXSystemStatus(device)
        ndicapy.ndiCommand(device, "TX:1000")
        assert ndicapy.ndiGetError(device) == ndicapy.NDI_OKAY
        k = ndicapy.ndiGetTXNumberOfPassiveStrays(device)
        tx = np.array([ndicapy.ndiGetTXPassiveStray(device, i) for i in range(k)], dtype=float) * 1e-3
        assert ndicapy.ndiCommand(device, "TSTOP:") == "OKAY"
        assert ndicapy.ndiCommand(device, "COMM:00000") == "OKAY"
        return bx.reshape(n, 3), tx.reshape(k, 3), status
    finally:
        ndicapy.ndiClose(device)


def test_ndicapy_reads_bx_from_the_fake_and_agrees_with_labcal_in_bx_mode():
    with FakeNDIDevice(lambda: SEEN, seed=11, extra_stray=True, shuffle=False) as dev:
        dev.system_status = 0x0021
        reference, tx, status = ndicapy_bx_and_tx(dev.port)
        assert status == 0x0021
        assert dev.received == [c[:-1].decode() for c in (INIT, COMM_115200, TSTART, BX, TX, TSTOP, COMM_9600)]
        assert encode_command("BX:1000") == BX

        profile = load_profile(REPO / "drivers" / "ndi-polaris.toml")
        profile = dataclasses.replace(profile, switch_delay=0.0, reply="bx")
        with SerialTracker(profile, TARGETS, url=dev.port) as tracker:
            m = tracker.measure()
        # labcal's BX session sent what ndicapy's did.
        assert dev.received[7:] == [c[:-1].decode() for c in (INIT, COMM_115200, TSTART, BX, TSTOP, COMM_9600)]

    assert reference.shape == (4, 3)  # three targets + the spurious reflection
    # ndicapy read the same float32 millimetres labcal did: labcal's points are exactly three of ndicapy's.
    np.testing.assert_array_equal(reference[:3], m.points)
    np.testing.assert_allclose(m.points, SEEN, atol=1e-7)
    assert m.quality == ("system_status:0x0021",)
    # The fake's TX and BX frames of the same markers agree to TX's 0.01 mm digits (the spurious one differs).
    np.testing.assert_allclose(tx[:3], reference[:3], atol=5e-6)


def test_ndicapy_sees_the_bx_faults_the_driver_must_handle():
    with FakeNDIDevice(lambda: SEEN, seed=5) as dev:
        device = ndicapy.ndiOpen(dev.port)
        try:
            for command in ("INIT:", "TSTART:"):
                ndicapy.ndiCommand(device, command)
            # An ERRORxx reply to BX is an ASCII line; ndicapy's binary reader stops at its CR (no 5 s timeout)
            # but then checks a binary CRC on it, so it reports a bad CRC rather than the error code (labcal
            # decodes the line: test_ndi_bx.py). This shows the fake frames its error reply as ndicapy expects.
            # It comes first on purpose: after an earlier BX reply, ndicapy 3.7.6's Python wrapper turns the
            # binary leftovers in its reply buffer into a str, gets NULL and crashes the interpreter (SIGSEGV).
            dev.inject("error:0C")
            with pytest.raises(OSError) as info:
                ndicapy.ndiBX(device, 0x1000)
            assert ndicapy.ndiGetError(device) == ndicapy.NDI_BAD_CRC != ndicapy.NDI_TIMEOUT, str(info.value)
            dev.inject("bad_crc")
            with pytest.raises(OSError, match="Bad CRC on reply"):
                ndicapy.ndiBX(device, 0x1000)
            ndicapy.ndiBX(device, 0x1000)
            assert ndicapy.ndiGetError(device) == ndicapy.NDI_OKAY
            assert ndicapy.ndiGetBXNumberOfPassiveStrays(device) == 3
        finally:
            ndicapy.ndiClose(device)


def test_ndicapy_reads_a_frame_with_a_hidden_target_as_two_strays():
    hidden = SEEN.copy()
    hidden[2] = np.nan  # the simulator says t3 is out of sight
    with FakeNDIDevice(lambda: hidden, seed=12) as dev:
        reference, _ = ndicapy_strays(dev.port)
    assert reference.shape == (2, 3)
    for p in SEEN[:2]:
        assert np.min(np.linalg.norm(reference - p, axis=1)) < 1e-5  # TX carries 0.01 mm
