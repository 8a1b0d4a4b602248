"""Does a calibration survive a tool change? Prints a table; not a test.

    python benchmarks/tool_change.py [--no-real] > benchmarks/results/tool_change.txt

The last section (unless ``--no-real``): the real UR10 data (../shared/data/ipa-robot-accuracy-ur10, a 6-DOF probe on
a ~93 mm mount, imported as ``benchmarks/real_ur10.py`` does) fitted with local POE on all poses from the robot
file's model (the mount not described): the identified measurement tool, and where tool0 of the robot and of the
ur-kinematics export sits against the nominal flange.

A simulated UR10 (``simulate(load("ur10"), ErrorSpec.paper())``: 0.5 mm / 0.5 mrad frame errors, 0.5 mrad joint
offsets, 0.05 mm tracker noise; seeds 1-3) is calibrated (local POE, 60 random well-conditioned poses) twice:

- with **fixture A**: three targets 100 mm apart (an equilateral triangle) on a mount 93 mm off the flange axis,
  turned by 90° (a probe mount). The user gives the targets in the flange frame either *close* (the mount's
  position guessed 9 mm off) or *far* (the mount forgotten: the targets as if on the flange itself);
- with **tool B** itself: three targets 100 mm apart around the TCP of a 250 mm tool at another orientation.

Each calibration then works with tool B (the TCP given at run time, ``correct(q, tcp=X_B)``) on 500 held-out
configurations: the table prints the TCP error of the true robot commanded ``q_cmd`` against the nominal pose of
the TCP at q (mean / max, mm and mrad), and its ratio to the calibration measured with B. "folded (before)" is what
the code before this change did with the same fit: the fixture frame was the robot's last frame, and ``correct``
moved the joints to bring it onto the nominal tool0. "uncorrected" commands q.

The floor. The flange's turn about and shift along the last joint's axis, and its own frame error, cannot be told
apart from a tool error by any measurement through a tool: they go with the measurement tool (the robot's tool0 is
held at the nominal on the identified axis, :mod:`labcal.calibration.tool`). So a TCP that was not measured carries
them, whichever fixture calibrated the robot: "B itself" at B's drawing has the same floor as A. Only a calibration
measured with B knows B's identified pose: the row "TCP set to its identified tool" (the program naming that TCP)
shows what that is worth, and what no calibration with another fixture can give.
"""

from __future__ import annotations

import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from labcal.calibration.local_poe import fit_local_poe
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition
from labcal.robots import load
from labcal.simulation.actual import ErrorSpec, simulate

SIDE = 0.1  # m between targets
TRIANGLE = np.array([[0.0, 0.0, 0.0], [SIDE, 0.0, 0.0], [SIDE / 2, SIDE * np.sqrt(3) / 2, 0.0]]) - [SIDE / 2, 0.03, 0]
X_A = se3.pose([0.093, 0.0, 0.02], [np.pi / 2, 0.0, np.pi / 2])  # the probe mount: 93 mm off the axis, 90°
X_A_CLOSE = X_A @ se3.pose([0.005, -0.006, 0.004])  # the user's guess, 9 mm off
X_B = se3.pose([0.03, -0.05, 0.243], [0.4, -0.5, 1.1])  # a 250 mm tool at another orientation
POSES, HELD_OUT, SEEDS = 60, 500, (1, 2, 3)


def configurations(nominal, k: int, rng: np.random.Generator) -> np.ndarray:
    """k random configurations of scaled condition below 30 (well away from singular wrists and elbows)."""
    out = []
    L = nominal.reach()
    while sum(len(o) for o in out) < k:
        q = rng.uniform(-np.pi, np.pi, size=(4 * k, 6))
        cond = scaled_condition(nominal.equivalent_jacobian(q, length_scale=L), L)
        out.append(q[cond < 30])
    return np.concatenate(out)[:k]


def calibrate(actual, nominal, q, X_true, X_guess, rng) -> CalibratedRobot:
    """Measure the targets of a fixture at X_true (in the true tool0) and fit, the user giving them at X_guess."""
    on_tool = (X_true[:3, :3] @ TRIANGLE.T).T + X_true[:3, 3]
    points = actual.measure(q, on_tool, rng)
    given = (X_guess[:3, :3] @ TRIANGLE.T).T + X_guess[:3, 3]
    robot, _ = fit_local_poe(Observations(q=q, points=points, targets=given), nominal)
    return robot


def tcp_errors(actual, nominal, q, q_cmd, X_work) -> tuple[np.ndarray, np.ndarray]:
    """(pos m, ori rad) of the true TCP at q_cmd against the nominal TCP pose at q."""
    return se3.pose_distance(actual.true_pose(q_cmd) @ X_work, nominal.fk(q) @ X_work)


def folded(robot: CalibratedRobot) -> CalibratedRobot:
    """The same fit as the code before this change used it: the fixture frame as the robot's last frame."""
    return CalibratedRobot(robot.nominal, robot.measurement_model, T_tracker_base=robot.T_tracker_base)


