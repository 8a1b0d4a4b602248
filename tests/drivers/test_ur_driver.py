"""URRobot against hand-written ur-rtde stand-ins: limits, safety state, moveJ results, staleness, errors."""

from __future__ import annotations

import numpy as np
import pytest
from ur_fixtures import HOME, StubControl, StubReceive, make_profile

from labcal.drivers.base import (
    ConnectionFailed,
    EmergencyStop,
    MotionFailed,
    MotionRejected,
    ProtectiveStop,
    ProtocolError,
    Robot,
    StaleData,
)
from labcal.drivers.ur import URRobot

TARGET = HOME + np.array([0.1, -0.05, 0.05, 0.1, 0.0, -0.2])


def make_robot(**profile_overrides: object) -> tuple[URRobot, StubReceive, StubControl]:
    rx = StubReceive()
    ctl = StubControl(rx)
    return URRobot(make_profile(**profile_overrides), rx, ctl), rx, ctl


def test_urrobot_satisfies_the_robot_port():
    robot, _, _ = make_robot()
    assert isinstance(robot, Robot)
    assert robot.n_joints == 6


def test_move_reaches_target_and_passes_speed_and_acceleration_through():
    robot, _rx, ctl = make_robot()
    robot.move_joints(TARGET, speed=0.3, acceleration=0.7)
    assert ctl.moves == [(pytest.approx(TARGET.tolist()), 0.3, 0.7, False)]
    np.testing.assert_allclose(robot.joint_positions(), TARGET)


@pytest.mark.parametrize(
    ("q", "speed", "acceleration", "named"),
    [
        (HOME + np.array([4.0, 0, 0, 0, 0, 0]), 0.3, 0.5, "joint 1"),  # beyond ±π in the test profile
        (HOME, 0.6, 0.5, "speed"),  # cap 0.5 rad/s
        (HOME, 0.3, 1.5, "acceleration"),  # cap 1.0 rad/s²
        (HOME[:5], 0.3, 0.5, "joint values"),
        (np.array([np.nan, 0, 0, 0, 0, 0]), 0.3, 0.5, "non-finite"),
    ],
)
def test_motion_outside_limits_is_rejected_before_reaching_the_controller(q, speed, acceleration, named):
    robot, _, ctl = make_robot()
    with pytest.raises(MotionRejected, match=named):
        robot.move_joints(q, speed=speed, acceleration=acceleration)
    assert ctl.moves == []


@pytest.mark.parametrize(("flag", "error"), [("protective", ProtectiveStop), ("emergency", EmergencyStop)])
def test_refuses_to_move_while_stopped(flag, error):
    robot, rx, ctl = make_robot()
    setattr(rx, flag, True)
    with pytest.raises(error, match="before the move"):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)
    assert ctl.moves == []


def test_refuses_to_move_unless_robot_mode_is_running():
    robot, rx, ctl = make_robot()
    rx.mode = 5  # IDLE
    with pytest.raises(MotionRejected, match="robot mode is 5"):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)
    assert ctl.moves == []


def test_movej_false_with_protective_stop_raises_protective_stop_with_position():
    robot, _rx, ctl = make_robot()
    ctl.outcome = "protective"
    with pytest.raises(ProtectiveStop, match="after a failed move") as info:
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)
    assert not isinstance(info.value, EmergencyStop)
    assert "q = [" in str(info.value)


def test_resume_after_a_cleared_protective_stop_restarts_the_script():
    robot, rx, ctl = make_robot()
    ctl.outcome = "protective"
    with pytest.raises(ProtectiveStop):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)
    with pytest.raises(ProtectiveStop, match="teach pendant"):
        robot.resume()  # still stopped: labcal does not unlock it
    assert ctl.reuploads == 0
    rx.protective = False  # the operator cleared it
    robot.resume()
    assert ctl.reuploads == 1
    ctl.outcome = "ok"
    robot.move_joints(TARGET, speed=0.3, acceleration=0.5)
    np.testing.assert_allclose(robot.joint_positions(), TARGET)
    robot.resume()  # script already running: nothing to do
    assert ctl.reuploads == 1


def test_movej_false_without_stop_raises_motion_failed():
    robot, _, ctl = make_robot()
    ctl.outcome = "false"
    with pytest.raises(MotionFailed, match="failed"):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)


def test_move_that_ends_outside_tolerance_raises_motion_failed():
    robot, _, ctl = make_robot()
    ctl.outcome = "short"
    with pytest.raises(MotionFailed, match="from the target"):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)


