"""Complete calibrated URDF: written by an XML writer (escaped), identified FK reproduced, limits from the robot
file, effort/velocity given or refused, inertials where masses are known, UR link names, and a learned term that
would be dropped refused with its size (or noted with --geometry-only)."""

from __future__ import annotations

import dataclasses
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from export_fixtures import hybrid, make_network, sample

from labcal.compensator import CalibratedRobot
from labcal.export.learned import dropped_learned_term
from labcal.export.urdf import urdf_text
from labcal.kinematics import se3
from labcal.kinematics.conversions import from_urdf
from labcal.robots import load

DYN = {"velocity": [2.0, 2.0, 3.0, 3.0, 3.0, 3.0], "effort": [330.0, 330.0, 150.0, 56.0, 56.0, 56.0]}


def dyn(n: int) -> dict:
    return {"velocity": [1.5] * n, "effort": [40.0] * n}


@pytest.mark.parametrize("name", ["ur10", "scara4", "fanuc-m1000ia"])
def test_round_trip_reproduces_identified_fk_and_limits(name):
    robot = hybrid(name, features=None, odd_twists=True, seed=5)
    text = urdf_text(robot, {"session": "S@v001"}, **dyn(robot.n))
    back = from_urdf(text)
    q = sample(robot, 50, seed=11, max_cond=1e9)
    np.testing.assert_allclose(back.fk(q), robot.model.fk(q), atol=1e-12, rtol=0)
    np.testing.assert_array_equal(back.limits, robot.nominal.limits)
    assert back.joint_names == robot.model.joint_names


def test_names_and_comments_are_escaped_by_the_writer():
    nominal = load("ur10").model.replace(name='ur10 <"lab" & cell>')
    robot = CalibratedRobot(nominal, nominal.perturbed(np.full((7, 6), 1e-4)), method="local-poe")
    text = urdf_text(robot, {"session": "a--b <x>", "note": "R&D"}, **DYN)
    root = ET.fromstring(text)  # well-formed despite <, &, " and -- in the names and provenance
    assert root.get("name") == 'ur10 <"lab" & cell>_calibrated'
    assert "--" not in text.split("<!--", 1)[1].split("-->", 1)[0]


def test_effort_and_velocity_are_written_or_the_export_refused():
    robot = hybrid("ur10", features=None, seed=1)
    root = ET.fromstring(urdf_text(robot, **DYN))
    limits = [j.find("limit") for j in root.findall("joint") if j.get("type") == "revolute"]
    assert [float(e.get("effort")) for e in limits] == DYN["effort"]
    assert [float(e.get("velocity")) for e in limits] == DYN["velocity"]
    with pytest.raises(ValueError, match=r"no joint velocity for joint\(s\) 1, 2, 3, 4, 5, 6"):
        urdf_text(robot, effort=DYN["effort"])
    with pytest.raises(ValueError, match=r"no joint effort for joint\(s\) 3"):
        urdf_text(robot, velocity=DYN["velocity"], effort=[1.0, 1.0, None, 1.0, 1.0, 1.0])
    zero = urdf_text(robot, unknown_dynamics="zero")
    assert "effort/velocity UNKNOWN" in zero


def test_inertials_where_masses_are_known():
    spec = load("ur10")
    robot = hybrid("ur10", features=None, seed=2)
    root = ET.fromstring(urdf_text(robot, masses=spec.masses, coms=spec.coms, **DYN))
    links = {link.get("name"): link for link in root.findall("link")}
    masses = [float(links[f"link_{j + 1}"].find("inertial/mass").get("value")) for j in range(6)]
    assert masses == list(spec.masses[:6])
    assert links["tool0"].find("inertial") is None  # ur10.toml's tool payload is 0 kg
    # the centre of mass is written in its link's frame: back in the base frame at q = 0 it is the file's
    model = from_urdf(ET.tostring(root, encoding="unicode"))
    frames0 = model.link_frames(np.zeros(6))[0]
    for j in range(6):
        com = np.array([float(v) for v in links[f"link_{j + 1}"].find("inertial/origin").get("xyz").split()])
        np.testing.assert_allclose((frames0[j] @ np.append(com, 1.0))[:3], spec.coms[j], atol=1e-12)
    assert root.find("link[@name='base_link']/inertial") is None


