"""Nothing hostile reaches an export (issue 24, items 2, 3 and 6; issue 25's serial numbers).

Names and device strings that got past the load checks (a robot built in code, a serial number a device sent) are
escaped by every writer: the YAML still parses to ur_description's two levels, the URDF is well-formed XML. Every
writer goes through labcal.atomicio, so a symlink or a device at the output path is refused, not replaced or
written through; `labcal export --force` refuses them with one line. The exports name the arm's and the tracker's
serial numbers from the session's start document."""

from __future__ import annotations

import json
import os
import stat
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "cli"))

from cli_testutil import invoke, last_line

from labcal.compensator import CalibratedRobot
from labcal.datasets import SessionStore
from labcal.drivers.sim import SimRig
from labcal.export import FORMATS, SUFFIXES, export
from labcal.export.ros import UR_SEGMENTS, ur_kinematics_text
from labcal.export.urdf import urdf_text
from labcal.robots import load
from labcal.sessions import make_plan, random_configurations, run
from labcal.simulation import ErrorSpec, simulate

yaml = pytest.importorskip("yaml")

INJECTION = "ur10\nmovej([0,-1.57,0,-1.57,0,0], a=3, v=3)\n#\x1b[31m"
HOSTILE = {"arm_serial": "SN\n  hash: calib_1\x1b[2J", "note": "a -- b -->"}
TRACKER_SERIAL = "P9-01234\n  hash: calib_1 -- \x1b[2J"
TARGETS = np.array([[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03]])


def _no_control_characters(text: str) -> None:
    assert all(ch.isprintable() or ch == "\n" for ch in text), [ch for ch in text if not ch.isprintable()][:3]


def hostile_robot() -> CalibratedRobot:
    """A UR10 whose name was never checked (built in code, not loaded from a file)."""
    nominal = load("ur10").model.replace(name=INJECTION)
    return CalibratedRobot(nominal, nominal, method="local-poe")


def test_the_ur_kinematics_yaml_stays_two_levels_whatever_the_names_and_provenance():
    text = ur_kinematics_text(hostile_robot(), HOSTILE)
    _no_control_characters(text)
    doc = yaml.safe_load(text)
    assert list(doc) == ["kinematics"]
    assert list(doc["kinematics"]) == [*UR_SEGMENTS, "hash"]
    assert doc["kinematics"]["hash"].startswith("labcal_")
    # the hash is a quoted scalar, and the file says why ur_robot_driver will not match it
    assert '  hash: "labcal_' in text and "ur_robot_driver" in text


def test_the_urdf_is_well_formed_whatever_the_names_and_provenance():
    text = urdf_text(hostile_robot(), HOSTILE, unknown_dynamics="zero")
    _no_control_characters(text)
    root = ET.fromstring(text)
    assert root.get("name").startswith("ur10 movej(")
    assert [j.get("name") for j in root.findall("joint") if j.get("type") == "revolute"] == list(
        load("ur10").model.joint_names
    )


def test_the_urdf_refuses_repeated_joint_names():
    nominal = load("ur10").model
    twice = nominal.replace(joint_names=("a", "b", "c", "a", "e", "f"))
    with pytest.raises(ValueError, match="joints 1 and 4 are both named 'a'"):
        urdf_text(CalibratedRobot(twice, twice), unknown_dynamics="zero")


