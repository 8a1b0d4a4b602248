"""`labcal export` for the deployment formats, through the real app: ur-kinematics, urdf (UR names, the learned
term refused with its size or left out with --geometry-only), and the URScript program, on stored sim fits."""

from __future__ import annotations

import sys
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "cli"))

from cli_testutil import TARGETS, invoke, last_line
from test_ur_kinematics import parse_yaml, rotation_vector_pose, yaml_fk

import urscript_subset
from labcal.compensator import Compensator
from labcal.kinematics import se3
from labcal.robots import load


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    """A 60-pose sim session of the UR10 with a local-poe and a hybrid fit."""
    root = tmp_path_factory.mktemp("export-cli")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"
    r = invoke(
        "session", "new", "--robot", "ur10", "--robot-driver", "sim", "--tracker-driver", "sim",
        "--targets", root / "targets.toml", "--poses", 60, "--seed", 3, store=store,
    )  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = last_line(r)
    out = {"root": root, "store": store, "ref": ref}
    for method in ("local-poe", "hybrid"):
        f = invoke("fit", ref, "--method", method, "--seed", 1, store=store)
        assert f.exit_code == 0, f.stdout + f.stderr
        out[method] = last_line(f)
    return out


def export(fits, method, fmt, name, *extra):
    out = fits["root"] / name
    r = invoke("export", fits["ref"], "--fit", fits[method], "--format", fmt, "--out", out, "--force", *extra,
               store=fits["store"])  # fmt: skip
    return r, out


def test_ur_kinematics_of_a_local_poe_fit_reproduces_the_compensator(fits):
    r, out = export(fits, "local-poe", "ur-kinematics", "calib.yaml")
    assert r.exit_code == 0, r.stderr
    assert last_line(r) == str(out)
    _, comp_path = export(fits, "local-poe", "json", "calib.json")
    comp = Compensator.load(comp_path)
    entries, _, tcp = parse_yaml(out.read_text())
    q = np.asarray(comp.robot.joint_ranges).mean(axis=1) + 0.1
    err = se3.log_se3(se3.inv(yaml_fk(entries, q) @ rotation_vector_pose(tcp)) @ comp.predict_pose(q))
    assert np.max(np.abs(err)) < 1e-12


def test_urdf_of_a_hybrid_fit_is_refused_with_the_size_or_left_out_explicitly(fits):
    r, out = export(fits, "hybrid", "urdf", "hybrid.urdf")
    assert r.exit_code != 0
    assert "learned joint-motion-error term moves the tool by" in r.stderr and "--geometry-only" in r.stderr
    assert not out.exists()
    r, out = export(fits, "hybrid", "urdf", "hybrid.urdf", "--geometry-only", "--ur-link-names")
    assert r.exit_code == 0, r.stderr
    assert "--geometry-only" in r.stderr and "leaves out the learned term" in r.stderr
    root = ET.fromstring(out.read_text())
    assert root.find("link[@name='base_link_inertia']") is not None
    assert "NOT INCLUDED (geometry only)" in out.read_text()
    r, _ = export(fits, "hybrid", "ur-kinematics", "hybrid.yaml")
    assert r.exit_code != 0 and "mm" in r.stderr


def test_urdf_takes_effort_and_velocity_from_the_robot_file(fits):
    r, out = export(fits, "local-poe", "urdf", "dyn.urdf", "--unknown-dynamics", "refuse")
    assert r.exit_code == 0, r.stderr
    assert "effort/velocity" not in r.stderr
    limits = [j.find("limit") for j in ET.fromstring(out.read_text()).findall("joint") if j.get("type") == "revolute"]
    rows = tomllib.loads(load("ur10").text)["joints"]
    assert [float(e.get("effort")) for e in limits] == [row["effort"] for row in rows]
    assert [float(e.get("velocity")) for e in limits] == [row["velocity"] for row in rows]
    assert [float(e.get("upper")) for e in limits] == [row["limits"][1] for row in rows]


def test_urscript_program_passes_the_checker_and_its_self_test(fits):
    r, out = export(fits, "hybrid", "urscript-program", "prog.script")
    assert r.exit_code == 0, r.stderr
    text = out.read_text()
    urscript_subset.check(text)
    ns = urscript_subset.load(text, float32=True)
    ns["labcal_program"]()
    assert ("textmsg", "labcal: compensator self test passed") in ns["stats"].messages
