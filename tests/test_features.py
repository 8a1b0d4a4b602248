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
    np.testing.assert_array_equal(features.get("harmonics:5").compute(q), x)
    column = features.get("harmonics:5").columns(("revolute",) * 3)[c]
    assert (column.op, column.order, column.joint) == ("sin", H, 2)


def test_prismatic_joints_map_their_stroke_onto_half_a_period():
    q = np.array([[0.3, 0.1], [0.3, 0.3]])
    x = features.harmonics(q, 2, ("revolute", "prismatic"), np.array([[-3, 3], [0.1, 0.3]]))
    theta = np.pi * (q[:, 1] - 0.1) / 0.2
    np.testing.assert_allclose(x[:, 4], np.sin(theta), atol=1e-12)
    np.testing.assert_allclose(x[:, 7], np.cos(2 * theta), atol=1e-12)
    np.testing.assert_allclose(x[:, 0], np.sin(0.3), atol=1e-12)


def test_parse_size_and_clear_errors():
    assert (features.get("harmonics:24").kind, features.get("harmonics:24").order) == ("harmonics", 24)
    assert features.get("sincos").kind == "sincos"
    assert features.is_feature("harmonics:3") and not features.is_feature("harmonics:0")
    assert features.get("harmonics:4").size(6) == 48
    with pytest.raises(ValueError, match="must be an integer, got 'x'"):
        features.get("harmonics:x")
    with pytest.raises(ValueError, match="1 … 512, got 0"):
        features.get("harmonics:0").compute(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="unknown feature 'gravitation'; known: q, sincos"):
        features.get("gravitation").compute(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="'gravity' needs the link frames"):
        features.get("gravity").compute(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="need the joint limits"):
        features.harmonics(np.zeros((1, 1)), 2, ("prismatic",))
    with pytest.raises(ValueError, match="joint 1 is prismatic with limits"):
        features.harmonics(np.zeros((1, 1)), 2, ("prismatic",), np.array([[0.2, 0.2]]))
    with pytest.raises(ValueError, match="2 entries for 1 joint values"):
        features.harmonics(np.zeros((1, 1)), 2, ("revolute", "revolute"))


NAMES = ("q", "sincos", "sincos2", "gravity", "harmonics:3")


def _evaluate_columns(cols, q, frames):
    """The Column recipes interpreted one by one with plain math: what a code generator must reproduce."""
    out = np.empty((q.shape[0], len(cols)))
    for c, col in enumerate(cols):
        if col.op == "q":
            out[:, c] = q[:, col.joint]
        elif col.op == "zero":
            out[:, c] = 0.0
        elif col.op == "gravity":
            out[:, c] = -frames[:, col.link, 2, col.axis]
        else:
            theta = q[:, col.joint]
            if col.stroke is not None:
                lo, hi = col.stroke
                theta = np.pi * (theta - lo) / (hi - lo)
            out[:, c] = (np.sin if col.op == "sin" else np.cos)(col.order * theta)
    return out


def _panda_mdh():
    """A 7-joint arm (the Franka Emika Panda's published modified DH, flange d = 0.107 m): features for n > 6."""
    from labcal.kinematics.conversions import from_mdh, trans

    a, d = (0, 0, 0, 0.0825, -0.0825, 0, 0.088), (0.333, 0, 0.316, 0, 0.384, 0, 0)
    alpha = (0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2)
    rows = [{"a": a[j], "alpha": alpha[j], "d": d[j], "theta": 0.0, "limits": [-2.8, 2.8]} for j in range(7)]
    return from_mdh(rows, trans(z=0.107))


@pytest.mark.parametrize("robot", ["ur10", "scara4", "panda-mdh"])
def test_every_registered_feature_matches_its_column_recipes_and_size(robot):
    from labcal.robots import load

    model = _panda_mdh() if robot == "panda-mdh" else load(robot).model
    rng = np.random.default_rng(1)
    q = rng.uniform(model.limits[:, 0], model.limits[:, 1], size=(9, model.n))
    frames = model.link_frames(q)
    for name in NAMES:
        feature = features.get(name)
        x = feature.compute(q, model.joint_types, model.limits, frames)
        assert x.shape == (9, feature.size(model.n))
        cols = feature.columns(model.joint_types, model.limits)
        np.testing.assert_allclose(x, _evaluate_columns(cols, q, frames), rtol=0, atol=1e-12, err_msg=name)
    together = features.compute_all(q, NAMES, model.joint_types, model.limits, frames)
    assert together.shape[1] == sum(features.get(name).size(model.n) for name in NAMES)
    assert all(features.is_feature(name) for name in NAMES) and not features.is_feature("harmonics")


def test_gravity_is_the_base_down_direction_in_each_link_frame():
    from labcal.robots import load

    model = load("ur10").model
    q = np.random.default_rng(2).uniform(-2, 2, size=(4, 6))
    frames = model.link_frames(q)
    g = features.get("gravity").compute(q, frames=frames).reshape(4, 6, 3)
    for j in range(6):
        R = frames[:, j + 1, :3, :3]
        np.testing.assert_allclose(g[:, j], np.einsum("kba,b->ka", R, [0.0, 0.0, -1.0]), atol=1e-15)


def test_module_imports_numpy_only():
    code = "import sys, labcal.features; bad = {'torch', 'scipy', 'pandas'} & set(sys.modules); print(sorted(bad))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("order", [1, 2, 32, 128])
def test_the_batch_recurrence_is_the_registry_harmonics_joint_major(order):
    rng = np.random.default_rng(order)
    edges = np.array([[0.0, np.pi / 2, -np.pi, 1e-9, 3.0, -2.9]])
    theta = np.concatenate([rng.uniform(-np.pi, np.pi, (7, 6)), edges])  # (k, n)
    x = features.harmonics_of_joints(np.cos(theta.T), np.sin(theta.T), order)  # (n, order, k) sin + i cos
    assert x.shape == (6, order, 8)
    layout = np.stack([x.real, x.imag], axis=2).reshape(6, 2 * order, 8).transpose(2, 0, 1)  # (k, n, 2·order)
    # a running product of unit complex numbers rounds about linearly in h, as the registry's sin h θ (|θ| ≤ π) does
    tol = order * np.pi * 2.3e-16 + 1e-15
    np.testing.assert_allclose(layout.reshape(8, -1), features.harmonics(theta, order), rtol=0, atol=tol)


def test_a_kind_without_a_computation_fails_loudly_instead_of_computing_another(monkeypatch):
    # a newcomer who adds a name to the registry but no branch must get an error, never sincos2 or empty columns
    monkeypatch.setattr(features, "SIMPLE", (*features.SIMPLE, "made_up"))
    features.get.cache_clear()
    try:
        made_up = features.get("made_up")
        q = np.zeros((1, 2))
        for call in (
            lambda: made_up.size(2),
            lambda: made_up.prepare(),
            lambda: made_up.columns(("revolute", "revolute")),
        ):
            with pytest.raises(ValueError, match="'made_up' has no computation"):
                call()
        with pytest.raises(ValueError, match="'made_up' has no computation"):
            features.compute_all(q, ("made_up",))
    finally:
        features.get.cache_clear()
