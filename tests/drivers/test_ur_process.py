"""ur-rtde in a child process (labcal.drivers.ur_process): what hung or crashed labcal before is now a bounded,
mapped error. Real ur-rtde 1.6.5 against a silent listener and the fake controller (other processes)."""

from __future__ import annotations

import contextlib
import os
import socket
import threading
from pathlib import Path

import pytest
from ur_fixtures import make_profile

from labcal.drivers import ur
from labcal.drivers.base import ConnectionFailed, StaleData
from labcal.drivers.ur import URRobot, load_ur_profile
from labcal.drivers.ur_process import RemoteInterface
from labcal_fakes.rtde_fake import FakeRTDEServer, candidate_hosts

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]


def children() -> list[int]:
    """Pids of this process's live ur-rtde children."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
            if int(fields[1]) == os.getpid() and fields[0] != "Z" and b"labcal.drivers.ur_process" in cmdline:
                found.append(int(stat.parent.name))
    return found


@pytest.fixture
def silent_host():
    """A listener on port 30004 that accepts and never answers (ur-rtde's constructor hangs on it forever)."""
    for host in candidate_hosts((os.getpid() * 53) % 60000):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, 30004))
        except OSError:
            sock.close()
            continue
        sock.listen(4)
        yield host
        sock.close()
        return
    pytest.skip("no free loopback address")


def test_a_peer_that_never_answers_costs_the_construct_timeout_not_a_hang(monkeypatch, silent_host):
    monkeypatch.setattr(ur, "CONSTRUCT_TIMEOUT", 1.0)
    with pytest.raises(ConnectionFailed, match=r"RTDE receive interface .* no answer within 1.0 s"):
        URRobot.connect(make_profile(silent_host), read_only=True, probe=False)  # probe=False: straight to ur-rtde
    assert children() == []  # the hung constructor's process is gone


def test_a_dead_interface_process_is_a_connection_failure_not_a_crash():
    with FakeRTDEServer() as fake:
        robot = URRobot.connect(make_profile(fake.host, stale_timeout=0.3), read_only=True)
        assert robot.state().ready
        receive = robot._receive
        assert isinstance(receive, RemoteInterface) and len(children()) == 1
        os.kill(receive._process.pid, 11)  # what ur-rtde did to labcal itself after a dropped link: SIGSEGV
        with pytest.raises(ConnectionFailed, match=f"lost the RTDE connection to {fake.host}"):
            robot.state()
        assert receive.isConnected() is False
        robot.close()
    assert children() == []


def test_a_controller_whose_clock_stops_mid_move_is_abandoned_by_the_watchdog():
    with FakeRTDEServer(control=True) as fake:
        robot = URRobot.connect(make_profile(fake.host, watchdog_timeout=0.3, connect_timeout=2.0))
        target = robot.state().q + 0.3  # 3 s at 0.1 rad/s: the clock stops long before the move would end
        timer = threading.Timer(0.5, fake.freeze_timestamp)
        timer.start()
        with pytest.raises(StaleData, match=r"silent during a move: .*watchdog 0.3 s"):
            robot.move_joints(target, speed=0.1, acceleration=1.0)
        timer.join()
        assert not robot._control.alive  # abandoned, not waited for
        robot.stop()  # the control interface is gone: the program is stopped through the dashboard
        assert ["dashboard", "stop"] in fake.snapshot()["log"]
        robot.close()
    assert children() == []


def test_the_watchdog_settings_are_checked_in_the_profile(tmp_path):
    text = (Path(__file__).resolve().parents[2] / "drivers" / "ur10-lab.toml").read_text()
    bad = tmp_path / "ur.toml"
    bad.write_text(text.replace("watchdog_timeout_s = 1.0", "watchdog_timeout_s = 30.0"))
    with pytest.raises(ValueError, match=r"watchdog_timeout_s.*must be within \[0.05, 4.0\]"):
        load_ur_profile(bad)


def test_a_control_interface_that_cannot_be_built_leaves_no_receive_process_behind():
    # connect() builds the receive interface first; when the control one then fails, the receive interface's own
    # process must end too (disconnect() alone leaves it waiting for calls until labcal itself exits).
    def failing_control(host: str, frequency: float):
        raise RuntimeError(f"Could not connect to: {host} at 30004")

    with FakeRTDEServer() as fake:
        with pytest.raises(ConnectionFailed, match="Could not connect"):
            URRobot.connect(make_profile(fake.host), probe=False, control_factory=failing_control)
        assert children() == []


def test_a_call_interrupted_just_after_it_was_sent_never_hands_its_answer_to_the_next_call():
    # Ctrl-C can land between sending a request and waiting for its answer; the answer still comes, and a later
    # call (stopJ on the way out, a getter) would take it for its own. The interface must be given up instead.
    class InterruptedAfterFlush:
        def __init__(self, stream):
            self.stream = stream

        def write(self, data):
            return self.stream.write(data)

        def flush(self):
            self.stream.flush()  # the request has left
            raise KeyboardInterrupt

        def close(self):
            self.stream.close()

    with FakeRTDEServer() as fake:
        rx = RemoteInterface("receive", fake.host, -1.0, ["timestamp", "actual_q"], start_timeout=10.0)
        try:
            stdin = rx._process.stdin
            rx._process.stdin = InterruptedAfterFlush(stdin)
            with pytest.raises(KeyboardInterrupt):
                rx.getActualQ()
            rx._process.stdin = stdin
            with pytest.raises(RuntimeError, match="interface is gone"):
                rx.getTimestamp()  # not getActualQ's list of six
            assert not rx.alive and children() == []
        finally:
            rx.kill()
