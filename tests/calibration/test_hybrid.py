"""The hybrid: local POE, then the network on the identified robot, kept only when validation improves."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from labcal.calibration import Observations
from labcal.calibration.fit import fit_hybrid
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


def test_second_stage_is_dropped_when_it_raises_the_cross_validated_error(fake_ann):
    nominal, obs = observe(ErrorSpec.paper())
    calls = fake_ann(lambda obs, base: register(obs, nominal)[0])  # stage 2 "forgets" the identification
    robot, info = fit_hybrid(obs, nominal, seed=3, stage2=("ann",), hidden=4)
    stage1, _ = fit_local_poe(obs, nominal)
    assert info["kept"] == "local-poe" and info["selection"] == "cross-validation"
    assert info["val_error_hybrid"] > info["val_error_local_poe"]
    assert np.array_equal(robot.model.frames, stage1.model.frames) and robot.network is None
    assert robot.method == "hybrid"
    # 40 fitting rows: 10 folds. Every fold gave stage 2 its own identified robot (fitted without the held-out
    # rows), the seed, the network options, eq. (20)'s loss and a single restart; far behind local POE after two
    # folds, the network was not pursued, and the dropped candidate is not refitted on all rows
    assert info["cv"]["folds"] == 10 and info["cv"]["pruned_after"] == {"hybrid+ann": 2} and len(calls) == 2
    assert info["cv"]["errors"]["hybrid+ann"][2:] == [None] * 8
    for base, seed, options in calls:
        assert not np.array_equal(base.model.frames, stage1.model.frames) and seed == 3
        assert options == {"hidden": 4, "loss": "task", "restarts": 1, "max_iter": 40, "max_rows": 1000}


def _inexact_stage1(nominal, obs):
    """Noise-free geometric data; local POE stopped after one step is ~1e-6 m off, the converged fit exact."""
    return {"max_iter": 1}, fit_local_poe(obs, nominal)[0]


def test_second_stage_is_kept_when_it_lowers_the_cross_validated_error(fake_ann):
    nominal, obs = observe(ErrorSpec.paper(tracker_noise=0.0))
    lp_options, exact = _inexact_stage1(nominal, obs)
    calls = fake_ann(lambda obs, base: exact)
    robot, info = fit_hybrid(obs, nominal, stage2=("ann",), local_poe_options=lp_options)
    assert info["kept"] == "local-poe+ann" and info["val_errors"]["ann"] < info["val_error_local_poe"]
    assert np.array_equal(robot.model.frames, exact.model.frames)
    assert len(calls) == info["cv"]["folds"] + 1  # the folds, then the kept stage refitted on all rows
    assert calls[-1][2] == {"loss": "task"}  # the final refit uses the caller's restarts (fit_ann's default)


def test_the_candidate_with_the_lower_cross_validated_error_is_kept(fake_ann, monkeypatch):
    nominal, obs = observe(ErrorSpec.paper(tracker_noise=0.0))
    lp_options, exact = _inexact_stage1(nominal, obs)
    fake_ann(lambda obs, base: register(obs, nominal)[0])  # the network candidate is worse than the series
    import labcal.calibration.joint_series as joint_series

    monkeypatch.setattr(joint_series, "fit_joint_series", lambda obs, base, **kw: (exact, {"fake_series": True}))
    robot, info = fit_hybrid(obs, nominal, local_poe_options=lp_options)
    assert info["kept"] == "local-poe+series"
    assert info["val_errors"]["series"] < info["val_errors"]["ann"]
    assert info["series"] == {"fake_series": True} and np.array_equal(robot.model.frames, exact.model.frames)
    with pytest.raises(ValueError, match="stage2"):
        fit_hybrid(obs, nominal, stage2=("kriging",))


def test_validation_rows_are_only_measured(fake_ann):
    nominal, obs = observe(ErrorSpec.paper())
    fake_ann(lambda obs, base: base)
    robot, info = fit_hybrid(obs, nominal, stage2=("ann",))
    moved = obs.points.copy()
    moved[obs.split == "val"] += 0.01
    other, info2 = fit_hybrid(Observations(obs.q, moved, obs.targets, split=obs.split), nominal, stage2=("ann",))
    assert np.array_equal(robot.model.frames, other.model.frames) and info["cv"] == info2["cv"]
    assert info2["val_error"] > info["val_error"]
    train_only = Observations(obs.q, obs.points, obs.targets, split=np.full(obs.k, "train", dtype=object))
    _, info3 = fit_hybrid(train_only, nominal, stage2=("ann",))
    assert info3["cv"]["folds"] == 5 and np.isnan(info3["val_error"])


def test_too_few_distinct_poses_skip_the_learned_stages(fake_ann):
    nominal, obs = observe(ErrorSpec.paper())
    fake_ann(lambda obs, base: pytest.fail("a network was fitted without cross-validation"))
    two = obs.subset(np.r_[np.zeros(20, int), np.ones(20, int)])  # two poses, each measured 20 times
    robot, info = fit_hybrid(two, nominal, stage2=("ann",))
    assert info["kept"] == "local-poe" and info["cv"] is None and robot.network is None
    assert any(n.startswith("stage-skipped") for n in info["notes"])


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
