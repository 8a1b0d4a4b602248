"""The fake RTDE server speaks RTDE: checked byte by byte with a plain socket client, then with ur-rtde 1.6.5 and,
where it is installed, UR's own Python RTDE client (RTDE_Python_Client_Library: not on PyPI, so usually skipped)."""

from __future__ import annotations

import contextlib
import itertools
import socket
import struct
import time

import numpy as np
import pytest

from labcal_fakes.rtde_fake import (
    FakeRTDEServer,
    SimController,
    _RTDESession,
    paced,
    pack_values,
    read_package,
    rtde_type,
    tcp_pose,
    unpack_values,
)

pytestmark = [pytest.mark.integration, pytest.mark.timeout(30)]


def request(sock: socket.socket, kind: str, payload: bytes = b"") -> tuple[str, bytes]:
    sock.sendall(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)
    return read_package(sock)


@pytest.fixture
def fake():
    server = FakeRTDEServer(q0=[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], controller_version=(5, 11, 2, 1234))
    try:
        server.start()
        yield server
    finally:
        server.stop()


@pytest.fixture
def client(fake):
    sock = socket.create_connection((fake.host, 30004), timeout=5)
    with contextlib.closing(sock):
        yield sock


def test_type_table_follows_the_rtde_guide():
    assert rtde_type("actual_q") == "VECTOR6D"
    assert rtde_type("timestamp") == "DOUBLE"
    assert rtde_type("safety_status_bits") == "UINT32"
    assert rtde_type("input_int_register_24") == "INT32"
    assert rtde_type("output_double_register_47") == "DOUBLE"
    assert rtde_type("output_int_register_48") is None
    assert rtde_type("no_such_thing") is None
    assert rtde_type("external_force_torque", "input") == "VECTOR6D"
    assert rtde_type("output_int_register_0", "input") is None, "clients cannot write output registers"
    assert rtde_type("actual_q", "input") is None
    values = [1.5, [1, 2, 3, 4, 5, 6], -7, True]
    types = ["DOUBLE", "VECTOR6D", "INT32", "BOOL"]
    assert unpack_values(types, pack_values(types, values)) == values


def test_handshake_version_and_recipe_replies(client):
    assert request(client, "V", struct.pack(">H", 2)) == ("V", b"\x01")
    assert request(client, "v") == ("v", struct.pack(">4I", 5, 11, 2, 1234))
    kind, body = request(client, "O", struct.pack(">d", 125.0) + b"timestamp,nonsense")
    assert (kind, body) == ("O", b"\x00DOUBLE,NOT_FOUND")
    kind, body = request(client, "O", struct.pack(">d", 125.0) + b"timestamp,actual_q,robot_mode,safety_status_bits")
    assert (kind, body) == ("O", b"\x01DOUBLE,VECTOR6D,INT32,UINT32")


def test_streams_data_packages_in_recipe_order(fake, client):
    request(client, "V", struct.pack(">H", 2))
    request(client, "O", struct.pack(">d", 500.0) + b"timestamp,actual_q,robot_mode,safety_status_bits")
    assert request(client, "S") == ("S", b"\x01")
    fake.set_safety(protective=True)
    fake.set_q([1, 2, 3, 4, 5, 6])
    types = ["DOUBLE", "VECTOR6D", "INT32", "UINT32"]
    stamps = []
    for _ in range(400):  # skip packages sent before the change took effect
        kind, body = read_package(client)
        assert kind == "U" and body[0] == 1
        timestamp, q, mode, bits = unpack_values(types, body[1:])
        stamps.append(timestamp)
        if q == [1, 2, 3, 4, 5, 6]:
            break
    assert q == [1, 2, 3, 4, 5, 6]
    assert mode == 7
    assert bits & (1 << 2), "protective stop bit (2) of safety_status_bits"
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)


