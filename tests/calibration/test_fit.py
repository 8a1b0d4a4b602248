"""The fit dispatcher: every row fitted, cross-validated choice and its tie rule, metrics, determinism, lazy torch."""

from __future__ import annotations

import subprocess
import sys
import types

import numpy as np
import pytest

from labcal.calibration import METHODS, FitResult, Observations, fit
from labcal.calibration.local_poe import fit_local_poe
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.12, 0.0, 0.05], [-0.06, 0.15, 0.05], [-0.07, -0.11, 0.04]])


def observe(errors=None, k=60, seed=4, split=None):
    spec = load("fanuc-m1000ia")
    actual = simulate(spec, errors or ErrorSpec.paper(), seed=seed)
    rng = np.random.default_rng(seed)
    q = rng.uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(k, spec.model.n))
    return spec.model, Observations(q, actual.measure(q, TARGETS, rng), TARGETS, split=split)


@pytest.fixture
def fake_ann(monkeypatch):
    def install(result_for):
        module = types.ModuleType("labcal.calibration.ann")
        module.fit_ann = lambda obs, base, *, seed=0, **options: (result_for(obs, base), {"fake": True})
        monkeypatch.setitem(sys.modules, "labcal.calibration.ann", module)

    return install


def test_methods_and_unknown_method():
    assert METHODS == ("nominal", "local-poe", "ann", "hybrid", "auto")
    nominal, obs = observe()
    with pytest.raises(ValueError, match="method must be one of"):
        fit(obs, nominal, "dh-least-squares")


def test_local_poe_fit_splits_the_rows_and_measures_every_split():
    split = np.array([""] * 60 + ["test"] * 20, dtype=object)
    nominal, obs = observe(k=80, split=split)
    lines = []
    result = fit(obs, nominal, "local-poe", seed=1, val_fraction=0.25, progress=lines.append)
    assert isinstance(result, FitResult)
    assert (result.method, result.chosen, result.robot.method) == ("local-poe", "local-poe", "local-poe")
    assert (result.n_train, result.n_val, result.n_test) == (45, 15, 20)
    assert list(result.obs.split[60:]) == ["test"] * 20
    assert set(result.metrics) == {"train", "val", "test", "all"}
    for part in ("train", "val", "test"):
        assert result.metrics[part]["after"]["pos_mean"] < 0.05 * result.metrics[part]["before"]["pos_mean"]
    assert result.info["rows"] == 45 and lines
    # the registered nominal is the "before" robot: nominal geometry
    assert np.array_equal(result.before.model.frames, nominal.frames)


def test_test_rows_never_influence_the_fit():
    split = np.array([""] * 40 + ["test"] * 20, dtype=object)
    nominal, obs = observe(split=split)
    moved = obs.points.copy()
    moved[40:] += 0.003
    a = fit(obs, nominal, "local-poe", seed=2)
    b = fit(Observations(obs.q, moved, obs.targets, split=split), nominal, "local-poe", seed=2)
    assert np.array_equal(a.robot.model.frames, b.robot.model.frames)
    assert a.metrics["test"]["after"]["pos_mean"] != b.metrics["test"]["after"]["pos_mean"]


def test_nominal_method_is_the_registered_nominal():
    nominal, obs = observe()
    result = fit(obs, nominal, "nominal")
    assert result.robot is result.before
    assert result.metrics["all"]["before"] == result.metrics["all"]["after"]
    assert result.cv is None and result.warnings == []


def test_by_default_local_poe_fits_every_row_and_reports_its_cross_validated_error():
    nominal, obs = observe()
    result = fit(obs, nominal, "local-poe")
    assert (result.n_train, result.n_val, result.n_test) == (60, 0, 0)
    every_row, _ = fit_local_poe(Observations(obs.q, obs.points, obs.targets), nominal)
    assert np.array_equal(result.robot.model.frames, every_row.model.frames)
    cv = result.cv
    assert (cv["folds"], cv["scheme"], cv["chosen"]) == (5, "kfold", "local-poe")
    assert len(cv["errors"]["local-poe"]) == 5 and cv["mean"]["local-poe"] < 0.1 * cv["mean"]["nominal"]
    assert result.warnings == []


