"""A simulated controller whose joints are not the model's (the coupled-elbow example robot): the rig speaks
controller joints, data recorded that way fit to the noise floor once converted to model joints and not without
the conversion, and the compensator built from that fit takes and returns controller joints."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labcal.calibration import Observations, fit_local_poe
from labcal.compensator import Compensator
from labcal.compensator import save as save_compensator
from labcal.drivers.base import MotionRejected
from labcal.drivers.sim import SimRig
from labcal.robots import load
from labcal.sessions import random_configurations
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.1, 0.0, 0.03], [-0.05, 0.08, 0.03], [-0.05, -0.08, 0.03]])
NOISE = 0.02e-3  # m, tracker noise per averaged measurement


@pytest.fixture(scope="module")
def spec():
    return load("coupled-elbow-6r")


def rig_for(spec, **kwargs) -> SimRig:
    actual = simulate(spec, ErrorSpec.paper(tracker_noise=NOISE), seed=3)  # geometric errors only
    return SimRig(actual, TARGETS, seed=2, joint_map=spec.joint_map, **kwargs)


@pytest.fixture(scope="module")
def recorded(spec):
    """60 poses planned in model joints, commanded and recorded in controller joints, as the runner does."""
    q_model = random_configurations(spec.model, 60, seed=0, targets=TARGETS)
    rig = rig_for(spec)
    q_rec, points = [], []
    with rig.robot() as robot, rig.tracker() as tracker:
        for q in spec.joints.to_controller(q_model):
            robot.move_joints(q, speed=0.5, acceleration=1.0)
            q_rec.append(robot.joint_positions())
            points.append(tracker.measure(samples=1).points)
    return q_model, np.array(q_rec), np.array(points)


def point_rms(robot, q_model, points) -> float:
    T = robot.predict_pose(q_model, tcp=robot.measurement_tool)  # the targets sit on the measurement tool
    pred = np.einsum("kab,mb->kma", T[:, :3, :3], TARGETS) + T[:, None, :3, 3]
    return float(np.sqrt(np.mean(np.sum((pred - points) ** 2, axis=2))))


def test_the_rig_reports_controller_joints_and_moves_the_model_joints(spec, recorded):
    q_model, q_rec, _ = recorded
    np.testing.assert_array_equal(q_rec, spec.joints.to_controller(q_model))  # exactly what it was commanded
    assert np.max(np.abs(q_rec - q_model)) > 0.1  # the controller's numbers really differ from the model's
    rig = rig_for(spec)
    with rig.robot() as robot:
        robot.move_joints(q_rec[0], speed=0.5, acceleration=1.0)
        np.testing.assert_allclose(rig.q_model, q_model[0], atol=1e-15)
        np.testing.assert_allclose(robot.state().q, q_rec[0], atol=1e-15)


def test_limits_are_the_models_checked_after_conversion(spec):
    rig = rig_for(spec)
    limits = spec.model.limits
    # Each controller value lies inside the limits of the joint with its number (a box check in controller joints
    # would pass it), but the model elbow J2 + J3 = 2.5 rad is beyond the elbow's limit.
    q = np.zeros(6)
    q[1], q[2] = 1.0, 1.5
    assert np.all((limits[:, 0] <= q) & (q <= limits[:, 1]))
    assert spec.joints.to_model(q)[2] > limits[2, 1]
    with rig.robot() as robot:
        with pytest.raises(MotionRejected, match=r"model joint 3 target 2\.500000 .* through the joint map"):
            robot.move_joints(q, speed=0.5, acceleration=1.0)
        q[2] = 0.5  # elbow 1.5 rad: allowed
        robot.move_joints(q, speed=0.5, acceleration=1.0)
        np.testing.assert_allclose(robot.joint_positions(), q)


def test_an_identity_map_changes_nothing(spec):
    fanuc = load("fanuc-m1000ia")
    a = SimRig(simulate(fanuc, ErrorSpec.paper(), seed=3), TARGETS, seed=2)
    b = SimRig(simulate(fanuc, ErrorSpec.paper(), seed=3), TARGETS, seed=2, joint_map=fanuc.joints)
    q = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    for rig in (a, b):
        with rig.robot() as robot:
            robot.move_joints(q, speed=0.5, acceleration=1.0)
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.true_points(), b.true_points())


def test_converted_data_fit_to_the_noise_floor_and_unconverted_data_do_not(spec, recorded):
    _, q_ctrl, points = recorded
    q_model = spec.joints.to_model(q_ctrl)
    good, _ = fit_local_poe(Observations(q_model, points, TARGETS), spec.model)
    after = point_rms(good, q_model, points)
    assert after < 2.5 * NOISE  # the noise floor: geometric errors only, fully identified
    # The same numbers taken as model joints (no conversion) cannot be explained by any geometric error model.
    bad, _ = fit_local_poe(Observations(q_ctrl, points, TARGETS), spec.model)
    assert point_rms(bad, q_ctrl, points) > 50 * after


def test_the_compensator_of_that_fit_takes_and_returns_controller_joints(spec, recorded, tmp_path):
    _, q_ctrl, points = recorded
    q_model = spec.joints.to_model(q_ctrl)
    robot, _ = fit_local_poe(Observations(q_model, points, TARGETS), spec.model)
    robot = dataclasses.replace(robot, joint_map=spec.joint_map)
    comp = Compensator.load(save_compensator(robot, tmp_path / "c.json"))
    assert comp.robot_hash == spec.hash and not comp.joint_map.is_identity
    q_cmd = comp.correct(q_ctrl[:10])
    np.testing.assert_allclose(q_cmd, spec.joints.to_controller(robot.correct(q_model[:10])), atol=1e-12)
    # Commanding the corrected controller joints puts the real tool where the nominal model puts q (robot and tool
    # apart: the targets at the fixture's identified pose on the nominal flange).
    X = np.eye(4) if robot.measurement_tool is None else robot.measurement_tool
    rig = rig_for(spec)
    with rig.robot() as rob:
        for want, cmd in zip(q_model[:5], q_cmd[:5], strict=True):
            rob.move_joints(cmd, speed=0.5, acceleration=1.0)
            T = spec.model.fk(want) @ X
            nominal = TARGETS @ T[:3, :3].T + T[:3, 3]
            assert np.max(np.abs(rig.true_points() - nominal)) < 5 * NOISE
    np.testing.assert_allclose(comp.predict_pose(q_ctrl[:3]), robot.predict_pose(q_model[:3]), atol=1e-15)


def test_a_protective_stop_halfway_leaves_controller_and_model_joints_consistent(spec):
    from labcal.drivers.base import ProtectiveStop
    from labcal.drivers.sim import SimFaults

    rig = rig_for(spec, faults=SimFaults(protective_stop_at=[2]))
    a, b = np.array([0.1, 0.2, 0.3, 0.0, 0.5, 0.0]), np.array([0.3, -0.2, 0.6, 0.2, 0.9, 0.1])
    with rig.robot() as robot:
        robot.move_joints(a, speed=0.5, acceleration=1.0)
        with pytest.raises(ProtectiveStop):
            robot.move_joints(b, speed=0.5, acceleration=1.0)
        np.testing.assert_allclose(robot.joint_positions(), 0.5 * (a + b), atol=1e-15)
        np.testing.assert_allclose(rig.q_model, spec.joints.to_model(0.5 * (a + b)), atol=1e-15)
