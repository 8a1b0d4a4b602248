"""The report findings of the newcomer run (issue 25): histogram bins that separate methods, a training curve whose
axis names its unit, a warning when calibration makes held-out data worse, and the units that were calibrated."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_testutil import TARGETS, invoke, last_line

from labcal import reports
from labcal.cli.ops.fitting import slim_info


def test_histogram_bins_separate_methods_a_third_apart_next_to_the_before_errors():
    """The demo's case: before ~3 mm, local POE ~0.10 mm and hybrid ~0.07 mm (0.25 mm bins put both in one bar)."""
    rng = np.random.default_rng(0)
    before = rng.lognormal(np.log(3.0), 0.4, 120)
    local_poe = rng.lognormal(np.log(0.10), 0.3, 120)
    hybrid = rng.lognormal(np.log(0.07), 0.3, 120)
    edges = reports.histogram_bins([before, local_poe, hybrid])
    assert edges[0] <= min(before.min(), local_poe.min(), hybrid.min())
    assert edges[-1] >= max(before.max(), local_poe.max(), hybrid.max())
    bar = np.searchsorted(edges, [np.median(local_poe), np.median(hybrid)])
    assert bar[0] != bar[1], "the two methods' typical errors fall in one bar"


def test_training_curve_axis_names_the_loss_and_its_unit(tmp_path, monkeypatch):
    plt = reports._plt()
    axes = []
    subplots = plt.subplots

    def keep(*args, **kwargs):
        fig, ax = subplots(*args, **kwargs)
        axes.append(ax)
        return fig, ax

    monkeypatch.setattr(plt, "subplots", keep)
    curve = {"train": [3.0, 2.0, 1.5], "val": [3.2, 2.5, 2.6]}
    reports._plot_curve(plt, curve, 1, tmp_path / "c.png", "network training", "joint")
    assert "dimensionless" in axes[0].get_ylabel() and "eq. 21" in axes[0].get_ylabel()
    reports._plot_curve(plt, curve, 1, tmp_path / "d.png", "network training", "task")
    assert "eq. 20" in axes[1].get_ylabel()
    assert (tmp_path / "c.png").stat().st_size > 0
    # the fit stores which loss its network trained on, so the report can say it
    stored = slim_info({"kept": "ann", "ann": {"curve": curve, "stopped_at": 1, "loss": "task", "lr": 0.1}})
    assert stored["ann"]["loss"] == "task" and "lr" not in stored["ann"]


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Arm sim-3 calibrated on 30 poses; evaluated on 12 new poses of the same arm and on 12 of another arm."""
    root = tmp_path_factory.mktemp("findings")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"

    def session(poses: int, seed: int, sim_seed: int) -> str:
        r = invoke(
            "session", "new", "--robot", "ur10", "--targets", root / "targets.toml", "--poses", poses,
            "--seed", seed, "--sim-seed", sim_seed, store=store,
        )  # fmt: skip
        assert r.exit_code == 0, r.stdout + r.stderr
        return last_line(r)

    ref, same_arm, other_arm = session(30, 3, 3), session(12, 30, 3), session(12, 40, 4)
    f = invoke("fit", ref, "--method", "local-poe", "--val-fraction", 0, store=store)
    assert f.exit_code == 0, f.stderr
    fit = last_line(f)
    evaluations = {}
    for name, data in (("same", same_arm), ("other", other_arm)):
        e = invoke("evaluate", fit, "--data", data, store=store)
        assert e.exit_code == 0, e.stderr
        evaluations[name] = last_line(e)
    r = invoke("report", ref, "--out", root / "report", store=store)
    assert r.exit_code == 0, r.stderr
    return {"text": Path(last_line(r)).read_text(), "fit": fit, "evaluations": evaluations, "refs": [ref, other_arm]}


def test_report_warns_when_a_fit_makes_held_out_data_worse(world):
    text = world["text"]
    warnings = text[text.index("## Warnings") : text.index("## Fit ")]
    assert "None:" not in warnings
    assert f"**WARNING [worse-than-before]** fit {world['fit']}" in warnings
    assert f"evaluation {world['evaluations']['other']} on {world['refs'][1]}" in warnings
    assert world["evaluations"]["same"] not in warnings, "the same arm's new poses got better: no warning"
    fit_section = text[text.index(f"## Fit {world['fit']}") :]
    assert "WARNING [worse-than-before]" in fit_section


def test_report_names_the_arm_and_tracker_it_calibrated(world):
    head = world["text"][: world["text"].index("## Warnings")]
    assert "Measured with: arm serial **sim-3** (model ur10), sim driver; tracker: serial not reported" in head


def test_held_out_worse_reads_val_and_test_of_the_fit_and_all_of_an_evaluation():
    better = {"before": {"pos_mean": 0.003}, "after": {"pos_mean": 0.001}}
    worse = {"before": {"pos_mean": 0.003}, "after": {"pos_mean": 0.004}, "points": {
        "before": {"mean": 0.0030}, "after": {"mean": 0.0035}}}  # fmt: skip
    assert reports.held_out_worse({"train": worse, "val": better, "test": better}, "the fit's") == []
    assert reports.held_out_worse({"val": worse}, "the fit's") == [
        "the fit's val split: mean point error 3.0000 → 3.5000 mm, mean position error 3.0000 → 4.0000 mm"
    ]
    assert reports.held_out_worse({"all": worse}, "evaluation E on S@v001") == [
        "evaluation E on S@v001: mean point error 3.0000 → 3.5000 mm, mean position error 3.0000 → 4.0000 mm"
    ]
    assert reports.held_out_worse({"all": {"before": {"pos_mean": float("nan")}, "after": {}}}, "evaluation E") == []