def test_auto_picks_local_poe_when_the_network_does_not_help_and_ties_go_to_the_simpler(fake_ann):
    nominal, obs = observe()
    fake_ann(lambda obs, base: base)  # a network that learns nothing: hybrid == local POE, ann == nominal
    result = fit(obs, nominal, "auto", seed=0, stage2=("ann",))
    c = result.info["candidates"]
    assert c["hybrid"] == c["local-poe"] < c["ann"]
    assert result.chosen == "local-poe" and result.robot.method == "local-poe"
    assert result.info["hybrid"]["kept"] == "local-poe"
    assert result.cv["chosen"] == "local-poe" and set(result.cv["errors"]) == {
        "nominal",
        "local-poe",
        "hybrid+ann",
        "ann",
    }


def test_auto_picks_the_lowest_cross_validated_error_and_prefers_hybrid_to_ann_on_a_tie(fake_ann):
    # Noise-free geometric data. The local-POE stage is stopped after one step (error ~1e-6 m); the fake network
    # returns the converged identification (error ~1e-15 m), so ann and hybrid reach the same, lower error.
    nominal, obs = observe(ErrorSpec.paper(tracker_noise=0.0))
    exact, _ = fit_local_poe(obs, nominal)
    fake_ann(lambda obs, base: exact)
    result = fit(obs, nominal, "auto", seed=0, local_poe_options={"max_iter": 1}, stage2=("ann",))
    c = result.info["candidates"]
    assert c["ann"] == c["hybrid"] < c["local-poe"]
    assert result.chosen == "hybrid" and result.info["hybrid"]["kept"] == "local-poe+ann"
    assert set(result.fit_seconds) >= {"nominal", "local-poe", "cross-validation", "hybrid"}


def test_held_out_rows_are_only_measured_never_used_to_choose(fake_ann):
    nominal, obs = observe(k=80)
    fake_ann(lambda obs, base: base)
    a = fit(obs, nominal, "auto", val_fraction=0.25, stage2=("ann",))
    moved = obs.points.copy()
    moved[a.obs.split == "val"] += 0.01
    b = fit(Observations(obs.q, moved, obs.targets), nominal, "auto", val_fraction=0.25, stage2=("ann",))
    assert (a.n_train, a.n_val) == (60, 20) and list(a.obs.split) == list(b.obs.split)
    assert a.cv["errors"] == b.cv["errors"] and np.array_equal(a.robot.model.frames, b.robot.model.frames)
    assert a.metrics["val"]["after"]["pos_mean"] < b.metrics["val"]["after"]["pos_mean"]


def test_local_poe_fit_does_not_import_torch():
    code = (
        "import sys, numpy as np\n"
        "from labcal.calibration import Observations, fit\n"
        "from labcal.robots import load\n"
        "from labcal.simulation import ErrorSpec, simulate\n"
        "spec = load('scara4'); act = simulate(spec, ErrorSpec.paper(), seed=0)\n"
        "rng = np.random.default_rng(0)\n"
        "q = rng.uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(30, 4))\n"
        "t = np.array([[0.05, 0, 0], [0, 0.05, 0], [-0.04, -0.03, 0.01]])\n"
        "fit(Observations(q, act.measure(q, t, rng), t), spec.model, 'local-poe')\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.slow
def test_same_data_and_seed_give_bit_identical_frames_and_network_weights():
    pytest.importorskip("torch")
    pytest.importorskip("labcal.calibration.ann")
    nominal, obs = observe(ErrorSpec.default(), k=60)
    a = fit(obs, nominal, "ann", seed=5, restarts=1)
    b = fit(obs, nominal, "ann", seed=5, restarts=1)
    c = fit(obs, nominal, "ann", seed=6, restarts=1)
    assert a.robot.network is not None
    assert np.array_equal(a.robot.model.frames, b.robot.model.frames)
    assert np.array_equal(a.robot.T_tracker_base, b.robot.T_tracker_base)
    for wa, wb in zip(
        a.robot.network.weights + a.robot.network.biases, b.robot.network.weights + b.robot.network.biases, strict=True
    ):
        assert np.array_equal(wa, wb)
    assert not np.array_equal(a.robot.network.weights[0], c.robot.network.weights[0])  # the seed matters
    h1 = fit(obs, nominal, "hybrid", seed=5, restarts=1)
    h2 = fit(obs, nominal, "hybrid", seed=5, restarts=1)
    assert np.array_equal(h1.robot.model.frames, h2.robot.model.frames)
    assert h1.info["kept"] == h2.info["kept"]
    if h1.robot.network is not None:
        assert all(
            np.array_equal(x, y) for x, y in zip(h1.robot.network.weights, h2.robot.network.weights, strict=True)
        )
