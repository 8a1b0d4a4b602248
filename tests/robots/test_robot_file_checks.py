"""Robot files: the [joint_map] table (parsing, errors naming the field, hash), and numbers that look like degrees
or millimetres refused unless the file says units_checked = true."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.robots import BUILTINS, EXAMPLES, RobotFileError, load, loads, model_hash

TWO = """
name = "two"
kinematics = "dh"
{top}
[[joints]]
type = "revolute"
a = {a}
alpha = {alpha}
d = 0.2
theta = 0.0
limits = {limits}

[[joints]]
type = "revolute"
a = 0.3
alpha = 0.0
d = 0.0
theta = 0.0
limits = [-2.0, 2.0]

[tool]
xyz = {tool_xyz}
{extra}
"""


def two(top="", a=0.4, alpha=0.5, limits="[-3.0, 3.0]", tool_xyz="[0.0, 0.0, 0.1]", extra=""):
    return TWO.format(top=top, a=a, alpha=alpha, limits=limits, tool_xyz=tool_xyz, extra=extra)


# -- joint maps --------------------------------------------------------------------------------------------------


def test_no_joint_map_is_the_identity_and_keeps_the_model_hash():
    spec = loads(two())
    assert spec.joint_map is None and spec.joints.is_identity
    assert spec.hash == model_hash(spec.model)
    identity = loads(two(extra="[joint_map]\nsigns = [1, 1]\noffsets = [0.0, 0.0]"))
    assert identity.hash == spec.hash  # an identity map declares nothing new


def test_matrix_and_offsets_are_parsed_and_change_the_hash():
    text = two(extra="[joint_map]\nmatrix = [[1, 0], [1, 1]]\noffsets = [0.0, 0.25]")
    spec = loads(text)
    np.testing.assert_array_equal(spec.joints.matrix, [[1.0, 0.0], [1.0, 1.0]])
    np.testing.assert_array_equal(spec.joints.offsets, [0.0, 0.25])
    np.testing.assert_allclose(spec.joints.to_model(np.array([0.1, 0.2])), [0.1, 0.55])
    plain = loads(two())
    assert spec.hash != plain.hash and spec.hash == model_hash(spec.model, spec.joint_map)
    other = loads(two(extra="[joint_map]\nmatrix = [[1, 0], [1, 1]]\noffsets = [0.0, 0.5]"))
    assert other.hash != spec.hash
    # the stored record carries the map in its text: reading it back gives the same robot and hash
    again = loads(spec.record()["text"], spec.record()["format"])
    assert again.hash == spec.hash
    np.testing.assert_array_equal(again.joints.matrix, spec.joints.matrix)


def test_signs_form_is_the_diagonal_matrix():
    spec = loads(two(extra="[joint_map]\nsigns = [1, -1]"))
    np.testing.assert_array_equal(spec.joints.matrix, np.diag([1.0, -1.0]))
    np.testing.assert_array_equal(spec.joints.offsets, [0.0, 0.0])
    same = loads(two(extra="[joint_map]\nmatrix = [[1, 0], [0, -1]]"))
    assert same.hash == spec.hash  # one canonical form whatever the spelling


@pytest.mark.parametrize(
    "table,match",
    [
        ("matrix = [[1, 0], [0, 1], [0, 0]]", r"joint_map\.matrix must be 2 rows of 2 numbers"),
        ("matrix = [[1, 0], [0, 'x']]", r"joint_map\.matrix must be"),
        ("matrix = [[1, 1], [1, 1]]", r"joint_map\.matrix is singular"),
        ("signs = [1, 2]", r"joint_map\.signs must be 2 values of 1 or -1"),
        ("matrix = [[1, 0], [0, 1]]\nsigns = [1, 1]", "exactly one of 'matrix'"),
        ("offsets = [0.0, 0.0]", "exactly one of 'matrix'"),
        ("signs = [1, 1]\noffsets = [0.0]", r"joint_map\.offsets must be a list of 2 numbers \(rad.*got \[0.0\]"),
        ("signs = [1, 1]\noffset = [0.0, 0.0]", r"joint_map: unknown key 'offset' \(did you mean 'offsets'\?\)"),
        ("signs = [1, 1]\noffsets = [0.0, 90.0]", r"joint_map\.offsets\[2\] = 90 looks like degrees"),
    ],
)
def test_bad_joint_maps_name_the_field(table, match):
    with pytest.raises(RobotFileError, match=match):
        loads(two(extra="[joint_map]\n" + table), source="arm.toml")


def test_joint_map_must_be_a_table():
    with pytest.raises(RobotFileError, match=r"joint_map must be a table, got 3"):
        loads(two(top="joint_map = 3"))


def test_the_coupled_elbow_example_is_shipped_and_maps_the_elbow():
    assert "coupled-elbow-6r" in EXAMPLES
    spec = load("coupled-elbow-6r")
    fanuc = load("fanuc-m1000ia")
    np.testing.assert_array_equal(spec.model.frames, fanuc.model.frames)  # same geometry, only the map is new
    assert not spec.joints.is_identity and spec.hash != fanuc.hash
    q_ctrl = np.array([0.1, 0.3, -0.2, 0.4, 0.5, 0.6])
    q = spec.joints.to_model(q_ctrl)
    np.testing.assert_allclose(q[[1, 2]], [-0.3, 0.1])  # q2 = -J2, q3 = J2 + J3
    np.testing.assert_allclose(q[1] + q[2], q_ctrl[2])  # the forearm's attitude follows J3 alone
    np.testing.assert_allclose(spec.joints.to_controller(q), q_ctrl, atol=1e-15)


# -- units -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"alpha": 90}, r"joints\[1\]\.alpha = 90 looks like degrees; robot files are in radians"),
        ({"alpha": -180.0}, r"joints\[1\]\.alpha = -180 looks like degrees"),
        ({"limits": "[-170, 170]"}, r"joints\[1\]\.limits\[1\] = -170 looks like degrees"),
        ({"a": 612}, r"joints\[1\]\.a = 612 looks like millimetres; robot files are in metres"),
        ({"tool_xyz": "[0.0, 0.0, 150.0]"}, r"tool\.xyz\[3\] = 150 looks like millimetres"),
    ],
)
def test_degrees_and_millimetres_are_refused_with_the_fix(kwargs, match):
    with pytest.raises(RobotFileError, match=match) as err:
        loads(two(**kwargs), source="arm.toml")
    assert "arm.toml" in str(err.value) and "units_checked = true" in str(err.value)
    # the explicit key is the only way through, and it changes nothing else
    spec = loads(two(top="units_checked = true", **kwargs))
    assert spec.model.n == 2


def test_poe_rpy_and_xyz_and_prismatic_limits_are_checked():
    poe = """
