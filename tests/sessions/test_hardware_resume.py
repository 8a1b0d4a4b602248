"""`labcal session resume` on hardware: the drivers are reopened from the profiles the session recorded.

The UR and serial drivers themselves are tested against fakes that speak their protocols (tests/drivers); here the
driver factory is replaced by the sim rig, so what is tested is which profiles a resume opens and what it refuses.
"""

from __future__ import annotations

import pytest
from sessions_testutil import TARGETS, CountingRobot

from labcal.cli.common import UserError
from labcal.cli.ops import sessions as session_ops
from labcal.cli.ops.sessions import resume_session
from labcal.datasets import SessionStore
from labcal.robots import load
from labcal.sessions import make_plan, random_configurations, run

RECORDED = {"robot": "drivers/ur10-lab.toml", "tracker": "drivers/ndi-polaris.toml"}


@pytest.fixture
def rig():
    return session_ops._sim_rig(load("ur10"), TARGETS, {"errors": "default", "seed": 3, "noise_seed": 3})


def _paused_hardware_session(store, rig, profiles):
    """A session recorded as on hardware (profiles in its metadata, no sim settings), stopped at its fifth move."""
    spec = load("ur10")
    plan = make_plan(random_configurations(spec.model, 8, seed=3, targets=TARGETS), samples=1, settle=0.0)
    robot = CountingRobot(rig.robot(), interrupt_at=5)
    metadata = {} if profiles is None else {"profiles": profiles}
    with robot, rig.tracker() as tracker:
        first = run(store, spec, TARGETS, plan, robot, tracker, frame="base", metadata=metadata)
    assert first.exit_status == "aborted"
    return first.session_id


@pytest.fixture
def opened(monkeypatch, rig):
    calls = []

    def drivers(profile, tracker_profile, targets, *overrides):
        calls.append((str(profile), str(tracker_profile), targets.shape))
        return rig.robot(), rig.tracker()

    monkeypatch.setattr(session_ops, "_real_drivers", drivers)
    return calls


def test_a_hardware_session_resumes_on_the_profiles_it_recorded(tmp_path, rig, opened):
    store = SessionStore(tmp_path / "store")
    session = _paused_hardware_session(store, rig, RECORDED)
    resumed = resume_session(store, session)
    assert opened == [(RECORDED["robot"], RECORDED["tracker"], TARGETS.shape)]
    assert (resumed.exit_status, resumed.valid) == ("success", 8)


def test_a_profile_given_replaces_the_recorded_one(tmp_path, rig, opened):
    store = SessionStore(tmp_path / "store")
    session = _paused_hardware_session(store, rig, RECORDED)
    resume_session(store, session, tracker_profile="/moved/ndi-polaris.toml")
    assert opened == [(RECORDED["robot"], "/moved/ndi-polaris.toml", TARGETS.shape)]


def test_a_hardware_session_without_recorded_profiles_names_the_flags_it_needs(tmp_path, rig, opened):
    store = SessionStore(tmp_path / "store")
    session = _paused_hardware_session(store, rig, None)
    with pytest.raises(UserError, match="did not record its driver profiles: pass --profile and --tracker-profile"):
        resume_session(store, session)
    with pytest.raises(UserError, match=r"pass --tracker-profile$"):
        resume_session(store, session, profile="drivers/ur10-lab.toml")
    assert opened == []  # nothing was opened, so nothing moved


def test_a_sim_session_refuses_hardware_profiles(tmp_path, rig, opened):
    store = SessionStore(tmp_path / "store")
    sim = {"errors": "default", "seed": 3, "noise_seed": 3}
    spec = load("ur10")
    plan = make_plan(random_configurations(spec.model, 6, seed=3, targets=TARGETS), samples=1, settle=0.0)
    with CountingRobot(rig.robot(), interrupt_at=3) as robot, rig.tracker() as tracker:
        first = run(store, spec, TARGETS, plan, robot, tracker, frame="base", metadata={"sim": sim})
    with pytest.raises(UserError, match="recorded on the sim rig: it resumes there"):
        resume_session(store, first.session_id, profile="drivers/ur10-lab.toml")
    assert opened == []


def test_opening_the_drivers_releases_the_robot_when_the_tracker_fails(monkeypatch):
    closed = []

    class Robot:
        def close(self):
            closed.append(True)

    import labcal.drivers.serial.tracker as serial_tracker
    import labcal.drivers.ur as ur

    monkeypatch.setattr(ur, "load_ur_profile", lambda path: path)
    monkeypatch.setattr(ur.URRobot, "connect", staticmethod(lambda profile: Robot()))

    def no_tracker(profile, targets, url=None):
        raise OSError("no such serial port")

    monkeypatch.setattr(serial_tracker, "open_tracker", no_tracker)
    with pytest.raises(UserError, match=r"tracker on /dev/ttyX: no such serial port \(check --tracker-port\)"):
        session_ops._real_drivers("ur.toml", "tracker.toml", TARGETS, tracker_port="/dev/ttyX")
    assert closed == [True]


def test_the_profiles_are_recorded_as_absolute_paths(tmp_path, monkeypatch, rig, opened):
    # a relative path recorded as given would not be found by a resume started from another folder
    (tmp_path / "ur.toml").write_text("")
    (tmp_path / "tracker.toml").write_text("")
    monkeypatch.chdir(tmp_path)
    request = session_ops.SessionRequest(
        robot="ur10", targets_file="t.toml", poses=12, robot_driver="ur", tracker_driver="serial", profile="ur.toml",
        tracker_profile="tracker.toml",
    )  # fmt: skip
    *_, metadata = session_ops._drivers(request, load("ur10"), TARGETS)
    assert metadata["profiles"] == {"robot": str(tmp_path / "ur.toml"), "tracker": str(tmp_path / "tracker.toml")}
    assert opened == [("ur.toml", "tracker.toml", TARGETS.shape)]
