"""Observations: validation errors name the row, and selecting a split that has no rows is not an error."""

import numpy as np
import pytest

from labcal.calibration.observations import ObservationError, Observations, rigid_fit
from labcal.kinematics import exp_se3

TARGETS = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.15, 0.0]])


def _obs(k: int = 4) -> Observations:
    points = np.broadcast_to(TARGETS, (k, 3, 3)).copy()
    return Observations(np.zeros((k, 6)), points, TARGETS)


def test_an_empty_split_gives_an_empty_observations():
    empty = _obs().where("val")
    assert empty.k == 0 and empty.n == 6 and empty.points.shape == (0, 3, 3)


def test_non_finite_point_names_its_row():
    obs = _obs()
    points = obs.points.copy()
    points[2, 1, 0] = np.nan
    with pytest.raises(ObservationError, match="row\\) 2"):
        Observations(obs.q, points, TARGETS)


def test_collinear_targets_are_refused():
    line = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]])
    with pytest.raises(ObservationError, match="collinear"):
        Observations(np.zeros((1, 6)), line[None], line)


def test_unknown_split_names_its_row_and_value():
    with pytest.raises(ObservationError, match="row 1 is 'holdout'"):
        Observations(np.zeros((2, 6)), _obs(2).points, TARGETS, split=np.array(["train", "holdout"], object))


def test_with_splits_keeps_assigned_rows_and_is_seeded():
    obs = Observations(np.zeros((10, 6)), _obs(10).points, TARGETS, split=np.array(["test"] + [""] * 9, object))
    a, b = obs.with_splits(0.5, seed=3), obs.with_splits(0.5, seed=3)
    assert a.split[0] == "test" and list(a.split) == list(b.split)
    assert sorted(a.split[1:]).count("val") in (4, 5)


def test_rigid_fit_recovers_random_poses():
    rng = np.random.default_rng(0)
    T = exp_se3(rng.normal(size=(20, 6)))
    points = np.einsum("kab,mb->kma", T[:, :3, :3], TARGETS) + T[:, None, :3, 3]
    assert np.allclose(rigid_fit(TARGETS, points), T, atol=1e-12)
