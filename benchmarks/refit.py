"""`labcal refit` throughput (issue 17): N simulated sessions refitted serially and on a Dask LocalCluster.

    python benchmarks/refit.py [--sessions 200] [--poses 30] [--method local-poe] [--jobs 2] [--auto-sample 4]
                               [--store DIR] [--out benchmarks/results/refit.txt]

1. Makes N small simulated ur10 sessions (one simulated robot per seed, the example targets) into a temporary
   store, or reuses --store DIR if it already holds them.
2. Refits all of them with --method through ``run_refit``: once in this process, once with --jobs worker
   processes (``LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True)``, started inside the timing).
3. Measures the executor alone: cluster start-up + shutdown, and the round trip of N tasks that do nothing but
   take a refit task and return a row, so the per-fit overhead is separated from the fit.
4. Times ``auto`` on a few sessions (the method a nightly refit would run) and prints, on paper, what a fleet's
   nightly refit takes on a small cluster from these numbers (assumptions printed with it).

The machine's load average is printed beside the times: the benchmark machine is shared and its load moves them.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tempfile
import time
from pathlib import Path

TARGETS = Path(__file__).resolve().parents[1] / "drivers" / "targets-example.toml"


def _noop(task):
    """A refit task's round trip without the fit: what the executor costs per task."""
    from labcal.cli.ops.refit import NOT_RUN, RefitRow

    return RefitRow(task.ref, NOT_RUN, task.before)


def make_store(root: Path, n: int, poses: int) -> tuple[list[str], float]:
    from labcal.cli.common import open_store
    from labcal.cli.ops.sessions import new_session

    store = open_store(root, create=True)
    have = store.session_ids()
    t0 = time.perf_counter()
    for seed in range(len(have), n):
        new_session(store, robot="ur10", targets_file=TARGETS, poses=poses, seed=seed)
    made = time.perf_counter() - t0
    refs = [f"{s}@v{store.versions(s)[-1]:03d}" for s in store.session_ids()[:n]]
    return refs, made


def _import_labcal() -> None:
    # What the first refit task in a fresh worker imports.
    import labcal.calibration.fit
    import labcal.cli.ops.fitting
    import labcal.cli.ops.refit  # noqa: F401


def executor_overhead(store, refs: list[str], jobs: int) -> tuple[float, float, float]:
    """(cluster start-up + shutdown s, labcal import in every worker s, per-task round trip s) of the
    LocalCluster that run_refit uses; the round trip is measured on warm workers with no-op refit tasks."""
    from distributed import Client, LocalCluster, as_completed

    from labcal.cli.ops.refit import plan_tasks

    tasks = plan_tasks(store, refs, "local-poe")
    t0 = time.perf_counter()
    cluster = LocalCluster(
        n_workers=jobs,
        threads_per_worker=1,
        processes=True,
        dashboard_address="127.0.0.1:0",
        silence_logs=logging.ERROR,
    )
    client = Client(cluster)
    started = time.perf_counter() - t0
    t1 = time.perf_counter()
    client.run(_import_labcal)
    imported = time.perf_counter() - t1
    t2 = time.perf_counter()
    futures = [client.submit(_noop, t, pure=False) for t in tasks]
    for f in as_completed(futures):
        f.result()
    per_task = (time.perf_counter() - t2) / len(tasks)
    t3 = time.perf_counter()
    client.close()
    cluster.close()
    return started + time.perf_counter() - t3, imported, per_task


def _numpy_work(seconds: float) -> int:
    """A CPU-bound numpy loop like a fit's (small SVDs), for about ``seconds`` on an idle core; returns its count."""
    import numpy as np

    rng = np.random.default_rng(0)
    a = rng.standard_normal((60, 30))
    n, t0 = 0, time.process_time()
    while time.process_time() - t0 < seconds:
        np.linalg.svd(a, full_matrices=False)
        n += 1
    return n


def machine_parallelism(jobs: int, seconds: float = 3.0) -> float:
    """How many of ``jobs`` processes' worth of numpy work this machine does at once right now (jobs = perfect).

    The same loop in 1 process and in ``jobs`` processes at once, each stopping after ``seconds`` of CPU time;
    the ratio of work per wall second. It tells what speed-up a parallel refit can find on this machine today."""
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(jobs) as pool:
        pool.map(_numpy_work, [0.01] * jobs)  # processes up and numpy imported
        t0 = time.perf_counter()
        one = pool.apply(_numpy_work, (seconds,)) / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        many = sum(pool.map(_numpy_work, [seconds] * jobs)) / (time.perf_counter() - t0)
    return many / one


