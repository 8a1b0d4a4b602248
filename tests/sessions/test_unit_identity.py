"""Unit identity (issue 17.1): a session records which arm it measured (``metadata["unit"]``: the controller's
serial number, else the operator's id) and what the devices said about themselves; sessions of different units are
not pooled unless asked; old sessions (no unit) read and pool as before."""

from __future__ import annotations

import pytest
from sessions_testutil import TARGETS, TARGETS_TOML

from labcal.cli.common import UserError
from labcal.cli.ops.common import check_units, load_observations
from labcal.cli.ops.sessions import SessionRequest, new_session
from labcal.datasets import JournalError, SessionHeader, SessionStore, StartDoc
from labcal.datasets.documents import check_unit
from labcal.drivers.sim import SimRig
from labcal.robots import load
from labcal.sessions import SessionError, make_plan, random_configurations, resume, run
from labcal.sessions.runner import session_unit
from labcal.simulation import ErrorSpec, simulate


@pytest.fixture
def store(tmp_path):
    return SessionStore(tmp_path / "store")


@pytest.fixture
def targets_file(tmp_path):
    path = tmp_path / "targets.toml"
    path.write_text(TARGETS_TOML)
    return path


def _sim(store, targets_file, **fields):
    return new_session(store, SessionRequest(robot="ur10", targets_file=targets_file, poses=12, **fields))


def _unit(store, ref):
    return store.manifest(ref)["session"]["metadata"].get("unit")


def test_a_sim_session_is_the_unit_of_its_simulated_robot(store, targets_file):
    a = _sim(store, targets_file, seed=1)
    again = _sim(store, targets_file, seed=5, sim_seed=1)  # the same simulated robot, other tracker noise
    other = _sim(store, targets_file, seed=2)
    assert [_unit(store, s.ref) for s in (a, again, other)] == ["sim-1", "sim-1", "sim-2"]
    assert store.session_meta(a.session_id)["metadata"]["unit"] == "sim-1"  # what session list / refit read
    assert store.session_meta(a.session_id)["robot_driver"]["identity"] == {"model": "ur10", "serial": "sim-1"}
    assert len(load_observations(store, [a.ref, again.ref])[0].q) == 24  # one unit: pooled as always
    with pytest.raises(UserError, match=r"2 different robot units \(sim-1: .*; sim-2: .*\).*--pool-units"):
        load_observations(store, [a.ref, other.ref])
    assert len(load_observations(store, [a.ref, other.ref], pool_units=True)[0].q) == 24


def test_an_operator_unit_is_recorded_and_checked(store, targets_file):
    s = _sim(store, targets_file, seed=1, unit="cell-3 arm")
    assert _unit(store, s.ref) == "cell-3 arm"
    for bad in ("", " padded", "x" * 65, "tab\there", 7):
        with pytest.raises(UserError, match="--unit"):
            SessionRequest(robot="ur10", targets_file=targets_file, poses=3, unit=bad).check()


class _Identified:
    """A driver wrapper that reports a device identity (as the UR driver does from the dashboard server)."""

    def __init__(self, device, identity):
        self._device, self._identity = device, identity

    def device_identity(self):
        if isinstance(self._identity, Exception):
            raise self._identity
        return dict(self._identity)

    def __getattr__(self, name):
        return getattr(self._device, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._device.close()


def _run(store, robot_identity, tracker_identity=None, *, unit=None, poses=6, seal=True):
    spec = load("ur10")
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=0), TARGETS, seed=0)
    plan = make_plan(random_configurations(spec.model, poses, seed=0, targets=TARGETS), samples=1, settle=0.0)
    robot = _Identified(rig.robot(), robot_identity)
    tracker = _Identified(rig.tracker(), tracker_identity or {})
    with robot, tracker:
        return run(store, spec, TARGETS, plan, robot, tracker, frame="base", unit=unit, seal=seal), rig


def test_the_robot_serial_becomes_the_unit_and_the_devices_identities_are_stored(store):
    summary, _ = _run(
        store,
        {"serial": "20185500001", "model": "UR10", "software": "5.11.0.0"},
        {"serial": "P9-01234", "firmware": "024.001"},
    )
    meta = store.session_meta(summary.session_id)
    assert meta["metadata"]["unit"] == "20185500001"
    assert meta["robot_driver"]["identity"] == {"serial": "20185500001", "model": "UR10", "software": "5.11.0.0"}
    assert meta["tracker"]["identity"] == {"serial": "P9-01234", "firmware": "024.001"}
    start = store.open_journal(summary.session_id).start
    assert (start.metadata["unit"], start.robot_identity["serial"], start.tracker["identity"]["firmware"]) == (
        "20185500001",
        "20185500001",
        "024.001",
    )


