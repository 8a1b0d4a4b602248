"""Hardware tier: a real UR controller named with --robot-host. Skipped unless that option is given.

Reads only, except test_small_guarded_move, which also needs LABCAL_ALLOW_MOTION=1 in the environment: it
turns wrist 3 by 0.05 rad (≈3 deg) at 0.1 rad/s and back. Profile: LABCAL_UR_PROFILE (default
drivers/ur10-lab.toml), its host replaced by --robot-host.

    pytest -m "hardware and robot" --robot-host 192.168.1.10 tests/drivers/test_ur_hardware.py
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from labcal.drivers.ur import URRobot, load_ur_profile, probe_rtde

pytestmark = [pytest.mark.hardware, pytest.mark.robot, pytest.mark.timeout(60)]

REPO = Path(__file__).resolve().parents[2]
WRIST_STEP = 0.05  # rad


@pytest.fixture
def profile(request):
    host = request.config.getoption("--robot-host")
    path = os.environ.get("LABCAL_UR_PROFILE", str(REPO / "drivers" / "ur10-lab.toml"))
    return load_ur_profile(path).with_host(host)


def test_controller_answers_rtde(profile):
    major, minor, _, _ = probe_rtde(profile.host, timeout=profile.connect_timeout)
    assert major >= 3, f"controller version {major}.{minor} is older than CB3"


def test_reads_joints_and_safety_state(profile):
    with URRobot.connect(profile, read_only=True) as robot:
        first = robot.state()
        second = robot.state()
    assert first.q.shape == (6,) and np.all(np.isfinite(first.q))
    assert second.timestamp > first.timestamp, "controller timestamp must advance"
    lo, hi = profile.limits.joint_limits.T
    assert np.all((first.q >= lo) & (first.q <= hi)), f"robot sits outside the profile's joint limits: {first.q}"
    print(f"q = {first.q.tolist()} rad, ready={first.ready}, protective={first.protective_stop}")


@pytest.mark.skipif(os.environ.get("LABCAL_ALLOW_MOTION") != "1", reason="set LABCAL_ALLOW_MOTION=1 to move")
def test_small_guarded_move(profile):
    with URRobot.connect(profile) as robot:
        start = robot.state()
        assert start.ready, f"robot not ready to move: {start}"
        target = start.q.copy()
        target[5] += WRIST_STEP if target[5] + WRIST_STEP <= profile.limits.joint_limits[5, 1] else -WRIST_STEP
        speed = min(0.1, profile.limits.max_speed)
        acceleration = min(0.3, profile.limits.max_acceleration)
        try:
            robot.move_joints(target, speed=speed, acceleration=acceleration)
            np.testing.assert_allclose(robot.joint_positions(), target, atol=profile.position_tolerance)
        finally:
            robot.move_joints(start.q, speed=speed, acceleration=acceleration)
        np.testing.assert_allclose(robot.joint_positions(), start.q, atol=profile.position_tolerance)
