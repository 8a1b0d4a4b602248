"""Seven joints (issue 28): ``python benchmarks/seven_joints.py [--splits 5] [--quick] [--out F]``.

A simulated Franka Emika Panda (``franka-panda``; ``--robot FILE`` for another 7-joint robot file) with geometric,
compliance and gear errors (``ErrorSpec.default``: 0.5 mm / 0.5 mrad frames and offsets, 0.2 mrad gravity
deflection, 0.05 mrad gears, 0.05 mm tracker noise), base frame, in two families:

- ``one-reflector``: one target, an SMR 50 mm along the flange axis;
- ``three-targets``: three targets on the flange (the CLI tests' nest: 120 / 117 / 117 mm off the axis).

Protocol (as ``benchmarks/robustness.py``): for split s = 0 … S−1 a true robot (seed s + 1) and ``--poses`` random
non-singular configurations over the full joint ranges (``sample_configurations`` of benchmarks/paper.py) are drawn
and a random third of them is held out. Every method is fitted on the other two thirds with
``labcal.calibration.fit(obs, nominal, method, seed=s)`` and no other option and scored on the held-out poses: the
mean distance (mm) between predicted and measured target points; beside it the ratio to the independent plain
least-squares fit (``benchmarks/plain_lsq.py``: global POE and scipy, no labcal calibration code) on the same
rows. A method that refuses (or fails) is a row ``refused: <message>``.

Exports without --force, per split: ``labcal export`` refuses a fit with blocking warnings (``FitResult.warnings``)
unless --force, so a fit with any is counted as refused for every format; otherwise the JSON and NPZ compensator
files and the URDF are written (:func:`labcal.export.export`, as ``labcal export`` calls it; effort/velocity
written as 0, as ``labcal export`` does where the robot file gives none), the JSON file is loaded back, and the
held-out configurations inside the calibration's validity region go through the program filter
(:func:`labcal.export.program.filter_joints`, what ``labcal filter --kind joints`` runs) one row at a time. A cell
reads ``ok/splits`` (filter: every row corrected); ``filter rows`` counts the rows corrected over all splits; the
first refusal of each is listed below. A URDF refused because it cannot hold a learned term is written again with
``--geometry-only`` (the flag the refusal names; it leaves that term out), counted as ``(+k --geometry-only)``.
The filter refuses, by design, a row whose nominal pose the calibrated robot cannot reach nearby: the Panda's
elbow is stretched at q4 ≈ −0.47 rad (not 0: the ±82.5 mm offsets of links 4 and 5), and the sampler's condition
limit (500) admits rows within about 0.1 rad of it, where the nominal pose can lie beyond the calibrated arm's
reach (no exact correction within 0.5 rad; the damped answer stays ~1 mm away), or where the least exact
correction exceeds the 0.1 rad bound.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import paper
from labcal.calibration import Observations, fit
from labcal.compensator import Compensator
from labcal.export import export
from labcal.export.program import filter_joints
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate
from plain_lsq import fit_plain
from robustness import HOLD_OUT, _first_line, _table, point_error

METHODS = ("local-poe", "hybrid", "auto")
FORMATS = ("json", "npz", "urdf", "filter")
FAMILIES = {
    "one-reflector": np.array([[0.0, 0.0, 0.05]]),
    "three-targets": np.array([[0.12, 0.0, 0.06], [-0.06, 0.10, 0.06], [-0.06, -0.10, 0.09]]),
}


def exports(result, q_test: np.ndarray, folder: Path) -> dict[str, str]:
    """{format: "ok" or the first line of why it was refused} for one fit, without --force."""
    if result.warnings:
        codes = ", ".join(sorted({str(w.get("code")) for w in result.warnings}))
        return {**dict.fromkeys(FORMATS, f"needs --force: fit warnings [{codes}]"), "filter-rows": (0, 0)}
    robot, out = result.robot, {}
    for fmt in ("json", "npz", "urdf"):
        # labcal export writes effort/velocity as 0 with a note where the robot file gives none: not a refusal
        options = {"unknown_dynamics": "zero"} if fmt == "urdf" else {}
        try:
            path = export(robot, fmt, folder / f"calib.{fmt}", None, **options)
            if fmt == "json":
                robot = Compensator.load(path).robot  # the filter works on what the file holds
            out[fmt] = "ok"
        except Exception as err:
            out[fmt] = _first_line(err)
            if fmt == "urdf" and robot.network is not None:  # refused for its learned term: the flag that asks for
                try:  # the frames alone, as labcal export's message says (not a --force)
                    export(robot, fmt, folder / "geometry.urdf", None, unknown_dynamics="zero", geometry_only=True)
                    out["urdf-geometry"] = "ok"
                except Exception as err2:
                    out["urdf-geometry"] = _first_line(err2)
    inside = q_test[robot.validity.inside(q_test)] if robot.validity is not None else q_test
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    inside = inside[((inside >= lo) & (inside <= hi)).all(axis=1)]
    # One row at a time: the filter refuses a whole program for one row it cannot correct (near a singularity),
    # so the count of rows says more than one verdict; the first refusal is kept.
    done, first = 0, None
    for row in inside:
        try:
            filter_joints(robot, row[None])
            done += 1
        except Exception as err:
            first = first or _first_line(err)
    out["filter"] = "ok" if done == len(inside) and done else (first or "no held-out row inside the validity region")
    out["filter-rows"] = (done, len(inside))
    return out


def run_family(name: str, spec, poses: int, splits: int, methods, say) -> dict:
    targets = FAMILIES[name]
    model = spec.model
    res: dict = {m: {"errors": {}, "refused": {}, "exports": {}, "chosen": [], "seconds": []} for m in methods}
    res["plain-lsq"] = {"errors": {}, "refused": {}, "seconds": []}
    for s in range(splits):
        actual = simulate(spec, ErrorSpec.default(), seed=s + 1)
        rng = np.random.default_rng(10_000 + s + 1)
        q = paper.sample_configurations(model, poses, "full", rng)
        points = actual.measure(q, targets, rng)
        order = np.random.default_rng([s, 33]).permutation(poses)
        n_test = round(HOLD_OUT * poses)
        test, train = np.sort(order[:n_test]), np.sort(order[n_test:])
        t = time.perf_counter()
        try:
            plain = fit_plain(model, q[train], points[train], targets, "base")
            pred = plain.predict_points(q[test], targets)
            res["plain-lsq"]["errors"][s] = float(np.linalg.norm(pred - points[test], axis=-1).mean())
        except Exception as err:
            res["plain-lsq"]["refused"][s] = _first_line(err)
        res["plain-lsq"]["seconds"].append(time.perf_counter() - t)
        obs = Observations(q[train], points[train], targets, "base")
        line = []
        for m in methods:
            cell = res[m]
            t = time.perf_counter()
            try:
                result = fit(obs, model, m, seed=s)
            except Exception as err:
                cell["refused"][s] = _first_line(err)
                cell["seconds"].append(time.perf_counter() - t)
                line.append(f"{m} refused")
                continue
            cell["seconds"].append(time.perf_counter() - t)
            cell["errors"][s] = point_error(result.robot, q[test], points[test], targets)
            if m == "auto":
                cell["chosen"].append(str(result.chosen))
            with tempfile.TemporaryDirectory(prefix="labcal-seven-") as tmp:
                cell["exports"][s] = exports(result, q[test], Path(tmp))
            failed = [f for f in FORMATS if cell["exports"][s][f] != "ok"]
            line.append(f"{m} {cell['errors'][s] * 1e3:.4f}" + (f" (refused: {', '.join(failed)})" if failed else ""))
        lsq = res["plain-lsq"]["errors"].get(s)
        say(f"  {name} split {s}: plain-lsq {'FAILED' if lsq is None else f'{lsq * 1e3:.4f}'}, {', '.join(line)}")
    return res


def report(results: dict, methods, splits: int) -> list[str]:
    lines = [
        "Held-out mean target-point error, mm (mean over the splits that ran), its ratio to the plain LSQ on the same "
        "splits, and the exports without --force (splits that succeeded)"
    ]
    header = ["family", "method", "held-out mm", "vs plain-lsq", "ran", *FORMATS, "filter rows", "s/fit"]
    rows, notes = [], []
    for fam, res in results.items():
        ref = res["plain-lsq"]["errors"]
        rows.append(
            [fam, "plain-lsq", f"{np.mean(list(ref.values())) * 1e3:.4f}" if ref else "FAILED", "1.00×",
             f"{len(ref)}/{splits}", *["-"] * (len(FORMATS) + 1), f"{np.mean(res['plain-lsq']['seconds']):.1f}"]
        )  # fmt: skip
        for m in methods:
            cell = res[m]
            if not cell["errors"]:
                first = next(iter(cell["refused"].values())).split(": ", 1)[-1]
                short = first if len(first) <= 60 else first[:57] + "..."
                rows.append([fam, m, f"refused: {short}", "", f"0/{splits}", *[""] * (len(FORMATS) + 1), ""])
                continue
            both = [s for s in cell["errors"] if s in ref]
            ratio = np.mean([cell["errors"][s] for s in both]) / np.mean([ref[s] for s in both])
            ok = [f"{sum(v[f] == 'ok' for v in cell['exports'].values())}/{len(cell['exports'])}" for f in FORMATS]
            geometry = sum(v.get("urdf-geometry") == "ok" for v in cell["exports"].values())
            if geometry:  # a URDF refused for the learned term, written with --geometry-only
                ok[FORMATS.index("urdf")] += f" (+{geometry} --geometry-only)"
            done, total = (sum(v["filter-rows"][i] for v in cell["exports"].values()) for i in (0, 1))
            rows.append(
                [fam, m + (f" ({'/'.join(sorted(set(cell['chosen'])))})" if cell["chosen"] else ""),
                 f"{np.mean(list(cell['errors'].values())) * 1e3:.4f}", f"{ratio:.3f}×",
                 f"{len(cell['errors'])}/{splits}", *ok, f"{done}/{total}",
                 f"{np.mean(cell['seconds']):.1f}"]
            )  # fmt: skip
            for s, msg in sorted(cell["refused"].items()):
                notes.append(f"  {fam} / {m} / split {s}: refused: {msg}")
            for f in FORMATS:
                bad = [(s, v[f]) for s, v in sorted(cell["exports"].items()) if v[f] != "ok"]
                if bad:
                    notes.append(f"  {fam} / {m} / {f}: {len(bad)} split(s), first (split {bad[0][0]}): {bad[0][1]}")
    lines += _table(header, rows)
    refusals = [
        f"  {fam} / {m}: {msg}" for fam, res in results.items() for m in methods
        for msg in sorted(set(res[m]["refused"].values()))
    ]  # fmt: skip
    lines += ["", "Methods refused (first line of the error):", *(refusals or ["  none"])]
    lines += ["", "Exports refused without --force:", *([n for n in notes if "refused:" not in n] or ["  none"])]
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="seven_joints", description=__doc__.split("\n\n")[0])
    p.add_argument("--splits", type=int, default=5, help="splits per family (default 5)")
    p.add_argument("--quick", action="store_true", help="2 splits")
    p.add_argument("--poses", type=int, default=120, help="poses per data set, a third held out (default 120)")
    p.add_argument("--robot", default="franka-panda", help="7-joint robot: built-in name or file (franka-panda)")
    p.add_argument("--families", default=",".join(FAMILIES), help="comma-separated subset of " + ",".join(FAMILIES))
    p.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of " + ",".join(METHODS))
    p.add_argument("--out", help="also write the output to this file")
    p.add_argument("--note", help="a line printed under the command (e.g. which commit was measured)")
    args = p.parse_args(argv)
    splits = 2 if args.quick else args.splits
    families = tuple(f.strip() for f in args.families.split(",") if f.strip())
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    for bad, known in ((set(families) - set(FAMILIES), FAMILIES), (set(methods) - set(METHODS), METHODS)):
        if bad:
            p.error(f"unknown {sorted(bad)}; known: {', '.join(known)}")
    spec = load(args.robot)
    out: list[str] = []

    def say(line: str = "") -> None:
        print(line, flush=True)
        out.append(line)

    say("seven_joints: a simulated 7-joint arm, held-out error of every method with default options vs a plain LSQ")
    say(f"command: python benchmarks/seven_joints.py {' '.join(argv if argv is not None else sys.argv[1:])}".rstrip())
    if args.note:
        say(f"note: {args.note}")
    say(
        f"robot: {spec.model.name} ({spec.model.n} joints, hash {spec.hash[:12]}); errors: ErrorSpec.default() "
        f"(geometric, compliance, gears, tracker noise); {args.poses} random poses per split over the full joint "
        f"ranges, a third held out; {splits} splits (seed = split)"
    )
    for fam in families:
        say(f"  {fam}: {len(FAMILIES[fam])} target(s) in the flange frame, mm: {(FAMILIES[fam] * 1e3).tolist()}")
    started, results = time.perf_counter(), {}
    for fam in families:
        results[fam] = run_family(fam, spec, args.poses, splits, methods, say)
    say("")
    for line in report(results, methods, splits):
        say(line)
    say("")
    say(f"total {time.perf_counter() - started:.0f} s")
    if args.out:
        Path(args.out).write_text("\n".join(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
