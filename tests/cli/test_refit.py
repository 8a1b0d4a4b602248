"""`labcal refit`: selection, the stored fits equal `labcal fit`'s byte for byte (serially and on a Dask
LocalCluster of processes), failures and Ctrl-C reported without stopping or half-writing, and a worker killed
mid-run loses no fit, stores none twice and leaves no partial one."""

from __future__ import annotations

import functools
import hashlib
import os
import signal
import sys
from pathlib import Path

import cloudpickle
import pytest
from distributed import LocalCluster
from typer.testing import CliRunner

from labcal.cli.app import app
from labcal.cli.common import open_store
from labcal.cli.ops.refit import FAILED, FITTED, NOT_RUN, Selection, run_refit, select_versions, session_created
from labcal.cli.ops.sessions import new_session
from labcal.datasets import SessionStore

TARGETS = "drivers/targets-example.toml"
METHOD = "local-poe"  # the quickest method that goes through every step of run_fit (CV, gates, store)

runner = CliRunner()

# Dask workers cannot import this test module: the fault-injecting hooks below travel by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def invoke(*args, store: Path):
    return runner.invoke(app, [str(a) for a in args] + ["--store", str(store)])


def sim(store: SessionStore, seed: int, *, robot: str = "ur10", unit: str | None = None, poses: int = 16) -> str:
    """A small simulated session (its own simulated robot per seed) of unit ``unit`` (default: sim-<seed>)."""
    return new_session(store, robot=robot, targets_file=TARGETS, poses=poses, seed=seed, unit=unit).ref


def sim_without_unit(store: SessionStore, seed: int, *, robot: str = "ur10", poses: int = 16) -> str:
    """A session like those recorded before units were stored: no "unit" in its metadata."""
    from labcal.cli.ops.sessions import sim_actual
    from labcal.datasets import load_targets
    from labcal.drivers.sim import SimRig
    from labcal.robots import load
    from labcal.sessions import make_plan, random_configurations, run

    spec = load(robot)
    targets = load_targets(TARGETS)
    plan = make_plan(random_configurations(spec.model, poses, seed=seed, targets=targets), samples=3, settle=0.0)
    rig = SimRig(sim_actual(spec, "default", seed), targets, seed=seed)
    meta = {"sim": {"errors": "default", "seed": seed, "noise_seed": seed}}
    with rig.robot() as rob, rig.tracker() as trk:
        ref = run(store, spec, targets, plan, rob, trk, frame="base", metadata=meta).ref
    assert "unit" not in store.session_meta(ref.split("@")[0])["metadata"]
    return ref


def fit_ids(store: SessionStore, ref: str) -> list[str]:
    return [f.fit_id for f in store.list_fits(ref)]


def fingerprint(store: SessionStore, ref: str, fit_id: str) -> dict:
    """What must not depend on how a fit was run: the sha256 of every fit file and fit.json's record apart from
    the fit id, the times and the measured fit duration."""
    record = store.load_fit(ref, fit_id)
    meta = {k: v for k, v in record.meta.items() if k not in ("fit_id", "created", "fit_sha256")}
    meta["metadata"] = {k: v for k, v in meta["metadata"].items() if k != "fit_seconds"}
    files = {name: hashlib.sha256(record.read(name)).hexdigest() for name in record.files}
    return {"files": files, "meta": meta}


def no_temp_folders(store: SessionStore) -> bool:
    return not list(Path(store.root).glob("*/v*/fits/.tmp-*"))


