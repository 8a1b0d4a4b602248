"""labcal filter (library): a program of TCP poses or nominal joints becomes joint targets that put the simulated
TRUE robot where the program asked; branch jumps, singular paths, unreachable rows and rows outside the calibrated
ranges are refused naming the row."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

import urscript_subset
from labcal.calibration import Observations
from labcal.calibration.fit import fit
from labcal.compensator import CalibratedRobot
from labcal.export.program import (
    ProgramError,
    filter_joints,
    filter_poses,
    joints_csv,
    movej_program,
    nominal_ik,
    pose_matrix,
)
from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec
from scenarios import good, joint_box


@pytest.fixture(scope="module")
def calibrated():
    """A simulated UR10 with known geometric errors, measured on 60 poses, fitted by local POE."""
    scn = good("ur10", 60, errors=ErrorSpec.paper(tracker_noise=1e-5), seed=4)
    result = fit(Observations(**scn.arrays()), load("ur10").model, "local-poe", seed=0)
    return scn.actual, result.robot


def program_poses(robot: CalibratedRobot, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A smooth program on one configuration branch: k TCP poses (x, y, z, rotation vector) the nominal model
    reaches along a joint path that stays well-conditioned (a program that really changes branch is refused)."""
    lo, hi = joint_box(robot.nominal, 0.4)
    rng = np.random.default_rng(seed)
    for _ in range(200):
        a = rng.uniform(lo, hi)
        b = a + rng.uniform(-0.5, 0.5, size=robot.n)
        dense = a + (b - a) * np.linspace(0, 1, 50)[:, None]
        J = robot.nominal.equivalent_jacobian(dense, length_scale=robot.length_scale)
        if np.max(scaled_condition(J, robot.length_scale)) < 50:
            break
    q = a + (b - a) * np.linspace(0, 1, k)[:, None]
    T = robot.nominal.fk(q)
    return np.concatenate([T[:, :3, 3], se3.log_so3(T[:, :3, :3])], axis=1), q


def test_filtered_poses_put_the_true_robot_where_the_program_asked(calibrated):
    actual, robot = calibrated
    poses, q_path = program_poses(robot, 12, seed=1)
    # the simulated robot's true tool is what the calibration identified as its measurement tool: the program's TCP
    X = robot.measurement_tool
    tcp = np.concatenate([X[:3, 3], se3.log_so3(X[:3, :3])])
    result = filter_poses(robot, poses, seed=q_path[0] + 0.05, tcp=tcp)
    # the nominal solution on the program's branch, for the TCP the program names
    np.testing.assert_allclose(robot.nominal.fk(result.q_nominal) @ X, pose_matrix(poses), atol=1e-8)
    assert np.abs(result.q_nominal - q_path).max() < 0.05
    asked = pose_matrix(poses)
    dp_filtered, dr_filtered = se3.pose_distance(actual.true_pose(result.q_command), asked)
    dp_plain, _ = se3.pose_distance(actual.true_pose(result.q_nominal), asked)
    assert dp_plain.max() > 1e-3  # the true robot misses the program by millimetres uncorrected …
    assert dp_filtered.max() < 0.05e-3 and dr_filtered.max() < 0.05e-3  # … and by micrometres filtered
    # the reported size is what the calibration predicts the filter removes
    np.testing.assert_allclose(result.position_error, dp_plain, rtol=0.1, atol=20e-6)
    assert "rows: joint correction" in result.summary()


def test_joint_programs_are_filtered_in_one_batch(calibrated):
    actual, robot = calibrated
    _, q_path = program_poses(robot, 20, seed=2)
    # the true robot carries the tool the calibration identified as its measurement tool: the working TCP
    result = filter_joints(robot, q_path, tcp=robot.measurement_tool)
    asked = robot.nominal.fk(q_path) @ robot.measurement_tool
    dp, _ = se3.pose_distance(actual.true_pose(result.q_command), asked)
    assert dp.max() < 0.05e-3
    np.testing.assert_array_equal(result.q_nominal, q_path)


def test_a_tcp_offset_is_taken_off_before_the_ik(calibrated):
    _, robot = calibrated
    poses, q_path = program_poses(robot, 3, seed=3)
    tcp = np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.3])
    at_tcp = pose_matrix(poses) @ pose_matrix(tcp)[0]
    tcp_poses = np.concatenate([at_tcp[:, :3, 3], se3.log_so3(at_tcp[:, :3, :3])], axis=1)
    result = filter_poses(robot, tcp_poses, seed=q_path[0], tcp=tcp)
    np.testing.assert_allclose(result.q_nominal, q_path, atol=1e-8)


def test_the_branch_of_the_seed_is_kept_and_a_jump_is_refused():
    nominal = load("ur10").model
    robot = CalibratedRobot(nominal, nominal)
    q_up = np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.4])
    T = nominal.fk(q_up)
    pose = np.concatenate([T[:3, 3], se3.log_so3(T[:3, :3])])[None]
    # seeded on the elbow-up side it finds the elbow-up solution
    np.testing.assert_allclose(nominal_ik(robot, pose_matrix(pose), q_up + 0.1), [q_up], atol=1e-8)
    # seeded with the elbow on the other side, the path would have to pass the stretched-elbow singularity
    q_down = q_up.copy()
    q_down[2] = -1.4
    with pytest.raises(ProgramError, match=r"row 1: .*(singular|branch)"):
        nominal_ik(robot, pose_matrix(pose), q_down)


