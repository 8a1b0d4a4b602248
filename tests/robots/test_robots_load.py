"""Robot model files: built-ins, clear errors for every kind of bad field, POE form, model hashes."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from labcal.kinematics import se3
from labcal.kinematics.poe import PRISMATIC
from labcal.robots import BUILTINS, RobotFileError, builtin_path, load, model_hash, parse

GOOD_DH = """
name = "two"
kinematics = "{kind}"

[[joints]]
name = "J1"
type = "revolute"
a = 0.3
alpha = 0.5
d = 0.2
theta = 0.0
limits = [-1.0, 1.0]
mass = 2.0

[[joints]]
name = "J2"
type = "prismatic"
a = 0.1
alpha = 0.0
d = 0.0
theta = 0.1
limits = [0.0, 0.5]
mass = 1.0
com = [0.1, 0.2, 0.3]

[tool]
xyz = [0.0, 0.0, 0.1]
rpy = [0.0, 0.0, 0.0]
mass = 0.5
"""

# The UR10 DH file rewritten by hand in POE form: A_1 = I, A_{j+1} = Rz(θ_j) Tz(d_j) Tx(a_j) Rx(α_j) as xyz/rpy.
UR10_POE = """
name = "ur10-poe"
kinematics = "poe"

[[joints]]
xyz = [0.0, 0.0, 0.0]

[[joints]]
xyz = [0.0, 0.0, 0.1273]
rpy = [1.5707963267948966, 0.0, 0.0]

[[joints]]
xyz = [-0.612, 0.0, 0.0]

[[joints]]
xyz = [-0.5723, 0.0, 0.0]
axis = [0.0, 0.0, 2.0]   # normalised on load

[[joints]]
xyz = [0.0, 0.0, 0.163941]
rpy = [1.5707963267948966, 0.0, 0.0]

[[joints]]
xyz = [0.0, 0.0, 0.1157]
rpy = [-1.5707963267948966, 0.0, 0.0]