def test_ur_link_names_follow_ur_description():
    robot = hybrid("ur10", features=None, odd_twists=True, seed=3)
    text = urdf_text(robot, ur_names=True, **DYN)
    root = ET.fromstring(text)
    names = {link.get("name") for link in root.findall("link")}
    assert {"base_link", "base_link_inertia", "shoulder_link", "wrist_3_link", "flange", "tool0", "base"} <= names
    joints = {j.get("name"): j for j in root.findall("joint")}
    assert joints["shoulder_pan_joint"].find("parent").get("link") == "base_link_inertia"
    # base_link is the controller's base turned by π about z; base_link_inertia (and base) is the base itself
    back = from_urdf(text, tip_link="tool0")
    q = sample(robot, 20, seed=4, max_cond=1e9)
    turn = se3.pose([0, 0, 0], [0, 0, np.pi])
    np.testing.assert_allclose(back.fk(q), turn @ robot.model.fk(q), atol=1e-12)
    # ur_description's fixed flange → tool0 turn, (π/2, 0, π/2)
    rpy = np.array([float(v) for v in joints["flange-tool0"].find("origin").get("rpy").split()])
    np.testing.assert_allclose(se3.rpy_to_matrix(rpy), se3.rpy_to_matrix([np.pi / 2, 0, np.pi / 2]), atol=1e-15)
    with pytest.raises(ValueError, match="Universal Robots"):
        urdf_text(hybrid("fanuc-m1000ia", features=None), ur_names=True, **DYN)


def test_a_learned_term_is_refused_with_its_size_or_noted():
    robot = hybrid("ur10", seed=5)
    dropped = dropped_learned_term(robot)
    with pytest.raises(ValueError, match=rf"up to {1e3 * dropped.position_max:.3f} mm") as info:
        urdf_text(robot, **DYN)
    assert "--geometry-only" in str(info.value)
    text = urdf_text(robot, geometry_only=True, **DYN)
    assert f"moves the tool by {1e3 * dropped.position_mean:.3f} mm on average" in text
    # an ann fit: identified frames = nominal, everything is in the network; geometry-only is the nominal robot
    nominal = load("ur10").model
    ann = CalibratedRobot(nominal, nominal, make_network(nominal, ("q", "sincos")), method="ann")
    assert dropped_learned_term(ann).position_max > 1e-5
    with pytest.raises(ValueError, match="ann calibration"):
        urdf_text(ann, **DYN)


def test_dropped_size_is_what_the_learned_term_moves():
    nominal = load("ur10").model
    nets = [dataclasses.replace(make_network(nominal, ("sincos",), out=s), out_mean=np.zeros(6)) for s in (1e-5, 1e-3)]
    small, large = (CalibratedRobot(nominal, nominal, net, method="ann") for net in nets)
    a, b = dropped_learned_term(small), dropped_learned_term(large)
    assert 50 < b.position_mean / a.position_mean < 200  # linear in the output scale (100×), to first order
    assert dropped_learned_term(CalibratedRobot(nominal, nominal)) is None


def test_urdf_refuses_a_screw_joint_and_a_joint_map():
    with pytest.raises(ValueError, match="screw"):
        urdf_text(hybrid("ur10", odd_twists=True, pitch=True), **DYN)
    spec = load("coupled-elbow-6r")
    robot = CalibratedRobot(spec.model, spec.model, joint_map=spec.joint_map)
    with pytest.raises(ValueError, match="joint map"):
        urdf_text(robot, **DYN)


def test_urdf_is_deterministic():
    robot = hybrid("ur10", seed=4)
    assert urdf_text(robot, {"fit": "x"}, geometry_only=True, **DYN) == urdf_text(
        robot, {"fit": "x"}, geometry_only=True, **DYN
    )
