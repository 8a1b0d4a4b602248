"""Plans are data: a sequence of commands the runner executes, inspectable and testable as a list.

Commands (frozen dataclasses, SI units):

- :class:`Move` ``(q, speed, acceleration)``: a joint move to q (n,) rad (m), speed rad/s, acceleration rad/s²;
- :class:`Settle` ``(seconds)``: wait for vibrations to die out before measuring;
- :class:`Measure` ``(samples)``: one tracker measurement averaging ``samples`` frames.

Every :class:`Move` starts a *pose*: it and the commands up to the next Move. Each pose holds exactly one
Measure, so pose i of the plan is the configuration whose measurement has ``pose_index = i`` in the journal.

Example::

    >>> plan = make_plan([[0.0, 0.1], [0.2, 0.3]], samples=3, settle=0.5, speed=0.4, acceleration=0.8)
    >>> [type(c).__name__ for c in plan]
    ['Move', 'Settle', 'Measure', 'Move', 'Settle', 'Measure']
    >>> plan.n_poses, plan[2]
    (2, Measure(samples=3))
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Union

import numpy as np

from labcal.drivers.base import move_time


class PlanError(ValueError):
    """A plan or one of its commands is malformed; the message names the command index and field."""


def checked_number(
    value: Any, name: str, *, least: float = 0, above: bool = False, integer: bool = False, error: type = PlanError
) -> Any:
    """``value`` as a float (an int with ``integer``) once it is a finite number (an integer; never a bool) >= ``least``
    (> with ``above``); else ``error`` naming ``name``, e.g. "Measure.samples must be an integer >= 1, got 0"."""
    kinds = int | np.integer if integer else int | float | np.number
    ok = not isinstance(value, bool) and isinstance(value, kinds) and math.isfinite(value)
    if not (ok and (value > least if above else value >= least)):
        what = "an integer" if integer else "a finite number"
        raise error(f"{name} must be {what} {'>' if above else '>='} {least}, got {value!r}")
    return int(value) if integer else float(value)


@dataclass(frozen=True)
class Move:
    """Joint move to ``q`` (n,) rad (m for prismatic joints) at ``speed`` rad/s and ``acceleration`` rad/s²."""

    q: tuple[float, ...]
    speed: float
    acceleration: float

    def __post_init__(self) -> None:
        q = np.asarray(self.q, dtype=float)
        if q.ndim != 1 or q.size == 0 or not np.all(np.isfinite(q)):
            raise PlanError(f"Move.q must be a non-empty finite 1-D joint vector, got {self.q!r}")
        object.__setattr__(self, "q", tuple(float(x) for x in q))
        object.__setattr__(self, "speed", checked_number(self.speed, "Move.speed (rad/s)", above=True))
        object.__setattr__(
            self, "acceleration", checked_number(self.acceleration, "Move.acceleration (rad/s²)", above=True)
        )


@dataclass(frozen=True)
class Settle:
    """Wait ``seconds`` (>= 0) before measuring."""

    seconds: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "seconds", checked_number(self.seconds, "Settle.seconds"))


@dataclass(frozen=True)
class Measure:
    """Measure the session's targets, averaging ``samples`` (>= 1) tracker frames."""

    samples: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "samples", checked_number(self.samples, "Measure.samples", least=1, integer=True))


Command = Union[Move, Settle, Measure]  # noqa: UP007 - a runtime alias, also used in isinstance checks
_KINDS: dict[str, type] = {"move": Move, "settle": Settle, "measure": Measure}


def command_to_dict(command: Command) -> dict:
    """JSON-able form: ``{"command": "move", "q": [...], "speed": ..., "acceleration": ...}`` etc."""
    if isinstance(command, Move):
        return {"command": "move", "q": list(command.q), "speed": command.speed, "acceleration": command.acceleration}
    if isinstance(command, Settle):
        return {"command": "settle", "seconds": command.seconds}
    if isinstance(command, Measure):
        return {"command": "measure", "samples": command.samples}
    raise PlanError(f"not a plan command: {command!r}")


def command_from_dict(data: Any, where: str = "command") -> Command:
    """Inverse of :func:`command_to_dict`; errors name ``where`` and the bad field."""
    if not isinstance(data, dict):
        raise PlanError(f"{where}: expected an object, got {data!r}")
    kind = data.get("command")
    cls = _KINDS.get(kind)  # type: ignore[arg-type]
    if cls is None:
        raise PlanError(f"{where}: unknown command {kind!r}; expected one of {sorted(_KINDS)}")
    fields = {k: v for k, v in data.items() if k != "command"}
    expected = set(cls.__dataclass_fields__)
    if set(fields) != expected:
        raise PlanError(f"{where}: {kind} needs fields {sorted(expected)}, got {sorted(fields)}")
    try:
        return cls(**fields)
    except PlanError as e:
        raise PlanError(f"{where}: {e}") from None


@dataclass(frozen=True)
class PoseStep:
    """One pose of a plan: ``index`` (0-based), the Move, total settle time (s) and samples to average."""

    index: int
    move: Move
    settle: float
    samples: int

    @property
    def q(self) -> np.ndarray:
        return np.asarray(self.move.q)


