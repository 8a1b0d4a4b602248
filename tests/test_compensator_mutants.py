"""Compensator files and ranges: an NPZ export never unpickles, and ``extrapolate=True`` is the one way past the
calibrated ranges (surviving mutations of benchmarks/mutation.py)."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.compensator import CalibratedRobot, Compensator, CompensatorFileError
from labcal.robots import load


def _robot() -> CalibratedRobot:
    nominal = load("ur10").model
    model = nominal.perturbed(np.random.default_rng(0).normal(size=(nominal.n + 1, 6)) * 0.5e-3)
    ranges = np.tile([-1.0, 1.0], (nominal.n, 1))
    return CalibratedRobot(nominal, model, joint_ranges=ranges, method="local-poe")


def test_an_npz_export_with_a_pickled_object_is_refused_unread(tmp_path):
    path = Compensator(_robot()).save(tmp_path / "c.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    name = next(k for k in arrays if k != "__meta__")  # an array the metadata references, made an object array
    arrays[name] = np.full(arrays[name].shape, {"payload": "would run code when unpickled"}, dtype=object)
    np.savez(path, **arrays)
    with pytest.raises(CompensatorFileError, match=rf"c\.npz: {name} must be float64"):
        Compensator.load(path)


def test_check_range_refuses_outside_the_calibrated_ranges_unless_extrapolating(tmp_path):
    comp = Compensator.load(Compensator(_robot()).save(tmp_path / "c.json"))
    q = np.array([0.1, -0.2, 1.5, 0.0, 0.3, -0.4])  # joint 3 beyond its calibrated [-1, 1]
    with pytest.raises(ValueError, match="joint 3"):
        comp.check_range(q)
    assert comp.check_range(q, extrapolate=True) is None
    comp.check_range(np.zeros(6))


def _integral_floats_as_ints(value):
    if isinstance(value, dict):
        return {k: _integral_floats_as_ints(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_integral_floats_as_ints(v) for v in value]
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def test_checksums_compare_numbers_by_value_not_by_how_a_json_writer_spelled_them(tmp_path):
    # A JSON file re-saved by a tool that writes 1.0 as 1 (JavaScript, many editors) is the same compensator.
    import json

    path = Compensator(_robot()).save(tmp_path / "c.json")
    data = json.loads(path.read_text())
    respelled = _integral_floats_as_ints(data)
    assert json.dumps(respelled) != json.dumps(data)  # the ranges, frames' zeros and ones … are now written as ints
    path.write_text(json.dumps(respelled))
    comp = Compensator.load(path)
    np.testing.assert_array_equal(comp.joint_ranges, _robot().joint_ranges)


def test_a_golden_pose_edited_by_a_micrometre_is_refused_even_with_resealed_checksums(tmp_path):
    import json

    from labcal.compensator.io import field_checksums

    path = Compensator(_robot()).save(tmp_path / "c.json")
    data = json.loads(path.read_text())
    data["golden"]["pose"][0][0][3] += 1e-6  # 1 µm in x of the first golden pose
    data["checksums"] = field_checksums(data)  # whoever edits can also recompute the checksums
    path.write_text(json.dumps(data))
    with pytest.raises(CompensatorFileError, match="golden vectors disagree"):
        Compensator.load(path)
