"""--sim-seed: record the same simulated robot again at other configurations (a held-out session)."""

from __future__ import annotations

import numpy as np

from labcal.cli.common import open_store
from labcal.cli.ops.evaluating import evaluate_fit
from labcal.cli.ops.fitting import run_fit
from labcal.cli.ops.sessions import new_session, resume_session

TARGETS = "drivers/targets-example.toml"


def test_a_session_with_the_same_sim_seed_measures_the_same_robot(tmp_path):
    store = open_store(tmp_path / "s", create=True)
    calibration = new_session(store, robot="ur10", targets_file=TARGETS, poses=40, seed=0).ref
    same = new_session(store, robot="ur10", targets_file=TARGETS, poses=30, seed=5, sim_seed=0).ref
    other = new_session(store, robot="ur10", targets_file=TARGETS, poses=30, seed=5).ref
    assert not np.allclose(store.load(same).q, store.load(calibration).q[:30])  # other configurations
    fit_id = run_fit(store, [calibration], "local-poe").fit_id

    def after(ref):
        return evaluate_fit(store, fit_id, ref).evaluation["metrics"]["all"]["points"]["after"]["mean"]

    # The same robot is predicted to the noise floor; another simulated robot keeps its own millimetres.
    assert after(same) < 0.5e-3 < 1e-3 < after(other)


def test_resume_recreates_the_robot_and_the_noise_of_a_sim_seed_session(tmp_path):
    store = open_store(tmp_path / "s", create=True)
    whole = new_session(store, robot="ur10", targets_file=TARGETS, poses=6, seed=5, sim_seed=0).ref
    meta = store.session_meta(whole.split("@")[0])
    assert meta["metadata"]["sim"] == {"errors": "default", "seed": 0, "noise_seed": 5}
    # Resuming a finished session has nothing to measure, but rebuilds the rig from the recorded seeds.
    assert resume_session(store, whole.split("@")[0]).remaining == 0