def test_pause_answers_and_stops_streaming(client):
    request(client, "V", struct.pack(">H", 2))
    request(client, "O", struct.pack(">d", 500.0) + b"timestamp")
    request(client, "S")
    client.settimeout(2.0)
    kind, body = request(client, "P")
    while kind == "U":  # data packages sent before the pause may precede its answer
        kind, body = read_package(client)
    assert (kind, body) == ("P", b"\x01")
    client.settimeout(0.3)
    with pytest.raises(TimeoutError):
        read_package(client)


def test_input_recipe_writes_registers(fake, client):
    request(client, "V", struct.pack(">H", 2))
    kind, body = request(client, "I", b"input_int_register_0,input_double_register_3")
    assert (kind, body) == ("I", b"\x01INT32,DOUBLE")
    client.sendall(struct.pack(">HB", 3 + 1 + 12, ord("U")) + b"\x01" + struct.pack(">id", 34, 2.5))
    # The fake applies the package on its own thread: wait for it (a fixed count of polls raced under load).
    deadline = time.monotonic() + 10.0
    while not (registers := fake.snapshot()["registers"]) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert registers == {"input_int_register_0": 34, "input_double_register_3": 2.5}


def test_stop_is_idempotent_and_kill_closes_the_port(fake):
    host = fake.host
    fake.kill()
    assert not fake.alive
    fake.stop()
    with pytest.raises(OSError):
        socket.create_connection((host, 30004), timeout=1).close()


# --------------------------------------------------------------------------------------------------------------
# The fake behaves like a controller on the points UR's own RTDE client found (issue 25, item 8).

# The standard output fields of the RTDE guide (e-Series 5.x) with their types, besides the numbered registers.
GUIDE_OUTPUTS = {
    **dict.fromkeys(
        "target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
        "actual_current_window joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force "
        "target_TCP_pose target_TCP_speed joint_temperatures actual_joint_voltage payload_inertia ft_raw_wrench "
        "tcp_offset".split(),
        "VECTOR6D",
    ),
    **dict.fromkeys(
        "timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum actual_main_voltage "
        "actual_robot_voltage actual_robot_current standard_analog_input0 standard_analog_input1 "
        "standard_analog_output0 standard_analog_output1 io_current euromap67_24V_voltage euromap67_24V_current "
        "tool_analog_input0 tool_analog_input1 tool_output_current tool_temperature tcp_force_scalar payload "
        "joint_position_deviation_ratio collision_detection_ratio".split(),
        "DOUBLE",
    ),
    **dict.fromkeys(
        "runtime_state robot_status_bits safety_status_bits analog_io_types euromap67_input_bits "
        "euromap67_output_bits tool_mode tool_analog_input_types script_control_line output_bit_registers0_to_31 "
        "output_bit_registers32_to_63 input_bit_registers0_to_31 input_bit_registers32_to_63".split(),
        "UINT32",
    ),
    **dict.fromkeys("tool_output_mode tool_digital_output0_mode tool_digital_output1_mode".split(), "UINT8"),
    **dict.fromkeys("actual_tool_accelerometer payload_cog elbow_position elbow_velocity".split(), "VECTOR3D"),
    "actual_digital_input_bits": "UINT64",
    "actual_digital_output_bits": "UINT64",
    "robot_mode": "INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "tool_output_voltage": "INT32",
    "time_scale_source": "INT32",
    "joint_mode": "VECTOR6INT32",
}


def setup_outputs(sock: socket.socket, names: list[str], frequency: float = 125.0) -> tuple[int, list[str]]:
    kind, body = request(sock, "O", struct.pack(">d", frequency) + ",".join(names).encode())
    assert kind == "O"
    return body[0], body[1:].decode().split(",")


def read_data(sock: socket.socket) -> bytes:
    kind, body = read_package(sock)
    while kind != "U":  # a text message may come first
        kind, body = read_package(sock)
    return body