def main() -> None:
    spec = load("ur10")
    nominal = spec.model
    t0 = time.perf_counter()
    rows: dict[str, list] = {}
    tool_errors: dict[str, list] = {}
    for seed in SEEDS:
        actual = simulate(spec, ErrorSpec.paper(), seed=seed)
        rng = np.random.default_rng(100 + seed)
        q_fit = configurations(nominal, POSES, rng)
        q_test = configurations(nominal, HELD_OUT, rng)
        fits = {
            "A, guess 9 mm off": (calibrate(actual, nominal, q_fit, X_A, X_A_CLOSE, rng), X_A_CLOSE),
            "A, mount forgotten": (calibrate(actual, nominal, q_fit, X_A, np.eye(4), rng), np.eye(4)),
            "B itself": (calibrate(actual, nominal, q_fit, X_B, X_B, rng), X_B),
        }
        for name, (robot, guess) in fits.items():
            q_cmd = robot.correct(q_test, tcp=X_B, extrapolate=True)
            rows.setdefault(name, []).append(tcp_errors(actual, nominal, q_test, q_cmd, X_B))
            if name.startswith("A"):
                old = folded(robot).correct(q_test, extrapolate=True)
                rows.setdefault(f"{name}, folded (before)", []).append(tcp_errors(actual, nominal, q_test, old, X_B))
            # the identified fixture: the user's guess moved by the measurement tool, against the true fixture
            X_true = X_B if name == "B itself" else X_A
            d = se3.pose_distance((robot.measurement_tool @ guess)[None], X_true[None])
            tool_errors.setdefault(name, []).append((d[0][0], d[1][0]))
            if name == "B itself":
                # B's own identified tool as the TCP the program names: only a calibration measured with B knows it
                X_hat = robot.measurement_tool @ guess
                err = se3.pose_distance(actual.true_pose(q_cmd) @ X_B, nominal.fk(q_test) @ X_hat)
                rows.setdefault("B itself, TCP set to its identified tool", []).append(err)
        rows.setdefault("uncorrected", []).append(tcp_errors(actual, nominal, q_test, q_test, X_B))
    print(f"# tool change: UR10, ErrorSpec.paper(), seeds {SEEDS}, {POSES} fitting poses, {HELD_OUT} held-out each")
    print(
        "# working TCP: tool B (250 mm, another orientation), given at run time: correct(q, tcp=X_B); error: the true"
    )
    print("# robot's TCP at q_cmd against the nominal pose of the TCP the program names (X_B, its drawing)")
    print()
    print("| calibrated with | TCP pos mean (mm) | max (mm) | TCP ori mean (mrad) | max (mrad) | mean / B itself |")
    print("|---|---:|---:|---:|---:|---:|")
    ref = np.concatenate([e[0] for e in rows["B itself"]]).mean()
    for name, errs in rows.items():
        pos = np.concatenate([e[0] for e in errs])
        ori = np.concatenate([e[1] for e in errs]) * 1e3
        print(
            f"| {name} | {pos.mean() * 1e3:.4f} | {pos.max() * 1e3:.4f} | {ori.mean():.4f} | {ori.max():.4f} | "
            f"{pos.mean() / ref:.3f} |"
        )
    print()
    print("Identified fixture (the user's guess moved by the measurement tool) against the true fixture in tool0:")
    for name, errs in tool_errors.items():
        e = np.array(errs)
        print(
            f"  {name}: position {e[:, 0].max() * 1e3:.3f} mm, rotation {e[:, 1].max() * 1e3:.3f} mrad (max of seeds)"
        )
    if "--no-real" not in sys.argv:
        real_ur10()
    print(f"\n({time.perf_counter() - t0:.0f} s)")


def real_ur10() -> None:
    """The real UR10 (a 6-DOF probe on a ~93 mm mount): the identified tool and where tool0 of the exports sits."""
    from labcal.calibration.fit import fit
    from labcal.calibration.tool import tool_lines
    from labcal.export.ros import ur_kinematics_text
    from real_ur10 import DataNotFound, load_observations, locate_data

    try:
        data = locate_data()
    except DataNotFound as e:
        print(f"(real UR10 data skipped: {e})")
        return
    with tempfile.TemporaryDirectory() as store:
        obs, _ = load_observations(data, Path(store))
    nominal = load("ur10").model
    robot = fit(obs, nominal, "local-poe", seed=0).robot  # the robot file's model: the probe mount not described
    print(f"\n# real UR10 ({obs.k} poses, local POE on all of them, the robot file's tool: the bare flange)")
    print("\n".join(tool_lines(robot.measurement_tool, robot.measurement_tool_std)))
    dp, dr = se3.pose_distance(robot.model.fk(obs.q), nominal.fk(obs.q))
    print(
        f"tool0 (the robot to its flange) against the nominal flange over the data: mean {dp.mean() * 1e3:.3f} mm / "
        f"{dr.mean() * 1e3:.3f} mrad, max {dp.max() * 1e3:.3f} mm / {dr.max() * 1e3:.3f} mrad"
    )
    text = ur_kinematics_text(robot)
    for line in text.splitlines():
        if line.startswith(("# tcp_in_tool0:", "# measurement_tool_in_tool0:")):
            print("ur-kinematics YAML " + line[2:])
    nom = _entries(ur_kinematics_text(CalibratedRobot(nominal, nominal)))
    got = _entries(text)
    print(
        "ur-kinematics YAML joint origins against the nominal file's: max |Δxyz| "
        f"{np.abs(got - nom)[:, :3].max() * 1e3:.3f} mm, max |Δrpy| {np.abs(got - nom)[:, 3:].max() * 1e3:.3f} mrad"
    )
    q = obs.q
    q_cmd = robot.correct(q, extrapolate=True)
    print(f"correct() on the data's configurations: max |q_cmd - q| {np.abs(q_cmd - q).max():.4f} rad")


def _entries(text: str) -> np.ndarray:
    """(6, 6) x y z roll pitch yaw of the six segments of a kinematics YAML."""
    values = re.findall(r"^    (?:x|y|z|roll|pitch|yaw): (\S+)$", text, flags=re.M)
    return np.array(values, dtype=float).reshape(6, 6)


if __name__ == "__main__":
    main()
