"""Hardware tier: the same measure() against a real serial tracker. Skipped unless --tracker-port is given.

    pytest tests/drivers/test_serial_hardware.py --tracker-port /dev/ttyUSB0 \\
        [--tracker-profile drivers/ndi-polaris.toml]   # and LABCAL_TRACKER_TARGETS=path/to/targets.toml

Keep the tool with the three targets still and in view of the tracker.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from labcal.datasets.targets import pair_distances
from labcal.drivers.serial.profiles import NDIProfile, load_profile
from labcal.drivers.serial.tracker import open_tracker

pytestmark = [pytest.mark.hardware, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def device(request):
    port = request.config.getoption("--tracker-port")
    profile = request.config.getoption("--tracker-profile") or str(REPO / "drivers" / "ndi-polaris.toml")
    targets = os.environ.get("LABCAL_TRACKER_TARGETS")
    if not targets:
        pytest.skip("set LABCAL_TRACKER_TARGETS to the targets TOML file of the tool in view")
    return port, profile, targets


def test_real_tracker_measures_the_three_targets(device):
    port, profile_path, targets_path = device
    with open_tracker(profile_path, targets_path, url=port) as tracker:
        m = tracker.measure(samples=5)
        nominal = tracker.targets
    assert m.points.shape == (3, 3) and np.all(np.isfinite(m.points))
    assert m.samples == 5
    # A still tool: samples agree to well under a millimetre, and the measured triangle is the nominal one.
    assert np.all(m.spread < 0.5e-3), m.spread
    profile = load_profile(profile_path)
    tol = profile.match_tolerance if isinstance(profile, NDIProfile) else (profile.triangle_tolerance or 2e-3)
    np.testing.assert_allclose(pair_distances(m.points), pair_distances(nominal), atol=tol)


def test_real_tracker_can_be_reopened(device):
    port, profile_path, targets_path = device
    for _ in range(2):
        with open_tracker(profile_path, targets_path, url=port) as tracker:
            assert tracker.measure().points.shape == (3, 3)
