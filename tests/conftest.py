"""Shared pytest options. Hardware tests run only when a device is named on the command line.

Write them with ``=`` (``--tracker-port=/dev/ttyUSB0``) or name test files: ``--tracker-port /dev/ttyUSB0`` alone
makes pytest take the existing device for the folder to test, so this file is never loaded and the option is
"unrecognized" (tests/sessions/test_lab_e2e.py runs the README's lines against the fakes).
"""

from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("labcal hardware")
    group.addoption("--tracker-port", default=None, help="serial URL of a real tracker (e.g. /dev/ttyUSB0)")
    group.addoption(
        "--tracker-profile",
        default=None,
        help="device profile TOML for --tracker-port (default: NDI Polaris)",
    )
    group.addoption(
        "--robot-host",
        default=None,
        help="IP address of a real UR controller (read-only unless LABCAL_ALLOW_MOTION=1 is also set)",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    has_tracker = config.getoption("--tracker-port") is not None
    has_robot = config.getoption("--robot-host") is not None
    skip = pytest.mark.skip(reason="needs real hardware: pass --tracker-port or --robot-host")
    for item in items:
        if "hardware" in item.keywords:
            wants_robot = "robot" in item.keywords
            available = has_robot if wants_robot else has_tracker
            if not available:
                item.add_marker(skip)
