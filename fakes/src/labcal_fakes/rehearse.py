"""Rehearse a hardware session on the fakes: a fake UR controller on loopback and a fake NDI tracker on a pty.

The fake controller (:class:`~labcal_fakes.rtde_fake.FakeRTDEServer`, RTDE + dashboard + script ports, in its
own process) moves a simulated joint state when ur-rtde commands it; the fake NDI Polaris
(:class:`~labcal_fakes.devices.FakeNDIDevice`, on a pseudo-terminal) reports where a simulated actual robot
(:func:`labcal.simulation.simulate`, with errors) puts the targets at the controller's current joints, in a
tracker frame. So ``labcal session new --robot-driver ur --tracker-driver serial`` runs its real drivers, exactly
as on the arm, only with ``--robot-host`` and ``--tracker-port`` pointing at the fakes::

    python -m labcal_fakes.rehearse --targets drivers/targets-example.toml
    # prints the fakes' address and port, and the `labcal session new …` line to run in another terminal;
    # Ctrl-C stops the fakes.

From Python (the end-to-end tests and ``benchmarks/lab_faults.py`` use this to inject faults)::

    with Rehearsal(targets) as rig:
        args = rig.session_args(profile, tracker_profile)   # --robot-host … --tracker-port …
        rig.kill_controller()                                 # or drop_rtde(), protective_stop_next_move(), …
"""

from __future__ import annotations

import argparse
import shlex
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from labcal_fakes.devices import FakeNDIDevice
from labcal_fakes.rtde_fake import FakeRTDEServer

HOME = (0.0, -1.5708, 1.5708, 0.0, 1.5708, 0.0)


