"""NDI stray markers when fewer than three (or not all m) targets are seen: byte-exact on a scripted transport.

Targets the camera does not see come back as NaN rows; a frame is rejected only when no marker can be labelled
unambiguously. Fewer than three markers are labelled from the frames of the same measurement that saw more.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scripted_transport import ScriptedTransport
from serial_fixtures import (
    BX,
    CLOSE_NDI,
    OPEN_NDI,
    TARGETS,
    TX,
    bx_reply,
    ndi_profile,
    ndi_reply,
    tool_to_tracker,
    tx_body,
)

from labcal.drivers.base import MeasurementRejected
from labcal.drivers.serial.matching import check_targets, match_targets
from labcal.drivers.serial.tracker import SerialTracker
from labcal_fakes.devices import FakeNDIDevice

TOL = 0.5e-3
SEEN = tool_to_tracker()  # (3, 3) m, rows t1, t2, t3 as the tracker sees them
FOUR = np.vstack([TARGETS, [[0.03, 0.02, 0.05]]])  # a fourth target off the plane of the first three
SEEN4 = tool_to_tracker(FOUR)


def tx(strays) -> bytes:
    return ndi_reply(tx_body(strays))


def scripted(script, targets=TARGETS, **profile):
    t = ScriptedTransport(script)
    tracker = SerialTracker(ndi_profile(**profile), targets, transport=t, clock=t.clock, sleep=t.sleep)
    return tracker, t


def test_two_markers_alone_cannot_be_told_apart_and_the_frame_is_rejected():
    tracker, t = scripted([*OPEN_NDI, (TX, tx(SEEN[[1, 0]]))])
    with pytest.raises(MeasurementRejected, match=r"only 2 marker\(s\) visible: fewer than three"):
        tracker.measure()
    t.assert_done()


def test_two_markers_are_labelled_from_the_complete_frames_of_the_same_measurement():
    # frame 2 lost t3 and reports t2 before t1: where frames 1 and 3 saw t1 and t2 says which is which
    script = [*OPEN_NDI, (TX, tx(SEEN[[2, 0, 1]])), (TX, tx(SEEN[[1, 0]])), (TX, tx(SEEN)), *CLOSE_NDI]
    tracker, t = scripted(script)
    m = tracker.measure(samples=3)
    tracker.close()
    t.assert_done()
    np.testing.assert_allclose(m.points, SEEN, atol=5e-6)
    assert m.seen.all() and m.quality == ()  # t3 was seen in two of the frames: not missing


def test_a_target_seen_in_no_frame_stays_nan():
    script = [*OPEN_NDI, (TX, tx(SEEN4[[3, 1, 0]])), (TX, tx(SEEN4[[0, 3, 1]]))]
    tracker, t = scripted(script, targets=FOUR)
    m = tracker.measure(samples=2)
    t.assert_done()
    assert m.seen.tolist() == [True, True, False, True] and m.quality == ("missing:t3",)
    np.testing.assert_allclose(m.points[m.seen], SEEN4[m.seen], atol=5e-6)
    assert np.isnan(m.spread[2])


def test_four_targets_three_markers_and_a_reflection_are_labelled_by_distances():
    spurious = SEEN4.mean(axis=0) + np.array([0.25, -0.2, 0.1])
    tracker, t = scripted([*OPEN_NDI, (TX, tx([SEEN4[2], spurious, SEEN4[3], SEEN4[0], SEEN4[1]]))], targets=FOUR)
    m = tracker.measure()
    np.testing.assert_allclose(m.points, SEEN4, atol=5e-6)
    tracker2, t2 = scripted([*OPEN_NDI, (TX, tx([SEEN4[3], spurious, SEEN4[0], SEEN4[1]]))], targets=FOUR)
    m2 = tracker2.measure()  # t3 hidden: the triangle t1 t2 t4 labels itself
    assert m2.seen.tolist() == [True, True, False, True]
    np.testing.assert_allclose(m2.points[m2.seen], SEEN4[m2.seen], atol=5e-6)
    t.assert_done()
    t2.assert_done()


def test_one_target_one_marker_over_binary_replies():
    smr = TARGETS[:1]
    point = SEEN[:1]
    tracker, t = scripted([*OPEN_NDI, (BX, bx_reply(point)), (BX, bx_reply(point + 1e-4))], targets=smr, reply="bx")
    m = tracker.measure(samples=2)
    t.assert_done()
    assert m.points.shape == (1, 3)
    np.testing.assert_allclose(m.points, point + 5e-5, atol=1e-6)  # float32 millimetres on the wire


def test_one_target_with_a_reflection_is_ambiguous():
    tracker, t = scripted([*OPEN_NDI, (TX, tx([SEEN[0], SEEN[0] + 0.3]))], targets=TARGETS[:1])
    with pytest.raises(MeasurementRejected, match="2 markers visible for the one target"):
        tracker.measure()
    t.assert_done()


def test_a_lone_marker_is_labelled_from_the_other_frames_and_a_stranger_is_not():
    script = [*OPEN_NDI, (TX, tx(SEEN)), (TX, tx(SEEN[[2]]))]
    tracker, t = scripted(script)
    m = tracker.measure(samples=2)
    assert m.seen.all()
    np.testing.assert_allclose(m.points, SEEN, atol=5e-6)
    t.assert_done()
    far = SEEN[[2]] + np.array([0.01, 0.0, 0.0])  # 10 mm from where t3 was: not t3, not anything
    tracker2, t2 = scripted([*OPEN_NDI, (TX, tx(SEEN)), (TX, tx(far))])
    with pytest.raises(MeasurementRejected, match=r"only 1 marker\(s\) visible"):
        tracker2.measure(samples=2)
    t2.assert_done()


def test_targets_that_no_marker_pattern_can_label_are_refused_at_configuration():
    with pytest.raises(ValueError, match="two targets cannot be told apart"):
        SerialTracker(ndi_profile(), TARGETS[:2], transport=ScriptedTransport([]))
    square = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0.0]])
    with pytest.raises(ValueError, match=r"target distances t\d-t\d .* differ by less than 2 x tolerance"):
        check_targets(square, TOL)
    np.testing.assert_array_equal(check_targets(FOUR, TOL), FOUR)


def test_match_targets_keeps_the_three_target_result_exactly():
    rng = np.random.default_rng(5)
    order = rng.permutation(3)
    m = match_targets(SEEN[order], TARGETS, TOL)
    np.testing.assert_array_equal(m.points, SEEN[order][list(m.indices)])
    np.testing.assert_array_equal(order[list(m.indices)], [0, 1, 2])


def test_reference_labels_only_markers_that_sit_on_a_reference_position():
    ref = SEEN.copy()
    ref[1] = np.nan  # where t2 was is unknown
    m = match_targets(SEEN[[1, 0]], TARGETS, TOL, reference=ref)
    assert m.indices == (1, -1, -1)  # t1 sits on its reference; t2's marker has nothing to sit on
    assert np.isnan(m.points[1]).all() and np.isnan(m.points[2]).all()


@pytest.mark.integration
@pytest.mark.timeout(30)
def test_the_pty_fake_hides_targets_the_simulator_says_are_not_seen():
    hidden = SEEN4.copy()
    hidden[1] = np.nan
    with FakeNDIDevice(lambda: hidden, seed=3) as dev:
        profile = dataclasses.replace(ndi_profile(), port=dataclasses.replace(ndi_profile().port, url=dev.port))
        with SerialTracker(profile, FOUR) as tracker:
            m = tracker.measure(samples=2)
    assert m.seen.tolist() == [True, False, True, True] and m.quality == ("missing:t2",)
    np.testing.assert_allclose(m.points[m.seen], SEEN4[m.seen], atol=1e-5)
