"""SerialLink.read_line / read_exact honour a per-call timeout, longer or shorter than the link's (issue 26: a
read_line that ignored it survived the other tests). The scripted transport's clock makes this exact and instant."""

from __future__ import annotations

import pytest
from scripted_transport import ScriptedTransport

from labcal.drivers.base import DriverTimeout
from labcal.drivers.serial.link import SerialLink


def _silent_link(link_timeout: float = 0.2) -> tuple[SerialLink, ScriptedTransport]:
    t = ScriptedTransport([], read_timeout=0.05)
    return SerialLink(t, write_terminator=b"\r", read_terminator=b"\r", timeout=link_timeout, clock=t.clock), t


def _waited(t: ScriptedTransport, seconds: float) -> bool:
    """The fake clock stopped at the deadline: at most one read timeout past it (float sums land either side)."""
    return seconds - 1e-9 <= t.now <= seconds + t.read_timeout + 1e-9


@pytest.mark.parametrize("per_call", [1.0, 0.05])  # longer than the link's 0.2 s (a slow command), and shorter
def test_read_line_waits_for_its_own_timeout_not_the_links(per_call):
    link, t = _silent_link()
    with pytest.raises(DriverTimeout, match=rf"within {per_call:g} s"):
        link.read_line(timeout=per_call)
    assert _waited(t, per_call)


def test_read_line_without_a_timeout_uses_the_links():
    link, t = _silent_link(0.4)
    with pytest.raises(DriverTimeout, match=r"within 0.4 s"):
        link.read_line()
    assert _waited(t, 0.4)


def test_a_reply_arriving_after_the_link_timeout_but_within_the_per_call_one_is_read():
    link, t = _silent_link(0.2)
    arrivals = iter([b""] * 10 + list(b"OKAY\r"))  # 10 empty reads = 0.5 s of silence, then the reply
    real_read = t.read

    def slow_read(size: int = 1) -> bytes:
        item = next(arrivals, None)
        if item is None:
            return real_read(size)
        if item == b"":
            t.now += t.read_timeout
            return b""
        return bytes([item])

    t.read = slow_read
    assert link.read_line(timeout=1.0) == b"OKAY"


@pytest.mark.parametrize("per_call", [1.0, 0.05])
def test_read_exact_waits_for_its_own_timeout(per_call):
    link, t = _silent_link()
    with pytest.raises(DriverTimeout, match=rf"within {per_call:g} s: 0 of 4 bytes"):
        link.read_exact(4, timeout=per_call)
    assert _waited(t, per_call)
