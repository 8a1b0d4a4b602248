"""The length-scaled metric helper: weights and the scaled condition number, against their definitions."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.kinematics import metric
from labcal.robots import load


def test_weights_follow_the_definition() -> None:
    assert metric.twist_weights(4.0).tolist() == [0.25, 0.25, 0.25, 1.0, 1.0, 1.0]
    assert metric.joint_weights(("revolute", "prismatic", "revolute", "prismatic"), 3.0, size=6).tolist() == [
        1.0,
        3.0,
        1.0,
        3.0,
        1.0,
        1.0,
    ]
    assert metric.parameter_weights(2, 5.0).tolist() == [1, 1, 1, 0.2, 0.2, 0.2] * 2


def test_scaled_condition_is_the_ratio_of_extreme_singular_values_of_the_scaled_matrix() -> None:
    model = load("ur10").model
    q = np.random.default_rng(0).uniform(-2, 2, size=(20, 6))
    J = model.equivalent_jacobian(q)
    L = model.reach()
    D = np.diag(metric.twist_weights(L))
    s = np.linalg.svd(D @ J, compute_uv=False)
    np.testing.assert_array_equal(metric.scaled_condition(J, L), s[:, 0] / s[:, -1])
    # np.linalg.cond of the same matrix: the spelling it replaces, bit for bit
    np.testing.assert_array_equal(metric.scaled_condition(J, L), np.linalg.cond(D[None] @ J))


def test_scaled_condition_weights_prismatic_columns_and_flags_rank_deficiency() -> None:
    J = np.zeros((2, 6, 6))
    J[0] = np.diag([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])
    J[0, :, 1] *= 0.5  # a prismatic column: weighted by L = 2, so the scaled matrix is the identity again
    J[1] = J[0]
    J[1, :, 5] = 0.0
    types = ("revolute", "prismatic", "revolute", "revolute")
    got = metric.scaled_condition(J, 2.0, types)
    assert got[0] == pytest.approx(1.0, abs=1e-15)
    assert np.isinf(got[1])
    assert metric.scaled_condition(J[0], 2.0, types).shape == ()
