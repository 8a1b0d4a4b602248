"""Robot and tool apart: the fit identifies the robot to tool0 and the measurement tool separately, the compensator
works at a TCP given at run time, and a calibration survives a tool change (issue 27)."""

import numpy as np
import pytest

from labcal.calibration.local_poe import fit_local_poe
from labcal.calibration.observations import Observations
from labcal.calibration.tool import split_tool
from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec, simulate

UR10 = load("ur10")
TRIANGLE = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.05, 0.0866, 0.0]])
MOUNT = se3.pose([0.093, 0.0, 0.02], [np.pi / 2, 0.0, np.pi / 2])  # a probe mount: 93 mm off the axis, 90°


def poses(k, seed=0):
    nominal, rng, out = UR10.model, np.random.default_rng(seed), []
    L = nominal.reach()
    while sum(len(o) for o in out) < k:
        q = rng.uniform(-np.pi, np.pi, size=(4 * k, 6))
        out.append(q[scaled_condition(nominal.equivalent_jacobian(q, length_scale=L), L) < 30])
    return np.concatenate(out)[:k]


def measure(X_true, X_given, targets=TRIANGLE, k=60, seed=1, noise=0.05e-3):
    """(actual robot, observations) of a fixture at X_true in the true tool0, the user giving it at X_given."""
    actual = simulate(UR10, ErrorSpec.paper(tracker_noise=noise), seed=seed)
    q = poses(k)
    on_tool = targets @ X_true[:3, :3].T + X_true[:3, 3]
    points = actual.measure(q, on_tool, np.random.default_rng(seed))
    return actual, Observations(q=q, points=points, targets=targets @ X_given[:3, :3].T + X_given[:3, 3])


@pytest.fixture(scope="module")
def forgotten():
    """The probe mount forgotten: the targets given as if on the flange."""
    actual, obs = measure(MOUNT, np.eye(4))
    robot, info = fit_local_poe(obs, UR10.model)
    return actual, obs, robot, info


def test_the_fit_keeps_the_robot_on_tool0_and_identifies_the_mount_as_the_measurement_tool(forgotten):
    _actual, obs, robot, info = forgotten
    assert np.array_equal(robot.model.frames[-1], UR10.model.frames[-1])  # tool0 held at the robot file's tool
    q = obs.q
    dp, dr = se3.pose_distance(robot.model.fk(q), UR10.model.fk(q))
    assert dp.max() < 10e-3 and dr.max() < 10e-3  # the robot's own errors: millimetres, not the 93 mm mount
    X = robot.measurement_tool
    assert np.linalg.norm(X[:3, 3] - MOUNT[:3, 3]) < 3e-3  # the mount, up to the flange's unobservable part
    assert np.linalg.norm(se3.log_so3(MOUNT[:3, :3].T @ X[:3, :3])) < 5e-3
    std = robot.measurement_tool_std
    assert np.isfinite(std).all() and (std[:3] < 0.1e-3).all() and (std[3:] < 0.1e-3).all()
    np.testing.assert_array_equal(info["measurement_tool"], X)
    # the data still see the fixture: the split changes no prediction of a measured point
    assert np.abs(robot.predict_points(q, obs.targets) - obs.points).max() < 0.5e-3


def test_the_robot_part_is_the_same_whichever_fixture_guess_measured_it(forgotten):
    """A calibration survives a tool change: the robot (to tool0) does not depend on the fixture it was seen
    through, nor on the user's guess of where that fixture sits."""
    _, _, robot, _ = forgotten
    _, obs = measure(MOUNT, MOUNT @ se3.pose([0.005, -0.006, 0.004]))  # the mount guessed 9 mm off
    close, _ = fit_local_poe(obs, UR10.model)
    q = poses(200, seed=5)
    dp, dr = se3.pose_distance(close.model.fk(q), robot.model.fk(q))
    assert dp.max() < 1e-6 and dr.max() < 1e-6
    tool_b = se3.pose([0.03, -0.05, 0.243], [0.4, -0.5, 1.1])
    np.testing.assert_allclose(close.correct(q, tcp=tool_b), robot.correct(q, tcp=tool_b), atol=1e-6)


