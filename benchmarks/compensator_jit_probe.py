"""What a compiled kernel would make of a single correction: a probe for a decision, not part of labcal.

Run: ``python benchmarks/compensator_jit_probe.py`` in an environment that has numba (labcal does not depend on it:
``pip install numba`` into a scratch virtual environment with labcal's requirements).

labcal's runtime is numpy only, and at one configuration numpy's per-call cost, not the arithmetic, sets the time
of ``correct()`` (README, Speed). This probe writes the local-POE part of a single correction (chain walk, pose
error, Gauss-Newton with the same stopping rule) as loops that numba compiles, runs it on the configurations of
``compensator_speed.py``'s ``local-poe`` model, and prints its median time beside labcal's, the largest difference of
the answers, and the compile time. It covers neither the learned term nor the damped fallback: it measures what
the per-call overhead costs, not a finished kernel.
"""

from __future__ import annotations

import time

import numpy as np

try:
    import numba
except ImportError:  # pragma: no cover - the probe's one requirement
    raise SystemExit("this probe needs numba (pip install numba); labcal itself does not use it") from None

from compensator_speed import make_models, median_call, well_conditioned


@numba.njit(cache=False)
def _product(A, B, out):
    for i in range(4):
        for j in range(4):
            s = 0.0
            for k in range(4):
                s += A[i, k] * B[k, j]
            out[i, j] = s


@numba.njit(cache=False)
def _walk(frames, q, T, J):
    """Tool pose T (4, 4) and spatial joint twists J (6, n) of a z-revolute local-POE chain at q."""
    n = q.shape[0]
    T[:, :] = frames[0]
    tmp, R = np.empty((4, 4)), np.eye(4)
    for j in range(n):
        z, p = T[:3, 2], T[:3, 3]
        J[0, j], J[1, j], J[2, j] = p[1] * z[2] - p[2] * z[1], p[2] * z[0] - p[0] * z[2], p[0] * z[1] - p[1] * z[0]
        J[3, j], J[4, j], J[5, j] = z[0], z[1], z[2]
        c, s = np.cos(q[j]), np.sin(q[j])
        R[0, 0], R[0, 1], R[1, 0], R[1, 1] = c, -s, s, c
        _product(T, R, tmp)
        _product(tmp, frames[j + 1], T)


@numba.njit(cache=False)
def _pose_error(Tt, T):
    """log(Tt T⁻¹) as (v, ω) for the small rotations of a correction (the series of labcal's kernel)."""
    dR = np.zeros((3, 3))  # Tt's rotation times T's transposed
    for i in range(3):
        for j in range(3):
            for k in range(3):
                dR[i, j] += Tt[i, k] * T[j, k]
    p = Tt[:3, 3].copy()
    for i in range(3):
        for k in range(3):
            p[i] -= dR[i, k] * T[k, 3]
    w = np.array([0.5 * (dR[2, 1] - dR[1, 2]), 0.5 * (dR[0, 2] - dR[2, 0]), 0.5 * (dR[1, 0] - dR[0, 1])])
    s2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    t2 = np.arctan2(np.sqrt(s2), 0.5 * (dR[0, 0] + dR[1, 1] + dR[2, 2] - 1.0)) ** 2
    w /= 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42))
    d = 1 / 12 + t2 / 720 + t2 * t2 / 30240
    c = np.cross(w, p)
    out = np.empty(6)
    out[:3] = p - 0.5 * c + d * np.cross(w, c)
    out[3:] = w
    return out


@numba.njit(cache=False)
def _lu_solve(A0, b0):
    A, b, n = A0.copy(), b0.copy(), b0.shape[0]
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[p, k]):
                p = i
        for j in range(n):
            A[k, j], A[p, j] = A[p, j], A[k, j]
        b[k], b[p] = b[p], b[k]
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k, n):
                A[i, j] -= f * A[k, j]
            b[i] -= f * b[k]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = b[i]
        for j in range(i + 1, n):
            s -= A[i, j] * x[j]
        x[i] = s / A[i, i]
    return x


@numba.njit(cache=False)
def correct_one(nominal_frames, model_frames, q, tol):
    """One correction on a local-POE model: labcal's Gauss-Newton rule (no damped fallback)."""
    n = q.shape[0]
    target, T, J = np.empty((4, 4)), np.empty((4, 4)), np.empty((6, n))
    _walk(nominal_frames, q, target, J)
    out, prev = q.copy(), -1.0
    for _ in range(10):
        _walk(model_frames, out, T, J)
        step = _lu_solve(J, _pose_error(target, T))
        size = np.abs(step).max()
        out += step
        if prev > 0.0:
            ratio = min(size / prev, 0.5)
            if size * ratio / (1 - ratio) < tol or size < 1e-3 * tol:
                break
        prev = size
    return out


def main() -> None:
    robot = make_models("ur10")["local-poe"]
    q = well_conditioned(robot, 300, 1)
    nominal, model = (np.ascontiguousarray(m.frames) for m in (robot.nominal, robot.model))
    t0 = time.perf_counter()
    correct_one(nominal, model, q[0], 1e-11)
    compile_s = time.perf_counter() - t0
    diff = np.array([np.abs(correct_one(nominal, model, row, 1e-11) - robot.correct(row)).max() for row in q])
    agree = diff < 1e-9
    compiled = median_call(lambda row: correct_one(nominal, model, row, 1e-11), q, 5)
    labcal = median_call(robot.correct, q, 5)
    print(f"numba {numba.__version__}, numpy {np.__version__}; local-POE UR10, {len(q)} configurations")
    print(f"single correct(): labcal {labcal * 1e6:.0f} µs, compiled probe {compiled * 1e6:.1f} µs")
    print(
        f"answers within 1e-9 rad of labcal's: {agree.sum()} of {len(q)} (largest difference there "
        f"{diff[agree].max():.1e} rad; the others are where labcal takes its damped fallback, which the probe lacks)"
    )
    print(f"first call (compilation): {compile_s:.1f} s")


if __name__ == "__main__":
    main()