def test_a_given_unit_wins_over_the_serial_with_a_note(store):
    summary, _ = _run(store, {"serial": "20185500001"}, unit="ARM-7")
    meta = store.session_meta(summary.session_id)
    assert meta["metadata"]["unit"] == "ARM-7"
    assert meta["robot_driver"]["identity"]["notes"] == [
        "unit 'ARM-7' was given, the controller reports serial number '20185500001'"
    ]
    assert session_unit(None, {"serial": ""}) == (None, [])  # an empty answer is no serial


def test_a_device_that_does_not_tell_is_a_note_not_a_failed_session(store):
    summary, _ = _run(store, RuntimeError("dashboard closed the connection"))
    assert summary.exit_status == "success" and summary.valid == 6
    meta = store.session_meta(summary.session_id)
    assert "unit" not in meta["metadata"]
    (note,) = meta["robot_driver"]["identity"]["notes"]
    assert "did not report its identity: dashboard closed the connection" in note


def test_resuming_on_another_arm_is_refused_before_anything_moves(store):
    first, rig = _run(store, {"serial": "A-1"}, poses=6, seal=False)
    other = _Identified(rig.robot(), {"serial": "B-2"})
    moves = rig.moves
    with other, rig.tracker() as tracker, pytest.raises(SessionError, match=r"serial number 'A-1'.*reports 'B-2'"):
        resume(store, first.session_id, other, tracker, spec=load("ur10"))
    assert rig.moves == moves


def test_old_start_documents_have_no_unit_and_pool_with_anything(store, targets_file):
    header = SessionHeader.of("ur10", "h" * 64, 6, targets=TARGETS, frame="base", metadata={"sim": {"seed": 1}})
    doc = header.start_document("S").to_json()
    assert "unit" not in doc["metadata"] and "identity" not in doc["robot_driver"]  # the JSON of before
    old = StartDoc.from_json(doc)
    assert ("unit" not in old.metadata, old.robot_identity, old.tracker) == (True, {}, {})
    new = SessionHeader.of(
        "ur10", "h" * 64, 6, targets=TARGETS, frame="base", unit="U1", robot_identity={"serial": "U1"}
    )
    doc = new.start_document("S").to_json()
    assert doc["metadata"]["unit"] == "U1" and doc["robot_driver"]["identity"] == {"serial": "U1"}
    assert StartDoc.from_json(doc).to_json() == doc
    with pytest.raises(JournalError, match="not a unit id"):
        SessionHeader.of("ur10", "h" * 64, 6, targets=TARGETS, frame="base", unit=" U1").start_document("S")
    assert check_unit("UR10-2019-0417") == "UR10-2019-0417"


class _Version:
    def __init__(self, ref, unit):
        self.ref = ref
        self.manifest = {"session": {"metadata": {} if unit is None else {"unit": unit}}}


def test_check_units_names_each_unit_with_its_sessions():
    versions = [_Version("A@v001", "U1"), _Version("B@v001", None), _Version("C@v002", "U2"), _Version("D@v001", "U1")]
    with pytest.raises(UserError) as e:
        check_units(versions)
    assert str(e.value) == (
        "the sessions are of 2 different robot units (U1: A@v001, D@v001; U2: C@v002): fit one unit at a time, or "
        "pass --pool-units to fit them as one"
    )
    assert check_units(versions, pool_units=True) == ["U1", "U2"]
    assert check_units(versions[:2]) == ["U1"]  # a session without a unit pools with any unit
    assert check_units([_Version("B@v001", None)]) == []


def test_an_interrupted_sim_session_resumes_on_its_own_simulated_arm(store):
    from sessions_testutil import CountingRobot

    from labcal.cli.ops.sessions import _sim_rig, resume_session

    spec, sim = load("ur10"), {"errors": "default", "seed": 3, "noise_seed": 3}
    rig = _sim_rig(spec, TARGETS, sim)  # the rig `session new` builds: serial sim-3
    plan = make_plan(random_configurations(spec.model, 8, seed=3, targets=TARGETS), samples=1, settle=0.0)
    robot = CountingRobot(rig.robot(), interrupt_at=5)  # Ctrl-C at the fifth move
    with robot, rig.tracker() as tracker:
        first = run(store, spec, TARGETS, plan, robot, tracker, frame="base", metadata={"sim": sim})
    assert first.exit_status == "aborted" and _unit(store, first.ref) == "sim-3"
    resumed = resume_session(store, first.session_id)  # the same simulated arm: its serial check passes
    assert (resumed.exit_status, resumed.valid) == ("success", 8)
    assert _unit(store, resumed.ref) == "sim-3"
