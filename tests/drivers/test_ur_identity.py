"""The UR driver asks the dashboard server (29999) who the arm is: serial number, model, PolyScope version.

Against the fake controller in another process (the same fake the real ur-rtde control interface connects to); a
controller that does not know a command, or is not there, gives an identity without it and a note, never an
error."""

from __future__ import annotations

import socket

import pytest
from ur_fixtures import make_profile

from labcal.drivers.ur import URRobot, parse_dashboard_identity, read_dashboard_identity
from labcal_fakes.rtde_fake import FakeRTDEServer

pytestmark = [pytest.mark.integration, pytest.mark.timeout(40)]


def _dashboard_log(fake) -> list[str]:
    return [value for kind, value in fake.snapshot()["log"] if kind == "dashboard"]


def test_the_dashboard_tells_serial_model_and_software():
    with FakeRTDEServer(control=True, serial="20195500417", robot_model="UR5", controller_version=(5, 11, 6, 0)) as f:
        identity = read_dashboard_identity(f.host, timeout=2.0)
        assert identity == {"serial": "20195500417", "model": "UR5", "software": "5.11.6.0"}
        assert _dashboard_log(f) == ["get serial number", "get robot model", "PolyscopeVersion"]


def test_connect_records_the_identity_the_runner_reads():
    pytest.importorskip("rtde_control")
    with FakeRTDEServer(control=True, serial="20185500123") as fake:
        robot = URRobot.connect(make_profile(fake.host, connect_timeout=2.0))
        try:
            assert robot.device_identity()["serial"] == "20185500123"
            assert robot.device_identity()["model"] == "UR10"
        finally:
            robot.close()


def test_a_controller_without_get_serial_number_gives_a_note_not_an_error():
    with FakeRTDEServer(control=True, serial=None) as fake:
        identity = read_dashboard_identity(fake.host, timeout=2.0)
    assert "serial" not in identity and identity["model"] == "UR10"
    assert identity["notes"] == [
        "the dashboard server answered 'get serial number' with \"could not understand: 'get serial number'\""
    ]


def test_no_dashboard_server_gives_a_note_not_an_error():
    with socket.socket() as s:  # a port nobody listens on: bind, read its number, close
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    identity = read_dashboard_identity("127.0.0.1", port, timeout=1.0)
    assert set(identity) == {"notes"}
    (note,) = identity["notes"]
    assert "failed" in note and "not known: get serial number, get robot model, PolyscopeVersion" in note


def test_stand_in_interfaces_have_no_identity():
    assert URRobot(make_profile(), receive=object()).device_identity() == {}


@pytest.mark.parametrize(
    "answers,expected",
    [
        (
            {"get serial number": "20185500001", "get robot model": "UR10e", "PolyscopeVersion": "URSoftware 5.9.4"},
            {"serial": "20185500001", "model": "UR10e", "software": "5.9.4"},
        ),
        (
            {"get serial number": "", "get robot model": "Failed to execute: get robot model"},
            {
                "notes": [
                    "the dashboard server answered 'get serial number' with ''",
                    "the dashboard server answered 'get robot model' with 'Failed to execute: get robot model'",
                    "the dashboard server did not answer 'PolyscopeVersion'",
                ]
            },
        ),
    ],
)
def test_dashboard_answers_are_parsed_or_noted(answers, expected):
    assert parse_dashboard_identity(answers) == expected


def test_a_session_on_the_fake_controller_is_recorded_as_the_unit_of_its_serial(tmp_path):
    """The whole path: real ur-rtde moves the fake's joints, the runner records the serial the dashboard told."""
    pytest.importorskip("rtde_control")
    import numpy as np

    from labcal.datasets import SessionStore
    from labcal.drivers.sim import SimRig
    from labcal.robots import load
    from labcal.sessions import make_plan, run
    from labcal.simulation import ErrorSpec, simulate

    q0 = [0.0, -1.5, 1.5, 0.0, 1.5, 0.0]
    plan = make_plan(np.array([q0, [0.05, -1.45, 1.45, 0.05, 1.55, 0.0]]), samples=1, settle=0.0, speed=0.5)
    spec = load("ur10")
    targets = np.array([[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03]])
    # The tracker is simulated (its points come from its own arm, which stands still): this test is about the unit.
    rig = SimRig(simulate(spec, ErrorSpec.none(), seed=0), targets, seed=0)
    store = SessionStore(tmp_path / "store")
    with FakeRTDEServer(q0=q0, control=True, serial="20185500777") as fake:
        robot = URRobot.connect(make_profile(fake.host, connect_timeout=2.0))
        with robot, rig.tracker() as tracker:
            summary = run(store, spec, targets, plan, robot, tracker, frame="tracker")
    assert summary.exit_status == "success" and summary.valid == 2
    meta = store.session_meta(summary.session_id)
    assert meta["metadata"]["unit"] == "20185500777"
    assert meta["robot_driver"]["identity"] == {"serial": "20185500777", "model": "UR10", "software": "5.11.0.0"}