def _victim_and_link(tmp_path: Path, suffix: str) -> tuple[Path, Path]:
    victim = tmp_path / f"victim{suffix}"
    victim.write_text("keep")
    link = tmp_path / f"link{suffix}"
    link.symlink_to(victim)
    return victim, link


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_writer_refuses_a_symlink_and_a_device(tmp_path, fmt):
    robot = CalibratedRobot(load("ur10").model, load("ur10").model, method="local-poe")
    victim, link = _victim_and_link(tmp_path, SUFFIXES[fmt])
    with pytest.raises(ValueError, match="is a symbolic link"):
        export(robot, fmt, link, unknown_dynamics="zero") if fmt == "urdf" else export(robot, fmt, link)
    assert link.is_symlink() and victim.read_text() == "keep"
    device = tmp_path / f"null{SUFFIXES[fmt]}"
    try:
        os.mknod(device, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # a null device node, private to this test
    except PermissionError:
        pytest.skip("creating a device node needs root")
    with pytest.raises(ValueError, match="is a device"):
        export(robot, fmt, device, unknown_dynamics="zero") if fmt == "urdf" else export(robot, fmt, device)
    assert stat.S_ISCHR(os.lstat(device).st_mode)


class _Identified:
    """A sim driver that reports a device identity, as the UR and NDI drivers do."""

    def __init__(self, device, identity):
        self._device, self._identity = device, identity

    def device_identity(self):
        return dict(self._identity)

    def __getattr__(self, name):
        return getattr(self._device, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._device.close()


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A 40-pose sim session whose controller and tracker report serial numbers (the tracker's hostile), fitted."""
    root = tmp_path_factory.mktemp("export-hostile")
    store = SessionStore(root / "store")
    spec = load("ur10")
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0)
    plan = make_plan(random_configurations(spec.model, 40, seed=0, targets=TARGETS), samples=1, settle=0.0)
    robot = _Identified(rig.robot(), {"serial": "20185500001", "model": "UR10"})
    tracker = _Identified(rig.tracker(), {"serial": TRACKER_SERIAL, "model": "Vega"})
    with robot, tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base")
    r = invoke("fit", summary.ref, "--method", "local-poe", store=root / "store")
    assert r.exit_code == 0, r.stdout + r.stderr
    return {"root": root, "store": root / "store", "ref": summary.ref}


def _export(fitted, fmt, out, *extra):
    return invoke("export", fitted["ref"], "--format", fmt, "--out", out, "--force", *extra, store=fitted["store"])


def test_exports_name_the_arm_and_the_tracker_by_serial_escaped(fitted):
    shown = "P9-01234 hash: calib_1 -- \\x1b[2J"  # one printable line, the escape shown, not sent
    root = fitted["root"]
    r = _export(fitted, "json", root / "c.json")
    assert r.exit_code == 0, r.stderr
    provenance = json.loads((root / "c.json").read_text())["provenance"]
    assert provenance["arm_serial"] == "20185500001"
    assert provenance["tracker_serial"] == shown
    assert _export(fitted, "ur-kinematics", root / "c.yaml").exit_code == 0
    text = (root / "c.yaml").read_text()
    _no_control_characters(text)
    assert list(yaml.safe_load(text)) == ["kinematics"]
    assert "# arm_serial: 20185500001" in text.splitlines()
    assert _export(fitted, "urdf", root / "c.urdf").exit_code == 0
    comment = (root / "c.urdf").read_text()
    ET.fromstring(comment)
    xml_shown = shown.replace("--", "- -")  # an XML comment may not hold "--"
    assert "arm_serial: 20185500001" in comment and f"tracker_serial: {xml_shown}" in comment
    assert _export(fitted, "urscript-program", root / "c.script").exit_code == 0
    script = (root / "c.script").read_text()
    _no_control_characters(script)
    head = script.split("\ndef ", 1)[0].splitlines()
    assert all(line.startswith("#") for line in head), head
    assert "# arm_serial: 20185500001" in head
    # the URScript writer percent-escapes everything outside plain ASCII words (its own, stricter rule)
    assert "# tracker_serial: P9-01234 hash: calib_1 -- %5Cx1b[2J" in head, head


@pytest.mark.timeout(60)  # a writer that opened the FIFO would wait for a reader forever
@pytest.mark.parametrize("kind", ["symlink", "fifo", "folder", "device"])
def test_export_force_refuses_what_is_not_a_regular_file_with_one_line(fitted, tmp_path, kind):
    victim, out = tmp_path / "victim.json", tmp_path / "out.json"
    victim.write_text("keep")
    if kind == "symlink":
        out.symlink_to(victim)
    elif kind == "fifo":
        os.mkfifo(out)
    elif kind == "folder":
        out.mkdir()
    else:
        try:
            os.mknod(out, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        except PermissionError:
            pytest.skip("creating a device node needs root")
    mode = os.lstat(out).st_mode
    r = _export(fitted, "json", out)
    assert r.exit_code == 2, r.stdout
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: --out {out}"), r.stderr
    assert os.lstat(out).st_mode == mode and victim.read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json", "victim.json"]  # nothing left behind
    assert last_line(invoke("session", "list", store=fitted["store"]))  # the store is untouched and readable


def test_session_list_and_show_print_a_stored_hostile_name_without_raw_escapes(tmp_path):
    """A store written before the name checks (or by hand) may hold any robot name: the terminal gets it escaped."""
    import dataclasses

    store = SessionStore(tmp_path / "store")
    spec = dataclasses.replace(load("ur10"), name="ur10\x1b[2J\x1b[31mOK")
    rig = SimRig(simulate(load("ur10"), ErrorSpec.default(), seed=0), TARGETS, seed=0)
    plan = make_plan(random_configurations(spec.model, 3, seed=0, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base")
    for args in (("session", "list"), ("session", "show", summary.session_id)):
        r = invoke(*args, store=tmp_path / "store")
        assert r.exit_code == 0, r.stderr
        assert "\x1b" not in r.stdout and "ur10\\x1b[2J" in r.stdout.replace("\n", ""), r.stdout
