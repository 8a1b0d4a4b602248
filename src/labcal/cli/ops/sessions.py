"""`labcal session new / resume` as functions: plan, pick the drivers, record or continue a session."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from labcal.cli.common import UserError
from labcal.cli.ops.common import check_choice, check_seed, check_unit_option, robot_for
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

    check_choice("--sim-errors", errors, SIM_ERRORS)
    spec_errors = {"paper": ErrorSpec.paper, "default": ErrorSpec.default, "none": ErrorSpec.none}[errors]()
    return simulate(spec, spec_errors, seed=seed)


def plan_configurations(
    spec: RobotSpec,
    poses: int,
    planner: str,
    seed: int,
    targets,
    samples: int = 2000,
    dropout: float | None = None,
    cell: dict | None = None,
):
    """(poses, n) model joints. ``dropout``: the tracker's chance of losing a target, which the optimal planner
    weighs in (it maximises the information of the points expected to be measured). ``cell``: the planner's
    cell arguments (:func:`plan_cell`: safety, joint_map, workspace, facing)."""
    from labcal.sessions import optimal_configurations, random_configurations

    check_plan_size(poses, planner, samples)
    check_choice("--planner", planner, PLANNERS)
    cell = cell or {}
    if planner == "random":
        return random_configurations(spec.model, poses, seed=seed, targets=targets, **cell)
    return optimal_configurations(
        spec.model, poses, seed=seed, targets=targets, candidates=samples, dropout=dropout or None, **cell
    )


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
    tracker noise from ``noise_seed`` (the same seed unless another session of the same robot was asked for), the
    per-target drop-out probability from ``dropout`` (absent: none)."""
    from labcal.drivers.sim import SimRig

    actual = sim_actual(spec, sim["errors"], int(sim["seed"]))
    # The simulated controller speaks the robot file's controller joints, as the real one would.
    try:
        return SimRig(
            actual,
            targets,
            seed=int(sim.get("noise_seed", sim["seed"])),
            joint_map=spec.joint_map,
            serial=f"sim-{int(sim['seed'])}",  # the errors' seed names the simulated robot (sim_seed pools sessions)
            dropout=float(sim.get("dropout") or 0.0),
        )
    except ValueError as e:  # e.g. a target count the sim rig does not support
        raise UserError(f"the sim rig refused the session's targets: {e}") from None


@dataclass(frozen=True)
class SessionRequest:
    """What ``labcal session new`` asks for: the robot model and targets file, the plan, the drivers, the sim rig.

    robot: built-in name or robot file; targets_file: targets TOML (1..k points, tool frame); poses / planner /
    samples / seed: the plan (seed also seeds the sim rig's noise); robot_driver / tracker_driver ("sim" | "ur",
    "sim" | "serial") with profile / tracker_profile for real hardware; sim_errors ("paper" | "default" | "none"),
    sim_seed (another simulated robot's errors than seed's: the same robot as another session's seed) and
    sim_dropout (probability that the sim tracker loses each target in a pose); allow: record-time sanity checks to
    override (see :mod:`labcal.datasets.sanity`); unit: the robot unit's id to record (default: the serial number
    the controller reports; on the sim rig ``sim-<seed of the simulated robot>``, so sessions of one simulated
    robot are one unit).
    """

    robot: str
    targets_file: str | Path
    poses: int
    robot_driver: str = "sim"
    tracker_driver: str = "sim"
    profile: str | None = None
    tracker_profile: str | None = None
    planner: str = "random"
    samples: int = 2000
    seed: int = 0
    sim_errors: str = "default"
    sim_seed: int | None = None
    sim_dropout: float = 0.0
    allow: tuple[str, ...] = ()
    unit: str | None = None
    robot_host: str | None = None
    tracker_port: str | None = None
    max_failed_poses: int = 5

    def check(self) -> None:
        """The checks that need nothing loaded: plan size, driver names, sim options, override names."""
        check_plan_size(self.poses, self.planner, self.samples)
        check_choice("--robot-driver", self.robot_driver, ROBOT_DRIVERS)
        check_choice("--tracker-driver", self.tracker_driver, TRACKER_DRIVERS)
        if (self.robot_driver == "sim") != (self.tracker_driver == "sim"):
            raise UserError(
                "the sim robot and the sim tracker go together: use --robot-driver sim --tracker-driver sim"
            )
        check_choice("--sim-errors", self.sim_errors, SIM_ERRORS)
        check_seed(self.seed)
        check_seed(self.sim_seed, "--sim-seed")
        dropout = self.sim_dropout
        if not (isinstance(dropout, int | float) and 0.0 <= float(dropout) < 1.0):
            raise UserError(
                f"--sim-dropout must be a probability in [0, 1) (each target lost independently), got {dropout}"
            )
        if self.sim_dropout and self.robot_driver != "sim":
            raise UserError("--sim-dropout is an option of the sim tracker (--tracker-driver sim)")
        _allowed(self.allow)
        check_unit_option(self.unit)
        if (self.robot_host or self.tracker_port) and self.robot_driver == "sim":
            raise UserError("--robot-host and --tracker-port are options of the hardware drivers (--robot-driver ur)")
        failed = self.max_failed_poses  # 0: never stop for rejected poses
        if isinstance(failed, bool) or not isinstance(failed, int) or failed < 0:
            raise UserError(f"--max-failed-poses must be an integer >= 0 (0: never stop early), got {failed!r}")

    def inputs(self):
        """(robot spec, targets, target normals: None or what the planner's line-of-sight check needs) read from the
        robot and the targets file."""
        from labcal.datasets import load_targets
        from labcal.datasets.targets import load_target_normals

        return load(self.robot), load_targets(self.targets_file), load_target_normals(self.targets_file)