def load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=200)
    ap.add_argument("--poses", type=int, default=30)
    ap.add_argument("--method", default="local-poe")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--auto-sample", type=int, default=4, help="sessions to time `auto` on (0: skip)")
    ap.add_argument("--store", type=Path, default=None, help="keep the sessions here (reused when present)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--parallel-first", action="store_true", help="run the --jobs refit before the serial one")
    ap.add_argument("--fleet", type=int, default=100, help="arms in the on-paper estimate")
    ap.add_argument("--cluster-workers", type=int, default=32, help="worker processes of the 'small cluster'")
    args = ap.parse_args(argv)

    from labcal.cli.common import open_store
    from labcal.cli.ops.refit import FITTED, run_refit

    lines: list[str] = []

    def say(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    tmp = None
    root = args.store
    if root is None:
        tmp = tempfile.TemporaryDirectory(prefix="labcal-refit-bench-")
        root = Path(tmp.name) / "store"
    refs, made = make_store(root, args.sessions, args.poses)
    store = open_store(root)
    say(f"# labcal refit benchmark: {len(refs)} simulated ur10 sessions x {args.poses} poses (3 targets), "
        f"--method {args.method}, {os.cpu_count()} cores")  # fmt: skip
    say(f"# command: python benchmarks/refit.py {' '.join(argv if argv is not None else sys.argv[1:])}".rstrip())
    say(f"# sessions made in {made:.1f} s (0 = reused)")
    say()

    results = {}
    for jobs in (args.jobs, 1) if args.parallel_first else (1, args.jobs):
        before = load()
        t0 = time.perf_counter()
        report = run_refit(store, refs, args.method, seed=0, jobs=jobs)
        wall = time.perf_counter() - t0
        fitted = [r for r in report.rows if r.status == FITTED]
        # fit() measures its stages' wall time into fit.json: how long the fits took where they ran (contention shows
        # here), apart from loading, storing and the executor.
        inside = sum(
            sum(store.load_fit(r.ref, r.after.fit_id, check_files=False).metadata["fit_seconds"].values())
            for r in fitted
        )
        results[jobs] = (report.executor, wall, len(fitted), inside / max(len(fitted), 1), f"{before} -> {load()}")
    serial = results[1][1]
    start_stop, imported, per_task = executor_overhead(store, refs, args.jobs)
    say("| executor | sessions fitted | wall s | fits/s | wall s per fit | speed-up | s inside fit() per fit | "
        "load avg (1/5/15 min) before -> after |")  # fmt: skip
    say("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for jobs in (1, args.jobs):
        executor, wall, fitted, inside, ld = results[jobs]
        say(f"| {executor} | {fitted}/{len(refs)} | {wall:.1f} | {len(refs) / wall:.2f} | {wall / len(refs):.3f} | "
            f"{serial / wall:.2f}x | {inside:.3f} | {ld} |")  # fmt: skip
    par = results[args.jobs][1]
    say()
    say(f"this machine's parallelism for numpy work right now ({args.jobs} processes vs 1, small SVDs): "
        f"{machine_parallelism(args.jobs):.2f}x of {args.jobs} (load {load()})")  # fmt: skip
    implied = (args.jobs * par - serial) / len(refs)
    say()
    say(f"executor alone ({args.jobs}-process LocalCluster, {len(refs)} no-op refit tasks):")
    say(f"  cluster start-up + shutdown: {start_stop:.2f} s per run")
    say(f"  importing labcal's fitting code in the fresh workers (in parallel): {imported:.2f} s per run")
    say(f"  per-task round trip on warm workers (submit, pickle the task, run, return the row): "
        f"{per_task * 1e3:.1f} ms "
        f"= {per_task / (serial / len(refs)) * 100:.1f} % of a serial {args.method} fit")  # fmt: skip
    say(f"  implied per-fit overhead of the {args.jobs}-worker run, (jobs x wall - serial wall) / N: "
        f"{implied * 1e3:.0f} ms (start-up, scheduling, imbalance and the machine's other load together)")  # fmt: skip

    fit_1 = serial / len(refs)
    fixed = start_stop + imported
    ideal = serial / (fixed + len(refs) * (fit_1 + per_task) / args.jobs)
    say(f"  on paper, the same run on {args.jobs} idle cores: {fixed:.1f} s + {len(refs)} x ({fit_1:.3f} s + "
        f"{per_task * 1e3:.0f} ms) / {args.jobs} = speed-up {ideal:.2f}x (the limit for many sessions: "
        f"{args.jobs * fit_1 / (fit_1 + per_task):.2f}x)")  # fmt: skip

    auto_fit = None
    if args.auto_sample:
        sample = refs[: args.auto_sample]
        t0 = time.perf_counter()
        report = run_refit(store, sample, "auto", seed=0)
        auto_fit = (time.perf_counter() - t0) / len(sample)
        say()
        say(f"auto on {len(sample)} of these sessions, serially: {auto_fit:.2f} s per fit "
            f"({sum(r.status == FITTED for r in report.rows)}/{len(sample)} fitted; load {load()})")  # fmt: skip

    fit_s = auto_fit if auto_fit is not None else serial / len(refs)
    w = args.cluster_workers
    waves = math.ceil(args.fleet / w)
    estimate = start_stop + imported + waves * (fit_s + per_task)
    say()
    say(f"On paper: nightly refit of a {args.fleet}-arm fleet on a small cluster ({w} worker processes, e.g. 4 "
        f"nodes x 8 cores):")  # fmt: skip
    say(f"  assumptions: one new {args.poses}-pose version per arm per night; {'auto' if auto_fit else args.method} "
        f"at the {fit_s:.1f} s per fit measured here (a core of this shared machine; a dedicated core is faster); "
        "fit time grows about linearly with poses for local POE and faster for the learned stages; the store on a "
        "shared file system where rename is atomic (NFS, CephFS); workers with labcal installed")  # fmt: skip
    say(f"  {args.fleet} fits / {w} workers = {waves} wave(s) x ({fit_s:.1f} s + {per_task * 1e3:.0f} ms) + "
        f"{start_stop + imported:.1f} s cluster start-up and imports = {estimate:.0f} s; serially on one core: "
        f"{args.fleet * fit_s / 60:.1f} min")  # fmt: skip
    say("  the fits are independent, so the time falls with workers until one fit per worker; below that the "
        "longest fit and the store's file system set it")  # fmt: skip
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