class Rehearsal:
    """A fake UR controller and a fake NDI tracker that see the same simulated robot. A context manager.

    targets: (m, 3) m, tool frame (or a targets TOML path); robot: the simulated robot's model (built-in name or
    robot file); seed / errors: its simulated errors ("default", "paper", "none"); q0: (6,) rad, start joints.
    ``host`` (controller address) is set once started; ``port`` (tracker pty) once made.
    """

    def __init__(self, targets: Any, *, robot: str = "ur10", seed: int = 0, errors: str = "default", q0=HOME) -> None:
        from labcal.robots import load
        from labcal.simulation import ErrorSpec, simulate

        if isinstance(targets, str | Path):
            from labcal.datasets import load_targets

            targets = load_targets(targets)
        self.targets = np.asarray(targets, dtype=float)
        spec = load(robot)
        errors_spec = {"paper": ErrorSpec.paper, "default": ErrorSpec.default, "none": ErrorSpec.none}[errors]()
        self.actual = simulate(spec, errors_spec, seed=seed)
        self.joints = spec.joints
        self.q0 = [float(v) for v in q0]
        self._rng = np.random.default_rng([seed, 7])
        self._lock = threading.Lock()
        self.garbage = False  # the tracker reports markers at random places (frames that match no target triangle)
        # Made here, started by start(); start_controller() / start_tracker() replace them with new ones.
        self.controller = FakeRTDEServer(q0=self.q0, control=True)
        self.tracker = FakeNDIDevice(self.points, seed=0)

    # -- lifecycle -------------------------------------------------------------------------------------------

    def __enter__(self) -> Rehearsal:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        try:
            self.controller.start()
            self.tracker.start()
        except BaseException:
            self.stop()
            raise

    def start_controller(self) -> str:
        """Restart the fake controller (a new process, perhaps on another address); returns its host."""
        self.controller.kill()
        self.controller = FakeRTDEServer(q0=self.q0, control=True)
        self.controller.start()
        return self.controller.host

    def start_tracker(self) -> str:
        """Restart the fake tracker on a new pty; returns its port."""
        self.tracker.close()
        self.tracker = FakeNDIDevice(self.points, seed=0)
        self.tracker.start()
        return self.tracker.port

    def stop(self) -> None:
        self.tracker.close()
        self.controller.stop()

    @property
    def host(self) -> str:
        return self.controller.host

    @property
    def port(self) -> str:
        return self.tracker.port

    # -- what the tracker sees -------------------------------------------------------------------------------

    def points(self) -> np.ndarray:
        """(m, 3) m in the tracker frame: the simulated robot's targets at the fake controller's joints."""
        if self.garbage:  # markers anywhere: no frame matches the target triangle
            return self._rng.uniform(-1.0, 1.0, size=self.targets.shape) + np.array([0.0, 0.0, -2.0])
        q = np.asarray(self.controller.snapshot()["q"], dtype=float)
        self.q0 = q.tolist()  # a restarted controller starts where the last one stopped
        with self._lock:
            return self.actual.measure(self.joints.to_model(q)[None], self.targets, self._rng)[0]

    # -- faults ----------------------------------------------------------------------------------------------

    def kill_controller(self) -> None:
        """SIGKILL the fake controller: the kernel closes its sockets (a controller that died)."""
        self.controller.kill()

    def drop_rtde(self) -> None:
        """Shut down every client connection of the controller, which keeps listening (a network drop)."""
        self.controller.drop_clients()

    def freeze_controller(self) -> None:
        """The controller keeps streaming, its timestamp no longer advances (a hung controller)."""
        self.controller.freeze_timestamp(True)

    def protective_stop_next_move(self, fraction: float = 0.5) -> None:
        self.controller.inject_stop_during_next_move("protective", fraction)

    def clear_protective_stop(self) -> None:
        self.controller.set_safety(protective=False)

    def send_garbage(self) -> None:
        """The tracker reports markers at random places from now on (no frame matches the target triangle)."""
        self.garbage = True

    def send_points(self) -> None:
        """The tracker reports the targets again."""
        self.garbage = False

    def kill_tracker(self) -> None:
        """Close the tracker's pty (a tracker unplugged or switched off)."""
        self.tracker.close()

    def silence_tracker(self) -> None:
        """The tracker stays plugged in but answers nothing (no reply to any command, no RESET after a break)."""
        self.tracker.handle = lambda line: None  # type: ignore[method-assign]

    # -- the command line ------------------------------------------------------------------------------------

    def session_args(self) -> list[str]:
        """The flags that point ``labcal session new`` / ``resume`` at these fakes."""
        return ["--robot-host", self.host, "--tracker-port", self.port]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m labcal_fakes.rehearse",
        description="Start a fake UR controller (loopback) and a fake NDI tracker (pty) that see one simulated "
        "robot, and print the `labcal session new` line that records a session on them. Ctrl-C stops them.",
    )
    parser.add_argument("--targets", default="drivers/targets-example.toml", help="targets TOML (tool frame)")
    parser.add_argument("--robot", default="ur10", help="robot model of the simulated arm (name or file)")
    parser.add_argument("--profile", default="drivers/ur10-lab.toml", help="robot profile to print in the command")
    parser.add_argument("--tracker-profile", default="drivers/ndi-polaris.toml", help="tracker profile to print")
    parser.add_argument("--poses", type=int, default=12, help="--poses of the printed command")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated robot's errors")
    args = parser.parse_args(argv)
    # Ctrl-C may arrive at any moment (mid-start, mid-print): it only asks for the stop, which happens in one place.
    stopped = threading.Event()
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, lambda *_: stopped.set())
    try:
        rig = Rehearsal(args.targets, robot=args.robot, seed=args.seed)
        rig.start()
    except (OSError, ValueError, RuntimeError, TimeoutError) as exc:
        print(f"error: cannot start the fakes: {exc}", file=sys.stderr)
        return 2
    command = [
        "labcal", "session", "new", "--robot", args.robot, "--targets", args.targets, "--poses", str(args.poses),
        "--robot-driver", "ur", "--tracker-driver", "serial", "--profile", args.profile,
        "--tracker-profile", args.tracker_profile, *rig.session_args(),
    ]  # fmt: skip
    print(f"fake UR controller on {rig.host} (RTDE 30004, dashboard 29999, script 30003)")
    print(f"fake NDI tracker on {rig.port}")
    print("record a session on them (in another terminal):")
    print("  " + shlex.join(command), flush=True)
    print("Ctrl-C stops the fakes.", flush=True)
    stopped.wait()
    rig.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