def _drivers(request: SessionRequest, spec: RobotSpec, targets):
    """(robot, tracker, frame, metadata) for the chosen drivers."""
    r = request
    if r.robot_driver == "sim":
        sim: dict[str, Any] = {"errors": r.sim_errors, "seed": r.seed if r.sim_seed is None else r.sim_seed}
        sim["noise_seed"] = r.seed
        if r.sim_dropout:
            sim["dropout"] = r.sim_dropout
        rig = _sim_rig(spec, targets, sim)
        return rig.robot(), rig.tracker(), "base", {"sim": sim}
    if r.profile is None or r.tracker_profile is None:
        raise UserError("real drivers need --profile drivers/<robot>.toml and --tracker-profile drivers/<tracker>.toml")
    robot, tracker = _real_drivers(r.profile, r.tracker_profile, targets, r.robot_host, r.tracker_port)
    # recorded as absolute paths where they are files, so that `session resume` finds them from any folder
    profiles = {k: str(Path(v).resolve()) if Path(v).is_file() else str(v)
                for k, v in (("robot", r.profile), ("tracker", r.tracker_profile))}  # fmt: skip
    meta: dict[str, Any] = {"profiles": profiles}
    # the overrides too: a resume without flags goes back to the same controller and port
    overrides = {k: v for k, v in (("robot_host", r.robot_host), ("tracker_port", r.tracker_port)) if v}
    if overrides:
        meta["overrides"] = overrides
    return robot, tracker, "tracker", meta


def _real_drivers(profile, tracker_profile, targets, robot_host=None, tracker_port=None):
    """(UR robot, serial tracker) opened from their profile files: what `session new` and `session resume` use.

    robot_host / tracker_port (--robot-host / --tracker-port) replace the profile's ``host`` and ``[port] url``.
    A controller or tracker that cannot be reached is a UserError naming the host or port and the profile key to
    fix (one line, exit 2): nothing has moved yet."""
    from labcal.drivers.base import DriverError
    from labcal.drivers.serial.tracker import open_tracker
    from labcal.drivers.ur import URRobot, load_ur_profile

    ur_profile = load_ur_profile(profile)
    if robot_host:
        ur_profile = ur_profile.with_host(robot_host)
    try:
        robot = URRobot.connect(ur_profile)
    except DriverError as e:
        where = "--robot-host" if robot_host else f"`host` in {profile}, or pass --robot-host"
        raise UserError(f"cannot use the UR controller at {ur_profile.host}: {e} (check {where})") from None
    try:
        return robot, open_tracker(tracker_profile, targets, url=tracker_port or None)
    except BaseException as e:
        robot.close()  # nothing moved: release the controller before reporting the tracker's error
        if isinstance(e, DriverError | OSError):
            url = tracker_port or _profile_url(tracker_profile)
            where = "--tracker-port" if tracker_port else f"[port] url in {tracker_profile}, or pass --tracker-port"
            raise UserError(f"cannot use the tracker on {url}: {_one_line(e)} (check {where})") from None
        raise