def test_ur_rtde_value_error_becomes_motion_rejected():
    robot, _, ctl = make_robot()
    ctl.outcome = ValueError("acceleration out of range")
    with pytest.raises(MotionRejected, match="ur-rtde refused"):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)


def test_ur_rtde_runtime_error_becomes_motion_failed_or_connection_failed():
    robot, rx, ctl = make_robot()
    ctl.outcome = RuntimeError("RTDE control script is not running!")
    with pytest.raises(MotionFailed, match="script is not running"):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)
    rx.connected = False
    with pytest.raises(ConnectionFailed):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)


def test_frozen_timestamp_raises_stale_data():
    robot, rx, _ = make_robot(stale_timeout=0.05)
    robot.state()
    rx.frozen = True
    with pytest.raises(StaleData, match="stuck"):
        robot.state()
    rx.frozen = False
    assert robot.state().timestamp > 0


def test_state_reports_safety_flags_and_readiness():
    robot, rx, _ = make_robot()
    assert robot.state().ready
    rx.protective = True
    state = robot.state()
    assert state.protective_stop and not state.emergency_stop and not state.ready
    rx.protective, rx.emergency = False, True
    state = robot.state()
    assert state.emergency_stop and not state.ready


def test_disconnected_receive_raises_connection_failed():
    robot, rx, _ = make_robot()
    rx.connected = False
    with pytest.raises(ConnectionFailed):
        robot.joint_positions()


def test_getter_runtime_error_is_mapped():
    robot, rx, _ = make_robot()
    rx.fail_with = RuntimeError("unable to get state data for specified key: actual_q")
    with pytest.raises(ProtocolError, match="actual_q"):
        robot.joint_positions()
    rx.connected = False
    with pytest.raises(ConnectionFailed):
        robot.joint_positions()


def test_stop_is_always_safe():
    robot, _, ctl = make_robot()
    robot.stop()
    assert ctl.stops == [(2.0, False)]
    ctl.stop_error = RuntimeError("not connected")
    robot.stop()  # must not raise
    robot.close()
    robot.stop()  # after close: no call, no raise
    assert len(ctl.stops) == 2


def test_close_is_idempotent_and_disconnects_both():
    robot, rx, ctl = make_robot()
    robot.close()
    robot.close()
    assert (rx.disconnects, ctl.disconnects) == (1, 1)
    with pytest.raises(ConnectionFailed, match="closed"):
        robot.joint_positions()


def test_context_manager_stops_on_error_and_closes():
    robot, rx, ctl = make_robot()
    with pytest.raises(KeyError), robot:
        raise KeyError("session failed")
    assert ctl.stops and rx.disconnects == 1


def test_a_second_ctrl_c_during_the_stop_on_the_way_out_still_closes_the_interfaces():
    # Leaving on an error, the robot is stopped, then closed; an operator's second Ctrl-C during that stop must not
    # skip the close (each ur-rtde interface is a process and a controller connection of its own).
    robot, rx, ctl = make_robot()
    ctl.stop_error = KeyboardInterrupt()
    with pytest.raises(KeyboardInterrupt), robot:
        raise KeyboardInterrupt
    assert ctl.stops and (rx.disconnects, ctl.disconnects) == (1, 1)


def test_read_only_robot_refuses_to_move():
    rx = StubReceive()
    robot = URRobot(make_profile(), rx, None)
    with pytest.raises(MotionRejected, match="read-only"):
        robot.move_joints(TARGET, speed=0.3, acceleration=0.5)
    robot.stop()  # still safe
    np.testing.assert_allclose(robot.joint_positions(), HOME)


def test_connect_uses_injected_factories_and_maps_constructor_errors():
    rx = StubReceive()
    made: list[tuple[str, float]] = []

    def receive_factory(host: str, frequency: float) -> StubReceive:
        made.append((host, frequency))
        return rx

    def failing_control(host: str, frequency: float) -> StubControl:
        raise RuntimeError(f"Could not connect to: {host} at 30004")

    robot = URRobot.connect(make_profile("10.0.0.9"), read_only=True, probe=False, receive_factory=receive_factory)
    assert made == [("10.0.0.9", -1.0)]
    assert robot.joint_positions().shape == (6,)
    with pytest.raises(ConnectionFailed, match="Could not connect"):
        URRobot.connect(make_profile(), probe=False, receive_factory=receive_factory, control_factory=failing_control)
    assert rx.disconnects == 1  # the half-built connection was released
