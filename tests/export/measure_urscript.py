"""Measure the URScript export on a hybrid fit of the simulated UR10 (not a test: prints a table).

    .venv/bin/python tests/export/measure_urscript.py [--poses 200] [--configs 100]

Statements per labcal_correct call, sync() calls per call (each costs at least one 2 ms frame), the most
statements between two syncs, and |float32 script − correct()| over configurations whose length-scaled Jacobian
condition is ≤ 100; the exporter of 5770eeb (git show; four fixed Newton steps) beside today's when git is available.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))  # urscript_subset, scenarios

from export_fixtures import sample

import urscript_subset
from labcal.calibration import Observations
from labcal.calibration.fit import fit
from labcal.export.urscript import FLOAT32_BOUND, urscript_text
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec
from scenarios import good

OLD = "5770eeb:src/labcal/export/urscript.py"


def run(text: str, q: np.ndarray, float32: bool):
    ns = urscript_subset.load(text, float32=float32)
    ns["stats"].reset()
    out = np.array([ns["labcal_correct"](list(map(float, row))) for row in q], dtype=float)
    return out, ns["stats"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--poses", type=int, default=200)
    ap.add_argument("--configs", type=int, default=100)
    args = ap.parse_args()
    scn = good("ur10", args.poses, errors=ErrorSpec.default(), seed=1)
    result = fit(Observations(**scn.arrays()), load("ur10").model, "hybrid", seed=0)
    robot = result.robot
    net = robot.network
    print(f"fit: {result.chosen}, features {net.features if net else None}, hidden {net.hidden if net else None}")
    q = sample(robot, args.configs, seed=2)
    expected = robot.correct(q)
    scripts = {"today": urscript_text(robot)}
    root = Path(__file__).parents[2]
    old = subprocess.run(["git", "show", OLD], capture_output=True, text=True, cwd=root)
    if old.returncode == 0:
        ns: dict = {"__name__": "old_urscript"}
        exec(compile(old.stdout, "old_urscript.py", "exec"), ns)
        scripts["5770eeb"] = ns["urscript_text"](robot)
    print(f"{len(q)} configurations, scaled condition <= 100; float32 bound {FLOAT32_BOUND:g} rad")
    print(
        "| exporter | statements / call | sync() / call | max statements between syncs | checker "
        "| |f64 - correct| max | |f32 - correct| max / median |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, text in scripts.items():
        try:
            urscript_subset.check(text)
            verdict = "passes"
        except SyntaxError as e:
            verdict = f"fails: {str(e).split(':', 2)[1].strip()[:40]}"
        got64, stats = run(text, q, False)
        got32, _ = run(text, q, True)
        e64 = np.max(np.abs(got64 - expected))
        e32 = np.max(np.abs(got32 - expected), axis=1)
        print(
            f"| {name} | {stats.total / len(q):.0f} | {stats.syncs / len(q):.1f} | {stats.max_window} | {verdict} | "
            f"{e64:.2g} | {e32.max():.2g} / {np.median(e32):.2g} |"
        )


if __name__ == "__main__":
    main()
