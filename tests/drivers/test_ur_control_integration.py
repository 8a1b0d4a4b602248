"""Tier 3: the REAL rtde_control.RTDEControlInterface drives the fake controller's simulated joints.

The fake emulates ur-rtde 1.6.5's private side (dashboard answers, script upload on 30003, command registers
over RTDE). What is exercised: connect with all three probes, blocking moveJ (command 1) moving the simulated
joints, stopJ (34), a protective stop during a move (moveJ returns False, the program halts), resume via
reuploadScript. Not exercised: asynchronous moves, acceleration profiles, anything but MOVEJ/STOPJ.
"""

from __future__ import annotations

import numpy as np
import pytest
from ur_fixtures import make_profile

from labcal.drivers.base import EmergencyStop, ProtectiveStop
from labcal.drivers.ur import URRobot
from labcal_fakes.rtde_fake import FakeRTDEServer

pytest.importorskip("rtde_control")
pytestmark = [pytest.mark.integration, pytest.mark.timeout(40)]

Q0 = [0.0, -1.5, 1.5, 0.0, 1.5, 0.0]
TARGET = np.array([0.08, -1.45, 1.42, 0.05, 1.55, -0.06])  # ≤ 0.08 rad: 0.16 s at 0.5 rad/s


@pytest.fixture
def fake():
    server = FakeRTDEServer(q0=Q0, control=True)
    try:
        server.start()
        yield server
    finally:
        server.stop()


@pytest.fixture
def robot(fake):
    robot = URRobot.connect(make_profile(fake.host, connect_timeout=2.0))
    try:
        yield robot
    finally:
        robot.close()


def commands(fake) -> list[int]:
    return [value for kind, value in fake.snapshot()["log"] if kind == "command"]


def test_real_movej_moves_the_simulated_robot(fake, robot):
    robot.move_joints(TARGET, speed=0.5, acceleration=1.0)
    np.testing.assert_allclose(fake.snapshot()["q"], TARGET, atol=1e-9)
    np.testing.assert_allclose(robot.joint_positions(), TARGET, atol=1e-9)
    log = fake.snapshot()["log"]
    moves = [value for kind, value in log if kind == "movej"]
    assert moves == [{"q": pytest.approx(TARGET.tolist()), "speed": 0.5, "async": False}]
    assert [entry for entry in log if entry[0] in ("not_found", "unsupported")] == [], "fake missed a request"


def test_stop_sends_stopj(fake, robot):
    robot.stop()
    assert 34 in commands(fake)


@pytest.mark.parametrize(("kind", "error"), [("protective", ProtectiveStop), ("emergency", EmergencyStop)])
def test_safety_stop_during_a_move_is_reported_not_ignored(fake, robot, kind, error):
    fake.inject_stop_during_next_move(kind, fraction=0.5)
    with pytest.raises(error) as info:
        robot.move_joints(TARGET, speed=0.5, acceleration=1.0)
    if kind == "protective":
        assert not isinstance(info.value, EmergencyStop)
    q = np.asarray(fake.snapshot()["q"])
    assert 0.2 < np.max(np.abs(q - Q0)) / np.max(np.abs(TARGET - np.array(Q0))) < 0.9, "stopped part-way"
    robot.stop()  # safe after the failure


def test_resume_after_the_operator_cleared_the_stop(fake, robot):
    fake.inject_stop_during_next_move("protective", fraction=0.3)
    with pytest.raises(ProtectiveStop):
        robot.move_joints(TARGET, speed=0.5, acceleration=1.0)
    with pytest.raises(ProtectiveStop):
        robot.resume()
    fake.set_safety()  # cleared on the "teach pendant"
    robot.resume()
    robot.move_joints(TARGET, speed=0.5, acceleration=1.0)
    np.testing.assert_allclose(robot.joint_positions(), TARGET, atol=1e-9)
    assert [v for k, v in fake.snapshot()["log"] if k == "program"].count("started") == 2
