"""The hybrid: local POE, then the network on the identified robot, kept only when validation improves."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from labcal.calibration import Observations
from labcal.calibration.hybrid import fit_hybrid, validation_error
from labcal.calibration.local_poe import fit_local_poe, register
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.12, 0.0, 0.05], [-0.06, 0.15, 0.05], [-0.07, -0.11, 0.04]])


def observe(errors, k=80, seed=2, robot="fanuc-m1000ia"):
    spec = load(robot)
    actual = simulate(spec, errors, seed=seed)
    rng = np.random.default_rng(seed)
    q = rng.uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(k, spec.model.n))
    obs = Observations(q, actual.measure(q, TARGETS, rng), TARGETS).with_splits(0.5, seed)
    return spec.model, obs


@pytest.fixture
def fake_ann(monkeypatch):
    """Replace labcal.calibration.ann by a module whose fit_ann returns a chosen robot (no torch)."""
    calls = []

    def install(result_for):
        def fit_ann(obs, base, *, seed=0, **options):
            calls.append((base, seed, options))
            return result_for(obs, base), {"fake": True}

        module = types.ModuleType("labcal.calibration.ann")
        module.fit_ann = fit_ann
        monkeypatch.setitem(sys.modules, "labcal.calibration.ann", module)
        return calls

    return install


def test_second_stage_is_dropped_when_it_raises_the_validation_error(fake_ann):
    nominal, obs = observe(ErrorSpec.paper())
    calls = fake_ann(lambda obs, base: register(obs, nominal)[0])  # stage 2 "forgets" the identification
    robot, info = fit_hybrid(obs, nominal, seed=3, stage2=("ann",), hidden=4)
    stage1, _ = fit_local_poe(obs, nominal)
    assert info["kept"] == "local-poe"
    assert info["val_error_hybrid"] > info["val_error_local_poe"]
    assert np.array_equal(robot.model.frames, stage1.model.frames) and robot.network is None
    assert robot.method == "hybrid"
    # stage 2 was given the identified robot as its base, the seed, the network options and eq. (20)'s loss
    base, seed, options = calls[0]
    assert np.array_equal(base.model.frames, stage1.model.frames) and seed == 3
    assert options == {"hidden": 4, "loss": "task"}


def test_second_stage_is_kept_when_it_lowers_the_validation_error(fake_ann):
    nominal, obs = observe(ErrorSpec.paper())
    good, _ = fit_local_poe(obs, nominal)
    fake_ann(lambda obs, base: good)
    poor = register(obs, nominal)  # a deliberately poor first stage
    robot, info = fit_hybrid(obs, nominal, stage1=poor, stage2=("ann",))
    assert info["kept"] == "local-poe+ann"
    assert info["val_error_hybrid"] == pytest.approx(validation_error(good, obs))
    assert np.array_equal(robot.model.frames, good.model.frames)


def test_the_candidate_with_the_lower_validation_error_is_kept(fake_ann, monkeypatch):
    nominal, obs = observe(ErrorSpec.paper())
    good, _ = fit_local_poe(obs, nominal)
    poor = register(obs, nominal)
    fake_ann(lambda obs, base: poor[0])  # the network candidate is worse than the series candidate
    import labcal.calibration.joint_series as joint_series

    monkeypatch.setattr(joint_series, "fit_joint_series", lambda obs, base, **kw: (good, {"fake_series": True}))
    robot, info = fit_hybrid(obs, nominal, stage1=poor)
    assert info["kept"] == "local-poe+series"
    assert info["val_errors"]["series"] < info["val_errors"]["ann"]
    assert info["series"] == {"fake_series": True} and np.array_equal(robot.model.frames, good.model.frames)
    with pytest.raises(ValueError, match="stage2"):
        fit_hybrid(obs, nominal, stage1=poor, stage2=("kriging",))


def test_hybrid_needs_validation_rows():
    nominal, obs = observe(ErrorSpec.paper())
    train_only = Observations(obs.q, obs.points, obs.targets, split=np.full(obs.k, "train", dtype=object))
    with pytest.raises(ValueError, match="validation rows"):
        fit_hybrid(train_only, nominal)


@pytest.mark.slow
def test_real_network_is_dropped_when_errors_are_purely_geometric():
    # Noise-free geometric errors: local POE is exact to round-off, so whatever the network learns can only
    # add error on the validation rows; the gate must drop it.
    pytest.importorskip("torch")
    pytest.importorskip("labcal.calibration.ann")
    nominal, obs = observe(ErrorSpec.paper(tracker_noise=0.0), k=60)
    robot, info = fit_hybrid(obs, nominal, seed=0, restarts=1)
    assert info["val_error_local_poe"] < 1e-9
    assert info["kept"] == "local-poe" and robot.network is None