def test_paced_deadlines_do_not_drift_when_every_sleep_oversleeps():
    """125 Hz for a simulated second although each sleep wakes 0.4 ms late and each package costs 0.1 ms."""
    now = [0.0]

    def clock() -> float:
        return now[0]

    def sleep(seconds: float) -> None:
        now[0] += seconds + 0.0004

    sent = 0
    for deadline in paced(0.008, 0.0, clock, sleep):
        if clock() >= 1.0:
            break
        assert clock() >= deadline, "a package left before its deadline"
        now[0] += 0.0001
        sent += 1
    assert sent == 125


def test_paced_catches_up_a_short_stall_and_skips_a_long_one():
    now = [0.0]
    schedule = paced(0.01, 0.0, lambda: now[0], lambda s: now.__setitem__(0, now[0] + s), max_lag=0.25)
    assert [next(schedule) for _ in range(3)] == pytest.approx([0.0, 0.01, 0.02])
    now[0] = 0.1  # a 75 ms stall: the overdue packages still go out, one per deadline
    assert [next(schedule) for _ in range(8)] == pytest.approx([0.03 + 0.01 * i for i in range(8)])
    now[0] = 5.0  # a stalled process: no flood of stale packages, the schedule resumes at the latest deadline
    assert next(schedule) == pytest.approx(5.0)
    assert next(schedule) == pytest.approx(5.01)


@pytest.mark.parametrize(("frequency", "step"), [(125.0, 0.008), (50.0, 0.02)])
def test_stream_timestamps_advance_by_one_output_period(fake, client, frequency, step):
    """The stamps are controller ticks: consecutive packages differ by exactly 1/frequency (no sleep drift).

    A package the fake could not send in time may be skipped on a loaded machine, so gaps must be whole periods.
    """
    request(client, "V", struct.pack(">H", 2))
    setup_outputs(client, ["timestamp"], frequency)
    request(client, "S")
    stamps = [unpack_values(["DOUBLE"], read_data(client)[1:])[0] for _ in range(40)]
    steps = [b - a for a, b in itertools.pairwise(stamps)]
    periods = [s / step for s in steps]
    assert all(abs(p - round(p)) < 1e-6 and round(p) >= 1 for p in periods), steps
    assert sum(round(p) == 1 for p in periods) >= 0.9 * len(periods), steps


def test_every_standard_output_of_the_rtde_guide_is_known_with_plausible_values(fake, client):
    request(client, "V", struct.pack(">H", 2))
    names = list(GUIDE_OUTPUTS)
    recipe, types = setup_outputs(client, names)
    assert recipe == 1
    assert dict(zip(names, types, strict=True)) == GUIDE_OUTPUTS
    request(client, "S")
    values = dict(zip(names, unpack_values(types, read_data(client)[1:]), strict=True))
    assert values["actual_q"] == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    assert 40.0 < values["actual_main_voltage"] < 50.0 and 40.0 < values["actual_robot_voltage"] < 50.0
    assert all(20.0 < t < 60.0 for t in values["joint_temperatures"]), "degC of a running arm"
    assert values["tool_mode"] == 253 and values["joint_mode"] == [253] * 6
    # UR10 at q1 = 0.2 rad: the elbow sits 0.612 m from the shoulder (z 0.1273 m above the base)
    x, y, z = values["elbow_position"]
    assert ((x**2 + y**2) + (z - 0.1273) ** 2) ** 0.5 == pytest.approx(0.612, abs=1e-6)
    assert values["elbow_velocity"] == pytest.approx([0.0, 0.0, 0.0])
    assert values["actual_TCP_pose"] == pytest.approx(tcp_pose([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], "UR10"))
    assert values["target_TCP_pose"] == pytest.approx(values["actual_TCP_pose"]), "at rest the target is reached"


