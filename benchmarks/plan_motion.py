"""Plans the cell can run: motion time before/after ordering, time per pose, and targets facing the tracker.

The robot is drivers/ur10-lab.toml (its speed and acceleration caps, its settle time) with its joint limits as
shipped (±360°) and narrowed to a collision-free workspace (NARROW_DEG), planned as `labcal session new` plans for
a real robot (the robot's own SafetyLimits, poses ordered by ``order_for_motion``). Targets: the three
reflectors of drivers/targets-example.toml, facing along the tool's z axis.

Motion time: sum of trapezoidal move times of the slowest joint (``labcal.sessions.plans.motion_time``), from the
first pose, in the planner's order ("before", what labcal did until now) and ordered ("after"). Time per pose =
motion per pose + the plan's settle (0.5 s) + the profile's settle_time_s (0.5 s); the tracker's measuring time
is left out (device-dependent, about 0.1-0.3 s for 5 frames).

Visibility, on the sim rig: a simulated ur10 (ErrorSpec.default, seed 0) with its tracker where the example
profile's [workspace] tracker_mm puts it; a pose counts as visible when every target's true normal (the
simulated robot's pose, not the planner's model) is within the acceptance angle of the direction to the
tracker. "without" plans without the facing check, "with" with it.

    python benchmarks/plan_motion.py      # about a minute; output kept in benchmarks/results/plan_motion.txt
    python benchmarks/plan_motion.py --floor   # also LKH-3's order (pip package elkai, not a labcal dependency):
                                               # how far from the best order this ordering is
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from labcal.datasets import load_targets
from labcal.drivers.ur import load_ur_profile
from labcal.robots import load
from labcal.sessions.planning import (
    TargetFacing,
    optimal_configurations,
    order_for_motion,
    random_configurations,
)
from labcal.sessions.plans import make_plan, motion_time
from labcal.simulation import ErrorSpec, simulate

ROOT = Path(__file__).resolve().parents[1]
NARROW_DEG = [[-90, 90], [-150, -30], [-150, 150], [-180, 0], [-180, 180], [-180, 180]]
PLAN_SETTLE = 0.5  # s, the Settle of every pose in a hardware plan (cli/ops/sessions.py)
TRACKER = (2.6, 0.0, 0.6)  # m, base frame: drivers/ur10-lab.toml [workspace] tracker_mm
NORMALS = np.array([[0.0, 0.0, 1.0]] * 3)


def _visible_share(actual, q, targets, facing: TargetFacing) -> float:
    """Share of poses whose every target faces the tracker, on the simulated robot's true poses."""
    T = actual.true_pose(q)
    points = np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]
    normals = np.einsum("kab,mb->kma", T[:, :3, :3], facing.normals)
    return float(facing.facing(points, normals).all(axis=1).mean())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--poses", type=int, default=100, help="poses per plan (default 100)")
    parser.add_argument("--seeds", type=int, default=3, help="plans per row (default 3)")
    parser.add_argument("--floor", action="store_true", help="also order with LKH-3 (needs the elkai package)")
    args = parser.parse_args(argv)

    spec = load("ur10")
    model = spec.model
    profile = load_ur_profile(ROOT / "drivers" / "ur10-lab.toml")
    targets = load_targets(ROOT / "drivers" / "targets-example.toml")
    full = profile.limits
    narrow = dataclasses.replace(full, joint_limits=np.radians(NARROW_DEG))
    speed, acc = full.max_speed, full.max_acceleration
    overhead = PLAN_SETTLE + profile.settle_time
    print(f"ur10-lab: {speed} rad/s, {acc} rad/s²; settle {PLAN_SETTLE} s (plan) + {profile.settle_time} s (profile)")
    print(f"{args.poses}-pose plans, seeds 0..{args.seeds - 1}; time per pose = motion + {overhead} s settle\n")

    print("Motion (planner's order → ordered)")
    header = (
        f"{'limits':<8} {'planner':<8} {'motion before':>14} {'after':>9} {'after/before':>13} "
        f"{'per pose before':>16} {'after':>7} {'ordering':>9}" + (f" {'LKH-3/before':>13}" if args.floor else "")
    )
    print(header)
    print("-" * len(header))
    for name, limits in (("±360°", full), ("narrowed", narrow)):
        for planner in ("random", "optimal"):
            before, after, cpu, floor = [], [], [], []
            for seed in range(args.seeds):
                if planner == "random":
                    q = random_configurations(model, args.poses, seed=seed, targets=targets, safety=limits)
                else:
                    q = optimal_configurations(
                        model, args.poses, seed=seed, targets=targets, candidates=2000, safety=limits
                    )
                start = time.perf_counter()
                order = order_for_motion(q, speed, acc)
                cpu.append(time.perf_counter() - start)
                before.append(motion_time(make_plan(q, speed=speed, acceleration=acc)))
                after.append(motion_time(make_plan(q[order], speed=speed, acceleration=acc)))
                if args.floor:
                    floor.append(motion_time(make_plan(q[_lkh_order(q, speed, acc)], speed=speed, acceleration=acc)))
            b, a = np.mean(before), np.mean(after)
            ratio = np.array(after) / np.array(before)
            print(
                f"{name:<8} {planner:<8} {b:>12.0f} s {a:>7.0f} s {ratio.mean():>7.3f} (max {ratio.max():.3f}) "
                f"{b / args.poses + overhead:>14.1f} s {a / args.poses + overhead:>5.1f} s {np.mean(cpu):>7.2f} s"
                + (f" {np.mean(np.array(floor) / np.array(before)):>13.3f}" if args.floor else "")
            )

    print("\nVisibility on the sim rig: share of planned poses with every target facing the tracker")
    actual = simulate(spec, ErrorSpec.default(T_tracker_base=_tracker_frame(TRACKER)), seed=0)
    header = f"{'limits':<8} {'acceptance':>10} {'without':>8} {'with':>6} {'motion/pose with, ordered':>26}"
    print(header)
    print("-" * len(header))
    for name, limits in (("±360°", full), ("narrowed", narrow)):
        for accept in (30.0, 60.0):
            facing = TargetFacing(TRACKER, NORMALS, np.radians(accept))
            shares = {"without": [], "with": []}
            per_pose = []
            for seed in range(args.seeds):
                for key, extra in (("without", {}), ("with", {"facing": facing})):
                    q = random_configurations(model, args.poses, seed=seed, targets=targets, safety=limits, **extra)
                    shares[key].append(_visible_share(actual, q, targets, facing))
                    if key == "with":
                        order = order_for_motion(q, speed, acc)
                        per_pose.append(motion_time(make_plan(q[order], speed=speed, acceleration=acc)) / len(q))
            print(
                f"{name:<8} {accept:>8.0f}° {np.mean(shares['without']):>8.1%} {np.mean(shares['with']):>6.1%} "
                f"{np.mean(per_pose):>24.1f} s"
            )


def _lkh_order(q, speed, acc) -> list[int]:
    """The open path LKH-3 finds (a dummy node at zero distance from every pose closes the tour), ms resolution."""
    import elkai

    from labcal.sessions.planning import move_time_matrix

    k = len(q)
    D = np.zeros((k + 1, k + 1))
    D[:k, :k] = move_time_matrix(q, q, speed, acc)
    tour = list(elkai.DistanceMatrix(np.round(D * 1000).astype(int).tolist()).solve_tsp(runs=10))[:-1]
    cut = tour.index(k)
    return [i for i in tour[cut + 1 :] + tour[:cut]]


def _tracker_frame(position) -> np.ndarray:
    """T_tracker_base of a tracker at ``position`` (base frame, m) with the base's orientation."""
    T = np.eye(4)
    T[:3, 3] = -np.asarray(position, dtype=float)
    return T


if __name__ == "__main__":
    main()
