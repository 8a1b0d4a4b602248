"""Sessions with 1..k targets and targets not seen (issue 15.1): runner validation, the CLI, the planner."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from labcal.cli.ops.common import load_observations
from labcal.cli.ops.sessions import new_session
from labcal.datasets import SessionStore, read_journal
from labcal.datasets.targets import pair_distances
from labcal.drivers.base import Measurement
from labcal.drivers.sim import SimRig
from labcal.robots import load
from labcal.sessions import (
    Validation,
    check_measurement,
    make_plan,
    random_configurations,
    run,
)
from labcal.sessions.planning import identifiable_basis, optimal_configurations, target_weights
from labcal.simulation import ErrorSpec, simulate
from planning import observability  # benchmarks/planning.py: the indices the planner maximises

FOUR = np.array([[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03], [0.0, 0.0, 0.09]])


def _measurement(points, spread=None):
    pts = np.asarray(points, dtype=float)
    seen = np.isfinite(pts).all(axis=1)
    return Measurement(pts, 0.0, spread=np.where(seen, 0.0, np.nan) if spread is None else spread)


def test_distances_are_checked_only_between_targets_seen_together():
    v = Validation(absolute_tolerance=0.5e-3, spread_factor=0.0)
    moved = FOUR.copy()
    moved[3, 2] += 2e-3  # t4 2 mm off: every pair with t4 is 2 mm off
    why, err = check_measurement(_measurement(moved), FOUR, v)
    off = max(abs(np.linalg.norm(moved[3] - FOUR[i]) - np.linalg.norm(FOUR[3] - FOUR[i])) for i in range(3))
    assert "distances between the targets seen" in why and err == pytest.approx(off, rel=1e-12) and off > 1e-3
    without_t4 = moved.copy()
    without_t4[3] = np.nan
    assert check_measurement(_measurement(without_t4), FOUR, v) == ("", pytest.approx(0.0, abs=1e-12))
    only_t4 = np.full((4, 3), np.nan)
    only_t4[3] = moved[3]
    assert check_measurement(_measurement(only_t4), FOUR, v) == ("", None)  # one target seen: valid, no distance
    # A driver's Measurement cannot be empty; a duck-typed one from another tracker still gets a clear reason.
    blind = SimpleNamespace(points=np.full((4, 3), np.nan), spread=np.full(4, np.nan))
    assert check_measurement(blind, FOUR, v)[0] == "no target seen"
    half = SimpleNamespace(points=np.where(np.arange(3)[None, :] == 1, np.nan, FOUR), spread=np.zeros(4))
    assert "t1, t2, t3, t4 partly non-finite" in check_measurement(half, FOUR, v)[0]
    two_of_three = _measurement(without_t4[[0, 1, 3]])
    assert "2 seen, 3 needed" in check_measurement(two_of_three, FOUR[:3], Validation(min_targets=3))[0]
    assert check_measurement(_measurement(FOUR[:1]), FOUR[:1], v) == ("", None)
    # Three targets: the pairs are the triangle's sides in the historical order.
    assert np.isnan(pair_distances(without_t4)[[2, 4, 5]]).all()  # the pairs with t4: t1t4, t2t4, t3t4


def test_a_one_target_run_with_dropouts_records_valid_rows_and_not_seen_targets(tmp_path):
    spec = load("ur10")
    targets = FOUR[:2]
    actual = simulate(spec, ErrorSpec.default(), seed=4)
    rig = SimRig(actual, targets, seed=4, dropout=[0.0, 0.5])
    q = random_configurations(spec.model, 16, seed=4, targets=targets)
    store = SessionStore(tmp_path)
    with rig.robot() as robot, rig.tracker() as tracker:
        summary = run(store, spec, targets, make_plan(q, samples=1, settle=0.0), robot, tracker, frame="base",
                      sleep=lambda t: None)  # fmt: skip
    assert summary.exit_status == "success" and summary.valid == 16
    ds = store.load(summary.ref)
    assert ds.points.shape == (16, 2, 3) and ds.seen[:, 0].all() and 0 < ds.seen[:, 1].sum() < 16
    docs = read_journal(store.session_dir(summary.session_id) / "journal.jsonl").measurements
    lost = [d for d in docs if d.points[1] is None]
    assert len(lost) == int((~ds.seen[:, 1]).sum()) and all(d.spread[1] is None for d in lost)
    assert all(d.extra["triangle_error"] is None for d in lost)  # one target seen: no distance to check


def test_session_new_with_a_single_target_and_sim_dropout_fits_from_the_store(tmp_path):
    tfile = tmp_path / "one.toml"
    tfile.write_text('unit = "mm"\npoints = [[0, 0, 45], [0, 60, 45]]\n')
    store = SessionStore(tmp_path / "s")
    summary = new_session(store, robot="ur10", targets_file=tfile, poses=30, seed=1, sim_dropout=0.3)
    assert summary.exit_status == "success"
    ds = store.load(summary.ref)
    assert ds.n_targets == 2 and not ds.seen.all() and ds.seen.any(axis=1).all()
    assert ds.manifest["session"]["metadata"]["sim"]["dropout"] == 0.3
    obs, _ = load_observations(store, [summary.ref])
    np.testing.assert_array_equal(obs.seen, ds.seen)


def test_sim_dropout_is_checked_before_anything_runs(tmp_path):
    from labcal.cli.common import UserError

    with pytest.raises(UserError, match="--sim-dropout must be a probability"):
        new_session(SessionStore(tmp_path / "s"), robot="ur10", targets_file=tmp_path / "none.toml", poses=3,
                    sim_dropout=1.0)  # fmt: skip
    assert not (tmp_path / "s").exists()


def test_observability_counts_the_points_measured():
    model = load("ur10").model
    q = random_configurations(model, 12, seed=2)
    basis = identifiable_basis(model, FOUR[:3])
    full = observability(model, q, FOUR[:3], basis=basis)
    assert full.rows == 12 * 9
    seen = np.ones((12, 3), bool)
    seen[::2, 2] = False  # t3 lost in every other configuration
    fewer = observability(model, q, FOUR[:3], basis=basis, seen=seen)
    assert fewer.rows == 3 * seen.sum() and fewer.log_det < full.log_det
    same = observability(model, q, FOUR[:3], basis=basis, seen=np.ones((12, 3), bool))
    assert same.rows == full.rows and same.log_det == pytest.approx(full.log_det, rel=1e-12)
    # A drop-out probability gives the expected information: det scales by (1 - p)^r on r parameters.
    half = observability(model, q, FOUR[:3], basis=basis, dropout=0.5)
    assert half.rows == pytest.approx(0.5 * full.rows)
    assert half.log_det == pytest.approx(full.log_det + full.parameters * np.log(0.5), rel=1e-9)
    assert target_weights(3, dropout=[0.0, 0.5, 0.25]).tolist() == [[1.0, 0.5, 0.75]]
    with pytest.raises(ValueError, match="probabilities"):
        target_weights(2, dropout=1.0)


def test_the_optimal_planner_weighs_targets_that_are_often_lost():
    model = load("ur10").model
    pool = random_configurations(model, 60, seed=3)
    plain = optimal_configurations(model, 10, seed=3, targets=FOUR[:3], pool=pool, criterion="d")
    same = optimal_configurations(model, 10, seed=3, targets=FOUR[:3], pool=pool, criterion="d", dropout=0.0)
    assert np.array_equal(plain, same)
    lossy = optimal_configurations(model, 10, seed=3, targets=FOUR[:3], pool=pool, criterion="d",
                                   dropout=[0.0, 0.0, 0.95])  # fmt: skip
    again = optimal_configurations(model, 10, seed=3, targets=FOUR[:3], pool=pool, criterion="d",
                                   dropout=[0.0, 0.0, 0.95])  # fmt: skip
    assert np.array_equal(lossy, again) and not np.array_equal(lossy, plain)  # t3's rows weigh 5 % now
    # The same drop-out for every target scales all information alike: the same choice as without drop-outs.
    uniform = optimal_configurations(model, 10, seed=3, targets=FOUR[:3], pool=pool, criterion="d", dropout=0.3)
    assert np.array_equal(uniform, plain)


def test_a_session_recorded_before_1_to_k_targets_resumes_and_keeps_its_rows(tmp_path):
    """The journal of a three-target session written by 65c384c, cut after 9 of its 14 poses (as a crash would):
    today's runner resumes it, validates as it was recorded, and the old rows come out of the seal bit for bit."""
    import json
    from pathlib import Path

    old = Path(__file__).parents[1] / "datasets" / "data" / "old-three-targets"
    lines = (old / "journal.jsonl").read_text().splitlines()
    measured = [i for i, line in enumerate(lines) if json.loads(line)["type"] == "measurement"]
    (tmp_path / old.name).mkdir()
    (tmp_path / old.name / "journal.jsonl").write_text("\n".join(lines[: measured[8] + 1]) + "\n")
    store = SessionStore(tmp_path)
    spec = load("ur10")
    targets = np.asarray(json.loads(lines[0])["targets"])
    rig = SimRig(simulate(spec, ErrorSpec.default(), seed=3), targets, seed=3)
    from labcal.sessions import resume

    with rig.robot() as robot, rig.tracker() as tracker:
        summary = resume(store, old.name, robot, tracker, sleep=lambda t: None)
    assert summary.exit_status == "success" and summary.measured == 5 and summary.remaining == 0
    new = store.load(summary.ref).table
    before = SessionStore(old.parent).load(f"{old.name}@v1").table
    assert list(new.columns) == list(before.columns) and len(new) == 14
    pd.testing.assert_frame_equal(new.iloc[:9], before.iloc[:9], check_exact=True)
    floats = [c for c in before.columns if before[c].dtype == np.float64]
    assert new[floats].iloc[:9].to_numpy().tobytes() == before[floats].iloc[:9].to_numpy().tobytes()
