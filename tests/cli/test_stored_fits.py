"""Stored fits across versions of labcal, and fits of a robot whose controller joints are not its model joints."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from labcal.cli.common import UserError, open_store
from labcal.cli.ops.exporting import export_fit
from labcal.cli.ops.fitting import load_stored_fit, run_fit
from labcal.cli.ops.sessions import new_session
from labcal.compensator import Compensator, CompensatorFileError, from_payload, to_payload
from labcal.robots import load

TARGETS = "drivers/targets-example.toml"


def _schema1(payload: dict) -> dict:
    """The payload as labcal wrote it before joint maps and field checksums (schema 1)."""
    old = {k: v for k, v in payload.items() if k not in ("joint_map", "checksums")}
    old["schema_version"] = 1
    return old


@pytest.fixture(scope="module")
def ur10_fit(tmp_path_factory):
    store = open_store(tmp_path_factory.mktemp("store"), create=True)
    ref = new_session(store, robot="ur10", targets_file=TARGETS, poses=40, seed=3).ref
    outcome = run_fit(store, [ref], "local-poe")
    return store, ref, outcome


def test_a_fit_stored_by_an_older_labcal_is_still_read_from_the_store(ur10_fit, tmp_path):
    store, ref, outcome = ur10_fit
    current = load_stored_fit(store, ref, outcome.fit_id)
    files = {
        name: json.dumps(_schema1(to_payload(robot)))
        for name, robot in (("robot.json", current.robot), ("before.json", current.before))
    }
    record = store.save_fit([ref], files, dict(current.meta))
    old = load_stored_fit(store, ref, record.fit_id)
    q = np.array([[0.3, -1.2, 1.4, -1.8, -1.5, 0.4]])
    assert np.array_equal(old.robot.correct(q), current.robot.correct(q))
    out = export_fit(store, ref, "json", tmp_path / "old.json", record.fit_id)
    assert Compensator.load(out).joint_map.is_identity  # re-exported in the current schema


def test_a_loose_schema_1_export_is_refused(ur10_fit):
    store, ref, outcome = ur10_fit
    payload = _schema1(to_payload(load_stored_fit(store, ref, outcome.fit_id).robot))
    with pytest.raises(CompensatorFileError, match=r"schema_version 1 is not supported.*export the fit again"):
        from_payload(payload, "old.json")


@pytest.fixture(scope="module")
def coupled(tmp_path_factory):
    store = open_store(tmp_path_factory.mktemp("store"), create=True)
    ref = new_session(store, robot="coupled-elbow-6r", targets_file=TARGETS, poses=60, seed=2).ref
    return store, ref, run_fit(store, [ref], "local-poe")


def test_a_coupled_elbow_fit_exports_a_compensator_in_controller_joints(coupled, tmp_path):
    store, ref, outcome = coupled
    spec = load("coupled-elbow-6r")
    errors = outcome.result.metrics["all"]
    assert errors["after"]["pos_mean"] < 0.1 * errors["before"]["pos_mean"]  # the map was applied before fitting
    comp = Compensator.load(export_fit(store, ref, "json", tmp_path / "c.json", outcome.fit_id))
    assert comp.robot_hash == spec.hash
    q_model = spec.model.limits.mean(axis=1) + 0.1
    q_ctrl = spec.joints.to_controller(q_model)
    q_cmd = comp.correct(q_ctrl)
    # The calibrated robot, commanded in controller joints, reaches the pose the nominal model gives for q.
    T_reached = comp.predict_pose(q_cmd)
    assert np.allclose(T_reached, spec.model.fk(q_model), atol=1e-9)
    # …and the command is not the model-joint answer: the map is applied at the compensator's edges.
    model_answer = outcome.result.robot.correct(q_model)
    assert np.allclose(spec.joints.to_model(q_cmd), model_answer, atol=1e-9)
    assert not np.allclose(q_cmd, model_answer, atol=1e-3)


def test_a_coupled_elbow_fit_is_not_exported_to_a_ur_controller(coupled, tmp_path):
    store, ref, outcome = coupled
    with pytest.raises(ValueError, match="joint map"):
        export_fit(store, ref, "urscript", tmp_path / "c.script", outcome.fit_id)


def test_a_fit_that_lost_its_joint_map_is_not_exported(coupled, tmp_path):
    store, ref, outcome = coupled
    stored = load_stored_fit(store, ref, outcome.fit_id)
    # What a fit stored before joint maps holds: the model without its map, in schema 1.
    files = {
        name: json.dumps(_schema1(to_payload(dataclasses.replace(robot, joint_map=None))))
        for name, robot in (("robot.json", stored.robot), ("before.json", stored.before))
    }
    record = store.save_fit([ref], files, dict(stored.meta))
    with pytest.raises(UserError, match="does not carry the joint map"):
        export_fit(store, ref, "json", tmp_path / "lost.json", record.fit_id)


def test_probe_data_fit_with_the_probe_mount_as_measurement_tool(tmp_path):
    """The committed example is real IPA UR10 probe data: the probe sits ~93 mm / 90° off the bare flange. Robot and
    tool apart: the mount is the fit's measurement tool, the robot stays to its flange."""
    import shutil

    shutil.copytree("sessions", tmp_path / "store")
    store = open_store(tmp_path / "store")
    outcome = run_fit(store, ["example"], "local-poe")
    assert any(note.startswith("probe data: the probe's mount") for note in outcome.gates["notes"])
    assert not [w for w in outcome.gates["warnings"] if w["code"] == "large-correction"]
    comp = Compensator.load(export_fit(store, "example", "json", tmp_path / "ipa.json", outcome.fit_id))
    q = store.load("example").q
    q = q[np.abs(q[:, 4]) > 0.2]  # away from the wrist singularity (the first row is the home pose, q5 = 0)
    # Folded into the robot, the mount turned the wrist ~0.6 rad to bring the probe onto the flange's pose.
    assert np.max(np.abs(comp.correct(q) - q)) < 0.05
    assert 0.08 < np.linalg.norm(comp.robot.measurement_tool[:3, 3]) < 0.11
    assert np.array_equal(comp.robot.model.frames[-1], comp.robot.nominal.frames[-1])