def test_unreachable_and_out_of_range_rows_are_refused_by_row(calibrated):
    _, robot = calibrated
    poses, q_path = program_poses(robot, 3, seed=5)
    far = poses.copy()
    far[2, :3] = [3.0, 0.0, 0.5]  # 3 m away: beyond a UR10's reach
    with pytest.raises(
        ProgramError, match=r"row 3: unreachable: the pose is 3.041 m from the base, beyond the robot's reach of 1.9 m$"
    ):
        filter_poses(robot, far, seed=q_path[0])
    in_mm = poses.copy()
    in_mm[:, :3] *= 1000  # a program in millimetres read as metres: named as such, not as a branch change
    with pytest.raises(
        ProgramError, match=r"row 1: unreachable: .* \(millimetres read as metres\? pass --length-unit mm\)"
    ):
        filter_poses(robot, in_mm, seed=q_path[0])
    q = q_path.copy()
    q[1, 4] = 7.0
    with pytest.raises(
        ProgramError, match=r"row 2: joint 5 = 7 is outside the robot's joint limits \[-6.28319, 6.28319\]$"
    ):
        filter_joints(robot, q)  # one wild value in a program in radians: no hint about degrees
    narrow = dataclasses.replace(robot, joint_ranges=np.stack([q_path.min(0) - 0.3, q_path.max(0) + 0.3], axis=1))
    q[1, 4] = narrow.joint_ranges[4, 1] + 0.1  # inside the robot's limits, outside the data
    with pytest.raises(ProgramError, match=r"row 2: joint 5 = .* is outside the calibrated range"):
        filter_joints(narrow, q)


def test_program_csv_outputs_in_the_units_asked(calibrated):
    _, robot = calibrated
    _, q_path = program_poses(robot, 4, seed=6)
    result = filter_joints(robot, q_path)
    rows = joints_csv(result).splitlines()
    assert rows[0].startswith("row,q1,q2,q3,q4,q5,q6,nominal_q1") and len(rows) == 5
    np.testing.assert_array_equal([float(v) for v in rows[1].split(",")[1:7]], result.q_command[0])
    in_deg = joints_csv(result, angle_unit="deg").splitlines()
    assert in_deg[0] == rows[0]  # the same names: the output reads back as a joint program in its unit
    np.testing.assert_allclose([float(v) for v in in_deg[1].split(",")[1:13]],
                               np.degrees([*result.q_command[0], *result.q_nominal[0]]), rtol=1e-15)  # fmt: skip
    assert in_deg[1].split(",")[13:] == rows[1].split(",")[13:]  # the sizes keep the units their names say
    script = movej_program(result.q_command, a=0.5, v=0.2)
    urscript_subset.check(script)
    ns = urscript_subset.load(script)
    ns["labcal_filtered"]()
    moves = [m[1] for m in ns["stats"].messages if m[0] == "movej"]
    np.testing.assert_array_equal(moves, result.q_command)


def test_a_correction_larger_than_allowed_is_refused_by_row(calibrated):
    _, robot = calibrated
    _, q_path = program_poses(robot, 3, seed=7)
    dq = np.max(np.abs(filter_joints(robot, q_path).correction), axis=1)
    with pytest.raises(ProgramError, match=r"row 1: the calibrated solution moves a joint by"):
        filter_joints(robot, q_path, max_correction=0.5 * dq.min())


# ------------------------------------------------------------------------------------------------------------
# issue 24 item 4: units and singularities


def elbow_robot():
    """A local-POE calibration of a UR10 (frames off by ~0.5 mm / mrad) whose elbow singularity (q3 = 0) is not
    quite the nominal one's, so a row a few µrad from it has its calibrated solution on the other side."""
    from export_fixtures import hybrid

    return hybrid("ur10", features=None, seed=7)


@pytest.mark.parametrize("q3", [1e-5, -1e-5, -1e-3])
def test_a_near_singular_elbow_row_is_called_singular_not_a_branch_change(q3):
    robot = elbow_robot()
    q = np.array([[0.3, -1.2, 1.4, -1.6, -1.5, 0.4], [0.3, -1.2, q3, -1.6, -1.5, 0.4]])
    with pytest.raises(ProgramError, match=r"^row 2: singular: ") as e:
        filter_joints(robot, q)
    message = str(e.value)
    assert "branch (" not in message and "changes configuration branch" not in message
    assert f"q3 = {q3:.6g} is the joint that leaves it fastest" in message  # the elbow, named
    assert e.value.row == 2
    filter_joints(robot, q[:1])  # the well-conditioned row alone goes through


