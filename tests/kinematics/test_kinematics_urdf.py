"""URDF import/export: a hand-written UR5e URDF against the DH model, exact round trips, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from kin_testutil import assert_poses_close, rot_z, shift, to_urdf

from labcal.kinematics import se3
from labcal.kinematics.conversions import from_urdf
from labcal.kinematics.poe import PRISMATIC, REVOLUTE, LocalPOEModel
from labcal.robots import BUILTINS, load

UR5E_URDF = Path(__file__).parent / "data" / "ur5e.urdf"


def test_hand_written_ur5e_urdf_equals_the_dh_model_up_to_base_and_tool():
    urdf = from_urdf(UR5E_URDF.read_text(), tip_link="tool0")
    dh = load("ur5e").model
    assert urdf.n == 6 and urdf.name == "ur5e"
    assert urdf.joint_names == dh.joint_names
    assert urdf.joint_types == (REVOLUTE,) * 6
    np.testing.assert_array_equal(urdf.limits[2], [-np.pi, np.pi])  # read from <limit>, not defaulted
    # ROS's base_link is the DH base turned by π about z; tool0 is the DH flange frame.
    X = rot_z(np.pi)
    Y = se3.inv(X @ dh.fk(np.zeros(6))) @ urdf.fk(np.zeros(6))
    assert_poses_close(Y, np.eye(4), atol=1e-15)
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, size=(100, 6))
    for A, B in zip(X @ dh.fk(q) @ Y, urdf.fk(q), strict=True):
        assert_poses_close(A, B, atol=1e-14)
    # the other branch leads to the controller's base frame: only fixed joints, so no robot
    with pytest.raises(ValueError, match="no movable joints"):
        from_urdf(UR5E_URDF.read_text(), tip_link="base")


def test_branching_urdf_needs_a_tip_link():
    with pytest.raises(ValueError, match=r"branches at link 'base_link'.*tip_link"):
        from_urdf(UR5E_URDF.read_text())
    with pytest.raises(ValueError, match=r"tip link 'nowhere'"):
        from_urdf(UR5E_URDF.read_text(), tip_link="nowhere")


def test_tip_link_in_the_middle_of_the_chain():
    part = from_urdf(UR5E_URDF.read_text(), tip_link="forearm_link")
    full = from_urdf(UR5E_URDF.read_text(), tip_link="tool0")
    assert part.n == 3
    q = np.array([0.1, 0.2, 0.3])
    # forearm_link is the frame of the elbow joint after the elbow has moved
    elbow = full.link_frames(np.r_[q, 0, 0, 0])[0, 2]
    np.testing.assert_allclose(part.fk(q), elbow @ rot_z(q[2]), atol=1e-15)


@pytest.mark.parametrize("robot", BUILTINS)
def test_to_urdf_from_urdf_round_trip_is_exact(robot):
    model = load(robot).model
    back = from_urdf(to_urdf(model, comment="round -- trip"))
    assert back.name == model.name
    assert back.joint_types == model.joint_types
    assert back.joint_names == model.joint_names
    np.testing.assert_allclose(back.frames, model.frames, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(back.twists, model.twists)
    np.testing.assert_array_equal(back.limits, model.limits)


def test_round_trip_of_a_perturbed_general_model_including_gimbal_lock():
    rng = np.random.default_rng(1)
    frames = se3.exp_se3(rng.normal(size=(5, 6)))
    frames[1, :3, :3] = se3.rpy_to_matrix([0.3, np.pi / 2, -1.0])  # pitch exactly at the lock
    frames[2, :3, :3] = se3.rpy_to_matrix([0.3, np.pi / 2 - 1e-7, -1.0])  # next to it
    axis = np.array([0.6, 0.0, 0.8])
    model = LocalPOEModel.from_frames(
        frames,
        (REVOLUTE, PRISMATIC, REVOLUTE, REVOLUTE),
        [[0, 0, 0, *axis], [*axis, 0, 0, 0], [0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, -1]],
        limits=[[-1, 2], [0, 0.3], [-3, 3], [-1, 1]],
    )
    back = from_urdf(to_urdf(model, robot_name="general"))
    assert back.name == "general"
    np.testing.assert_allclose(back.frames, model.frames, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.twists, model.twists, rtol=0, atol=1e-15)


def _joint(name, kind, parent, child, xyz="0 0 0", rpy="0 0 0", axis=None, limit=None) -> str:
    text = f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
    text += f'<origin xyz="{xyz}" rpy="{rpy}"/>'
    if axis is not None:
        text += f'<axis xyz="{axis}"/>'
    if limit is not None:
        text += f'<limit lower="{limit[0]}" upper="{limit[1]}" effort="1" velocity="1"/>'
    return text + "</joint>"


def _robot(*joints: str) -> str:
    return '<?xml version="1.0"?><robot name="t">' + "".join(joints) + "</robot>"


def test_non_z_axes_and_a_fixed_joint_in_the_middle():
    text = _robot(
        _joint("j1", "revolute", "a", "b", xyz="0 0 0.3", axis="1 0 0", limit=(-1, 1)),
        _joint("mid", "fixed", "b", "c", xyz="0.2 0 0", rpy="0 0.5 0"),
        _joint("j2", "continuous", "c", "d", xyz="0 0.1 0", rpy="0.1 0 0", axis="0 3 4"),  # not unit: normalised
        _joint("j3", "prismatic", "d", "e", xyz="0 0 0.05", axis="0 -1 0", limit=(0, 0.2)),
        _joint("tcp", "fixed", "e", "f", xyz="0 0 0.1"),
    )
    model = from_urdf(text)
    assert model.joint_types == (REVOLUTE, REVOLUTE, PRISMATIC)
    assert model.joint_names == ("j1", "j2", "j3")
    np.testing.assert_array_equal(model.limits, [[-1, 1], [-np.pi, np.pi], [0, 0.2]])
    np.testing.assert_allclose(model.twists[1], [0, 0, 0, 0, 0.6, 0.8], atol=1e-16)

    def rot(axis, angle):
        axis = np.asarray(axis, float) / np.linalg.norm(axis)
        return se3.pose(np.zeros(3)) @ scipy.linalg.block_diag(scipy.linalg.expm(se3.skew(axis) * angle), np.eye(1))

    for q in np.random.default_rng(2).uniform(-1, 1, size=(10, 3)):
        # the URDF semantics written out: parent→joint origin, then motion about/along the axis in the joint frame
        ref = (
            shift(z=0.3)
            @ rot([1, 0, 0], q[0])
            @ shift(0.2)
            @ se3.pose([0, 0, 0], [0, 0.5, 0])
            @ se3.pose([0, 0.1, 0], [0.1, 0, 0])
            @ rot([0, 3, 4], q[1])
            @ shift(z=0.05)
            @ shift(y=-q[2])
            @ shift(z=0.1)
        )
        assert_poses_close(model.fk(q), ref, atol=1e-14)


def test_default_urdf_axis_is_x():
    model = from_urdf(_robot(_joint("j", "revolute", "a", "b")))
    np.testing.assert_array_equal(model.twists[0], [0, 0, 0, 1, 0, 0])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("<robot", r"not valid XML"),
        ('<model name="x"/>', r"root element must be <robot>"),
        (_robot('<joint name="j" type="revolute"><child link="b"/></joint>'), r"needs a name, a <parent link>"),
        (
            _robot(_joint("j1", "revolute", "a", "b"), _joint("j2", "revolute", "x", "c")),
            r"exactly one root link",
        ),
        (_robot(_joint("j", "revolute", "a", "b", xyz="0 zero 0")), r"joint j origin xyz: not a list of numbers"),
        (_robot(_joint("j", "revolute", "a", "b", rpy="0 0")), r"joint j origin rpy: expected 3 numbers"),
        (_robot(_joint("j", "revolute", "a", "b", axis="0 0 0")), r"joint j: zero axis"),
        (_robot(_joint("j", "floating", "a", "b")), r"joint j: unsupported URDF joint type 'floating'"),
        (_robot(_joint("j", "fixed", "a", "b")), r"no movable joints"),
        (_robot(_joint("j1", "revolute", "a", "b"), _joint("j2", "revolute", "b", "a")), r"exactly one root"),
    ],
)
def test_bad_urdfs_raise_clear_errors(text, message):
    with pytest.raises(ValueError, match=message):
        from_urdf(text)


def test_robots_load_reads_urdf_files(tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_text(to_urdf(load("ur10").model))
    spec = load(path)
    assert spec.name == "ur10"
    np.testing.assert_allclose(spec.model.frames, load("ur10").model.frames, atol=1e-12)


def test_to_urdf_escapes_names_and_comments():
    import xml.etree.ElementTree as ET

    model = load("ur10").model
    text = to_urdf(model, robot_name='arm "A" & <B>', comment="fit -- 3 < 4 & done")
    root = ET.fromstring(text.split("\n", 1)[1])
    assert root.get("name") == 'arm "A" & <B>'
    back = from_urdf(text)
    np.testing.assert_array_equal(back.frames, from_urdf(to_urdf(model)).frames)


def test_a_tip_on_a_cycle_of_links_is_not_found_instead_of_hanging():
    cycle = (_joint("j1", "revolute", "a", "b"), _joint("j2", "revolute", "c", "d"), _joint("j3", "revolute", "d", "c"))
    with pytest.raises(ValueError, match=r"tip link 'c' not found"):
        from_urdf(_robot(*cycle), tip_link="c")
