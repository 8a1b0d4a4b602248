"""The simulation on 7-joint arms: a Panda with geometric, compliance and gear errors measured with one reflector
and with three targets, the scenario generators (wrist, coupled elbow) and the sim rig's joint limits."""

from __future__ import annotations

import numpy as np
import pytest

import scenarios as S
from labcal.drivers.base import MotionRejected
from labcal.drivers.sim import SimRig
from labcal.robots import load
from labcal.robots.joint_map import JointMap
from labcal.simulation import ErrorSpec, simulate

NOISE = ErrorSpec.default().tracker_noise
SEVEN = ("franka-panda", "kuka-iiwa14-r820")


@pytest.fixture(scope="module")
def panda():
    return load("franka-panda")


def test_the_default_error_model_gives_a_panda_all_three_kinds_of_error(panda):
    actual = simulate(panda, ErrorSpec.default(), seed=3)
    assert actual.n == 7 and actual.joint_offsets.shape == (7,) and actual.gear.shape == (7, 2, 2)
    assert np.all(actual.delta_zeta != 0)  # geometric: every frame, 7 joints + tool
    assert np.all(actual.gear[:, :, 0] != 0)  # gears: both harmonics on every joint
    # compliance: every joint gravity loads (all but the vertical joint 1 and joint 7, whose link is on its axis)
    q = S.good("franka-panda", 50, seed=3).q
    loaded = np.abs(actual.gravity_torque(q)).max(axis=0) > 1e-6
    assert loaded[1:6].all() and np.all(actual.compliance[loaded] > 0)
    # each part moves the tool: switching one source off changes the true pose
    for off in ({"compliance_deflection": 0.0}, {"gear_std": 0.0}, {"length_std": 0.0, "angle_std": 0.0}):
        other = simulate(panda, ErrorSpec.default(**off), seed=3)
        shift = np.linalg.norm(actual.true_pose(q)[:, :3, 3] - other.true_pose(q)[:, :3, 3], axis=1)
        assert shift.max() > 1e-5, off


@pytest.mark.parametrize("robot", SEVEN)
def test_one_reflector_and_three_targets_are_measured_from_the_true_robot(robot):
    three = S.good(robot, 40, seed=1)
    one = S.with_targets(three, [0])
    model = load(robot).model
    assert three.q.shape == (40, 7) and three.points.shape == (40, 3, 3) and one.points.shape == (40, 1, 3)
    assert np.all((three.q >= model.limits[:, 0]) & (three.q <= model.limits[:, 1]))
    true = three.actual.true_points(three.q, three.targets)
    assert np.abs(three.points - true).max() < 6 * NOISE
    np.testing.assert_array_equal(one.points[:, 0], three.points[:, 0])
    # and the errors are far above the noise: the true robot is not the nominal one
    nominal = model.target_points(three.q, three.targets)
    assert np.linalg.norm(three.points - nominal, axis=-1).mean() > 20 * NOISE


@pytest.mark.parametrize("robot", SEVEN)
def test_the_wrist_of_a_7r_arm_is_joint_6_and_sweeps_hold_it(robot):
    model = load(robot).model
    wrist = S.wrist_joint(model)
    assert wrist == 5
    scn = S.sweeps(robot, 32, 4, seed=2)
    moved = [int(np.flatnonzero(np.ptp(scn.q[scn.group == g], axis=0) > 0)[0]) for g in np.unique(scn.group)]
    assert moved == [g % 7 for g in range(8)]
    held = np.abs(scn.q[:, wrist]) < S.WRIST_TOL
    assert np.all(held[scn.group % 7 != wrist]) and not held.all()
    # what makes it the wrist: with q6 = 0 the axes of joints 5 and 7 are parallel
    w = model.joint_twists(scn.q[held])[:, 3:]
    assert np.abs(np.cross(w[:, :, 4], w[:, :, 6])).max() < 2 * S.WRIST_TOL
    assert "|q6| < 1 mrad" in scn.description
    singular = S.singular_wrist(robot, 20, fraction=0.5, seed=0)
    assert (np.abs(singular.q[:, wrist]) < S.WRIST_TOL).sum() == 10


def test_an_arm_without_such_a_wrist_says_so():
    assert S.wrist_joint(load("scara4").model) is None
    with pytest.raises(ValueError, match="'scara4' has no wrist joint"):
        S.singular_wrist("scara4", 10)


def test_coupled_elbow_on_seven_joints_maps_back(panda):
    scn = S.coupled_elbow("franka-panda", 12, seed=4)
    qc = scn.q_controller
    assert scn.joint_map.shape == (7, 7)
    np.testing.assert_allclose(qc[:, 1] + qc[:, 2], scn.q[:, 2], atol=1e-12)
    np.testing.assert_allclose(np.delete(qc, 2, axis=1), np.delete(scn.q, 2, axis=1), atol=1e-12)
    np.testing.assert_allclose(JointMap(scn.joint_map, np.zeros(7)).to_model(qc), scn.q, atol=1e-12)


def test_the_sim_rig_moves_a_panda_within_its_limits_and_measures_it(panda):
    actual = simulate(panda, ErrorSpec.default(), seed=5)
    targets = S.TARGETS
    rig = SimRig(actual, targets, seed=5)
    # the rig starts at the zeros clipped into Franka's limits (joint 4 never reaches 0)
    np.testing.assert_array_equal(rig.q, np.clip(np.zeros(7), panda.model.limits[:, 0], panda.model.limits[:, 1]))
    q = S.good("franka-panda", 1, seed=5).q[0]
    with rig.robot() as robot, rig.tracker() as tracker:
        assert robot.n_joints == 7
        robot.move_joints(q, speed=0.5, acceleration=1.0)
        m = tracker.measure(samples=4)
        bad = q.copy()
        bad[3] = 0.0  # joint 4 at zero: outside [-3.0718, -0.0698]
        with pytest.raises(MotionRejected, match="joint 4"):
            robot.move_joints(bad, speed=0.5, acceleration=1.0)
        with pytest.raises(MotionRejected):
            robot.move_joints(q[:6], speed=0.5, acceleration=1.0)
    np.testing.assert_array_equal(rig.q, q)  # the refused moves did not move it
    assert np.abs(m.points - actual.true_points(q, targets)[0]).max() < 6 * NOISE
