"""Helpers shared by the session tests: a custom robot file, interrupted sim sessions, robot wrappers."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labcal.drivers.sim import SimRig
from labcal.robots import builtin_path, load
from labcal.sessions import make_plan, random_configurations, run

TARGETS = np.array([[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03]])
TARGETS_TOML = 'unit = "m"\npoints = [[0.08, 0.0, 0.03], [-0.04, 0.07, 0.03], [-0.04, -0.07, 0.03]]\n'


def write_custom_robot(folder: Path, name: str = "lab-arm") -> Path:
    """A robot file that is not a built-in: the ur10 with another name and a 3 mm longer base (another hash)."""
    text = builtin_path("ur10").read_text()
    text = text.replace('name = "ur10"', f'name = "{name}"', 1)  # the robot's name; joint names stay unique
    assert "d = 0.1273" in text
    text = text.replace("d = 0.1273", "d = 0.1303", 1) + "\n"
    path = folder / f"{name}.toml"
    path.write_text(text)
    assert load(path).hash != load("ur10").hash
    return path


class CountingRobot:
    """Wraps a robot: counts moves; raises KeyboardInterrupt (an operator's Ctrl-C) on move number ``interrupt_at``."""

    def __init__(self, robot, interrupt_at: int | None = None):
        self._robot, self.interrupt_at = robot, interrupt_at
        self.n_joints, self.limits = robot.n_joints, robot.limits
        self.moves = 0
        self.commanded: list[np.ndarray] = []

    def move_joints(self, q, speed, acceleration):
        self.moves += 1
        if self.interrupt_at is not None and self.moves == self.interrupt_at:
            raise KeyboardInterrupt
        self.commanded.append(np.array(q, dtype=float))
        return self._robot.move_joints(q, speed, acceleration)

    def __getattr__(self, name):
        return getattr(self._robot, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._robot.close()


def record_interrupted(
    store, spec, n_poses: int, interrupt_at: int, *, errors: str = "default", seed: int = 0, seal: bool = True
):
    """A sim session (resumable by ``cli.ops.sessions.resume_session``) aborted by Ctrl-C at move ``interrupt_at``;
    ``seal=False`` leaves its journal unsealed (as a crash would)."""
    from labcal.cli.ops.sessions import sim_actual

    rig = SimRig(sim_actual(spec, errors, seed), TARGETS, seed=seed)
    q = random_configurations(spec.model, n_poses, seed=seed, targets=TARGETS)
    plan = make_plan(q, samples=3, settle=0.0)
    robot = CountingRobot(rig.robot(), interrupt_at)
    with robot, rig.tracker() as tracker:
        summary = run(store, spec, TARGETS, plan, robot, tracker, frame="base",
                      metadata={"sim": {"errors": errors, "seed": seed}}, seal=seal)  # fmt: skip
    assert summary.exit_status == "aborted"
    return summary