def intact(store: SessionStore, ref: str) -> bool:
    return store.verify(ref).ok and store.verify_fits(ref).ok


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Three ur10 sessions (two of unit arm-1, one of arm-2), one ur5e session without a unit, one of unit sim-5."""
    store = open_store(tmp_path_factory.mktemp("refit") / "store", create=True)
    refs = [sim(store, 1, unit="arm-1"), sim(store, 2, unit="arm-2"), sim(store, 3, unit="arm-1")]
    refs.append(sim_without_unit(store, 4, robot="ur5e"))
    refs.append(sim(store, 5, robot="ur5e"))
    return store, refs


def test_selection_by_robot_unit_and_start_time(fleet):
    store, (a1, a2, a3, other, sim5) = fleet
    assert select_versions(store, Selection(everything=True))[0] == [a1, a2, a3, other, sim5]
    assert select_versions(store, Selection(robot="UR10"))[0] == [a1, a2, a3]
    assert select_versions(store, Selection(robot="ur5e"))[0] == [other, sim5]
    # The unit identity is the session metadata's "unit" (`session new` records sim-<seed> on the sim rig).
    assert select_versions(store, Selection(unit="arm-1"))[0] == [a1, a3]
    assert select_versions(store, Selection(unit="sim-5"))[0] == [sim5]
    assert select_versions(store, Selection(unit="arm-1", robot="ur5e"))[0] == []
    since = session_created(store, a2.split("@")[0])
    assert select_versions(store, Selection(since=since))[0] == [a2, a3, other, sim5]
    assert select_versions(store, Selection(refs=(a3.split("@")[0],)))[0] == [a3]


def test_no_selection_is_a_usage_error(fleet):
    store, _ = fleet
    result = invoke("refit", "--method", METHOD, store=store.root)
    assert result.exit_code == 2
    assert "--all" in result.stderr
    result = invoke("refit", "--all", "--since", "last tuesday", store=store.root)
    assert result.exit_code == 2 and "--since" in result.stderr


def test_refit_stores_what_labcal_fit_stores_serially_and_on_a_local_cluster(fleet):
    store, (a1, a2, a3, *_) = fleet
    result = invoke("fit", a1, "--method", METHOD, "--seed", "3", store=store.root)
    assert result.exit_code == 0, result.stderr
    by_fit = result.stdout.strip().splitlines()[-1]

    serial = invoke("refit", "--unit", "arm-1", "--method", METHOD, "--seed", "3", store=store.root)
    assert serial.exit_code == 0, serial.stderr
    dask = invoke("refit", "--unit", "arm-1", "--method", METHOD, "--seed", "3", "--jobs", "2", store=store.root)
    assert dask.exit_code == 0, dask.stderr
    assert "LocalCluster (2 processes)" in dask.stdout

    first, by_serial, by_dask = fit_ids(store, a1)
    assert first == by_fit
    expected = fingerprint(store, a1, by_fit)
    assert fingerprint(store, a1, by_serial) == expected
    assert fingerprint(store, a1, by_dask) == expected
    # a3 had no fit before; both runs stored the same fit; a2 (unit arm-2) was not touched.
    serial_a3, dask_a3 = fit_ids(store, a3)
    assert fingerprint(store, a3, serial_a3) == fingerprint(store, a3, dask_a3)
    assert fit_ids(store, a2) == []
    # The table's "before" of the second run is the first run's fit; every fit verifies.
    assert by_serial in dask.stdout and by_dask in dask.stdout
    assert intact(store, a1) and intact(store, a3) and no_temp_folders(store)


def test_a_failed_session_is_reported_and_the_others_are_fitted_warnings_and_all(tmp_path):
    store = open_store(tmp_path / "store", create=True)
    good, bad, warned = sim(store, 5), sim(store, 6), sim(store, 10, poses=5)
    data = store.version_dir(bad) / "measurements.parquet"
    data.chmod(0o644)
    data.write_bytes(data.read_bytes() + b"x")  # damaged after it was sealed: the fit must refuse it
    result = invoke("refit", "--all", "--method", METHOD, store=store.root)
    assert result.exit_code == 1
    assert "1 failed" in result.stderr and "DatasetCorrupted" in result.stdout
    assert len(fit_ids(store, good)) == 1 and intact(store, good)
    # A fit with warnings is stored as `labcal fit` stores it (export refuses it), listed with its warning codes.
    (stored,) = store.list_fits(warned)
    assert "few-poses" in {w["code"] for w in stored.metadata["warnings"]}
    assert "few-poses" in result.stdout and intact(store, warned)
    assert not (store.version_dir(bad) / "fits").exists() or fit_ids(store, bad) == []


def test_ctrl_c_keeps_the_finished_fits_and_half_writes_nothing(tmp_path, monkeypatch):
    store = open_store(tmp_path / "store", create=True)
    first, second, third = sim(store, 7), sim(store, 8), sim(store, 9)
    import labcal.datasets.store as store_module

    write = store_module.write_file_durable
    seen = []

    def interrupted_on_the_second_fit_json(path, data):
        if path.name == "fit.json":
            seen.append(path)
            if len(seen) == 2:
                raise KeyboardInterrupt  # after the second fit's files are in its temporary folder
        return write(path, data)

    monkeypatch.setattr(store_module, "write_file_durable", interrupted_on_the_second_fit_json)
    result = invoke("refit", "--all", "--method", METHOD, store=store.root)
    assert result.exit_code == 130
    assert "interrupted" in result.stderr
    assert len(fit_ids(store, first)) == 1
    assert fit_ids(store, second) == [] and fit_ids(store, third) == []
    assert no_temp_folders(store) and all(intact(store, r) for r in (first, second, third))


def _die_once(markers: str | None, when: str, task) -> None:
    """In the worker: kill this worker process (SIGKILL, no clean-up) once per marker file (every time without
    ``markers``), at ``when``: "mid-write" (the fit's files are in its temporary folder, fit.json not yet written)
    or "published" (the fit was renamed into place, the task has not returned)."""
    import labcal.datasets.store as store_module

    if markers is not None:
        marker = Path(markers) / f"{task.ref}.{when}"
        if marker.exists():
            return
        marker.touch()
    original = store_module.write_file_durable if when == "mid-write" else store_module.publish_dir

    def die(*args, **kwargs):
        if when == "mid-write" and Path(args[0]).name == "fit.json":
            os.kill(os.getpid(), signal.SIGKILL)
        result = original(*args, **kwargs)
        if when == "published":
            os.kill(os.getpid(), signal.SIGKILL)
        return result

    setattr(store_module, "write_file_durable" if when == "mid-write" else "publish_dir", die)


def _die_by_ref(markers: str, plan: dict, task) -> None:
    if task.ref in plan:
        _die_once(markers, plan[task.ref], task)


def test_a_worker_killed_mid_run_loses_no_fit_and_leaves_no_partial_one(tmp_path):
    store = open_store(tmp_path / "store", create=True)
    mid_write, published, calm = sim(store, 11), sim(store, 12), sim(store, 13)
    reference = run_refit(store, [mid_write, published, calm], METHOD, seed=1)
    assert [r.status for r in reference.rows] == [FITTED] * 3
    markers = tmp_path / "markers"
    markers.mkdir()
    hook = functools.partial(_die_by_ref, str(markers), {mid_write: "mid-write", published: "published"})

    # A cluster of its own, reached by address like `--scheduler`, so that path is covered too (--jobs is above).
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        report = run_refit(store, [mid_write, published, calm], METHOD, seed=1, scheduler=cluster.scheduler_address,
                           hook=hook)  # fmt: skip
    assert report.executor.startswith("dask scheduler tcp://")

    # Both faults happened (each worker process was killed once) and Dask ran the tasks again elsewhere.
    assert sorted(p.name for p in markers.iterdir()) == sorted([f"{mid_write}.mid-write", f"{published}.published"])
    assert [r.status for r in report.rows] == [FITTED] * 3, [r.message for r in report.rows]
    assert report.exit_code == 0
    # The attempt that died after publishing had stored the fit: the retry found it instead of fitting again.
    assert "earlier attempt" in report.rows[1].message
    for ref, before, row in zip((mid_write, published, calm), reference.rows, report.rows, strict=True):
        assert fit_ids(store, ref) == [before.after.fit_id, row.after.fit_id]  # one new fit each, none twice
        assert fingerprint(store, ref, row.after.fit_id) == fingerprint(store, ref, before.after.fit_id)
        assert row.before.fit_id == before.after.fit_id
        assert intact(store, ref)
    assert no_temp_folders(store)  # the dead attempt's temporary folder was removed


def test_not_run_rows_after_an_interrupt_name_every_selected_version(tmp_path, monkeypatch):
    store = open_store(tmp_path / "store", create=True)
    refs = [sim(store, 14), sim(store, 15)]
    import labcal.cli.ops.refit as refit_module

    def interrupt(task):
        raise KeyboardInterrupt

    monkeypatch.setattr(refit_module, "refit_one", interrupt)
    report = run_refit(store, refs, METHOD)
    assert report.interrupted and report.exit_code == 130
    assert [(r.ref, r.status) for r in report.rows] == [(refs[0], NOT_RUN), (refs[1], NOT_RUN)]
    assert FAILED not in {r.status for r in report.rows}


def test_a_task_whose_worker_keeps_dying_is_failed_unless_its_fit_was_published(tmp_path):
    import dask

    store = open_store(tmp_path / "store", create=True)
    never, published = sim(store, 16), sim(store, 17)
    die_writing, die_published = (functools.partial(_die_once, None, when) for when in ("mid-write", "published"))
    # Dask gives a task up (KilledWorker) after its worker died more often than allowed: here at the first death.
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
            address = cluster.scheduler_address
            lost = run_refit(store, [never], METHOD, scheduler=address, hook=die_writing)
            kept = run_refit(store, [published], METHOD, scheduler=address, hook=die_published)
    (row,) = lost.rows
    assert row.status == FAILED and "KilledWorker" in row.message and lost.exit_code == 1
    assert fit_ids(store, never) == []
    # The attempt that died after publishing had stored a complete fit: it is reported, not lost.
    (row,) = kept.rows
    assert row.status == FITTED and "gave up" in row.message and kept.exit_code == 0
    assert fit_ids(store, published) == [row.after.fit_id]
    assert intact(store, never) and intact(store, published) and no_temp_folders(store)
