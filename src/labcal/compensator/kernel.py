"""The compiled single-configuration kernel of :meth:`CalibratedRobot.correct` (numba), optional at run time.

The batched numpy residual and solver (:meth:`CalibratedRobot.residual`, :func:`labcal.compensator.solve.solve`)
are the definition of a correction. A control loop corrects one configuration at a time, where numpy's cost per
call, not the arithmetic, is the price (a numpy correction costs more than one plain numpy DH forward kinematics
call; the compiled one a fraction of it: benchmarks/compensator_kernel.py). So :func:`build` prepares, for a robot
whose correction it implements, a function ``(q (n,) float array, extrapolate, iterations, tol, damped_iterations,
tcp (4, 4) or None) → q_cmd (n,) or None`` that takes the same steps as the definition on compiled code
(:mod:`labcal.compensator._jit`), tested against it to 1e-12 rad (a damped answer to the definition's own rounding
resolution: tests/compensator/test_kernel.py). None means
"take the batched path": q is not finite, or outside the calibrated ranges or validity region (the batched path
then raises the error that names it), or within rounding of the region's boundary, or an option is not a plain
bool, int or float count the compiled code reads as the definition does (the batched path decides them).

What it covers: arms of 6 or more joints that all turn about their local z axis (nominal and identified model),
without a network (local POE) or with one on max(n, 6) outputs whose features are ``q``, ``sincos``, ``sincos2``,
``gravity`` and ``harmonics:H`` (the ANN and hybrid methods; a 6-joint one-layer linear series takes the
definition's Newton Jacobian; a redundant arm, n > 6, the step to the least total change). Anything else (n < 6
with virtual joints, prismatic or tilted joint axes) gets None from :func:`build` and takes the batched numpy path
with a batch of one, as does every robot when numba is not importable (numba is a default dependency, but labcal
runs without it).

Compilation is lazy: numba is imported and the kernel compiled (or loaded from numba's on-disk cache, when its
directory is writable) at the first single correction, never when labcal is imported.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from labcal import features as feature_lib
from labcal.compensator import solve as solver

if TYPE_CHECKING:
    from labcal.compensator.model import CalibratedRobot

Kernel = Callable[..., "np.ndarray | None"]


@functools.cache
def compiled() -> ModuleType | None:
    """labcal.compensator._jit (importing numba on first use), or None without numba."""
    try:
        from labcal.compensator import _jit
    except ImportError:  # numba is optional at run time
        return None
    return _jit


_OPS = {"q": 0, "zero": 1, "sin": 2, "cos": 3, "gravity": 4}
_CONSTS = np.array(
    [
        solver.GN_MAX_STEP, solver.REUSE_BELOW, solver.NOISE_FLOOR, solver.DAMPED_MAX_STEP, solver.LAMBDA_START,
        solver.LAMBDA_MIN, solver.LAMBDA_GIVE_UP, solver.STALL_WINDOW, solver.STALL_FALL, solver.MAX_CORRECTION,
    ]
)  # fmt: skip
_CONSTS.setflags(write=False)
_MAX_COUNT = 2**31  # iteration counts the kernel takes (int64 in compiled code; a damped budget is allocated)


def _feature_table(robot: CalibratedRobot) -> np.ndarray:
    """(f, 3) int rows (op, joint or link, order or axis) from the registry's Column recipes of the network's
    features; ValueError for a column the kernel does not compute (a prismatic joint's stroke)."""
    assert robot.network is not None
    rows = []
    for name in robot.network.features:
        for col in feature_lib.get(name).columns(robot.model.joint_types, robot.model.limits):
            if col.op not in _OPS or col.stroke is not None:
                raise ValueError(f"feature column {col} has no compiled form")
            second = col.link if col.op == "gravity" else col.joint
            third = col.axis if col.op == "gravity" else col.order
            rows.append((_OPS[col.op], second, third))
    return np.array(rows, dtype=np.int64).reshape(-1, 3)


def _series_runs(robot: CalibratedRobot) -> np.ndarray:
    """(R, 4) int rows (kind, joint or link, first column, length) of a linear series' feature columns
    (``harmonics:H``, ``gravity``, ``q``; the registry's layouts): what :func:`labcal.compensator._jit._series`
    walks."""
    assert robot.network is not None
    n, start, runs = robot.n, 0, []
    for name in robot.network.features:
        feature = feature_lib.get(name)
        if feature.kind == "harmonics":  # joint j: sin h q_j, cos h q_j for h = 1 … H
            runs += [(0, j, start + 2 * feature.order * j, feature.order) for j in range(n)]
        elif feature.kind == "gravity":  # link j: −R_j[2, 0 … 2]
            runs += [(1, j, start + 3 * (j - 1), 3) for j in range(1, n + 1)]
        elif feature.kind == "q":
            runs += [(2, j, start + j, 1) for j in range(n)]
        else:
            raise ValueError(f"feature {name!r} is not a series feature")
        start += feature.size(n)
    return np.array(runs, dtype=np.int64).reshape(-1, 4)


def _layers(robot: CalibratedRobot) -> tuple[np.ndarray, np.ndarray]:
    """The network's folded layers (``Network._folded``) packed flat: (weights, (L, 4) in, out, W offset, b
    offset)."""
    assert robot.network is not None
    Wt, bs = robot.network._folded
    parts, layers, offset = [], [], 0
    for W, b in zip(Wt, bs, strict=True):
        layers.append((W.shape[0], W.shape[1], offset, offset + W.size))
        parts += [np.ravel(W), np.ravel(b)]
        offset += W.size + b.size
    return np.ascontiguousarray(np.concatenate(parts), dtype=float), np.array(layers, dtype=np.int64)


def build(robot: CalibratedRobot) -> Kernel | None:
    """The compiled single correction of ``robot`` (module docstring), or None when it takes the numpy path."""
    n = robot.n
    if n < 6 or not (robot.nominal._all_revolute_z and robot.model._all_revolute_z):
        return None
    network = robot.network
    if network is None:
        mode, cols, weights, layers = 0, np.zeros((0, 3), dtype=np.int64), np.zeros(1), np.zeros((1, 4), np.int64)
    else:
        if network.outputs != n:
            return None
        try:
            cols = _feature_table(robot)
        except ValueError:
            return None
        weights, layers = _layers(robot)
        mode = 1 if robot._linear_series is not None else 2  # the definition's choice of Jacobian
        if mode == 1:
            cols = _series_runs(robot)
    jit = compiled()
    if jit is None:
        return None
    lo, hi = robot._ranges
    ranges = np.ascontiguousarray(np.stack([lo, hi]), dtype=float)
    region = robot.validity
    has_region = region is not None
    centres = np.zeros((1, n)) if region is None else np.ascontiguousarray(region.centres, dtype=float)
    scale = np.ones(n) if region is None else np.ascontiguousarray(region.weights, dtype=float)
    radius = 0.0 if region is None else float(region.radius)
    nominal, model = (np.ascontiguousarray(m.frames, dtype=float) for m in (robot.nominal, robot.model))
    w = np.ascontiguousarray(robot._twist_weights, dtype=float)
    no_tcp = np.eye(4)
    no_tcp.setflags(write=False)  # typed as a checked tcp is (read-only): one compiled signature for both
    # the workspace of one call: the highest harmonic order of the features, the widest layer
    trig = np.isin(cols[:, 0], (_OPS["sin"], _OPS["cos"])) if mode == 2 else np.zeros(len(cols), dtype=bool)
    sizes = int(cols[trig, 2].max(initial=0)), int(layers[:, 1].max(initial=1))
    static = (nominal, model, mode, cols, weights, layers, *sizes, w, ranges, centres, scale, radius, has_region)
    run = jit.correct_one
    # Compile (or load) now, and call the compiled entry point directly from then on: numba's dispatcher would type
    # every argument of every call to choose among signatures, about a microsecond of a single correction. The
    # arguments always have the probe's types (correct() checked q's dtype and shape; a strided q is copied: the
    # dispatcher would compile a second signature for it, a minute's pause in a control loop).
    probe = (np.zeros(n), np.empty(n), *static, no_tcp, False, True, 1, 1e-11, 0, _CONSTS)
    run(*probe)
    entry = run.overloads[tuple(jit.numba.typeof(a) for a in probe)].entry_point

    def kernel(q, extrapolate, iterations, tol, damped_iterations, tcp) -> np.ndarray | None:
        # Options the compiled code would read otherwise than the definition does, or could not hold (a float or
        # text iteration count, a tol in float32 arithmetic, a negative or int64-overflowing count), take the
        # batched path, which answers or refuses them its own way: the kernel never answers where it raises.
        if damped_iterations is None:
            budget = solver.DAMPED_BUDGET
        elif type(damped_iterations) is int and 0 <= damped_iterations <= _MAX_COUNT:
            budget = damped_iterations
        else:
            return None
        if not (
            type(iterations) is int and -_MAX_COUNT <= iterations <= _MAX_COUNT
            and isinstance(tol, float) and type(extrapolate) is bool
        ):  # fmt: skip
            return None
        out = np.empty(n)
        if not q.flags.c_contiguous:
            q = np.ascontiguousarray(q)
        status = entry(
            q, out, *static, no_tcp if tcp is None else tcp, tcp is not None, extrapolate, iterations, tol, budget,
            _CONSTS,
        )  # fmt: skip
        return out if status == 0 else None

    return kernel