def plan_cell(request: SessionRequest, spec: RobotSpec, normals, robot) -> dict:
    """What the planner must respect, as keyword arguments of the planners: the robot driver's own
    ``robot.limits`` (the SafetyLimits every move is checked against: no planned pose is refused for its joints),
    the ``[workspace]`` boxes of the profile the robot was opened with (``robot.profile``), and, when the targets
    file gives normals and the tracker's position is known, targets facing the tracker. The tracker's position
    comes from the robot profile's ``[workspace] tracker_mm`` or the tracker profile's ``[placement] position_mm``
    (both given: they must agree within 1 mm). ``normals``: ``load_target_normals`` of the targets file (None: no
    line-of-sight check)."""
    from labcal.sessions.planning import TargetFacing

    cell: dict[str, Any] = {"safety": robot.limits, "joint_map": spec.joints}
    tracker = None
    # The sim rig's tracker frame is the base frame (a convention, not a place in a cell): no line of sight there.
    if request.robot_driver != "sim":
        from labcal.drivers.serial.profiles import load_placement
        from labcal.drivers.ur import load_ur_profile

        # The profile the robot was opened with (its limits are cell["safety"]), not the file read again: edited
        # in between, the two would disagree. (A stand-in robot without one: the file.)
        opened = getattr(robot, "profile", None)
        workspace = (opened if opened is not None else load_ur_profile(request.profile)).workspace
        cell["workspace"] = workspace
        sources = {
            f"{request.profile} [workspace] tracker_mm": workspace.tracker if workspace else None,
            f"{request.tracker_profile} [placement] position_mm": load_placement(request.tracker_profile),
        }
        given = {k: v for k, v in sources.items() if v is not None}
        if len(given) == 2 and np.linalg.norm(np.subtract(*given.values())) > 1e-3:
            raise UserError(
                f"the tracker's position differs between {' and '.join(given)}: keep one, or make them agree"
            )
        tracker = next(iter(given.values()), None)
    if normals is not None and tracker is not None:
        cell["facing"] = TargetFacing(tracker, *normals)
    return cell


def _profile_url(tracker_profile) -> str:
    from labcal.drivers.serial.profiles import load_profile

    try:
        return load_profile(tracker_profile).port.url or "(no port)"
    except (OSError, ValueError):
        return "(the profile's port)"


def _one_line(e: BaseException) -> str:
    text = str(e).strip() or type(e).__name__
    return text.splitlines()[0]


def new_session(store: SessionStore, request: SessionRequest | None = None, *, progress=None, **fields: Any):
    """Plan and record a session; returns the runner's RunSummary (its .ref is the new SESSION@vNNN).

    ``request``: a :class:`SessionRequest`, or its fields as keywords (``new_session(store, robot="ur10",
    targets_file="t.toml", poses=40)``). ``progress``: the runner's progress callback. Every argument is checked
    before anything is connected or moved; the plan is drawn once the robot is open, inside its own limits."""
    from labcal.sessions import RetryPolicy, RunOptions, make_plan, run

    request = SessionRequest(**fields) if request is None else dataclasses.replace(request, **fields)
    request.check()  # before anything is loaded, planned or allocated
    spec, targets, normals = request.inputs()
    sim = request.robot_driver == "sim"
    rob, trk, frame, meta = _drivers(request, spec, targets)
    # The unit: --unit, else the serial the robot driver reports (the sim rig's is sim-<seed of its errors>).
    options = RunOptions(
        frame=frame, progress=progress, metadata=meta, allow=_allowed(request.allow), unit=request.unit,
        retry=RetryPolicy(max_failed_poses=request.max_failed_poses),
    )  # fmt: skip
    with rob, trk:
        # Planned after the drivers open, inside the limits object the robot checks every move against.
        cell = plan_cell(request, spec, normals, rob)
        q = plan_configurations(
            spec, request.poses, request.planner, request.seed, targets, request.samples, request.sim_dropout, cell
        )
        plan = make_plan(q, samples=3, settle=0.0) if sim else plan_for_robot(q, spec, rob.limits)
        return run(store, spec, targets, plan, rob, trk, options)