def test_tcp_pose_is_the_ur10_dh_forward_kinematics_with_a_rotation_vector():
    """actual_TCP_pose against the tests' reference DH product of the shipped UR10 file (an independent route)."""
    import sys
    import tomllib
    from importlib import resources
    from pathlib import Path

    from scipy.spatial.transform import Rotation

    sys.path.insert(0, str(Path(__file__).parents[1] / "kinematics"))
    from kin_testutil import dh_product

    rows = tomllib.loads(resources.files("labcal.robots").joinpath("ur10.toml").read_text())["joints"]
    rng = np.random.default_rng(4)
    configurations = [*rng.uniform(-np.pi, np.pi, size=(20, 6)), [0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0]]
    for q in configurations:
        T = dh_product(rows, np.asarray(q))
        pose = tcp_pose(list(q), "UR10")
        assert pose[:3] == pytest.approx(T[:3, 3], abs=1e-12)
        assert np.linalg.norm(pose[3:]) <= np.pi + 1e-12
        assert Rotation.from_rotvec(pose[3:]).as_matrix() == pytest.approx(T[:3, :3], abs=1e-9)
    upright = tcp_pose([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0], "UR10")
    assert np.linalg.norm(upright[3:]) == pytest.approx(np.pi), "the last configuration is the half-turn edge case"


def test_register_ranges_follow_the_rtde_guide(client):
    for direction in ("input", "output"):
        assert rtde_type(f"{direction}_bit_register_64", direction) == "BOOL"
        assert rtde_type(f"{direction}_bit_register_127", direction) == "BOOL"
        assert rtde_type(f"{direction}_bit_register_63", direction) is None, "bits 0..63 are the UINT32 words"
        assert rtde_type(f"{direction}_bit_register_128", direction) is None
        assert rtde_type(f"{direction}_bit_registers0_to_31", direction) == "UINT32"
        for kind, name in (("int", "INT32"), ("double", "DOUBLE")):
            assert rtde_type(f"{direction}_{kind}_register_0", direction) == name
            assert rtde_type(f"{direction}_{kind}_register_47", direction) == name
            assert rtde_type(f"{direction}_{kind}_register_48", direction) is None
    assert rtde_type("input_bit_register_100") == "BOOL", "outputs may read input registers back"
    assert rtde_type("output_bit_register_100", "input") is None
    request(client, "V", struct.pack(">H", 2))
    assert setup_outputs(client, ["output_bit_register_64", "output_bit_register_0"]) == (0, ["BOOL", "NOT_FOUND"])
    kind, body = request(client, "I", b"input_bit_register_127,input_bit_register_5")
    assert (kind, body) == ("I", b"\x00BOOL,NOT_FOUND")


def test_an_input_field_another_client_owns_is_answered_in_use(fake):
    with contextlib.ExitStack() as stack:
        first, second = (
            stack.enter_context(contextlib.closing(socket.create_connection((fake.host, 30004), timeout=5)))
            for _ in range(2)
        )
        for sock in (first, second):
            request(sock, "V", struct.pack(">H", 2))
        assert request(first, "I", b"input_int_register_24,input_double_register_24") == ("I", b"\x01INT32,DOUBLE")
        # the owner may name its field again in another recipe (ur-rtde's control interface does)
        assert request(first, "I", b"input_int_register_24,input_int_register_25") == ("I", b"\x02INT32,INT32")
        kind, body = request(second, "I", b"input_double_register_30,input_int_register_24")
        assert (kind, body) == ("I", b"\x00DOUBLE,IN_USE")
        assert request(second, "I", b"input_double_register_30") == ("I", b"\x01DOUBLE"), "a free field still works"
        first.close()  # a client that goes away frees its fields at once, as a reconnecting driver needs
        assert request(second, "I", b"input_int_register_24") == ("I", b"\x02INT32")


def test_a_session_sees_its_client_gone_before_its_reader_thread_does():
    """The IN_USE check peeks at the owner's socket, so a client restarted right away gets its fields back."""
    server_end, client_end = socket.socketpair()
    with contextlib.closing(server_end):
        session = _RTDESession(server_end, SimController([0.0] * 6, (5, 11, 0, 0)))
        assert not session.gone()
        client_end.sendall(b"\x00\x03V")  # unread data: still there
        assert not session.gone()
        client_end.close()
        assert server_end.recv(3) == b"\x00\x03V"
        assert session.gone()


