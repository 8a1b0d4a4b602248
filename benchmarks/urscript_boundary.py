"""At the boundary of what ``correct()`` accepts, does the URScript export refuse too? Prints tables; not a test.

    python benchmarks/urscript_boundary.py [--directions 200] [--no-real] > benchmarks/results/urscript_boundary.txt

``correct()`` (without ``extrapolate``) refuses a configuration outside the calibrated joint ranges or farther than
the validity radius from every stored configuration (:mod:`labcal.compensator.validity`); ``labcal_correct`` must
refuse it too (popup + halt), in float64 and in the controller's float32. Exports: those of
``benchmarks/urscript_agreement.py`` (its ``exports()``), each evaluated in the URScript interpreter of
:mod:`urscript_subset` in float64 and float32 (the configurations are passed as float64 numbers; in float32 the
interpreter rounds them, as a controller holds them).

- **validity region**: the export with the nominal robot's joint limits for its ranges (the region check alone
  decides), ``--directions`` pairs (centre c, random unit direction u in the scaled joint space) whose
  boundary point c + r u is farther than 1.01 r from every other centre and inside those limits by 1e-3 (so
  this ball alone decides); for each δ the configurations (c + r (1 ± δ) u) / w.
  Also the simulated local-POE export with its region as if joint 5 had never moved (at 4.74 rad, scaled by
  1 / MIN_SPREAD: issue 27's narrow series), where float32 resolves the scaled distance most coarsely.
- **joint ranges**: the export without its validity region (the range check alone decides), each joint j at each
  bound b of its range moved by |b| δ outwards ("outside") and inwards ("inside"), b (1 ± δ) for a positive upper
  bound; the other joints at the first four golden configurations.

Columns: the configurations, how many ``correct()`` refuses, **unsafe** (the script passes its range and region
check where ``correct()`` refuses: it would go on to command the robot; must be 0) and fail-stop (the script
refuses where ``correct()`` accepts: the safe direction, the band its float32 margins give up). Below the table:
how much smaller (relative) the radius is that the script compares with.

Before a change, with a worktree of it (the interpreter and this file from here):
``PYTHONPATH=/tmp/before/src python benchmarks/urscript_boundary.py > benchmarks/results/urscript_boundary_before.txt``
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time
from pathlib import Path

import numpy as np

import labcal
import urscript_subset
from labcal.compensator import golden_configurations
from labcal.compensator.validity import MIN_SPREAD, ValidityRegion
from labcal.export.urscript import urscript_text
from urscript_agreement import exports

DELTAS = (1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3)
CHECK_TEXTS = ("outside the validity region", "outside the calibrated range")


def script_refuses(ns, q: np.ndarray) -> np.ndarray:
    """(k,) whether labcal_correct stopped at its range or region check (any later outcome: it passed them)."""
    out = np.zeros(len(q), dtype=bool)
    with np.errstate(all="ignore"):
        for i, row in enumerate(q):
            ns["stats"].messages.clear()
            try:
                ns["labcal_correct"](list(map(float, row)))
            except urscript_subset.Halted:
                popups = [text for kind, text in ns["stats"].messages if kind == "popup"]
                out[i] = any(t in popups[-1] for t in CHECK_TEXTS)
            except (ZeroDivisionError, OverflowError, ValueError):
                pass  # a run-time failure after the checks
    return out


def correct_refuses(robot, q: np.ndarray) -> np.ndarray:
    """(k,) whether correct() (without extrapolate) refuses each configuration: its range and validity checks."""
    out = np.zeros(len(q), dtype=bool)
    for i, row in enumerate(q):
        try:
            robot.check_range(row[None])
        except ValueError:
            out[i] = True
    return out


def region_configurations(robot, count: int, rng) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """(centres c, unit directions u, radius r, weights w) of ``count`` boundary points only one ball decides."""
    region = robot.validity
    c_all, r, w = region.centres, region.radius, region.weights
    lo, hi = robot.joint_ranges[:, 0] + 1e-3, robot.joint_ranges[:, 1] - 1e-3
    keep_c, keep_u = [], []
    for _ in range(200):
        idx = rng.integers(0, len(c_all), size=4096)
        u = rng.normal(size=(4096, c_all.shape[1]))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        x = c_all[idx] + r * u
        d = np.linalg.norm(x[:, None, :] - c_all[None], axis=2)
        d[np.arange(len(x)), idx] = np.inf
        q = x / w
        ok = (d.min(axis=1) > 1.01 * r) & np.all((q >= lo) & (q <= hi), axis=1)
        keep_c.append(c_all[idx][ok])
        keep_u.append(u[ok])
        if sum(map(len, keep_c)) >= count:
            break
    c, u = np.concatenate(keep_c)[:count], np.concatenate(keep_u)[:count]
    if len(c) < count:
        raise SystemExit(f"only {len(c)} boundary points where one ball decides")
    return c, u, r, w


def range_configurations(robot, delta: float, sign: float) -> np.ndarray:
    """Configurations with one joint at a bound b of its range times (1 ± δ), "+" (sign 1) outside the range."""
    base = golden_configurations(robot)[:4]
    rows = []
    for j in range(robot.n):
        for side, b in ((-1.0, robot.joint_ranges[j, 0]), (1.0, robot.joint_ranges[j, 1])):
            q = base.copy()
            q[:, j] = b + sign * side * abs(b) * delta  # b (1 ± δ), moved outwards for sign 1
            rows.append(q)
    return np.concatenate(rows)


def never_moved(robot, q5: float = 4.74):
    """The export with its region as if the data had kept joint 5 at q5 (issue 27's narrow series): the joint scaled
    by 1 / MIN_SPREAD, so its scaled values are ~4,700 and float32 resolves them to ~5e-4 of the radius."""
    region = robot.validity
    w = region.weights.copy()
    w[4] = 1.0 / MIN_SPREAD
    centres = region.centres.copy()
    centres[:, 4] = q5 * w[4]
    return dataclasses.replace(robot, validity=ValidityRegion(centres=centres, radius=region.radius, weights=w))


def table(robots: dict, directions: int) -> list[str]:
    """The table's lines and the notes below it, for the exports ``robots`` (name → CalibratedRobot)."""
    header = (
        "| export | check | δ | configurations (outside + inside) | correct() refuses | float64 **unsafe** "
        "| float64 fail-stop | float32 **unsafe** | float32 fail-stop |"
    )
    rows, notes = [header, "|---|---|---|---|---|---|---|---|---|"], []
    for name, robot in robots.items():
        # each check alone: the region within the nominal robot's limits, the ranges without the region
        alone = {
            "region": dataclasses.replace(robot, joint_ranges=robot.nominal.limits),
            "ranges": dataclasses.replace(robot, validity=None),
        }
        c, u, r, w = region_configurations(alone["region"], directions, np.random.default_rng(0))
        for check, bot in alone.items():
            script = urscript_text(bot)
            spaces = [urscript_subset.load(script, float32=f32) for f32 in (False, True)]
            for delta in DELTAS:
                if check == "region":
                    q = np.concatenate([(c + r * (1.0 + s * delta) * u) / w for s in (1.0, -1.0)])
                else:
                    q = np.concatenate([range_configurations(bot, delta, s) for s in (1.0, -1.0)])
                refuse = correct_refuses(bot, q)
                cells = [f"{len(q) // 2} + {len(q) // 2}", str(refuse.sum())]
                for ns in spaces:
                    script_refuse = script_refuses(ns, q)
                    cells += [f"**{(~script_refuse & refuse).sum()}**", str((script_refuse & ~refuse).sum())]
                rows.append(f"| {name} | {check} | {delta:.0e} | {' | '.join(cells)} |")
            if check == "region":
                vr2 = float(re.search(r"^lc_vr2 = (.+)$", script, re.M).group(1))
                notes.append(
                    f"{name}: validity radius {r:.6g} (scaled units), largest |centre coordinate| "
                    f"{np.abs(robot.validity.centres).max():.4g}; the script compares with a radius "
                    f"{1 - np.sqrt(vr2) / r:.2e} of it smaller"
                )
    return [*rows, "", *notes]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--directions", type=int, default=200, help="boundary points per export and δ (region)")
    ap.add_argument("--no-real", action="store_true", help="skip the real UR10 data")
    args = ap.parse_args()
    t0 = time.perf_counter()
    print(f"exporter: {Path(labcal.__file__).parent}; {args.directions} boundary points per export, δ and side")
    robots = exports(not args.no_real)
    robots["sim local-POE, q5 never moved"] = never_moved(robots["sim local-POE"])
    print("\n".join(table(robots, args.directions)))
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