def plan_for_robot(q, spec: RobotSpec, limits, *, samples: int = 5, settle: float = 0.5):
    """The plan a real robot runs: poses ordered for the least motion time (``order_for_motion`` on the
    controller joints the runner commands), moves at the robot's speed and acceleration caps (``limits``: its
    SafetyLimits). The sim rig moves instantly, so its plans keep the planner's order (and their recorded data)."""
    from labcal.sessions import make_plan
    from labcal.sessions.planning import order_for_motion

    speed, acceleration = limits.max_speed, limits.max_acceleration
    q = q[order_for_motion(spec.joints.to_controller(q), speed, acceleration)]
    return make_plan(q, samples=samples, settle=settle, speed=speed, acceleration=acceleration)


def _allowed(allow) -> tuple[str, ...]:
    from labcal.datasets.sanity import check_names

    return tuple(sorted(check_names(allow)))  # an unknown name raises, listing the checks


def resume_session(
    store: SessionStore,
    session_id: str,
    *,
    robot: str | None = None,
    progress=None,
    allow: tuple[str, ...] = (),
    profile=None,
    tracker_profile=None,
    robot_host: str | None = None,
    tracker_port: str | None = None,
):
    """Resume a session on the drivers it was recorded with: a sim session re-creates its simulated robot from the
    recorded errors and seed; a hardware session reopens the UR and the tracker from the profile files it recorded
    (``profile`` / ``tracker_profile`` replace them, e.g. when the files moved; ``robot_host`` / ``tracker_port``
    replace the host and port, else those the session was started with). The runner then refuses, before
    anything moves, another arm (serial number), another robot model (hash) or a robot still in a protective stop.

    allow: record-time sanity checks to override, added to those the session was started with."""
    from labcal.datasets import DatasetCorrupted
    from labcal.sessions import SessionError, resume

    try:  # the whole session (versions, journal, start document) before anything is opened or moved
        store.check_before_recording(session_id)
    except DatasetCorrupted as e:
        raise SessionError(str(e)) from None
    meta = store.session_meta(session_id)
    spec = robot_for(meta["robot"], robot)
    metadata = meta.get("metadata") or {}
    targets = np.asarray(meta["targets"], dtype=float).reshape(-1, 3)
    allowed = _allowed(allow)
    if metadata.get("sim"):
        if any(v is not None for v in (profile, tracker_profile, robot_host, tracker_port)):
            raise UserError(
                f"session {session_id} was recorded on the sim rig: it resumes there, without profiles, "
                "--robot-host or --tracker-port"
            )
        rig = _sim_rig(spec, targets, metadata["sim"])
        rob, trk = rig.robot(), rig.tracker()
    else:
        recorded = metadata.get("profiles") or {}
        profile, tracker_profile = profile or recorded.get("robot"), tracker_profile or recorded.get("tracker")
        if profile is None or tracker_profile is None:
            missing = " and ".join(
                flag for flag, value in (("--profile", profile), ("--tracker-profile", tracker_profile)) if not value
            )
            raise UserError(f"session {session_id} did not record its driver profiles: pass {missing}")
        overrides = metadata.get("overrides") or {}
        robot_host = robot_host or overrides.get("robot_host")
        tracker_port = tracker_port or overrides.get("tracker_port")
        rob, trk = _real_drivers(profile, tracker_profile, targets, robot_host, tracker_port)
    with rob, trk:
        return resume(store, session_id, rob, trk, spec=spec, progress=progress, allow=allowed)