name = "p"
kinematics = "poe"
[[joints]]
xyz = [0.0, 0.0, {z}]
rpy = [{r}, 0.0, 0.0]
[[joints]]
type = "prismatic"
xyz = [0.0, 0.0, 0.1]
axis = [0, 0, 1]
limits = [0.0, {lim}]
"""
    loads(poe.format(z=0.5, r=1.57, lim=0.2))
    with pytest.raises(RobotFileError, match=r"joints\[1\]\.xyz\[3\] = 500 looks like millimetres"):
        loads(poe.format(z=500, r=1.57, lim=0.2))
    with pytest.raises(RobotFileError, match=r"joints\[1\]\.rpy\[1\] = 90 looks like degrees"):
        loads(poe.format(z=0.5, r=90, lim=0.2))
    with pytest.raises(RobotFileError, match=r"joints\[2\]\.limits\[2\] = 200 looks like millimetres"):
        loads(poe.format(z=0.5, r=1.57, lim=200))


def test_plausible_values_pass_and_every_shipped_file_is_in_si_units():
    loads(two(alpha=6.2, limits="[-12.0, 12.0]", a=3.0))  # a two-turn wrist and a 3 m link are real arms
    for name in (*BUILTINS, *EXAMPLES):
        load(name)


def test_units_checked_must_be_a_boolean():
    with pytest.raises(RobotFileError, match="units_checked must be true or false, got 'yes'"):
        loads(two(top='units_checked = "yes"'))


# -- the schema: unknown keys, shapes and the keys a kinematics takes ------------------------------------------


@pytest.mark.parametrize(
    "extra,match",
    [
        ("[tool]\nxyz = [0.0, 0.0, 0.1]\nrpz = [0.0, 0.0, 0.0]", r"tool: unknown key 'rpz' \(did you mean 'rpy'\?\)"),
        ("kinematic = 'dh'", r"robot file: unknown key 'kinematic' \(did you mean 'kinematics'\?\)"),
    ],
)
def test_unknown_keys_are_refused_with_a_did_you_mean(extra, match):
    text = two().replace("[tool]\nxyz = [0.0, 0.0, 0.1]\n", "") + "\n" + extra if "[tool]" in extra else two(top=extra)
    with pytest.raises(RobotFileError, match=match) as err:
        loads(text, source="arm.toml")
    assert str(err.value).startswith("arm.toml: ")


def test_a_joint_key_of_the_other_kinematics_is_refused():
    # a dh file with a poe key is almost surely a mixed-up file: the key would be ignored without a word
    limits = "limits = [-3.0, 3.0]"
    text = two().replace(f"theta = 0.0\n{limits}", f"theta = 0.0\nxyz = [0.0, 0.0, 0.1]\n{limits}")
    with pytest.raises(RobotFileError, match=r"joints\[1\]: unknown key 'xyz'; allowed: a, alpha, com, d, effort"):
        loads(text, source="arm.toml")


def test_every_builtin_and_example_follows_the_schema():
    for name in BUILTINS + EXAMPLES:
        assert load(name).model.n >= 4


def test_joint_velocity_and_effort_are_accepted_checked_and_not_part_of_the_model():
    plain = loads(two())
    text = two().replace("limits = [-3.0, 3.0]", "limits = [-3.0, 3.0]\nvelocity = 2.0\neffort = 150.0")
    assert loads(text).hash == plain.hash
    with pytest.raises(RobotFileError, match=r"joints\[1\]\.effort must be > 0, got -1.0"):
        loads(text.replace("effort = 150.0", "effort = -1.0"))
    import tomllib

    ur10 = tomllib.loads(load("ur10").text)
    assert [j["effort"] for j in ur10["joints"]] == [330.0, 330.0, 150.0, 56.0, 56.0, 56.0]
