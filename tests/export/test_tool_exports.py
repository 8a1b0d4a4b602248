"""Robot and tool apart in the exports: tool0 stays on the flange, the measurement tool is written beside it, and
the compensator file stores it (schema 3) while schema-2 files still load (issue 27)."""

import json
import re

import numpy as np
import pytest

from labcal.calibration.local_poe import fit_local_poe
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot, Compensator, CompensatorFileError
from labcal.compensator import save as save_compensator
from labcal.compensator.io import field_checksums, from_payload, to_payload
from labcal.export.ros import ur_kinematics_text
from labcal.export.urdf import urdf_text
from labcal.kinematics import se3
from labcal.kinematics.conversions import from_urdf
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec, simulate

UR10 = load("ur10")
TRIANGLE = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.05, 0.0866, 0.0]])
MOUNT = se3.pose([0.093, 0.0, 0.02], [np.pi / 2, 0.0, np.pi / 2])


@pytest.fixture(scope="module")
def probe_fit():
    """A UR10 measured through a 93 mm, 90° probe mount that the user did not describe (targets on the flange)."""
    actual = simulate(UR10, ErrorSpec.paper(), seed=1)
    rng = np.random.default_rng(0)
    q = rng.uniform(-np.pi, np.pi, size=(60, 6))
    q[:, 4] = rng.uniform(0.4, 2.6, size=60) * rng.choice([-1, 1], size=60)  # wrist away from q5 = 0
    points = actual.measure(q, TRIANGLE @ MOUNT[:3, :3].T + MOUNT[:3, 3], rng)
    robot, _ = fit_local_poe(Observations(q=q, points=points, targets=TRIANGLE), UR10.model)
    return robot


def _yaml_numbers(text: str, key: str) -> np.ndarray:
    line = next(ln for ln in text.splitlines() if ln.startswith(f"# {key}: "))
    return np.array([float(v) for v in line.split(": ", 1)[1].split()])


def _entries(text: str) -> np.ndarray:
    """(6, 6) x y z roll pitch yaw of the six segments of a kinematics YAML."""
    values = re.findall(r"^    (?:x|y|z|roll|pitch|yaw): (\S+)$", text, flags=re.M)
    return np.array(values, dtype=float).reshape(6, 6)


def test_ur_kinematics_keeps_tool0_on_the_flange_and_writes_the_probe_beside_it(probe_fit):
    text = ur_kinematics_text(probe_fit)
    rest = _yaml_numbers(text, "tcp_in_tool0")  # what the description cannot hold of the robot's tool0
    assert np.linalg.norm(rest[:3]) < 5e-3 and np.linalg.norm(rest[3:]) < 5e-3  # the robot's own errors: mm
    # every joint origin within millimetres / milliradians of the nominal file's: wrist_3 holds no probe mount
    nominal = _entries(ur_kinematics_text(CalibratedRobot(UR10.model, UR10.model)))
    assert np.abs(_entries(text) - nominal).max() < 5e-3
    tool = _yaml_numbers(text, "measurement_tool_in_tool0")
    X = se3.pose(tool[:3]) @ np.block([[se3.exp_so3(tool[3:]), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
    assert np.linalg.norm(X[:3, 3] - MOUNT[:3, 3]) < 5e-3
    assert np.linalg.norm(se3.log_so3(MOUNT[:3, :3].T @ X[:3, :3])) < 5e-3


def test_urdf_ends_at_tool0_with_the_measurement_tool_as_a_separate_link(probe_fit):
    text = urdf_text(probe_fit, unknown_dynamics="zero")
    q = np.random.default_rng(3).uniform(-1, 1, size=(5, 6))
    np.testing.assert_allclose(from_urdf(text, tip_link="tool0").fk(q), probe_fit.predict_pose(q), atol=1e-12)
    fixture = from_urdf(text, tip_link="measurement_tool").fk(q)
    np.testing.assert_allclose(fixture, probe_fit.predict_pose(q, tcp=probe_fit.measurement_tool), atol=1e-12)


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_the_compensator_file_stores_the_measurement_tool(probe_fit, tmp_path, suffix):
    path = save_compensator(probe_fit, tmp_path / f"c{suffix}")
    loaded = Compensator.load(path).robot
    np.testing.assert_array_equal(loaded.measurement_tool, probe_fit.measurement_tool)
    np.testing.assert_array_equal(loaded.model.frames, probe_fit.model.frames)
    q = np.zeros((1, 6)) + 0.3
    np.testing.assert_allclose(loaded.predict_points(q, TRIANGLE), probe_fit.predict_points(q, TRIANGLE), atol=0)


def test_a_schema_2_file_still_loads_and_an_edited_tool_is_refused(probe_fit):
    payload = json.loads(json.dumps(to_payload(probe_fit)))
    old = {key: value for key, value in payload.items() if key not in ("measurement_tool", "checksums")}
    old["schema_version"] = 2
    old["checksums"] = field_checksums(old)
    robot, _ = from_payload(old, "old.json")
    assert robot.measurement_tool is None  # a version-2 model is whatever the fit identified, as it was
    edited = json.loads(json.dumps(payload))
    edited["measurement_tool"][0][3] += 0.01
    with pytest.raises(CompensatorFileError, match="measurement_tool does not match its checksum"):
        from_payload(edited, "edited.json")


def test_the_urscript_header_names_the_measurement_tool_and_its_answer_is_the_tcp_free_correction(probe_fit):
    from labcal.export.urscript import urscript_text

    text = urscript_text(probe_fit)
    line = next(ln for ln in text.splitlines() if "measurement tool in tool0" in ln)
    values = np.array([float(v) for v in line.rsplit(": ", 1)[1].split()])
    np.testing.assert_allclose(values[:3], probe_fit.measurement_tool[:3, 3], atol=1e-12)
    # what the script solves is the flange's equation: any TCP gives the same exact correction
    q = np.array([[0.3, -1.2, 1.1, -1.4, 1.2, 0.4]])
    tcp = se3.pose([0.03, -0.05, 0.243], [0.4, -0.5, 1.1])
    np.testing.assert_allclose(probe_fit.correct(q, tcp=tcp), probe_fit.correct(q), atol=1e-10)


def test_the_runtime_compensator_takes_the_tcp_too(probe_fit, tmp_path):
    comp = Compensator.load(save_compensator(probe_fit, tmp_path / "c.json"))
    np.testing.assert_array_equal(comp.measurement_tool, probe_fit.measurement_tool)
    q = np.array([0.3, -1.2, 1.1, -1.4, 1.2, 0.4])
    tcp = se3.pose([0.03, -0.05, 0.243], [0.4, -0.5, 1.1])
    q_cmd = comp.correct(q, tcp=tcp, extrapolate=True)
    np.testing.assert_allclose(comp.predict_pose(q_cmd, tcp=tcp, extrapolate=True), UR10.model.fk(q) @ tcp, atol=1e-9)
    with pytest.raises(ValueError, match="tcp must be"):
        comp.correct(q, tcp=[[1, 2]], extrapolate=True)
