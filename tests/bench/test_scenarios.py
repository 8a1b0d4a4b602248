"""Each adversarial generator has the property its name claims, is seeded, and measures what its robot does."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

import scenarios as S
from labcal.robots import load
from labcal.robots.joint_map import JointMap


def _sides(points: np.ndarray) -> np.ndarray:
    """(…, 3) distances t1-t2, t1-t3, t2-t3 of (…, 3, 3) points."""
    p = np.asarray(points)
    return np.stack(
        [np.linalg.norm(p[..., 0, :] - p[..., 1, :], axis=-1),
         np.linalg.norm(p[..., 0, :] - p[..., 2, :], axis=-1),
         np.linalg.norm(p[..., 1, :] - p[..., 2, :], axis=-1)], axis=-1,
    )  # fmt: skip


def _noise_only(scn) -> float:
    """Largest |measured − true| coordinate (m) for a base-frame scenario made by its actual robot."""
    return float(np.abs(scn.points - scn.actual.true_points(scn.q, scn.targets)).max())


NOISE = S.ErrorSpec.default().tracker_noise  # 0.05 mm per coordinate
WRIST = 4  # q5: the joint whose zero is singular on the 6R built-ins (S.wrist_joint)


@pytest.fixture(scope="module")
def base():
    return S.good("ur10", 30, seed=3)


@pytest.mark.parametrize(
    "make",
    [
        lambda s: S.good("ur10", 12, seed=s),
        lambda s: S.sweeps("ur10", 20, 4, seed=s),
        lambda s: S.singular_wrist("fanuc-m1000ia", 15, seed=s),
        lambda s: S.coupled_elbow("ur10", 10, seed=s),
    ],
)
def test_same_seed_same_data_and_another_seed_other_data(make):
    a, b, c = make(1), make(1), make(2)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.points, b.points)
    assert not np.allclose(a.q, c.q) and not np.allclose(a.points, c.points)


def test_good_is_nonsingular_and_measured_by_its_robot(base):
    model = load("ur10").model
    assert base.q.shape == (30, 6) and base.points.shape == (30, 3, 3) and base.frame == "base"
    assert np.all(S.condition(model, base.q) <= S.MAX_CONDITION)
    assert _noise_only(base) < 6 * NOISE
    assert np.allclose(_sides(base.points), _sides(base.targets), atol=6 * NOISE * 2)


@pytest.mark.parametrize("robot", ["ur10", "fanuc-m1000ia"])
def test_sweeps_move_one_joint_per_group_and_keep_the_wrist_singular(robot):
    scn = S.sweeps(robot, 30, 4, seed=5)
    assert scn.k == 30 and scn.group is not None and scn.group.shape == (30,)
    groups = np.unique(scn.group)
    assert len(groups) == 8  # 7 sweeps of 4 and a last one of 2
    moved = []
    for g in groups:
        block = scn.q[scn.group == g]
        varying = np.flatnonzero(np.ptp(block, axis=0) > 0)
        assert len(varying) == 1, f"sweep {g} moves joints {varying.tolist()}"
        assert len(np.unique(block[:, varying[0]])) == len(block)  # a few distinct poses, not repeats
        moved.append(int(varying[0]))
    assert moved == [g % 6 for g in range(8)]  # every joint gets a sweep
    singular = np.abs(scn.q[:, WRIST]) < S.WRIST_TOL
    assert singular.mean() > 0.5
    assert np.all(singular[scn.group % 6 != WRIST])  # only q5's own sweeps leave the singularity
    assert np.all(S.condition(load(robot).model, scn.q[singular]) > 1e3)  # and they really are singular
    assert _noise_only(scn) < 6 * NOISE


def test_sweeps_without_singular_wrist_leave_q5_free():
    scn = S.sweeps("ur10", 24, 4, singular_wrist=False, seed=0)
    assert np.mean(np.abs(scn.q[:, WRIST]) < S.WRIST_TOL) < 0.2


def test_singular_wrist_has_the_requested_fraction_of_singular_rows():
    scn = S.singular_wrist("ur10", 40, fraction=0.8, seed=1)
    singular = np.abs(scn.q[:, WRIST]) < S.WRIST_TOL
    assert singular.sum() == 32
    cond = S.condition(load("ur10").model, scn.q)
    assert np.all(cond[singular] > 1e3) and np.all(cond[~singular] <= S.MAX_CONDITION)
    assert _noise_only(scn) < 6 * NOISE


def test_coupled_elbow_controller_joints_map_back_to_model_joints():
    scn = S.coupled_elbow("ur10", 20, seed=2)
    qc = scn.q_controller
    assert qc is not None and scn.joint_map is not None
    assert np.allclose(qc[:, 1] + qc[:, 2], scn.q[:, 2], atol=1e-12)  # model elbow = J2 + J3
    assert np.allclose(np.delete(qc, 2, axis=1), np.delete(scn.q, 2, axis=1), atol=1e-12)
    assert not np.allclose(qc[:, 2], scn.q[:, 2])  # the unconverted joints really are different
    assert np.allclose(JointMap(scn.joint_map, np.zeros(6)).to_model(qc), scn.q, atol=1e-12)
    assert _noise_only(scn) < 6 * NOISE  # the points belong to the model joints


def test_identical_poses_repeat_one_configuration():
    scn = S.identical_poses("ur10", 60, seed=0)
    assert scn.k == 60 and np.all(scn.q == scn.q[0]) and np.all(scn.group == 0)
    spread = np.ptp(scn.points, axis=0).max()
    assert 0 < spread < 12 * NOISE  # only the tracker noise differs


def test_few_poses_has_k_rows():
    assert S.few_poses("ur10", 10, seed=0).k == 10


@pytest.mark.parametrize("factor", [1000.0, 0.001, S.INCH])
def test_unit_slip_scales_the_measured_triangle(base, factor):
    bad = S.unit_slip(base, factor)
    ratio = _sides(bad.points) / _sides(base.targets)
    assert np.allclose(ratio, factor, rtol=1e-2)
    assert np.array_equal(bad.q, base.q) and np.array_equal(bad.targets, base.targets)


def test_degrees_as_radians_converts_the_joints(base):
    bad = S.degrees_as_radians(base)
    assert np.allclose(bad.q, base.q * 180 / np.pi)
    assert np.abs(bad.q).max() > 2 * np.pi  # outside any revolute range
    scn = S.degrees_as_radians(S.coupled_elbow("ur10", 5, seed=0))
    assert scn.q_controller is not None and np.abs(scn.q_controller).max() > np.pi


def test_swapped_targets_exchanges_two_columns(base):
    bad = S.swapped_targets(base, 0, 1)
    assert np.array_equal(bad.points[:, 0], base.points[:, 1]) and np.array_equal(bad.points[:, 1], base.points[:, 0])
    sides, expected = _sides(bad.points).mean(axis=0), _sides(base.targets)
    assert abs(sides[0] - expected[0]) < 1e-3  # t1-t2 keeps its length …
    assert abs(sides[1] - expected[2]) < 1e-3 and abs(sides[1] - expected[1]) > 0.03  # … the others trade places


def test_wrong_targets_change_the_triangle(base):
    bad = S.wrong_targets(base)
    assert np.array_equal(bad.points, base.points)
    assert np.allclose(_sides(bad.targets), 0.7 * _sides(base.targets))


def test_pure_noise_is_unrelated_to_the_robot(base):
    noise = S.pure_noise(base, seed=1)
    assert noise.actual is None
    assert np.abs(_sides(noise.points) - _sides(base.targets)).max() > 0.05  # the triangle is broken
    rigid = S.pure_noise(base, rigid=True, seed=1)
    assert np.allclose(_sides(rigid.points), _sides(base.targets), atol=1e-9)  # every row a valid triangle …
    far = np.linalg.norm(rigid.points - base.points, axis=-1).mean(axis=1)
    assert np.median(far) > 0.1  # … at a pose the joints do not explain


def test_shuffled_rows_pair_points_with_other_joints(base):
    bad = S.shuffled_rows(base, seed=0)
    assert np.array_equal(np.sort(bad.points.reshape(30, -1), axis=0), np.sort(base.points.reshape(30, -1), axis=0))
    assert np.mean(np.any(bad.points != base.points, axis=(1, 2))) > 0.8


def test_in_tracker_frame_is_a_known_rigid_offset_out_of_reach(base):
    scn = S.in_tracker_frame(base)
    T = scn.T_tracker_base
    assert scn.frame == "tracker" and T is not None
    back = np.einsum("ba,kmb->kma", T[:3, :3], scn.points - T[:3, 3])
    assert np.allclose(back, base.points, atol=1e-12)
    assert np.linalg.norm(scn.points, axis=-1).min() > load("ur10").model.reach()  # read as base: out of reach


def test_subset_keeps_rows_aligned():
    scn = S.sweeps("ur10", 20, 4, seed=0)
    part = scn.subset(scn.group == 1)
    assert part.k == 4 and np.all(part.group == 1) and np.array_equal(part.q, scn.q[scn.group == 1])


def test_wrist_joint_is_q5_on_the_6r_arms():
    assert S.wrist_joint(load("ur10").model) == S.wrist_joint(load("fanuc-m1000ia").model) == WRIST


def test_docstring_examples_run():
    # scenarios lives in benchmarks/, outside the package tests/test_doctests.py walks: its examples run here.
    result = doctest.testmod(S, optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS)
    assert result.attempted >= 10 and result.failed == 0
