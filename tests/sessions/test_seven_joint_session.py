"""`labcal session new` with the sim drivers on a 7-joint arm (Franka Panda), one reflector and three targets,
through to a stored local-POE fit."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from labcal.cli.app import app
from labcal.datasets import SessionStore
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

runner = CliRunner()
TARGETS = {
    "one": ('unit = "mm"\npoints = [[0, 0, 45]]\n', [[0.0, 0.0, 0.045]]),
    "three": (
        'unit = "mm"\npoints = [[0, 0, 45], [0, 80, 45], [60, 0, 45]]\n',
        [[0.0, 0.0, 0.045], [0.0, 0.08, 0.045], [0.06, 0.0, 0.045]],
    ),
}


@pytest.mark.parametrize("targets", ["one", "three"])
def test_a_sim_panda_session_records_seven_joints_within_limits_and_fits(tmp_path, targets):
    text, points = TARGETS[targets]
    (tmp_path / "t.toml").write_text(text)
    store = tmp_path / "store"
    r = runner.invoke(app, ["session", "new", "--robot", "franka-panda", "--targets", str(tmp_path / "t.toml"),
                            "--poses", "40", "--seed", "3", "--store", str(store)])  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = r.stdout.strip().splitlines()[-1]
    ds = SessionStore(store).load(ref)
    spec = load("franka-panda")
    assert ds.q.shape == (40, 7) and ds.points.shape == (40, len(points), 3) and ds.seen.all()
    assert np.all((ds.q >= spec.model.limits[:, 0]) & (ds.q <= spec.model.limits[:, 1]))
    # measured from the simulated Panda of --seed 3 with the default errors (geometric + compliance + gears)
    actual = simulate(spec, ErrorSpec.default(), seed=3)
    true = actual.true_points(ds.q, np.array(points))
    assert np.abs(ds.points - true).max() < 6 * ErrorSpec.default().tracker_noise
    assert np.abs(ds.points - spec.model.target_points(ds.q, np.array(points))).max() > 1e-3  # not the nominal

    fit = runner.invoke(app, ["fit", ref, "--method", "local-poe", "--json", "--store", str(store)])
    assert fit.exit_code == 0, fit.stdout + fit.stderr
    doc = json.loads(fit.stdout)
    points = doc["metrics"]["all"]["points"]  # point errors: a single reflector gives no pose
    assert points["after"]["count"] == 40 * len(TARGETS[targets][1])
    assert points["after"]["mean_m"] < 0.05 * points["before"]["mean_m"] and points["after"]["mean_m"] < 0.2e-3
