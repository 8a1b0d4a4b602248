"""The stubs used by test_ur_driver.py must look like ur-rtde 1.6.5: same method names, same parameters.

pybind11 methods have no inspect.signature, so the real parameter lists come from the first line(s) of each
method's ``__doc__`` (one line per overload).
"""

from __future__ import annotations

import inspect

import pytest
from ur_fixtures import CONTROL_METHODS, RECEIVE_METHODS, StubControl, StubReceive

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")


def parse_pybind_signatures(doc: str, name: str) -> list[tuple[str, list[str]]]:
    """Parameter names of each signature line ``name(self: T, a: float = 1.0, ...) -> R`` in a pybind11 doc.

    Overloaded functions list numbered lines ``1. name(...)``; a plain one has its signature on line one.
    """
    signatures = []
    for raw in doc.splitlines():
        line = raw.strip()
        if line[:1].isdigit() and ". " in line:
            line = line.split(". ", 1)[1]
        if not line.startswith(name + "(") or line.startswith(name + "(*args"):
            continue
        inner = line[len(name) + 1 : line.rindex(")")] if ")" in line else ""
        params = [p.split(":")[0].split("=")[0].strip() for p in _split_params(inner)]
        signatures.append((name, [p for p in params if p and p != "self"]))
    return signatures


def _split_params(text: str) -> list[str]:
    """Split a parameter list on top-level commas (defaults and annotations may contain brackets)."""
    parts, depth, current = [], 0, []
    for ch in text:
        if ch in "[(<{":
            depth += 1
        elif ch in "])>}":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append("".join(current))
            current = []
        else:
            current.append(ch)
    if current:
        parts.append("".join(current))
    return parts


def stub_params(cls: type, name: str) -> list[str]:
    return [p for p in inspect.signature(getattr(cls, name)).parameters if p != "self"]


def public_methods(cls: type) -> set[str]:
    return {n for n, v in vars(cls).items() if callable(v) and not n.startswith("_")}


def test_parser_reads_plain_and_overloaded_pybind_docs():
    doc = (
        "moveJ(*args, **kwargs)\nOverloaded function.\n\n"
        "1. moveJ(self: X, path: list[list[float]], asynchronous: bool = False) -> bool\n\ntext\n\n"
        "2. moveJ(self: X, q: list[float], speed: float = 1.05, flags: int = <Flags.A: 1>) -> bool\n"
    )
    assert parse_pybind_signatures(doc, "moveJ") == [
        ("moveJ", ["path", "asynchronous"]),
        ("moveJ", ["q", "speed", "flags"]),
    ]
    assert parse_pybind_signatures("getActualQ(self: X) -> list[float]\n", "getActualQ") == [("getActualQ", [])]


@pytest.mark.parametrize(
    ("stub", "real", "names"),
    [
        (StubReceive, rtde_receive.RTDEReceiveInterface, RECEIVE_METHODS),
        (StubControl, rtde_control.RTDEControlInterface, CONTROL_METHODS),
    ],
    ids=["receive", "control"],
)
def test_stub_methods_match_real_names_and_parameters(stub, real, names):
    assert public_methods(stub) == set(names), "the stub must offer exactly the methods labcal calls"
    for name in names:
        real_overloads = parse_pybind_signatures(getattr(real, name).__doc__ or "", name)
        assert real_overloads, f"{real.__name__}.{name} has no parseable signature in its __doc__"
        assert stub_params(stub, name) in [params for _, params in real_overloads], (
            f"{stub.__name__}.{name}{stub_params(stub, name)} matches no overload of the real {name}: {real_overloads}"
        )


def test_constructor_parameters_labcal_passes_positionally():
    receive = parse_pybind_signatures(rtde_receive.RTDEReceiveInterface.__init__.__doc__, "__init__")
    control = parse_pybind_signatures(rtde_control.RTDEControlInterface.__init__.__doc__, "__init__")
    # _real_receive passes (host, frequency, variables); _real_control passes (host, frequency).
    assert receive[0][1][:3] == ["hostname", "frequency", "variables"]
    assert control[0][1][:2] == ["hostname", "frequency"]