def test_a_near_singular_wrist_row_names_q5():
    robot = elbow_robot()
    q = np.array([[0.3, -1.2, 1.4, -1.6, 1e-5, 0.4]])
    with pytest.raises(ProgramError, match=r"^row 1: singular: .*q5 = 1e-05 is the joint that leaves it fastest"):
        filter_joints(robot, q)


def test_a_correction_that_does_not_reach_the_pose_is_refused():
    # Near the wrist singularity (condition about 2e3, under MAX_CONDITION) the calibrated robot reaches the row's
    # nominal pose only with q4 and q6 turned by ~0.4 rad; correct() (default damped budget, main 5770eeb) stops
    # millimetres away instead, which the filter wrote out. Either way this row is no correction: refused by row.
    robot = elbow_robot()
    q = np.array([[0.3, -1.2, 1.4, -1.6, 0.003, 0.4]])
    with pytest.raises(
        ProgramError,
        match=r"^row 1: the calibrated (robot does not reach the row's pose: .*q5 = 0.003|solution moves a joint by)",
    ):
        filter_joints(robot, q)


def test_rotation_vectors_in_degrees_are_refused_with_the_hint(calibrated):
    from labcal.export.program import check_rotation_vectors

    _, robot = calibrated
    poses, q_path = program_poses(robot, 4, seed=8)
    in_deg = poses.copy()
    in_deg[:, 3:] = np.degrees(in_deg[:, 3:])
    expected = (
        r"^row 1: rx, ry, rz = .* has the norm .* rad: a rotation vector's norm is its angle, at most 2π rad "
        r"\(degrees read as radians\? pass --angle-unit deg\); 3 more"
    )
    with pytest.raises(ProgramError, match=expected):
        filter_poses(robot, in_deg, seed=q_path[0])
    check_rotation_vectors(np.array([[0.5, 0, 0.5, 0.0, 0.0, 1.9 * np.pi]]))  # up to 2π: a rotation, kept continuous
    with pytest.raises(ProgramError, match=r"norm 400 deg: .* at most 360 deg$"):  # read in degrees: no hint
        check_rotation_vectors(np.array([[0.5, 0, 0.5, 0.0, 0.0, np.radians(400)]]), angle_unit="deg")


def test_joints_in_degrees_read_as_radians_get_the_hint(calibrated):
    _, robot = calibrated
    poses, q_path = program_poses(robot, 4, seed=9)
    hint = r"\(degrees read as radians\? pass --angle-unit deg\)$"
    with pytest.raises(ProgramError, match=r"^row \d: joint \d = .* is outside the robot's joint limits .*" + hint):
        filter_joints(robot, np.degrees(q_path))
    with pytest.raises(ProgramError, match=r"is outside the robot's joint limits [^(]*$"):  # read in deg: no hint
        filter_joints(robot, np.degrees(q_path), angle_unit="deg")
    with pytest.raises(ProgramError, match=r"^--seed-joints: joint \d = .* joint limits .*" + hint):
        filter_poses(robot, poses, seed=np.degrees(q_path[0]))  # a seed in degrees is not followed


def test_a_prismatic_joint_is_read_and_written_in_the_length_unit():
    from labcal.export.program import FilteredProgram, joint_factors

    np.testing.assert_array_equal(joint_factors(("revolute", "prismatic"), "mm", "deg"), [np.pi / 180, 1e-3])
    result = FilteredProgram(np.array([[0.5, 0.25]]), np.array([[0.5, 0.2505]]), np.array([1e-3]), np.array([2e-3]))
    row = joints_csv(result, angle_unit="deg", length_unit="mm", joint_types=("revolute", "prismatic")).splitlines()[1]
    np.testing.assert_allclose([float(v) for v in row.split(",")[1:5]], [np.degrees(0.5), 250.5, np.degrees(0.5), 250])
    assert [float(v) for v in row.split(",")[5:]] == pytest.approx([0.5, 1.0, 2.0])  # mrad, mm, mrad as named


def test_a_row_outside_the_validity_region_is_refused_by_its_row_number():
    """correct() refuses configurations away from the calibration's data; the filter names the program row."""
    from labcal.compensator import CalibratedRobot
    from labcal.compensator.validity import ValidityRegion
    from labcal.export.program import ProgramError, filter_joints
    from labcal.robots import load

    model = load("ur10").model
    q = np.random.default_rng(0).uniform(-0.3, 0.3, (40, 6)) + np.array([0, -1.2, 1.0, -1.4, -1.5, 0.2])
    robot = CalibratedRobot(
        nominal=model, model=model.perturbed(np.full((7, 6), 1e-4)), validity=ValidityRegion.from_configurations(q)
    )
    assert filter_joints(robot, q[:3]).q_command.shape == (3, 6)  # the data's own configurations are corrected
    far = q[3] + np.array([0.0, 0.0, 0.0, 1.5, 0.0, 0.0])  # inside the joint limits, far from every pose
    with pytest.raises(ProgramError, match="row 2: outside the calibration's validity region") as refused:
        filter_joints(robot, np.stack([q[4], far]))
    assert refused.value.row == 2