def test_only_the_last_output_recipe_streams_under_its_id(client):
    request(client, "V", struct.pack(">H", 2))
    assert setup_outputs(client, ["timestamp", "actual_q"])[0] == 1
    assert setup_outputs(client, ["robot_mode", "timestamp"])[0] == 2
    assert request(client, "S") == ("S", b"\x01")
    bodies = [read_data(client) for _ in range(20)]
    assert {body[0] for body in bodies} == {2}
    assert {len(body) for body in bodies} == {1 + 4 + 8}, "recipe 2 only: INT32 + DOUBLE"


def test_protocol_version_1_carries_no_recipe_ids(client):
    """A client that negotiates version 1 sends no frequency and gets neither recipe ids nor ids in the data."""
    assert request(client, "V", struct.pack(">H", 1)) == ("V", b"\x01")
    assert request(client, "O", b"timestamp,robot_mode") == ("O", b"DOUBLE,INT32")
    request(client, "S")
    bodies = [read_data(client) for _ in range(5)]
    assert {len(body) for body in bodies} == {8 + 4}
    stamps = [unpack_values(["DOUBLE", "INT32"], body)[0] for body in bodies]
    assert [round((b - a) / 0.008, 6) for a, b in itertools.pairwise(stamps)] == [1.0] * 4, "125 Hz in version 1"


def test_ur_rtde_receives_its_full_default_recipe_without_not_found(fake):
    """ur-rtde 1.6.5 with no variable list subscribes every output it knows for the controller version."""
    rtde_receive = pytest.importorskip("rtde_receive")
    receive = rtde_receive.RTDEReceiveInterface(fake.host, 125.0, [])
    try:
        assert receive.getActualQ() == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
        assert receive.getActualMainVoltage() == pytest.approx(48.0)
        log = fake.snapshot()["log"]
    finally:
        receive.disconnect()
    setups = [entry[1] for entry in log if entry[0] == "setup_outputs"]
    assert len(setups) == 1 and setups[0]["recipe"] == 1 and len(setups[0]["names"]) > 40
    assert not [entry for entry in log if entry[0] == "not_found"]


def _official_client():
    """UR's own Python RTDE client (RTDE_Python_Client_Library, module ``rtde``): not on PyPI, so usually absent."""
    module = pytest.importorskip("rtde.rtde", reason="UR's RTDE_Python_Client_Library is not installed")
    if not hasattr(module, "RTDE") or not hasattr(module.RTDE, "send_output_setup"):
        pytest.skip("an `rtde` module that is not UR's client")
    return module


def test_official_client_reads_every_standard_output_and_one_recipe(fake):
    rtde = _official_client()
    con = rtde.RTDE(fake.host)
    con.connect()
    try:
        assert con.get_controller_version() == (5, 11, 2, 1234)
        assert con.send_output_setup(list(GUIDE_OUTPUTS), frequency=125)
        assert con.send_output_setup(["timestamp", "actual_q"], frequency=125)  # replaces the first recipe
        assert con.send_start()
        states = [con.receive() for _ in range(10)]
        assert all(state.actual_q == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5, 0.6]) for state in states)
        assert con.send_pause()
    finally:
        con.disconnect()


def test_official_client_is_told_in_use(fake):
    rtde = _official_client()
    owner, other = rtde.RTDE(fake.host), rtde.RTDE(fake.host)
    owner.connect()
    other.connect()
    try:
        assert owner.send_input_setup(["input_int_register_24"]).recipe_id == 1
        with pytest.raises(ValueError, match="in use"):
            other.send_input_setup(["input_int_register_24"])
    finally:
        owner.disconnect()
        other.disconnect()
