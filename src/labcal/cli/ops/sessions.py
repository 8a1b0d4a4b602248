"""`labcal session new / resume` as functions: plan, pick the drivers, record or continue a session."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labcal.cli.ops.common import UserError, robot_for
from labcal.datasets import SessionStore
from labcal.robots import RobotSpec, load

ROBOT_DRIVERS = ("sim", "ur")
TRACKER_DRIVERS = ("sim", "serial")
PLANNERS = ("random", "optimal")
SIM_ERRORS = ("paper", "default", "none")

# Planning holds every pose in memory several times over (candidates, checks, plan, the start document's JSON):
# measured 0.7 GB peak, 10 s and a 25 MB start document for 100,000 poses on the ur10 (about 7 KB per pose, so
# --poses 100000000 would need some 700 GB; it grew to 24 GB before the OS killed it). At a few seconds per pose
# on a real robot 100,000 poses are already days of measuring, so a larger request is a typo.
MAX_POSES = 100_000
# The optimal planner's candidate pool costs one identification Jacobian (9 × ~30 numbers) per candidate and
# an exchange search over it: 100,000 candidates are already ~0.2 GB and minutes.
MAX_SAMPLES = 100_000


def sim_actual(spec: RobotSpec, errors: str, seed: int):
    """The simulated actual robot of a sim session (recreated identically on resume from errors + seed)."""
    from labcal.simulation import ErrorSpec, simulate

    if errors not in SIM_ERRORS:
        raise UserError(f"--sim-errors must be one of {', '.join(SIM_ERRORS)}, got {errors!r}")
    spec_errors = {"paper": ErrorSpec.paper, "default": ErrorSpec.default, "none": ErrorSpec.none}[errors]()
    return simulate(spec, spec_errors, seed=seed)


def plan_configurations(spec: RobotSpec, poses: int, planner: str, seed: int, targets, samples: int = 2000):
    from labcal.sessions import optimal_configurations, random_configurations

    check_plan_size(poses, planner, samples)
    if planner == "random":
        return random_configurations(spec.model, poses, seed=seed, targets=targets)
    if planner == "optimal":
        return optimal_configurations(spec.model, poses, seed=seed, targets=targets, candidates=samples)
    raise UserError(f"--planner must be one of {', '.join(PLANNERS)}, got {planner!r}")


def check_plan_size(poses: int, planner: str = "random", samples: int = 2000) -> None:
    """Refuse a plan size that cannot be planned (or measured) before any memory is allocated for it."""
    if poses < 1:
        raise UserError(f"--poses must be at least 1, got {poses}")
    if poses > MAX_POSES:
        raise UserError(
            f"--poses {poses:,} is more than labcal plans in one session ({MAX_POSES:,}): planning keeps about 7 KB "
            f"per pose in memory (0.7 GB at {MAX_POSES:,}) and a real robot needs days for that many; split the "
            "measurement into several sessions (they can be pooled when fitting)"
        )
    if planner == "optimal":
        if samples > MAX_SAMPLES:
            raise UserError(
                f"--samples {samples:,} is more candidates than the optimal planner handles ({MAX_SAMPLES:,}: each "
                "costs an identification Jacobian and an exchange search over the pool)"
            )
        if samples < poses:
            raise UserError(f"--samples ({samples}) must be at least --poses ({poses}) for the optimal planner")


def _sim_rig(spec: RobotSpec, targets, sim: dict):
    """The sim rig of a session's recorded ``sim`` metadata: the simulated robot's errors come from ``seed``, the
    tracker noise from ``noise_seed`` (the same seed unless another session of the same robot was asked for)."""
    from labcal.drivers.sim import SimRig

    actual = sim_actual(spec, sim["errors"], int(sim["seed"]))
    # The simulated controller speaks the robot file's controller joints, as the real one would.
    return SimRig(actual, targets, seed=int(sim.get("noise_seed", sim["seed"])), joint_map=spec.joint_map)


def _drivers(robot_driver, tracker_driver, spec, targets, *, profile, tracker_profile, sim_errors, seed, sim_seed):
    """(robot, tracker, frame, metadata, closers) for the chosen drivers."""
    if robot_driver not in ROBOT_DRIVERS:
        raise UserError(f"--robot-driver must be one of {', '.join(ROBOT_DRIVERS)}, got {robot_driver!r}")
    if tracker_driver not in TRACKER_DRIVERS:
        raise UserError(f"--tracker-driver must be one of {', '.join(TRACKER_DRIVERS)}, got {tracker_driver!r}")
    if (robot_driver == "sim") != (tracker_driver == "sim"):
        raise UserError("the sim robot and the sim tracker go together: use --robot-driver sim --tracker-driver sim")
    if robot_driver == "sim":
        sim = {"errors": sim_errors, "seed": seed if sim_seed is None else sim_seed, "noise_seed": seed}
        rig = _sim_rig(spec, targets, sim)
        return rig.robot(), rig.tracker(), "base", {"sim": sim}
    from labcal.drivers.serial_tracker import open_tracker
    from labcal.drivers.ur import URRobot, load_ur_profile

    if profile is None or tracker_profile is None:
        raise UserError("real drivers need --profile drivers/<robot>.toml and --tracker-profile drivers/<tracker>.toml")
    robot = URRobot.connect(load_ur_profile(profile))
    tracker = open_tracker(tracker_profile, targets)
    return robot, tracker, "tracker", {"profiles": {"robot": str(profile), "tracker": str(tracker_profile)}}


def new_session(
    store: SessionStore,
    *,
    robot: str,
    targets_file: str | Path,
    poses: int,
    robot_driver: str = "sim",
    tracker_driver: str = "sim",
    profile: str | None = None,
    tracker_profile: str | None = None,
    planner: str = "random",
    samples: int = 2000,
    seed: int = 0,
    sim_errors: str = "default",
    progress=None,
    allow: tuple[str, ...] = (),
    sim_seed: int | None = None,
):
    """Plan and record a session; returns the runner's RunSummary (its .ref is the new SESSION@vNNN).

    seed: the planner's and the sim rig's (robot errors and tracker noise); sim_seed: another simulated robot's
    errors than seed's (the same robot as another session's seed, measured at other configurations).

    allow: record-time sanity checks to override (see :mod:`labcal.datasets.sanity`), checked before planning."""
    from labcal.datasets import load_targets
    from labcal.sessions import make_plan, run

    check_plan_size(poses, planner, samples)  # before anything is loaded, planned or allocated
    allowed = _allowed(allow)
    spec = load(robot)
    targets = load_targets(targets_file)
    if sim_errors not in SIM_ERRORS:
        raise UserError(f"--sim-errors must be one of {', '.join(SIM_ERRORS)}, got {sim_errors!r}")
    q = plan_configurations(spec, poses, planner, seed, targets, samples)
    sim = robot_driver == "sim"
    plan = make_plan(q, samples=3 if sim else 5, settle=0.0 if sim else 0.5)
    rob, trk, frame, meta = _drivers(
        robot_driver, tracker_driver, spec, targets, profile=profile, tracker_profile=tracker_profile,
        sim_errors=sim_errors, seed=seed, sim_seed=sim_seed,
    )  # fmt: skip
    with rob, trk:
        return run(store, spec, targets, plan, rob, trk, frame=frame, progress=progress, metadata=meta, allow=allowed)


def _allowed(allow) -> tuple[str, ...]:
    from labcal.datasets.sanity import check_names

    return tuple(sorted(check_names(allow)))  # an unknown name raises, listing the checks


def resume_session(
    store: SessionStore, session_id: str, *, robot: str | None = None, progress=None, allow: tuple[str, ...] = ()
):
    """Resume a session; a sim session re-creates its simulated robot from the recorded errors and seed.

    allow: record-time sanity checks to override, added to those the session was started with."""
    from labcal.sessions import resume

    meta = store.session_meta(session_id)
    spec = robot_for(meta["robot"], robot)
    sim = (meta.get("metadata") or {}).get("sim")
    if not sim:
        raise UserError(
            f"session {session_id} was not recorded on the sim rig; resume real-hardware sessions from Python with "
            "the same drivers (labcal.sessions.resume)"
        )
    rig = _sim_rig(spec, np.asarray(meta["targets"], dtype=float), sim)
    with rig.robot() as rob, rig.tracker() as trk:
        return resume(store, session_id, rob, trk, spec=spec, progress=progress, allow=_allowed(allow))
