"""labcal.features: the numpy feature library the compensator runtime evaluates."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from labcal import features


def test_harmonics_match_the_direct_formula_column_by_column():
    rng = np.random.default_rng(0)
    q = rng.uniform(-6, 6, size=(7, 3))
    H = 5
    x = features.harmonics(q, H)
    assert x.shape == (7, 2 * 3 * H)
    for j in range(3):
        for h in range(1, H + 1):
            c = j * 2 * H + 2 * (h - 1)
            np.testing.assert_allclose(x[:, c], np.sin(h * q[:, j]), rtol=0, atol=1e-12)
            np.testing.assert_allclose(x[:, c + 1], np.cos(h * q[:, j]), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(features.compute(q, "harmonics:5"), x)
    assert features.harmonic_orders(H, 3)[c] == H and features.column_joints(H, 3)[c] == 2


def test_prismatic_joints_map_their_stroke_onto_half_a_period():
    q = np.array([[0.3, 0.1], [0.3, 0.3]])
    x = features.harmonics(q, 2, ("revolute", "prismatic"), np.array([[-3, 3], [0.1, 0.3]]))
    theta = np.pi * (q[:, 1] - 0.1) / 0.2
    np.testing.assert_allclose(x[:, 4], np.sin(theta), atol=1e-12)
    np.testing.assert_allclose(x[:, 7], np.cos(2 * theta), atol=1e-12)
    np.testing.assert_allclose(x[:, 0], np.sin(0.3), atol=1e-12)


def test_parse_size_and_clear_errors():
    assert features.parse("harmonics:24") == ("harmonics", 24)
    assert features.parse("sincos") is None
    assert features.is_feature("harmonics:3") and not features.is_feature("harmonics:0")
    assert features.size("harmonics:4", 6) == 48
    with pytest.raises(ValueError, match="must be an integer, got 'x'"):
        features.parse("harmonics:x")
    with pytest.raises(ValueError, match="1 … 512, got 0"):
        features.compute(np.zeros((1, 2)), "harmonics:0")
    with pytest.raises(ValueError, match="unknown feature 'gravity'"):
        features.compute(np.zeros((1, 2)), "gravity")
    with pytest.raises(ValueError, match="need the joint limits"):
        features.harmonics(np.zeros((1, 1)), 2, ("prismatic",))
    with pytest.raises(ValueError, match="joint 1 is prismatic with limits"):
        features.harmonics(np.zeros((1, 1)), 2, ("prismatic",), np.array([[0.2, 0.2]]))
    with pytest.raises(ValueError, match="2 entries for 1 joint values"):
        features.harmonics(np.zeros((1, 1)), 2, ("revolute", "revolute"))


def test_module_imports_numpy_only():
    code = "import sys, labcal.features; bad = {'torch', 'scipy', 'pandas'} & set(sys.modules); print(sorted(bad))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]"