def test_the_flange_turn_and_shift_are_those_closest_to_the_nominal_over_the_data(forgotten):
    """What no data can tell apart from the tool (a turn about / shift along the last axis) is chosen where the
    robot's own errors look smallest over the data: any other turn or shift moves tool0 farther from the nominal."""
    from labcal.calibration.tool import _moved

    _, obs, robot, _ = forgotten
    L = UR10.model.reach()
    w = np.array([1, 1, 1, L, L, L])  # the split's metric: angles weighted by the reach

    def cost(p):
        moved, _, _ = _moved(robot.model, robot.measurement_tool, None, np.array([*p, 0.0, 0.0]))
        return float(np.sum((se3.log_se3(se3.inv(UR10.model.fk(obs.q)) @ moved.fk(obs.q)) * w) ** 2))

    best = cost((0.0, 0.0))
    for p in ((1e-3, 0), (-1e-3, 0), (0, 1e-3), (0, -1e-3)):
        assert cost(p) > best


def test_split_tool_changes_no_pose_and_moves_the_commuting_part_into_the_tool():
    nominal = UR10.model
    frames = np.array(nominal.frames)
    frames[5] = frames[5] @ se3.pose([0.0, 0.0, 0.004], [0.0, 0.0, 0.3])  # a turn/shift of A_6 about its z axis
    frames[6] = frames[6] @ MOUNT
    model = nominal.replace(frames=frames)
    robot, X = split_tool(nominal, model)
    np.testing.assert_allclose(robot.frames, nominal.frames, atol=1e-12)  # nothing of it was the robot's
    q = poses(20)
    chain = robot.replace(frames=np.concatenate([robot.frames[:-1], (robot.frames[-1] @ X)[None]]))
    np.testing.assert_allclose(chain.fk(q), model.fk(q), atol=1e-12)


def test_one_target_leaves_the_tool_orientation_unseen():
    _actual, obs = measure(MOUNT, np.eye(4), targets=TRIANGLE[:1])
    robot, _ = fit_local_poe(obs, UR10.model)
    std = robot.measurement_tool_std
    assert np.isnan(std[3:]).all() and np.isfinite(std[:3]).all()


def test_correct_at_a_tcp_reaches_the_nominal_tcp_pose(forgotten):
    _, _, robot, _ = forgotten
    tcp = se3.pose([0.03, -0.05, 0.243], [0.4, -0.5, 1.1])
    q = poses(5, seed=3)
    batch = robot.correct(q, tcp=tcp, extrapolate=True)
    np.testing.assert_allclose(robot.predict_pose(batch, tcp=tcp), UR10.model.fk(q) @ tcp, atol=1e-9)
    one = robot.correct(q[0], tcp=tcp, extrapolate=True)  # the single-configuration path
    np.testing.assert_allclose(one, batch[0], atol=1e-12)
    with pytest.raises(ValueError, match="tcp must be"):
        robot.correct(q[0], tcp=np.eye(3), extrapolate=True)


def test_a_tcp_sets_where_a_least_squares_correction_is_measured():
    """n < 6: the correction is a least-squares compromise, and the TCP says where it is best."""
    scara = load("scara4")
    actual = simulate(scara, ErrorSpec.paper(), seed=2)
    rng = np.random.default_rng(0)
    lo, hi = scara.model.limits.T
    q = lo + (hi - lo) * rng.uniform(0.2, 0.8, size=(40, 4))
    points = actual.measure(q, TRIANGLE, rng)
    robot, _ = fit_local_poe(Observations(q=q, points=points, targets=TRIANGLE), scara.model)
    tcp = se3.pose([0.3, 0.0, -0.2])
    at_tool0 = robot.correct(q[:5], extrapolate=True)
    at_tcp = robot.correct(q[:5], tcp=tcp, extrapolate=True)
    assert np.abs(at_tcp - at_tool0).max() > 1e-7

    def miss(q_cmd):
        return se3.pose_distance(robot.predict_pose(q_cmd, tcp=tcp), scara.model.fk(q[:5]) @ tcp)[0]

    assert (miss(at_tcp) <= miss(at_tool0) + 1e-12).all()
