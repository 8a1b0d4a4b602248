"""The fake RTDE server speaks RTDE: checked byte by byte with a plain socket client (no ur-rtde involved)."""

from __future__ import annotations

import contextlib
import socket
import struct

import pytest

from labcal.testing.rtde_fake import (
    FakeRTDEServer,
    pack_values,
    read_package,
    rtde_type,
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
    for _ in range(50):
        registers = fake.snapshot()["registers"]
        if registers:
            break
    assert registers == {"input_int_register_0": 34, "input_double_register_3": 2.5}


def test_stop_is_idempotent_and_kill_closes_the_port(fake):
    host = fake.host
    fake.kill()
    assert not fake.alive
    fake.stop()
    with pytest.raises(OSError):
        socket.create_connection((host, 30004), timeout=1).close()
