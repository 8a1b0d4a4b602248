"""The paper benchmark's machinery: workspaces, sampling, one run and the tables (fast, local POE only)."""

from __future__ import annotations

import numpy as np
import pytest

import paper
from labcal.robots import load


@pytest.mark.parametrize("workspace", paper.WORKSPACES)
def test_sampled_configurations_are_non_singular_and_inside_their_workspace(workspace):
    model = load(paper.ROBOT).model
    q = paper.sample_configurations(model, 60, workspace, np.random.default_rng(0))
    assert q.shape == (60, 6)
    assert np.all(paper.condition(model, q) <= paper.MAX_CONDITION)
    assert np.all(model.within_limits(q))
    lo, hi = model.limits[:, 0], model.limits[:, 1]
    if workspace == "half":
        assert np.all(np.abs(q - (lo + hi) / 2) <= (hi - lo) / 4 + 1e-12)
    if workspace == "cell":
        T = model.fk(q)
        assert np.all(np.abs(T[:, :3, 3] - paper.CELL_CENTRE) <= paper.CELL_SIZE / 2 + 1e-9)
        tilt = np.arccos(np.clip(-T[:, 2, 2], -1, 1))  # tool z against straight down
        assert np.all(tilt <= paper.CELL_TILT + 1e-9)


def test_targets_form_the_documented_scalene_triangle():
    t = paper.TARGETS
    sides = sorted(np.linalg.norm(t[i] - t[j]) for i, j in ((0, 1), (0, 2), (1, 2)))
    assert np.allclose(sides, [0.2236, 0.2693, 0.3354], atol=1e-4)


def test_one_geometric_run_reaches_the_noise_floor_and_tables_print():
    runs = [paper.run_once(paper.ErrorSpec.paper(), 1, 50, 50, "full", ("local-poe",), n_hold=100)]
    r = runs[0]
    assert r["local-poe"].hold_pos.max() < 0.02 * r["before"].hold_pos.max()
    assert r["local-poe"].cal_pos.shape == (100,) and r["local-poe"].hold_pos.shape == (100,)
    # compensation on the simulated actual robot: the nominal pose is reached to the identification accuracy
    assert np.median(r["local-poe"].comp_pos) < 0.05 * np.median(r["before"].comp_pos)
    lines = paper.scenario_tables(runs, ("local-poe",), paper=True)
    text = "\n".join(lines)
    assert "77.12 / 76.63" in text and "Held-out" in text and "compensated" in text


def test_main_quick_smoke(capsys):
    assert (
        paper.main(["--quick", "--seeds", "1", "--scenarios", "A", "--methods", "local-poe", "--held-out", "50"]) == 0
    )
    out = capsys.readouterr().out
    assert "Scenario A" in out and "=== Goals ===" in out and "local-POE held-out max position" in out
    with pytest.raises(SystemExit):
        paper.main(["--methods", "dh"])


def test_condition_grows_towards_the_wrist_singularity():
    model = load(paper.ROBOT).model
    q = np.array([[0.3, 0.2, 0.1, 0.5, q5, 0.2] for q5 in (1.0, 0.1, 0.01)])
    c = paper.condition(model, q)
    assert c[0] < c[1] < c[2] and c[2] > paper.MAX_CONDITION
