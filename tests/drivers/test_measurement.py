"""Measurement values with unseen targets (NaN rows) and averaging frames target by target."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.drivers.base import Measurement, MeasurementRejected, average_frames

NAN3 = [np.nan] * 3


def test_a_measurement_holds_m_targets_and_says_which_were_seen():
    m = Measurement(np.array([[0.1, 0.2, 1.5], NAN3, [0.3, 0.1, 1.4], [0.0, 0.0, 1.0]]), timestamp=2.0)
    assert m.m == 4 and m.seen.tolist() == [True, False, True, True]
    assert m.spread.tolist()[0] == 0.0 and np.isnan(m.spread[1])


@pytest.mark.parametrize(
    "points, message",
    [
        ([[0.1, np.nan, 1.5]], "t1 is partly missing"),
        ([NAN3, NAN3], "no target seen"),
        (np.zeros((0, 3)), r"\(m, 3\)"),
        (np.zeros((3, 2)), r"\(m, 3\)"),
    ],
)
def test_malformed_measurements_are_refused(points, message):
    with pytest.raises(ValueError, match=message):
        Measurement(np.asarray(points, dtype=float), timestamp=0.0)


def test_spread_must_have_one_value_per_target():
    with pytest.raises(ValueError, match=r"spread must be \(2,\)"):
        Measurement(np.zeros((2, 3)), timestamp=0.0, spread=np.zeros(3))


def test_complete_frames_average_exactly_as_the_plain_mean():
    rng = np.random.default_rng(3)
    frames = [rng.normal(size=(3, 3)) for _ in range(5)]
    m = average_frames(frames, timestamp=1.0)
    stack = np.array(frames)
    mean = stack.mean(axis=0)
    np.testing.assert_array_equal(m.points, mean)
    np.testing.assert_array_equal(m.spread, np.sqrt(np.mean(np.sum((stack - mean) ** 2, axis=2), axis=0)))
    assert m.quality == () and m.samples == 5


def test_each_target_is_averaged_over_the_frames_that_saw_it():
    a = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], NAN3])
    b = np.array([[3.0, 0.0, 0.0], NAN3, NAN3])
    c = np.array([[2.0, 0.0, 0.0], [0.0, 3.0, 0.0], NAN3])
    m = average_frames([a, b, c], timestamp=4.0, quality=("system_status:0x0001",))
    np.testing.assert_allclose(m.points[0], [2.0, 0.0, 0.0])
    np.testing.assert_allclose(m.points[1], [0.0, 2.0, 0.0])  # t2 seen twice: (1 + 3) / 2, frame b not counted
    assert np.all(np.isnan(m.points[2])) and np.isnan(m.spread[2])
    np.testing.assert_allclose(m.spread[:2], [np.sqrt(2 / 3), 1.0])
    assert m.samples == 3 and m.quality == ("system_status:0x0001", "missing:t3")


def test_a_frame_that_saw_no_target_is_rejected():
    with pytest.raises(MeasurementRejected, match="frame 2 of 2 saw none of the 2 targets"):
        average_frames([np.zeros((2, 3)), np.full((2, 3), np.nan)], timestamp=0.0)


def test_a_partly_missing_point_is_rejected_naming_frame_and_target():
    bad = np.zeros((3, 3))
    bad[2, 1] = np.nan
    with pytest.raises(MeasurementRejected, match="frame 2: target t3"):
        average_frames([np.zeros((3, 3)), bad], timestamp=0.0)


@pytest.mark.parametrize("frames", [[], [np.zeros((3, 3)), np.zeros((2, 3))], [np.zeros((3, 2))]])
def test_frames_of_the_wrong_shape_are_rejected(frames):
    with pytest.raises(MeasurementRejected):
        average_frames(frames, timestamp=0.0)
