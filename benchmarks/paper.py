"""The paper benchmark: the Section V protocol on the simulator, the paper's figures beside ours.

Scenarios (all on ``fanuc-m1000ia``, three targets on the tool, 0.05 mm tracker noise):

- **A** (the paper): geometric errors only (:meth:`ErrorSpec.paper`: 0.5 mm / 0.5 mrad frame errors, joint
  offsets and axis misalignments), 100 random non-singular configurations over the full joint ranges (the paper's
  50 train + 50 validation; here every one is fitted, as ``fit`` does by default). Reported: the reduction (%) of
  the max and std of the position and orientation error over those
  100 configurations (calibrated prediction vs the true pose), the paper's figures beside; then the same fitted
  models on 1,000 fresh held-out configurations (mean / p95 / max), and the compensated error there (the actual
  robot commanded ``robot.correct(q)`` against the nominal pose of q).
- **B**: A plus the simulator's non-geometric errors (:meth:`ErrorSpec.default`: gravity compliance 0.2 mrad,
  gear harmonics 0.05 mrad).
- **C**: A and B for three workspaces and 100 / 400 / 1,600 fitted configurations.

Workspaces:

- ``full``: uniform over the full joint ranges;
- ``half``: uniform over half of each joint range, centred on its middle;
- ``cell``: a machining cell — tool positions uniform in a 0.6 m × 0.6 m × 0.4 m box centred 2 m in front of
  joint 1's axis and 1 m above the base origin (:data:`CELL_CENTRE`), tool z axis within 20° of straight down and
  spun up to ±45° about it; configurations by damped Newton inverse kinematics on the nominal model from
  :data:`CELL_SEED` (one solution branch: elbow up, wrist flipped down).

Every workspace rejects configurations whose equivalent-robot Jacobian J_ρ is ill-conditioned in a
length-scaled metric: cond(diag(1/L, 1/L, 1/L, 1, 1, 1) · J_ρ) > :data:`MAX_CONDITION`, L the robot's reach
(4.25 m). Over uniform full-range configurations the median of this number is ~30 and 500 rejects ~6 %: the
configurations near the wrist (q5 ≈ 0) and elbow singularities, where eq. 21 turns noise into radians. Up to 500
some configurations still lie within a few centiradians of the stretched-elbow singularity; there the nominal
pose can need a large joint correction or be out of the real robot's reach, which shows as the compensated
maximum error being far above the predicted one (the compensated p95 is the robust figure).

"After" error = the calibrated robot's predicted pose against the true (noise-free) pose; "before" = the
registered nominal. Statistics are means over the true-robot seeds, ± their standard deviation.

Run: ``python benchmarks/paper.py [--seeds 5] [--quick]``. A full run's output is committed as
benchmarks/results/paper.txt.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from labcal.calibration import Observations, fit
from labcal.calibration.metrics import reduction
from labcal.compensator.solve import MAX_CORRECTION
from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition, twist_weights
from labcal.kinematics.poe import LocalPOEModel
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

ROBOT = "fanuc-m1000ia"
# A scalene target triangle on the tool (m, tool frame), 50 mm in front of the flange: sides 224, 269, 335 mm.
TARGETS = np.array([[0.20, 0.00, 0.05], [-0.10, 0.15, 0.05], [0.00, -0.10, 0.05]])
MAX_CONDITION = 500.0
CELL_CENTRE = np.array([2.0, 0.0, 1.0])  # m, base frame: 2 m in front of the axis of joint 1, 1 m up
CELL_SIZE = np.array([0.6, 0.6, 0.4])  # m
CELL_TILT = math.radians(20.0)
CELL_SPIN = math.radians(45.0)
CELL_SEED = np.array([0.0, 0.35, 0.0, 0.0, 1.2, 0.0])  # rad: start of the IK, wrist down, elbow up
WORKSPACES = ("full", "half", "cell")
METHODS = ("local-poe", "ann", "hybrid")
PAPER = {"local-poe": (77.12, 76.63), "ann": (91.90, 90.21)}  # max position / orientation reduction, %

Print = Callable[[str], None]


# ---------------------------------------------------------------------------------------------------------------
# configurations
def condition(model: LocalPOEModel, q: np.ndarray) -> np.ndarray:
    """(k,) cond of the length-scaled equivalent Jacobian (see module docstring)."""
    return scaled_condition(model.equivalent_jacobian(q), model.reach())


def _ik(model: LocalPOEModel, targets: np.ndarray, q0: np.ndarray, iterations: int = 60) -> tuple[np.ndarray, bool]:
    """Damped Newton IK for many target poses (k, 4, 4) from one seed; returns q (k, n) and converged (k,)."""
    k = targets.shape[0]
    q = np.broadcast_to(q0, (k, model.n)).copy()
    D = twist_weights(model.reach())
    for _ in range(iterations):
        T, J = model.fk_and_twists(q)
        err = se3.log_se3(targets @ se3.inv(T)) * D
        Js = J * D[None, :, None]
        JtJ = np.einsum("kai,kaj->kij", Js, Js) + 1e-6 * np.eye(model.n)
        step = np.linalg.solve(JtJ, np.einsum("kai,ka->ki", Js, err)[..., None])[..., 0]
        q += np.clip(step, -0.2, 0.2)
    T = model.fk(q)
    dp, dr = se3.pose_distance(T, targets)
    return q, (dp < 1e-9) & (dr < 1e-9)


def _cell_poses(model: LocalPOEModel, k: int, rng: np.random.Generator) -> np.ndarray:
    down = np.diag([1.0, -1.0, -1.0])  # tool z straight down, tool x along base x
    axis = rng.normal(size=(k, 3))
    axis[:, 2] = 0.0
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    tilt = np.arccos(1 - rng.uniform(0, 1 - math.cos(CELL_TILT), size=k))  # uniform on the spherical cap
    spin = rng.uniform(-CELL_SPIN, CELL_SPIN, size=k)
    R = se3.exp_so3(axis * tilt[:, None]) @ down @ se3.exp_so3(np.array([0, 0, 1.0]) * spin[:, None])
    out = np.tile(np.eye(4), (k, 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = CELL_CENTRE + rng.uniform(-0.5, 0.5, size=(k, 3)) * CELL_SIZE
    return out


def sample_configurations(
    model: LocalPOEModel, k: int, workspace: str, rng: np.random.Generator, max_condition: float = MAX_CONDITION
) -> np.ndarray:
    """(k, n) random non-singular configurations of a workspace ("full", "half", "cell")."""
    if workspace not in WORKSPACES:
        raise ValueError(f"workspace must be one of {', '.join(WORKSPACES)}, got {workspace!r}")
    lo, hi = model.limits[:, 0], model.limits[:, 1]
    if workspace == "half":
        mid, half = (lo + hi) / 2, (hi - lo) / 4
        lo, hi = mid - half, mid + half
    chunks, have = [], 0
    for _ in range(1000):
        m = max(2 * (k - have), 16)
        if workspace == "cell":
            q, ok = _ik(model, _cell_poses(model, m, rng), CELL_SEED)
            ok &= model.within_limits(q)
        else:
            q = rng.uniform(lo, hi, size=(m, model.n))
            ok = np.ones(m, bool)
        ok &= condition(model, q) <= max_condition
        chunks.append(q[ok])
        have += int(ok.sum())
        if have >= k:
            return np.concatenate(chunks)[:k]
    raise RuntimeError(f"could not sample {k} non-singular configurations in workspace {workspace!r}")


# ---------------------------------------------------------------------------------------------------------------
# one run
@dataclass
class Run:
    """Errors (m, rad) of one fitted method on one true robot."""

    cal_pos: np.ndarray  # (k,) on the calibration configurations
    cal_ori: np.ndarray
    hold_pos: np.ndarray  # (1000,) held-out
    hold_ori: np.ndarray
    comp_pos: np.ndarray  # (1000,) compensated, held-out
    comp_ori: np.ndarray
    seconds: float
    note: str = ""
    bounded: np.ndarray | None = None  # (1000,) rows where the 0.1 rad bound changed correct()'s answer
    free_pos: np.ndarray | None = None  # (1000,) compensated position error without the bound


def _errors(robot, actual, q):
    return se3.pose_distance(robot.predict_pose(q, tcp=robot.measurement_tool), actual.true_pose(q))


def _compensated(robot, actual, q):
    return _compensated_at(robot, actual, q, robot.correct(q, extrapolate=True))[:2]


def _compensated_at(robot, actual, q, q_cmd):
    # The working TCP is the tool the simulated robot carries, known as the calibration identified it.
    tcp = np.eye(4) if robot.measurement_tool is None else robot.measurement_tool
    return se3.pose_distance(actual.true_pose(q_cmd), robot.nominal.fk(q) @ tcp)


def _bound_price(robot, actual, q) -> dict:
    """Where the MAX_CORRECTION bound inside the validity region changed correct()'s answer, and the compensated
    position error without it (the same robot without a region): what the bound costs on this workspace."""
    if getattr(robot, "validity", None) is None:
        return {}
    bounded_cmd = robot.correct(q, extrapolate=True)
    free_cmd = dataclasses.replace(robot, validity=None).correct(q, extrapolate=True)
    changed = np.max(np.abs(bounded_cmd - free_cmd), axis=1) > 1e-12
    return {"bounded": changed, "free_pos": _compensated_at(robot, actual, q, free_cmd)[0]}


def run_once(
    errors: ErrorSpec,
    seed: int,
    n_train: int,
    n_val: int,
    workspace: str,
    methods: tuple[str, ...],
    n_hold: int = 1000,
    ann_options: dict | None = None,
) -> dict[str, Run]:
    """Simulate a true robot (seed), measure, fit every method, evaluate. Returns {"before", method: Run}."""
    spec = load(ROBOT)
    nominal = spec.model
    actual = simulate(spec, errors, seed=seed)
    rng = np.random.default_rng(10_000 + seed)
    q = sample_configurations(nominal, n_train + n_val, workspace, rng)
    rng.permutation(n_train + n_val)  # kept so the measurement noise and held-out draws stay those of earlier runs
    # The paper's 50 + 50 configurations are all fitted, as fit() does by default: learned stages are chosen by
    # cross-validation and the network early-stops on an inner split; the 1,000 fresh configurations are the test.
    obs = Observations(q, actual.measure(q, TARGETS, rng), TARGETS)
    q_hold = sample_configurations(nominal, n_hold, workspace, rng)
    out: dict[str, Run] = {}
    before = None
    for method in methods:
        t = time.perf_counter()
        opts = dict(ann_options or {}) if method in ("ann", "hybrid") else {}
        result = fit(obs, nominal, method, seed=seed, **opts)
        seconds = time.perf_counter() - t
        if before is None:
            before = result.before
            out["before"] = Run(
                *_errors(before, actual, q), *_errors(before, actual, q_hold), *_compensated(before, actual, q_hold), 0
            )
        note = result.info.get("kept", "") if method == "hybrid" else ""
        out[method] = Run(
            *_errors(result.robot, actual, q),
            *_errors(result.robot, actual, q_hold),
            *_compensated(result.robot, actual, q_hold),
            seconds,
            note,
            **_bound_price(result.robot, actual, q_hold),
        )
    return out


# ---------------------------------------------------------------------------------------------------------------
# tables
def _ms(values, fmt="{:.2f}") -> str:
    v = np.asarray([x for x in values if np.isfinite(x)], float)
    if v.size == 0:
        return "n/a"
    if v.size == 1:
        return fmt.format(v[0])
    return f"{fmt.format(v.mean())} ± {fmt.format(v.std(ddof=1))}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(r):
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))

    return [line(header), "  ".join("-" * w for w in widths), *[line(r) for r in rows]]


def scenario_tables(runs: list[dict[str, Run]], methods: tuple[str, ...], paper: bool) -> list[str]:
    """The text tables of one scenario from the runs of all seeds."""
    lines = ["On the 100 fitted configurations: reduction vs the registered nominal, %"]
    rows = []
    for m in methods:
        stats = {"max": np.max, "std": np.std}
        red = {
            f"{stat}{attr[4]}": [
                reduction(stats[stat](getattr(r["before"], attr)), stats[stat](getattr(r[m], attr))) for r in runs
            ]
            for stat in ("max", "std")
            for attr in ("cal_pos", "cal_ori")
        }
        row = [m, _ms(red["maxp"]), _ms(red["stdp"]), _ms(red["maxo"]), _ms(red["stdo"])]
        if paper:
            row.append(" / ".join(f"{x:.2f}" for x in PAPER[m]) if m in PAPER else "—")
        rows.append(row)
    header = ["method", "max pos", "std pos", "max ori", "std ori"] + (["paper max pos / ori"] if paper else [])
    lines += _table(header, rows)
    for title, pa, oa in (
        ("Held-out configurations: predicted vs true pose", "hold_pos", "hold_ori"),
        ("Held-out configurations, compensated: actual(correct(q)) vs nominal(q)", "comp_pos", "comp_ori"),
    ):
        lines += ["", f"{title} (mm, mrad; reduction of the max, %)"]
        rows = []
        for m in ("before", *methods):
            P = [getattr(r[m], pa) for r in runs]
            O = [getattr(r[m], oa) for r in runs]
            red = [reduction(getattr(r["before"], pa).max(), getattr(r[m], pa).max()) for r in runs]
            rows.append(
                [
                    m,
                    _ms([1e3 * p.mean() for p in P], "{:.4f}"),
                    _ms([1e3 * np.percentile(p, 95) for p in P], "{:.4f}"),
                    _ms([1e3 * p.max() for p in P], "{:.4f}"),
                    _ms([1e3 * o.mean() for o in O], "{:.4f}"),
                    _ms([1e3 * o.max() for o in O], "{:.4f}"),
                    "" if m == "before" else _ms(red),
                ]
            )
        lines += _table(["method", "mean pos", "p95 pos", "max pos", "mean ori", "max ori", "max pos red. %"], rows)
    for m in methods:
        priced = [r[m] for r in runs if r[m].bounded is not None]
        if priced:
            lines.append(
                f"{m}: the {MAX_CORRECTION:g} rad bound inside the validity region changed "
                f"{_ms([p.bounded.sum() for p in priced], '{:.1f}')} of {priced[0].bounded.size} held-out "
                f"corrections; without it the compensated mean / max position would be "
                f"{_ms([1e3 * p.free_pos.mean() for p in priced], '{:.4f}')} / "
                f"{_ms([1e3 * p.free_pos.max() for p in priced], '{:.4f}')} mm"
            )
    times = [[m, _ms([r[m].seconds for r in runs])] for m in methods]
    kept = [r["hybrid"].note for r in runs if "hybrid" in r]
    lines += ["", "Fit time, s (hybrid includes its local-POE stage)", *_table(["method", "seconds"], times)]
    if kept:
        counts = {name: sum(k == f"local-poe+{name}" for k in kept) for name in ("ann", "series")}
        lines.append(
            f"hybrid second stage kept in {sum(counts.values())} of {len(kept)} seeds "
            f"(network {counts['ann']}, joint series {counts['series']})"
        )
    return lines


# ---------------------------------------------------------------------------------------------------------------
def run(
    seeds: int = 5,
    quick: bool = False,
    scenarios: str = "ABC",
    methods: tuple[str, ...] = METHODS,
    n_hold: int = 1000,
    ann_options: dict | None = None,
    out: Print = print,
) -> dict:
    """Run the benchmark, printing tables through ``out``. Returns the raw runs and the goal checks.

    quick: 2 seeds, 200 held-out configurations, scenario C with 50 / 200 training configurations only.
    """
    if quick:
        seeds, n_hold = min(seeds, 2), min(n_hold, 200)
    seed_list = list(range(1, seeds + 1))
    results: dict = {}
    scen = {"A": ErrorSpec.paper(), "B": ErrorSpec.default()}
    out(
        f"labcal paper benchmark — robot {ROBOT}, targets (mm, tool frame) {np.round(TARGETS * 1e3).tolist()}, "
        f"seeds {seed_list}, {n_hold} held-out configurations, max condition {MAX_CONDITION:g}"
    )
    for name in ("A", "B"):
        if name not in scenarios:
            continue
        desc = "geometric errors only (the paper)" if name == "A" else "geometric + non-geometric errors"
        out("")
        out(f"=== Scenario {name}: {desc}; 100 configurations, all fitted, full joint ranges ===")
        t = time.perf_counter()
        runs = [run_once(scen[name], s, 50, 50, "full", methods, n_hold, ann_options) for s in seed_list]
        results[name] = runs
        for line in scenario_tables(runs, methods, paper=(name == "A")):
            out(line)
        out(f"({time.perf_counter() - t:.0f} s)")
    if "C" in scenarios:
        sizes = (50, 200) if quick else (50, 200, 800)
        out("")
        out("=== Scenario C: workspace size × fitted configurations ===")
        out("held-out mean position error, mm (mean ± sd over seeds); hybrid: seeds where a learned term was kept")
        rows = []
        results["C"] = {}
        for name in ("A", "B"):
            for ws in WORKSPACES:
                for n in sizes:
                    runs = [run_once(scen[name], s, n, n, ws, methods, n_hold, ann_options) for s in seed_list]
                    results["C"][(name, ws, n)] = runs
                    row = [name, ws, str(2 * n), _ms([1e3 * r["before"].hold_pos.mean() for r in runs], "{:.4f}")]
                    row += [_ms([1e3 * r[m].hold_pos.mean() for r in runs], "{:.4f}") for m in methods]
                    if "ann" in methods:
                        row.append(
                            _ms(
                                [reduction(r["before"].hold_pos.mean(), r["ann"].hold_pos.mean()) for r in runs],
                                "{:.1f}",
                            )
                        )
                    if "hybrid" in methods:
                        row.append(f"{sum(r['hybrid'].note != 'local-poe' for r in runs)}/{len(runs)}")
                    rows.append(row)
                    out(f"  … {name} {ws} {n}: done")
        header = ["scen", "workspace", "fitted", "before", *methods]
        header += (["ann red. %"] if "ann" in methods else []) + (["hybrid kept"] if "hybrid" in methods else [])
        for line in _table(header, rows):
            out(line)
    results["goals"] = goals(results, methods)
    out("")
    out("=== Goals ===")
    for line in results["goals"]["lines"]:
        out(line)
    return results


def goals(results: dict, methods: tuple[str, ...]) -> dict:
    lines, ok = [], {}
    if "A" in results and "local-poe" in methods:
        red = [reduction(r["before"].hold_pos.max(), r["local-poe"].hold_pos.max()) for r in results["A"]]
        ok["A"] = min(red) >= 98.0
        lines.append(
            f"A: local-POE held-out max position error reduction ≥ 98 %: min over seeds {min(red):.2f} % "
            f"→ {'met' if ok['A'] else 'NOT met'}"
        )
    if "B" in results and {"local-poe", "hybrid"} <= set(methods):
        lp = np.array([r["local-poe"].hold_pos.mean() for r in results["B"]])
        hy = np.array([r["hybrid"].hold_pos.mean() for r in results["B"]])
        gain = 100 * (1 - hy / lp)
        ok["B"] = bool(np.all(gain >= 30.0))
        ok["B_never_worse"] = bool(np.all(hy <= lp * (1 + 1e-9)))
        lines.append(
            f"B: hybrid held-out mean position error vs local POE: {_ms(gain, '{:.1f}')} % lower "
            f"(min {gain.min():.1f} %) → ≥ 30 %: {'met' if ok['B'] else 'NOT met'}; never worse: "
            f"{'yes' if ok['B_never_worse'] else 'NO'}"
        )
    for name in ("A", "B"):
        if name in results:
            for m in methods:
                worst = max(r[m].seconds for r in results[name])
                lines.append(
                    f"{name}: fit time for 100 configurations, {m}: max {worst:.2f} s "
                    f"→ ≤ 10 s: {'met' if worst <= 10 else 'NOT met'}"
                )
    return {"ok": ok, "lines": lines}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="labcal paper benchmark (Section V protocol on the simulator)")
    parser.add_argument("--seeds", type=int, default=5, help="number of true-robot seeds (default 5)")
    parser.add_argument("--quick", action="store_true", help="fast smoke run: 2 seeds, 200 held-out, small C")
    parser.add_argument("--scenarios", default="ABC", help="which scenarios to run, e.g. A or AB (default ABC)")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of " + ",".join(METHODS))
    parser.add_argument("--held-out", type=int, default=1000, help="held-out configurations per run")
    args = parser.parse_args(argv)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    bad = [m for m in methods if m not in METHODS]
    if bad:
        parser.error(f"unknown method(s) {bad}; known: {', '.join(METHODS)}")
    run(seeds=args.seeds, quick=args.quick, scenarios=args.scenarios.upper(), methods=methods, n_hold=args.held_out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