[tool]
xyz = [0.0, 0.0, 0.0922]
"""


def _write(tmp_path, text: str, name: str = "robot.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("robot", BUILTINS)
def test_every_builtin_loads(robot):
    spec = load(robot)
    data = tomllib.loads(builtin_path(robot).read_text())
    n = len(data["joints"])
    assert spec.name == robot == spec.model.name
    assert spec.model.n == n
    assert spec.masses.shape == (n + 1,) and spec.coms.shape == (n + 1, 3)
    assert np.all(spec.masses >= 0) and spec.masses[:n].sum() > 0
    assert spec.model.joint_names == tuple(j["name"] for j in data["joints"])
    np.testing.assert_array_equal(spec.model.limits, [j["limits"] for j in data["joints"]])
    assert spec.hash == model_hash(spec.model) and len(spec.hash) == 64
    assert spec.source.endswith(f"{robot}.toml")


def test_scara_has_a_prismatic_joint_and_four_axes():
    spec = load("scara4")
    assert spec.model.n == 4 and spec.model.joint_types[2] == PRISMATIC


def test_masses_and_default_centres_of_mass(tmp_path):
    spec = load(_write(tmp_path, GOOD_DH.format(kind="dh")))
    np.testing.assert_array_equal(spec.masses, [2.0, 1.0, 0.5])
    np.testing.assert_array_equal(spec.coms[1], [0.1, 0.2, 0.3])
    origins = spec.model.link_frames(np.zeros(2))[0, :, :3, 3]
    np.testing.assert_allclose(spec.coms[0], 0.5 * (origins[0] + origins[1]))  # link midpoint by default
    np.testing.assert_allclose(spec.coms[2], origins[2])  # payload at the tool frame
    assert spec.model.joint_types == ("revolute", "prismatic")


def test_dh_and_mdh_kinds_differ(tmp_path):
    dh, mdh = (
        load(_write(tmp_path, GOOD_DH.format(kind="dh"), "a.toml")),
        load(_write(tmp_path, GOOD_DH.format(kind="mdh"), "b.toml")),
    )
    assert dh.hash != mdh.hash
    assert not np.allclose(dh.model.fk(np.array([0.3, 0.1])), mdh.model.fk(np.array([0.3, 0.1])))


def test_poe_file_equivalent_to_the_ur10_dh_file(tmp_path):
    poe, dh = load(_write(tmp_path, UR10_POE)), load("ur10")
    assert poe.model.n == 6
    np.testing.assert_allclose(poe.model.twists[3], [0, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(poe.model.limits, [[-np.pi, np.pi]] * 6)  # defaults
    q = np.random.default_rng(0).uniform(-np.pi, np.pi, size=(50, 6))
    for A, B in zip(poe.model.fk(q), dh.model.fk(q), strict=True):
        assert np.max(np.abs(se3.log_se3(se3.inv(A) @ B))) < 1e-14


def _bad(field_edit: str) -> str:
    """GOOD_DH with one line replaced (old => new)."""
    old, new = field_edit.split(" => ")
    text = GOOD_DH.format(kind="dh")
    assert old in text, old
    return text.replace(old, new, 1)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ("a = 0.3 => ", r"joints\[1\]\.a is missing"),
        ('alpha = 0.5 => alpha = "half"', r"joints\[1\]\.alpha must be a finite number \(rad\), got 'half'"),
        ("alpha = 0.5 => alpha = true", r"joints\[1\]\.alpha must be a finite number"),
        ("alpha = 0.5 => alpha = nan", r"joints\[1\]\.alpha must be a finite number"),
        ("limits = [-1.0, 1.0] => limits = [1.0, -1.0]", r"joints\[1\]\.limits has lo 1.0 greater than hi -1.0"),
        ("limits = [-1.0, 1.0] => limits = [-1.0]", r"joints\[1\]\.limits must be \[lo, hi\]"),
        ('kinematics = "dh" => kinematics = "dhx"', r"kinematics must be one of 'dh', 'mdh', 'poe', got 'dhx' \(did"),
        ('type = "prismatic" => type = "helical"', r"joints\[2\]\.type must be one of 'revolute', 'prismatic', got"),
        ("com = [0.1, 0.2, 0.3] => com = [0.1, 0.2]", r"joints\[2\]\.com must be a list of 3 numbers"),
        ("mass = 1.0 => mass = -1.0", r"joints\[2\]\.mass must be >= 0, got -1.0"),
        ('name = "two" => name = ""', r"name must not be empty"),
        ("xyz = [0.0, 0.0, 0.1] => xyz = [0.0, 0.1]", r"tool\.xyz must be a list of 3 numbers"),
        ("mass = 1.0 => mass = true", r"joints\[2\]\.mass must be a finite number \(kg\), got True"),
        ("limits = [0.0, 0.5] => limits = [false, 0.5]", r"joints\[2\]\.limits must be \[lo, hi\] numbers"),
        ("limits = [0.0, 0.5] => limits = [-inf, 0.5]", r"joints\[2\]\.limits must be \[lo, hi\] numbers"),
        ("com = [0.1, 0.2, 0.3] => com = [0.1, 0.2, nan]", r"joints\[2\]\.com must be a list of 3 numbers"),
    ],
)
def test_bad_fields_raise_robot_file_errors_naming_the_field(tmp_path, edit, message):
    path = _write(tmp_path, _bad(edit))
    with pytest.raises(RobotFileError, match=message) as info:
        load(path)
    assert str(path) in str(info.value)


def test_bad_poe_fields(tmp_path):
    with pytest.raises(RobotFileError, match=r"joints\[1\]\.xyz is missing"):
        load(_write(tmp_path, UR10_POE.replace("xyz = [0.0, 0.0, 0.0]\n", "", 1)))
    with pytest.raises(RobotFileError, match=r"joints\[4\]\.axis must not be zero"):
        load(_write(tmp_path, UR10_POE.replace("axis = [0.0, 0.0, 2.0]", "axis = [0.0, 0.0, 0.0]")))


def test_missing_unreadable_and_empty_files(tmp_path):
    with pytest.raises(RobotFileError, match=r"neither a built-in .*ur10.* nor an existing file"):
        load("ur11")
    with pytest.raises(RobotFileError, match=r"not valid TOML"):
        load(_write(tmp_path, "name = ", "broken.toml"))
    with pytest.raises(RobotFileError, match=r"at least one \[\[joints\]\]"):
        parse({"name": "x", "kinematics": "dh", "joints": []})
    row = {"a": 0.0, "alpha": 0.0, "d": 0.0, "theta": 0.0}
    with pytest.raises(RobotFileError, match=r"tool must be a table, got 3"):
        parse({"name": "x", "kinematics": "dh", "joints": [row], "tool": 3})
    with pytest.raises(RobotFileError, match=r"joints\[2\] must be a table, got 3"):
        parse({"name": "x", "kinematics": "dh", "joints": [row, 3]})


def test_model_hash_is_stable_and_sensitive(tmp_path):
    text = builtin_path("ur10").read_text()
    a, b = load("ur10"), load(_write(tmp_path, text, "copy.toml"))
    assert a.hash == b.hash == model_hash(load("ur10").model)
    # reformatting (comments, whitespace, key order of the tool table) keeps the identity
    reformatted = "# a comment\n" + text.replace("d = 0.1273", "d   =   0.12730")
    assert load(_write(tmp_path, reformatted, "reformatted.toml")).hash == a.hash
    # a 1e-12 m change does not
    nudged = text.replace("d = 0.1273", f"d = {0.1273 + 1e-12!r}")
    assert nudged != text
    assert load(_write(tmp_path, nudged, "nudged.toml")).hash != a.hash
    # so do a changed limit, a renamed joint type order and a tiny frame perturbation
    assert model_hash(a.model.replace(limits=a.model.limits * (1 + 1e-15))) != a.hash
    dz = np.zeros((7, 6))
    dz[6, 0] = 1e-12
    assert model_hash(a.model.perturbed(dz)) != a.hash
