"""URRobot with the REAL rtde_receive.RTDEReceiveInterface against the fake controller in another process."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from ur_fixtures import make_profile, silent_listener

from labcal.drivers.base import ConnectionFailed, DriverTimeout, ProtocolError, StaleData
from labcal.drivers.ur import ProbeTimeout, URRobot, probe_rtde
from labcal_fakes.rtde_fake import FakeRTDEServer

pytest.importorskip("rtde_receive")
pytestmark = [pytest.mark.integration, pytest.mark.timeout(30)]

Q0 = [0.1, -1.2, 1.3, -0.4, 1.5, -0.6]


@pytest.fixture
def fake():
    server = FakeRTDEServer(q0=Q0)
    try:
        server.start()
        yield server
    finally:
        server.stop()


@pytest.fixture
def robot(fake):
    robot = URRobot.connect(make_profile(fake.host, stale_timeout=0.3), read_only=True)
    try:
        yield robot
    finally:
        robot.close()


def eventually(check, timeout: float = 2.0):
    """Poll check() until it returns a truthy value (the fake streams at 500 Hz; changes land within ms)."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value or time.monotonic() > deadline:
            return value
        time.sleep(0.005)


def test_probe_returns_the_controller_version(fake):
    assert probe_rtde(fake.host, timeout=2.0) == (5, 11, 0, 0)


def test_reads_joint_positions_through_the_real_interface(fake, robot):
    np.testing.assert_allclose(robot.joint_positions(), Q0)
    fake.set_q([0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    assert eventually(lambda: np.allclose(robot.joint_positions(), [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]))


def test_reads_safety_state_through_the_real_interface(fake, robot):
    state = robot.state()
    assert state.ready and not state.protective_stop and not state.emergency_stop
    fake.set_safety(protective=True)
    state = eventually(lambda: (s := robot.state()).protective_stop and s)
    assert state and not state.emergency_stop and not state.ready
    fake.set_safety(emergency=True)
    state = eventually(lambda: (s := robot.state()).emergency_stop and s)
    assert state and not state.protective_stop
    fake.set_safety()
    fake.set_robot_mode(5)  # IDLE
    assert eventually(lambda: robot.robot_mode() == 5)
    assert not robot.state().ready


def test_fake_knows_every_variable_of_ur_rtdes_default_recipe(fake):
    import rtde_receive

    # With no variable list, ur-rtde asks for its full default recipe (~59 names); NOT_FOUND would raise.
    interface = rtde_receive.RTDEReceiveInterface(fake.host)
    try:
        assert eventually(lambda: interface.getTimestamp() > 0)
        assert interface.getActualQ() == pytest.approx(Q0)
    finally:
        interface.disconnect()
    assert [entry for entry in fake.snapshot()["log"] if entry[0] == "not_found"] == []


def test_consecutive_states_have_advancing_timestamps(robot):
    stamps = [robot.state().timestamp for _ in range(5)]
    assert all(b > a for a, b in itertools.pairwise(stamps))


def test_frozen_controller_clock_raises_stale_data(fake, robot):
    robot.state()
    fake.freeze_timestamp()
    with pytest.raises(StaleData):
        # the first call may still see a package sent before the freeze
        for _ in range(3):
            robot.state()
    fake.freeze_timestamp(False)
    assert robot.state().timestamp > 0


def test_controller_death_mid_session_raises_instead_of_hanging(fake, robot):
    robot.state()
    fake.kill()
    with pytest.raises((ConnectionFailed, StaleData)):
        for _ in range(3):
            robot.state()
    robot.stop()  # read-only: nothing to stop, still no exception
    robot.close()


def test_dropped_connection_raises(fake, robot):
    robot.state()
    fake.drop_clients()
    with pytest.raises((ConnectionFailed, StaleData)):
        for _ in range(3):
            robot.state()


def test_controller_lacking_a_variable_is_a_protocol_error():
    with FakeRTDEServer(unknown_variables=["safety_status_bits"]) as old:
        with pytest.raises(ProtocolError, match="safety_status_bits"):
            URRobot.connect(make_profile(old.host), read_only=True)


def test_probe_refuses_a_peer_that_accepts_but_never_answers():
    with silent_listener() as host:
        started = time.monotonic()
        with pytest.raises(ProbeTimeout) as info:
            probe_rtde(host, timeout=0.3)
        assert isinstance(info.value, ConnectionFailed) and isinstance(info.value, DriverTimeout)
        assert time.monotonic() - started < 5.0


def test_connect_never_hands_a_silent_peer_to_ur_rtde():
    def must_not_construct(host: str, frequency: float):
        raise AssertionError("ur-rtde would hang here")

    with silent_listener() as host, pytest.raises(ProbeTimeout):
        URRobot.connect(make_profile(host, connect_timeout=0.3), read_only=True, receive_factory=must_not_construct)


def test_nothing_listening_is_connection_failed():
    with silent_listener() as host:
        pass  # the address is free again: nothing listens there now
    with pytest.raises(ConnectionFailed, match="cannot connect"):
        probe_rtde(host, timeout=0.5)
    with pytest.raises(ConnectionFailed):
        URRobot.connect(make_profile(host, connect_timeout=0.5), read_only=True)
