"""Export formats: URScript computes the same correction as the runtime, the URDF reproduces the identified FK,
the dispatcher checks formats and suffixes."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from export_fixtures import hybrid, make_network, sample

import urscript_subset
from labcal.compensator import CalibratedRobot, Compensator
from labcal.export import SUFFIXES, export
from labcal.export.urscript import urscript_text
from labcal.kinematics import se3
from labcal.kinematics.poe import REVOLUTE, LocalPOEModel
from labcal.robots import load


def redundant_robot(seed=3) -> CalibratedRobot:
    """A 7-joint arm (a random z-revolute chain) and its calibrated copy: local POE only."""
    rng = np.random.default_rng(seed)
    nominal = LocalPOEModel.from_frames(se3.exp_se3(rng.normal(size=(8, 6)) * 0.3), (REVOLUTE,) * 7)
    return CalibratedRobot(nominal, nominal.perturbed(rng.normal(size=(8, 6)) * 0.5e-3), method="local-poe")


def run_script(text: str, q: np.ndarray, name: str = "labcal_correct") -> np.ndarray:
    urscript_subset.check(text)
    ns = urscript_subset.load(text)
    return np.array([ns[name](list(map(float, row))) for row in q])


@pytest.mark.parametrize(
    "features,odd",
    [(("q", "sincos", "sincos2", "gravity"), False), (("sincos", "gravity"), True), (("harmonics:2",), False)],
)
def test_urscript_newton_matches_correct(features, odd):
    robot = hybrid("ur10", features=features, odd_twists=odd, seed=3)
    q = sample(robot, 30, seed=8)
    # The script has no damped fallback: compare where Gauss-Newton converges from q (small corrections).
    q = q[np.max(np.abs(robot.correct(q) - q), axis=1) < 0.05][:12]
    assert len(q) >= 8
    got = run_script(urscript_text(robot), q)
    np.testing.assert_allclose(got, robot.correct(q), atol=1e-9, rtol=0)
    assert np.max(np.abs(got - q)) > 1e-4  # it did correct something


def test_urscript_paper_method_matches_eq_24():
    nominal = load("ur10").model
    robot = CalibratedRobot(nominal, nominal, make_network(nominal, ("q", "sincos", "gravity"), seed=4), method="ann")
    q = sample(robot, 10, seed=9)
    got = run_script(urscript_text(robot, method="paper"), q)
    np.testing.assert_allclose(got, robot.correct(q, method="paper"), atol=1e-12, rtol=0)


def test_urscript_local_poe_lower_mobility_robot():
    nominal = load("scara4").model
    model = nominal.perturbed(np.random.default_rng(1).normal(size=(5, 6)) * 0.5e-3)
    robot = CalibratedRobot(nominal, model, method="local-poe")
    q = sample(robot, 8, seed=10, max_cond=1e4)
    got = run_script(urscript_text(robot, iterations=6), q)
    np.testing.assert_allclose(got, robot.correct(q), atol=1e-9, rtol=0)


def test_urscript_halts_outside_the_calibrated_range():
    nominal = load("ur10").model
    robot = CalibratedRobot(
        nominal, nominal, make_network(nominal, ("sincos",)), joint_ranges=np.tile([-1.0, 1.0], (6, 1))
    )
    ns = urscript_subset.load(urscript_text(robot))
    with pytest.raises(urscript_subset.Halted):
        ns["labcal_correct"]([0.0, 0.0, 0.0, 0.0, 1.5, 0.0])


def test_urscript_refuses_what_it_cannot_express():
    nominal = load("scara4").model
    with pytest.raises(ValueError, match="not supported"):
        urscript_text(CalibratedRobot(nominal, nominal, make_network(nominal, ("sincos",))))
    with pytest.raises(ValueError, match="needs a network"):
        urscript_text(CalibratedRobot(nominal, nominal), method="paper")
    with pytest.raises(ValueError, match="7-joint robot is not supported"):
        urscript_text(redundant_robot())


def test_subset_checker_rejects_python_only_syntax():
    with pytest.raises(SyntaxError):
        urscript_subset.translate("def f(a):\n  return a[1:2]\nend\n")
    with pytest.raises(SyntaxError):
        urscript_subset.translate("x = [i for i in y]\n")
    with pytest.raises(SyntaxError):
        urscript_subset.translate("x = 2 ** 3\n")


OPTIONS = {
    "urdf": {"geometry_only": True, "velocity": [3.0] * 6, "effort": [50.0] * 6},
    "ur-kinematics": {"geometry_only": True},
}


@pytest.mark.parametrize("fmt,suffix", list(SUFFIXES.items()))
def test_export_dispatch_writes_every_format(tmp_path, fmt, suffix):
    robot = hybrid("ur10")
    path = export(robot, fmt, tmp_path / f"out{suffix}", provenance={"fit_id": "abc"}, **OPTIONS.get(fmt, {}))
    assert path.is_file() and path.stat().st_size > 0
    if fmt in ("json", "npz"):
        q = sample(robot, 5, seed=12)
        np.testing.assert_array_equal(Compensator.load(path).correct(q), robot.correct(q))


def test_export_dispatch_rejects_bad_format_and_suffix(tmp_path):
    robot = hybrid("ur10")
    with pytest.raises(ValueError, match="unknown export format"):
        export(robot, "xml", tmp_path / "a.xml")
    with pytest.raises(ValueError, match=r"ending in \.npz"):
        export(robot, "npz", tmp_path / "a.json")


def test_a_listed_format_without_a_writer_is_an_error_not_a_urdf(tmp_path, monkeypatch):
    import labcal.export as export_module

    # export() dispatches on its table of writers: a name listed elsewhere is an unknown format, never another's
    monkeypatch.setattr(export_module, "FORMATS", (*export_module.FORMATS, "new-format"))
    target = tmp_path / "out.new"
    with pytest.raises(ValueError, match=r"unknown export format 'new-format'"):
        export(hybrid("ur10"), "new-format", target)
    assert not target.exists()
