"""Self-contained versions: a session stores its robot file, so fit, report, export and resume need nothing else;
and the joint map converts controller joints (stored) to model joints (fitted) in one place."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from sessions_testutil import TARGETS, CountingRobot, record_interrupted, write_custom_robot

from labcal.calibration.observations import Observations
from labcal.cli.common import UserError
from labcal.cli.ops.common import load_observations, robot_for
from labcal.cli.ops.exporting import export_fit
from labcal.cli.ops.fitting import run_fit
from labcal.cli.ops.sessions import resume_session
from labcal.datasets import SessionStore, read_journal
from labcal.drivers.sim import SimRig
from labcal.robots import load, loads
from labcal.sessions import make_plan, random_configurations, run
from labcal.simulation import ErrorSpec, simulate


@pytest.fixture
def store(tmp_path):
    return SessionStore(tmp_path / "store")


def test_a_custom_robot_session_is_refitted_exported_reported_and_resumed_after_its_file_is_deleted(tmp_path, store):
    path = write_custom_robot(tmp_path)
    spec = load(path)
    first = record_interrupted(store, spec, n_poses=24, interrupt_at=17)  # 16 poses measured, then Ctrl-C
    sid = first.session_id
    assert first.ref.endswith("@v001") and first.valid == 16
    path.unlink()  # from here on only the store knows the model

    manifest = store.manifest(first.ref)
    assert manifest["session"]["robot"]["text"] == spec.text and manifest["session"]["robot"]["hash"] == spec.hash
    assert robot_for(manifest["session"]["robot"]).hash == spec.hash

    resumed = resume_session(store, sid)  # the sim rig is re-created from the stored model, errors and seed
    assert (resumed.exit_status, resumed.valid, resumed.remaining) == ("success", 24, 0)
    assert resumed.ref.endswith("@v002") and len(store.load(resumed.ref)) == 24

    outcome = run_fit(store, [resumed.ref], "local-poe", val_fraction=0.0)
    assert outcome.fit_id and store.load_fit(resumed.ref, outcome.fit_id)
    # force: this test is about finding the model without its file, not about the fit gates (tested by CLI).
    exported = export_fit(store, resumed.ref, "json", tmp_path / "comp.json", outcome.fit_id, force=True)
    assert json.loads(exported.read_text())

    from labcal.reports import write_session_report

    report = write_session_report(store, resumed.ref, tmp_path / "report")
    assert outcome.fit_id in report.read_text()


def test_robot_override_must_match_the_stored_hash(tmp_path, store):
    path = write_custom_robot(tmp_path)
    spec = load(path)
    record = spec.record()
    assert robot_for(record, str(path)).hash == spec.hash  # the same file as an override: accepted
    with pytest.raises(UserError, match="not the model the session was recorded with"):
        robot_for(record, "ur10")
    # Stored text that does not give the stored hash is refused, not silently used.
    with pytest.raises(UserError, match="has hash"):
        robot_for({**record, "hash": "0" * 64})


def test_old_sessions_without_robot_text_use_the_builtin_or_say_to_pass_the_file(tmp_path):
    ur10 = load("ur10")
    assert robot_for({"name": "ur10", "hash": ur10.hash, "n_joints": 6}).hash == ur10.hash
    custom = load(write_custom_robot(tmp_path))
    with pytest.raises(UserError, match="--robot PATH"):
        robot_for({"name": custom.name, "hash": custom.hash, "n_joints": 6})
    with pytest.raises(UserError, match="changed since the session was recorded"):
        robot_for({"name": "ur10", "hash": "f" * 64, "n_joints": 6})


def _rows(q: np.ndarray, points: np.ndarray) -> pd.DataFrame:
    rows = {"pose": np.arange(len(q), dtype=np.int64)}
    rows.update({f"q{j + 1}": q[:, j] for j in range(q.shape[1])})
    for i in range(3):
        for a, axis in enumerate("xyz"):
            rows[f"t{i + 1}_{axis}"] = points[:, i, a]
    rows["split"] = [""] * len(q)
    return pd.DataFrame(rows)


def _imported(store, spec, q_controller, points, *, record_in_metadata: bool) -> str:
    """An imported session as IMPORT writes it: the robot record either in meta['robot'] or in the metadata."""
    robot = {"name": spec.name, "hash": spec.hash, "n_joints": spec.model.n}
    meta = {
        "robot": robot if record_in_metadata else spec.record(),
        "targets": TARGETS.tolist(),
        "targets_unit": "m",
        "frame": "base",
        "tracker": {},
        "robot_driver": {},
        "extra_units": {},
        "metadata": {"robot": spec.record()} if record_in_metadata else {},
    }
    return store.create_imported_session(_rows(q_controller, points), meta, source="import:test", provenance={})


@pytest.mark.parametrize("record_in_metadata", [True, False])
def test_an_imported_session_keeps_the_robot_file_and_verifies(tmp_path, store, record_in_metadata):
    spec = load(write_custom_robot(tmp_path))
    q = random_configurations(spec.model, 6, seed=2, targets=TARGETS)
    ref = _imported(store, spec, q, np.zeros((6, 3, 3)), record_in_metadata=record_in_metadata)
    manifest = store.manifest(ref)
    assert manifest["session"]["robot"]["text"] == spec.text
    assert "robot" not in manifest["session"]["metadata"]  # stored once
    assert store.verify(ref).ok
    obs, _, got = load_observations(store, [ref], with_spec=True)
    assert got.hash == spec.hash and np.array_equal(obs.q, q)


def test_a_record_of_another_model_in_the_import_metadata_is_refused(tmp_path, store):
    spec = load(write_custom_robot(tmp_path))
    q = random_configurations(spec.model, 3, seed=2, targets=TARGETS)
    meta = {
        "robot": {"name": "ur10", "hash": load("ur10").hash, "n_joints": 6},
        "targets": TARGETS.tolist(), "frame": "base", "extra_units": {}, "metadata": {"robot": spec.record()},
    }  # fmt: skip
    with pytest.raises(Exception, match="not the model the data are labelled with"):
        store.create_imported_session(_rows(q, np.zeros((3, 3, 3))), meta, source="import:test", provenance={})


def test_stored_controller_joints_become_model_joints_once_in_load_observations(store):
    spec = load("coupled-elbow-6r")
    assert not spec.joints.is_identity
    q_model = random_configurations(spec.model, 5, seed=4, targets=TARGETS)
    q_ctrl = spec.joints.to_controller(q_model)
    assert not np.allclose(q_ctrl, q_model)
    ref = _imported(store, spec, q_ctrl, np.zeros((5, 3, 3)), record_in_metadata=False)
    np.testing.assert_array_equal(store.load(ref).q, q_ctrl)  # the store keeps what the controller said
    obs, _ = load_observations(store, [ref])
    np.testing.assert_allclose(obs.q, q_model, atol=1e-12)


def test_pooled_sessions_are_labelled_by_session_when_observations_have_groups(store):
    spec = load("ur10")
    q = random_configurations(spec.model, 4, seed=5, targets=TARGETS)
    a = _imported(store, spec, q, np.zeros((4, 3, 3)), record_in_metadata=False)
    b = _imported(store, spec, q[:3], np.zeros((3, 3, 3)), record_in_metadata=False)
    obs, _ = load_observations(store, [a, b])
    assert len(obs.q) == 7
    if "group" not in {f.name for f in __import__("dataclasses").fields(Observations)}:
        pytest.skip("Observations has no group field yet (CALIB adds it)")
    assert list(obs.group) == [a] * 4 + [b] * 3


class ControllerJointsRobot:
    """A robot whose controller reports coupled joints: it takes and returns controller joints and drives the sim
    rig (which works in model joints) through the joint map, like a real controller with a coupled elbow."""

    def __init__(self, robot, joints):
        self._robot, self.joints = robot, joints
        self.n_joints, self.limits = robot.n_joints, robot.limits
        self.received: list[np.ndarray] = []

    def move_joints(self, q, speed, acceleration):
        self.received.append(np.array(q, dtype=float))
        return self._robot.move_joints(self.joints.to_model(q), speed, acceleration)

    def joint_positions(self):
        return self.joints.to_controller(self._robot.joint_positions())

    def __getattr__(self, name):
        return getattr(self._robot, name)


def test_the_runner_plans_in_model_joints_and_commands_and_records_controller_joints(store):
    spec = load("coupled-elbow-6r")
    actual = simulate(spec, ErrorSpec.none(), seed=1)
    rig = SimRig(actual, TARGETS, seed=1)
    q_model = random_configurations(spec.model, 4, seed=6, targets=TARGETS)
    with rig.robot() as sim_robot, rig.tracker() as tracker:
        robot = ControllerJointsRobot(sim_robot, spec.joints)
        summary = run(store, spec, TARGETS, make_plan(q_model, samples=1, settle=0.0), robot, tracker, frame="base")
    assert summary.exit_status == "success" and summary.valid == 4
    q_ctrl = spec.joints.to_controller(q_model)
    np.testing.assert_allclose(np.array(robot.received), q_ctrl, atol=1e-12)
    docs = read_journal(store.session_dir(summary.session_id) / "journal.jsonl").measurements
    np.testing.assert_allclose([d.q_commanded for d in docs], q_ctrl, atol=1e-12)
    np.testing.assert_allclose([d.q_actual for d in docs], q_ctrl, atol=1e-9)
    obs, _ = load_observations(store, [summary.ref])
    np.testing.assert_allclose(obs.q, q_model, atol=1e-9)


def test_resume_uses_the_joint_map_stored_with_the_session(store):
    spec = load("coupled-elbow-6r")
    rig = SimRig(simulate(spec, ErrorSpec.none(), seed=1), TARGETS, seed=1)
    q_model = random_configurations(spec.model, 5, seed=7, targets=TARGETS)
    plan = make_plan(q_model, samples=1, settle=0.0)
    with rig.robot() as sim_robot, rig.tracker() as tracker:
        first = CountingRobot(ControllerJointsRobot(sim_robot, spec.joints), interrupt_at=3)
        summary = run(store, spec, TARGETS, plan, first, tracker, frame="base")
    assert summary.exit_status == "aborted"
    from labcal.sessions import resume

    rig2 = SimRig(simulate(spec, ErrorSpec.none(), seed=1), TARGETS, seed=1)
    with rig2.robot() as sim_robot, rig2.tracker() as tracker:
        robot = ControllerJointsRobot(sim_robot, spec.joints)
        done = resume(store, summary.session_id, robot, tracker)  # no spec given: the stored robot file is used
    assert done.exit_status == "success" and done.valid == 5
    np.testing.assert_allclose(np.array(robot.received), spec.joints.to_controller(q_model[2:]), atol=1e-12)
    assert loads(spec.text).hash == spec.hash


def test_an_imported_custom_robot_session_is_refitted_and_exported_after_the_file_is_deleted(tmp_path):
    from labcal.cli.ops.imports import import_session

    path = write_custom_robot(tmp_path)
    spec = load(path)
    # Measurements of the custom arm (sim rig, base frame), written as the CSV a user would import.
    recorded = SessionStore(tmp_path / "rec")
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=2), TARGETS, seed=2)
    plan = make_plan(random_configurations(spec.model, 30, seed=2, targets=TARGETS), samples=1, settle=0.0)
    with rig.robot() as robot, rig.tracker() as tracker:
        ds = recorded.load(run(recorded, spec, TARGETS, plan, robot, tracker, frame="base").ref)
    cols = [f"q{j + 1}" for j in range(6)] + [f"t{i}_{a}" for i in (1, 2, 3) for a in "xyz"]
    csv = tmp_path / "data.csv"
    ds.table[cols].to_csv(csv, index=False)
    targets = tmp_path / "targets.toml"
    targets.write_text(f'unit = "m"\npoints = {TARGETS.tolist()}\n')

    store = SessionStore(tmp_path / "store")
    ref = import_session(store, csv, robot=str(path), targets_file=targets)
    path.unlink()
    assert store.manifest(ref)["session"]["robot"]["text"] == spec.text
    outcome = run_fit(store, [ref], "local-poe", val_fraction=0.0)
    assert export_fit(store, ref, "json", tmp_path / "c.json", outcome.fit_id, force=True).is_file()
