"""Output rate of labcal's fake UR controller (issue 25 item 8): packages per second and stamp steps per recipe.

Starts the fake (``labcal_fakes.rtde_fake``) in its own process, sets up one output recipe with a plain socket
client at each frequency, counts the data packages that arrive in a window of wall time and prints a table.
``--before SRC`` also runs the fake from another source tree (e.g. a ``git worktree`` of an older commit) in
the same way, interleaved, so the machine's load falls on both alike:

    git worktree add /tmp/before-rtde a264b60~1
    .venv/bin/python benchmarks/rtde_fake_rate.py --before /tmp/before-rtde/src --window 3

A wall-clock measurement on a shared machine: read the rate next to the load printed with it.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import socket
import statistics
import struct
import time

from labcal_fakes.rtde_fake import FakeRTDEServer, read_package


def measure(host: str, frequency: float, window: float) -> tuple[float, float, int]:
    """(packages per second, median stamp step in ms, recipe ids seen) over ``window`` s of wall time."""
    with contextlib.closing(socket.create_connection((host, 30004), timeout=5)) as sock:

        def request(kind: str, payload: bytes = b"") -> tuple[str, bytes]:
            sock.sendall(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)
            return read_package(sock)

        request("V", struct.pack(">H", 2))
        request("O", struct.pack(">d", frequency) + b"timestamp")
        request("S")
        read_package(sock)  # the first package starts the window
        start, stamps = time.monotonic(), []
        while time.monotonic() - start < window:
            kind, body = read_package(sock)
            if kind == "U":
                stamps.append(struct.unpack(">d", body[-8:])[0])
        elapsed = time.monotonic() - start
    steps = [b - a for a, b in itertools.pairwise(stamps)]
    return len(stamps) / elapsed, 1e3 * statistics.median(steps), len(stamps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="src folder of another labcal tree to run the fake from")
    parser.add_argument("--window", type=float, default=3.0, help="s of wall time per measurement")
    args = parser.parse_args()
    trees = [("after", None)] + ([("before", args.before)] if args.before else [])
    print(f"load average {os.getloadavg()[0]:.2f}; window {args.window} s")
    print(f"{'tree':<7} {'asked Hz':>8} {'packages/s':>10} {'median step ms':>14} {'packages':>8}")
    for frequency in (125.0, 500.0):
        for name, src in trees:
            saved = os.environ.get("PYTHONPATH")
            if src:  # the fake's own process imports labcal from that tree
                os.environ["PYTHONPATH"] = src
            try:
                with FakeRTDEServer() as fake:
                    rate, step, count = measure(fake.host, frequency, args.window)
            finally:
                if saved is None:
                    os.environ.pop("PYTHONPATH", None)
                else:
                    os.environ["PYTHONPATH"] = saved
            print(f"{name:<7} {frequency:>8.0f} {rate:>10.1f} {step:>14.3f} {count:>8}")


if __name__ == "__main__":
    main()