@dataclass(frozen=True)
class Plan(Sequence):
    """An immutable sequence of commands; see the module docstring for the pose structure."""

    commands: tuple[Command, ...]

    def __post_init__(self) -> None:
        commands = tuple(self.commands)
        object.__setattr__(self, "commands", commands)
        if not commands:
            raise PlanError("a plan needs at least one Move followed by a Measure")
        if not isinstance(commands[0], Move):
            raise PlanError(f"command 0: a plan must start with a Move, got {type(commands[0]).__name__}")
        n = len(commands[0].q)
        measures = 0
        for i, c in enumerate(commands):
            if isinstance(c, Move):
                if len(c.q) != n:
                    raise PlanError(f"command {i}: Move has {len(c.q)} joint values, the first Move has {n}")
                if i > 0 and measures != 1:
                    raise PlanError(f"command {i}: the pose before this Move has {measures} Measure commands, needs 1")
                measures = 0
            elif isinstance(c, Measure):
                measures += 1
            elif not isinstance(c, Settle):
                raise PlanError(f"command {i}: not a Move, Settle or Measure: {c!r}")
        if measures != 1:
            raise PlanError(f"the last pose has {measures} Measure commands, needs exactly 1")

    # Sequence protocol (iteration, ``in``, ``index`` … follow from these two): a plan *is* its list of commands.
    def __len__(self) -> int:
        return len(self.commands)

    def __getitem__(self, i):  # type: ignore[override]
        return self.commands[i]

    @property
    def n_joints(self) -> int:
        return len(self.commands[0].q)  # type: ignore[union-attr]

    def _pose_commands(self) -> list[list[Command]]:
        """The commands of each pose: a Move and the commands up to the next one."""
        groups: list[list[Command]] = []
        for c in self.commands:
            if isinstance(c, Move):
                groups.append([])
            groups[-1].append(c)
        return groups

    def poses(self) -> list[PoseStep]:
        """The plan grouped into poses (one per Move), in order."""
        return [
            PoseStep(
                i,
                group[0],  # type: ignore[arg-type]
                sum((c.seconds for c in group if isinstance(c, Settle)), 0.0),
                next(c.samples for c in group if isinstance(c, Measure)),
            )
            for i, group in enumerate(self._pose_commands())
        ]

    @functools.cached_property
    def n_poses(self) -> int:
        # counted once: the runner asks at every pose, and a count per call made long sessions quadratic
        return sum(isinstance(c, Move) for c in self.commands)

    @property
    def configurations(self) -> np.ndarray:
        """(n_poses, n) the Move targets, rad (m)."""
        return np.array([c.q for c in self.commands if isinstance(c, Move)])

    def pose_documents(self) -> list[dict]:
        """One JSON-able entry per pose ``{"pose": i, "commands": [...]}``: the plan as stored in a journal's
        start document, so the journal's plan length is the number of poses."""
        return [{"pose": i, "commands": [command_to_dict(c) for c in g]} for i, g in enumerate(self._pose_commands())]

    @classmethod
    def from_pose_documents(cls, docs: Sequence[Any]) -> Plan:
        """Inverse of :meth:`pose_documents`."""
        commands: list[Any] = []
        for i, d in enumerate(docs):
            if not isinstance(d, dict) or d.get("pose") != i or not isinstance(d.get("commands"), list):
                raise PlanError(f"pose document {i}: expected {{'pose': {i}, 'commands': [...]}}, got {d!r}")
            commands += d["commands"]
        return cls(tuple(command_from_dict(c, f"command {i}") for i, c in enumerate(commands)))


def motion_time(plan: Plan) -> float:
    """Seconds the plan's moves take (the longest joint of each move, at each Move's speed and acceleration), from
    the first pose (its move is free). Settling and measuring excluded.

    >>> motion_time(make_plan([[0.0, 0.0], [2.0, 0.1], [2.0, 0.0]], speed=0.5, acceleration=1.0))
    5.132455532033676
    """
    q = plan.configurations
    moves = [c for c in plan.commands if isinstance(c, Move)]
    steps = np.abs(np.diff(np.concatenate([q[:1], q]), axis=0))  # (k, n): the first move is from where it ends
    speed = np.array([m.speed for m in moves])[:, None]
    acceleration = np.array([m.acceleration for m in moves])[:, None]
    return float(move_time(steps, speed, acceleration).max(axis=1).sum())


def make_plan(
    configurations,
    *,
    samples: int = 5,
    settle: float = 0.5,
    speed: float = 0.5,
    acceleration: float = 0.5,
) -> Plan:
    """A plan visiting configurations (k, n) rad in order: Move → Settle (if settle > 0, s) → Measure(samples).

    speed in rad/s, acceleration in rad/s².
    """
    q = np.asarray(configurations, dtype=float)
    if q.ndim != 2 or q.shape[0] == 0:
        raise PlanError(f"configurations must be a non-empty (k, n) array, got shape {q.shape}")
    commands: list[Command] = []
    for i, row in enumerate(q):
        try:
            commands.append(Move(tuple(row), speed, acceleration))
            if settle:
                commands.append(Settle(settle))
            commands.append(Measure(samples))
        except PlanError as e:
            raise PlanError(f"configuration {i}: {e}") from None
    return Plan(tuple(commands))
