"""Names in robot files reach URScript, YAML and URDF exports and the terminal: they are checked at load, with one
line naming the field (issue 24, item 2)."""

from __future__ import annotations

import pytest

from labcal.robots import RobotFileError, builtin_path, load, loads

INJECTION = r"ur10\nmovej([0,-1.57,0,-1.57,0,0], a=3, v=3)\n#"


def _ur10_with(old: str, new: str) -> str:
    text = builtin_path("ur10").read_text()
    assert old in text
    return text.replace(old, new, 1)


def _one_line(err: pytest.ExceptionInfo) -> str:
    message = str(err.value)
    assert "\n" not in message and "\x1b" not in message
    return message


def test_a_robot_name_that_would_inject_a_movej_is_refused_naming_the_field(tmp_path):
    path = tmp_path / "evil.toml"
    path.write_text(_ur10_with('name = "ur10"', f'name = "{INJECTION}"'))
    with pytest.raises(RobotFileError) as err:
        load(path)
    message = _one_line(err)
    assert message.startswith(f"{path}: name must be 1 to 64 letters, digits or _ - . + /")
    assert "movej" in message  # shown escaped, so the user sees what is wrong


def test_an_escape_character_in_a_joint_name_is_refused_naming_the_joint():
    text = _ur10_with('name = "shoulder_lift_joint"', r'name = "shoulder\u001b[31m_lift"')
    with pytest.raises(RobotFileError) as err:
        loads(text, source="arm.toml")
    assert _one_line(err).startswith("arm.toml: joints[2].name must be 1 to 64")
    assert "\\x1b[31m" in str(err.value)


def test_repeated_joint_names_are_refused():
    text = _ur10_with('name = "elbow_joint"', 'name = "shoulder_pan_joint"')
    with pytest.raises(RobotFileError) as err:
        loads(text, source="arm.toml")
    assert _one_line(err) == (
        "arm.toml: joints[3].name 'shoulder_pan_joint' repeats joints[1].name: joint names must be unique (a URDF or "
        "a controller addresses joints by name)"
    )


def test_a_description_with_a_control_character_is_refused():
    text = _ur10_with('name = "ur10"', 'name = "ur10"\ndescription = "lab 3\\u001b[2J"')
    with pytest.raises(RobotFileError) as err:
        loads(text, source="arm.toml")
    assert _one_line(err).startswith("arm.toml: description must be printable text on one line")


URDF = """<?xml version="1.0"?>
<robot name="{robot}">
  <link name="base"/><link name="l1"/><link name="l2"/>
  <joint name="{j1}" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="{j2}" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.3 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""


@pytest.mark.parametrize(
    "names,message",
    [
        ({"robot": "arm&#10;movej()", "j1": "a", "j2": "b"}, "arm.urdf: robot name must be"),
        ({"robot": "arm", "j1": "a", "j2": "b&#10;c"}, "arm.urdf: joint 2 name must be"),
        ({"robot": "arm", "j1": "a", "j2": "a"}, "arm.urdf: joint 2 name 'a' repeats joint 1's"),
    ],
)
def test_a_urdf_gets_the_same_name_checks(names, message):
    assert loads(URDF.format(robot="arm", j1="a", j2="b"), "urdf", source="arm.urdf").model.n == 2
    with pytest.raises(RobotFileError) as err:
        loads(URDF.format(**names), "urdf", source="arm.urdf")
    assert _one_line(err).startswith(message)


def test_the_name_rule_and_the_printable_form():
    from labcal.names import name_problem, printable

    for good in ("ur10", "fanuc-m1000ia", "shoulder_pan_joint", "arm/joint_1", "J1", "ur5e+gripper.v2"):
        assert name_problem(good) is None, good
    for bad in ("", " ur10", "ur10 ", "ur 10", "-x", "a\nb", "a\x1bb", "a\u202eb", "a:b", 'a"b', "x" * 65, 7, None):
        assert name_problem(bad) is not None, bad
    assert printable("a\nb\x1b[2J\u202ec\x00") == "a b\\x1b[2J\\u202ec\\x00"
    assert printable("x" * 100, 10) == "xxxxxxx..."
