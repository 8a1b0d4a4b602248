"""The batched joint-series terms of a hybrid (``CalibratedRobot._linear_series``: the block-sparse slope
product and the harmonics one order at a time) and the Newton bracket, against their plain definitions: the network
itself, the dense derivative of its features, a finite difference, and ad(ξ) as a 6 × 6 matrix."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from labcal import features
from labcal.compensator.model import _bracket
from labcal.kinematics import se3
from test_compensator import _pose_error, hybrid, make_series, sample


def _series_robot(names):
    robot = hybrid("ur10", features=names)
    return dataclasses.replace(robot, network=make_series(robot.model, names, seed=2, out=2e-3))


def _slope_definition(robot, q: np.ndarray) -> np.ndarray:
    """(k, 6, n) dδρ/dq of the network's harmonics and ``q`` features (gravity's part left out, as _linear_series
    documents), as the dense product of the features' full derivative with the network's weights:
    d sin(h q_j)/dq_j = h cos(h q_j), d cos(h q_j)/dq_j = −h sin(h q_j), dq_j/dq_j = 1, every other entry 0."""
    n, network = robot.n, robot.network
    (Wt,), _ = network._folded  # δρ = x @ Wt + bias for the raw features x
    dx = np.zeros((len(q), Wt.shape[0], n))  # dx[i, c, j] = d x_c / d q_j at configuration i
    start = 0
    for name in network.features:
        feature = features.get(name)
        width = feature.size(n)
        if feature.kind == "harmonics":
            x = features.harmonics(q, feature.order)
            cols = np.arange(width)
            partner = cols + 1 - 2 * (cols % 2)  # sin ↔ cos of the same order and joint
            sign = 1 - 2 * (cols % 2)  # + for a sin column, − for a cos column
            recipes = feature.columns(("revolute",) * n)  # the order and joint of every column
            h = np.array([c.order for c in recipes])
            dx[:, start + cols, [c.joint for c in recipes]] = sign * h * x[:, partner]
        elif feature.kind == "q":
            dx[:, start + np.arange(n), np.arange(n)] = 1.0
        start += width
    return np.einsum("icj,co->ioj", dx, Wt)


@pytest.mark.parametrize("names", [("gravity", "harmonics:32"), ("harmonics:5", "gravity", "q"), ("q", "harmonics:3")])
def test_batch_series_is_the_network_and_the_dense_slope(names):
    robot = _series_robot(names)
    series = robot._linear_series
    assert series is not None  # a linear network of harmonics (+ gravity, q): the series path
    q = np.random.default_rng(4).uniform(-np.pi, np.pi, (5000, 6))  # more than one chunk of the batch form
    rho, slope = series(q, robot.model.link_frames(q))
    np.testing.assert_allclose(rho, robot.network(q, robot.model), rtol=0, atol=1e-15)
    expected = _slope_definition(robot, q)
    assert np.abs(expected).max() > 1e-4  # ten orders above the tolerance: a wrong or missing block shows
    np.testing.assert_allclose(slope, expected, rtol=0, atol=1e-14)
    if "gravity" not in names:  # without gravity the slope is the network's whole derivative
        step = 1e-6
        for j in range(6):
            dq = np.zeros(6)
            dq[j] = step
            numeric = (robot.network(q[:50] + dq, robot.model) - robot.network(q[:50] - dq, robot.model)) / (2 * step)
            np.testing.assert_allclose(slope[:50, :, j], numeric, rtol=0, atol=1e-8)


def test_batched_correct_of_a_32_harmonic_hybrid_reaches_the_nominal_pose():
    robot = _series_robot(("gravity", "harmonics:32"))
    q = sample(robot, 2500, seed=6)  # the residual's series terms come in two chunks
    q_cmd = robot.correct(q)
    assert np.max(np.abs(q_cmd - q)) > 1e-4  # a real correction
    assert np.max(_pose_error(robot, q, q_cmd)) < 1e-10  # against the plain kinematics and the network


def test_bracket_is_ad_of_each_twist_applied_to_the_later_terms():
    rng = np.random.default_rng(9)
    k, n = 40, 6
    J, dy, e = rng.normal(size=(k, 6, n)), rng.normal(size=(k, 6, n)) * 1e-3, rng.normal(size=(k, 6)) * 1e-3
    expected = np.empty((k, 6, n))
    for i in range(k):
        for col in range(n):
            v, w = J[i, :3, col], J[i, 3:, col]
            ad = np.block([[se3.skew(w), se3.skew(v)], [np.zeros((3, 3)), se3.skew(w)]])
            z = dy[i, :, col + 1 :].sum(axis=1) - 0.5 * e[i]
            expected[i, :, col] = ad @ z
    np.testing.assert_allclose(_bracket(J, dy, e), expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(_bracket(J[3], dy[3], e[3]), expected[3], rtol=0, atol=1e-15)  # one configuration
