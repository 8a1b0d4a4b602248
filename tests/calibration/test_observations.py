"""Observations: validation errors name the row, and selecting a split that has no rows is not an error."""

import numpy as np
import pytest

from labcal.calibration.observations import ObservationError, Observations, rigid_fit, target_geometry
from labcal.kinematics.se3 import exp_se3

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


def test_collinear_targets_are_accepted_and_measure_no_pose():
    line = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]])
    obs = Observations(np.zeros((1, 6)), line[None], line)
    assert target_geometry(line)[0] == "line" and not obs.pose_rows().any()
    assert np.isnan(obs.measured_poses()).all()


def test_target_geometry_names_point_line_and_plane():
    assert target_geometry(np.zeros((1, 3)))[0] == "point"
    assert target_geometry(np.array([[0.0, 0, 0], [0.0004, 0, 0]]))[0] == "point"  # closer than MIN_SPREAD
    kind, (_on, direction) = target_geometry(np.array([[0.0, 0, 0], [0.0, 0.2, 0]]))
    assert kind == "line" and np.allclose(np.abs(direction), [0, 1, 0])
    assert target_geometry(TARGETS)[0] == "plane"


def test_missing_targets_are_nan_rows_and_a_partly_empty_point_names_its_row_and_target():
    points = _obs(3).points.copy()
    points[1, 2] = np.nan  # t3 not seen in row 1
    obs = Observations(np.zeros((3, 6)), points, TARGETS)
    assert obs.m == 3 and obs.seen.tolist() == [[True] * 3, [True, True, False], [True] * 3]
    assert not obs.complete and not obs.seen.flags.writeable
    points = points.copy()
    points[2, 0, 1] = np.nan
    with pytest.raises(ObservationError, match=r"t1 of configuration \(row\) 2 is partly empty"):
        Observations(np.zeros((3, 6)), points, TARGETS)


def test_a_row_without_any_target_is_refused_by_row():
    points = np.full((3, 1, 3), 0.1)
    points[2] = np.nan
    with pytest.raises(ObservationError, match="row 2 has no target seen"):
        Observations(np.zeros((3, 6)), points, TARGETS[:1])


def test_measured_poses_only_where_three_non_collinear_targets_are_seen():
    rng = np.random.default_rng(1)
    four = np.vstack([TARGETS, [[0.05, 0.05, 0.1]]])
    T = exp_se3(rng.normal(size=(4, 6)))
    points = np.einsum("kab,mb->kma", T[:, :3, :3], four) + T[:, None, :3, 3]
    points[1, [0, 1]] = np.nan  # two left: no pose
    points[2, 3] = np.nan  # three left: a pose
    obs = Observations(np.zeros((4, 6)), points, four)
    assert obs.pose_rows().tolist() == [True, False, True, True]
    poses = obs.measured_poses()
    assert np.isnan(poses[1]).all()
    assert np.allclose(poses[[0, 2, 3]], T[[0, 2, 3]], atol=1e-12)


def test_unknown_split_names_its_row_and_value():
    with pytest.raises(ObservationError, match="row 1 is 'holdout'"):
        Observations(np.zeros((2, 6)), _obs(2).points, TARGETS, split=np.array(["train", "holdout"], object))


def test_with_splits_keeps_assigned_rows_and_is_seeded():
    q = np.arange(60.0).reshape(10, 6)  # ten distinct poses
    obs = Observations(q, _obs(10).points, TARGETS, split=np.array(["test"] + [""] * 9, object))
    a, b = obs.with_splits(0.5, seed=3), obs.with_splits(0.5, seed=3)
    assert a.split[0] == "test" and list(a.split) == list(b.split)
    assert sorted(a.split[1:]).count("val") in (4, 5)


def test_units_join_repeated_poses_and_groups():
    q = np.array([[0.0] * 6, [1.0] * 6, [0.0] * 6, [2.0] * 6, [3.0] * 6, [4.0] * 6])
    group = np.array(["a", "b", "c", "d", "d", "e"], dtype=object)
    obs = Observations(q, _obs(6).points, TARGETS, group=group)
    # rows 0 and 2 are one pose, rows 3 and 4 one group; numbered by first appearance
    assert obs.units().tolist() == [0, 1, 0, 2, 2, 3]
    assert obs.subset([3, 4]).group.tolist() == ["d", "d"]
    with pytest.raises(ObservationError, match="group must have shape"):
        Observations(q, _obs(6).points, TARGETS, group=group[:3])


def test_units_chain_the_fine_steps_of_a_sweep():
    # a fold that fits one step and scores the next measured interpolation (0.1 mm) where new poses were off by mm
    step = np.deg2rad(0.25)
    sweep = np.zeros((8, 6))
    sweep[:, 1] = np.arange(8) * step  # one joint, 0.25° apart: one unit
    apart = np.zeros((82, 6))
    apart[:, 2] = 0.5 + np.arange(82) * np.deg2rad(1.5)  # 1.5° apart: separate poses
    q = np.vstack([sweep, apart])
    units = Observations(q, _obs(len(q)).points, TARGETS).units()
    assert units.tolist() == [0] * 8 + list(range(1, 83))


def test_sweeps_through_one_home_pose_stay_several_units():
    # chained without a bound, 0.5° sweeps of every joint from one home pose became one unit: no folds at all, and a
    # validation split put every row in val
    step, home = np.deg2rad(0.5), np.array([0.0, -1.2, 1.0, -1.4, -1.5, 0.2])
    rows = [home + np.eye(6)[j] * step * i for j in range(6) for i in range(40)]  # each sweep starts at home
    obs = Observations(np.array(rows), _obs(len(rows)).points, TARGETS)
    units = obs.units()
    assert np.bincount(units).max() <= len(rows) // 10 and len(np.unique(units)) >= 10
    split = obs.with_splits(0.2, seed=0).split
    assert 0 < (split == "val").sum() < len(rows) // 2


def test_repeated_poses_are_never_split_across_train_and_validation():
    rng = np.random.default_rng(0)
    q = np.repeat(rng.normal(size=(8, 6)), 5, axis=0)  # eight poses measured five times each
    obs = Observations(q, _obs(40).points, TARGETS)
    for seed in range(5):
        split = obs.with_splits(0.5, seed=seed).split.reshape(8, 5)
        assert all(len(set(row)) == 1 for row in split)
        assert 2 <= np.sum(split[:, 0] == "val") <= 6


def test_rigid_fit_recovers_random_poses():
    rng = np.random.default_rng(0)
    T = exp_se3(rng.normal(size=(20, 6)))
    points = np.einsum("kab,mb->kma", T[:, :3, :3], TARGETS) + T[:, None, :3, 3]
    assert np.allclose(rigid_fit(TARGETS, points), T, atol=1e-12)
