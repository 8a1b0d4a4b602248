"""The compiled single-configuration correction (numba): the steps of :func:`labcal.compensator.solve.solve` over
:meth:`labcal.compensator.model.CalibratedRobot.residual`, for one configuration of a z-revolute arm of n ≥ 6 joints.

Imported only by :mod:`labcal.compensator.kernel`, and only when a single ``correct()`` first needs it (importing
numba and compiling cost seconds: ``labcal --help`` must not pay them). Every function here mirrors a step of the
batched numpy definition, which is what the tests compare it with (tests/compensator/test_kernel.py, to 1e-12 rad;
a damped answer to the definition's own rounding resolution, which one ulp of the residual moves by up to 5e-10):

- :func:`_walk`: the local POE chain (:meth:`LocalPOEModel.link_frames`) and the joint twists ``(p × z, z)``;
- :func:`_log_pose`: ``log(T_target T⁻¹)``, series below 1e-2 rad as ``model._log_small``, closed forms above;
- :func:`_residual`: ``CalibratedRobot.residual``: e (local POE), e − J δρ (a network), or for a linear series the
  Newton Jacobian ``J + J S + bracket`` (``model._bracket``); twists about the TCP when one is given;
- :func:`correct_one`: the range and validity checks (the region's boundary, within rounding, left to the
  definition), Gauss-Newton with its verdicts and J reuse, the ``max_correction`` box and the damped
  (Levenberg-Marquardt) fallback with Nielsen's rule and the stall stop.

The constants are solve.py's, passed in by the caller (one definition). No fastmath and no parallelism: the same
input gives the same bits on every call.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# feature column ops (kernel.py builds the table from labcal.features' Column recipes)
OP_Q, OP_ZERO, OP_SIN, OP_COS, OP_GRAVITY = 0, 1, 2, 3, 4
# network modes
NET_NONE, NET_SERIES, NET_LAYERS = 0, 1, 2
# runs of a linear series' columns (kernel.py builds them from the network's features)
RUN_HARMONICS, RUN_GRAVITY, RUN_Q = 0, 1, 2
# status of correct_one
DONE, OUTSIDE = 0, 1

_SMALL = 1e-2  # rad: series below this, as kinematics.se3 and model._log_small


def _jit(fn=None, **extra):
    """numba.njit with an on-disk cache when numba can place one (a read-only install compiles per process)."""
    if fn is None:
        return lambda f: _jit(f, **extra)
    # numpy's error model: a singular pivot gives inf, not an exception
    options = {"nogil": True, "error_model": "numpy", **extra}
    try:
        return numba.njit(cache=True, **options)(fn)
    except RuntimeError:  # numba found no writable cache directory
        return numba.njit(**options)(fn)


@_jit
def _walk(frames, q, T, J):
    """Link frames T (n+1, 4, 4) of the chain ``frames`` at q (n,) and joint twists J (6, n): LocalPOEModel's walk
    (M · Rz(q_j) · A_{j+1}(0)) and _twists_from_walk (ω = z_j, v = p_j × z_j)."""
    n = q.shape[0]
    T[0] = frames[0]
    for j in range(n):
        c, s = math.cos(q[j]), math.sin(q[j])
        F = frames[j + 1]
        for a in range(3):
            m0, m1 = T[j, a, 0], T[j, a, 1]
            c0, c1, c2, c3 = m0 * c + m1 * s, m1 * c - m0 * s, T[j, a, 2], T[j, a, 3]
            for b in range(4):
                T[j + 1, a, b] = c0 * F[0, b] + c1 * F[1, b] + c2 * F[2, b]
            T[j + 1, a, 3] += c3
        T[j + 1, 3, 0] = T[j + 1, 3, 1] = T[j + 1, 3, 2] = 0.0
        T[j + 1, 3, 3] = 1.0
    for j in range(n):
        zx, zy, zz = T[j, 0, 2], T[j, 1, 2], T[j, 2, 2]
        px, py, pz = T[j, 0, 3], T[j, 1, 3], T[j, 2, 3]
        J[0, j], J[1, j], J[2, j] = py * zz - pz * zy, pz * zx - px * zz, px * zy - py * zx
        J[3, j], J[4, j], J[5, j] = zx, zy, zz


@_jit
def _log_pose(Tt, T, e):
    """e (6,) = log(Tt · T⁻¹) of two (4, 4) poses (v, ω), rotation angle in [0, π] (scalars: no allocation)."""
    r00 = Tt[0, 0] * T[0, 0] + Tt[0, 1] * T[0, 1] + Tt[0, 2] * T[0, 2]
    r01 = Tt[0, 0] * T[1, 0] + Tt[0, 1] * T[1, 1] + Tt[0, 2] * T[1, 2]
    r02 = Tt[0, 0] * T[2, 0] + Tt[0, 1] * T[2, 1] + Tt[0, 2] * T[2, 2]
    r10 = Tt[1, 0] * T[0, 0] + Tt[1, 1] * T[0, 1] + Tt[1, 2] * T[0, 2]
    r11 = Tt[1, 0] * T[1, 0] + Tt[1, 1] * T[1, 1] + Tt[1, 2] * T[1, 2]
    r12 = Tt[1, 0] * T[2, 0] + Tt[1, 1] * T[2, 1] + Tt[1, 2] * T[2, 2]
    r20 = Tt[2, 0] * T[0, 0] + Tt[2, 1] * T[0, 1] + Tt[2, 2] * T[0, 2]
    r21 = Tt[2, 0] * T[1, 0] + Tt[2, 1] * T[1, 1] + Tt[2, 2] * T[1, 2]
    r22 = Tt[2, 0] * T[2, 0] + Tt[2, 1] * T[2, 1] + Tt[2, 2] * T[2, 2]
    px = Tt[0, 3] - (r00 * T[0, 3] + r01 * T[1, 3] + r02 * T[2, 3])
    py = Tt[1, 3] - (r10 * T[0, 3] + r11 * T[1, 3] + r12 * T[2, 3])
    pz = Tt[2, 3] - (r20 * T[0, 3] + r21 * T[1, 3] + r22 * T[2, 3])
    ax, ay, az = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    s2 = ax * ax + ay * ay + az * az
    cos_t = 0.5 * (r00 + r11 + r22 - 1.0)
    theta = math.atan2(math.sqrt(s2), cos_t)
    t2 = theta * theta
    if theta < _SMALL:
        a = 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42))
        d = 1 / 12 + t2 / 720 + t2 * t2 / 30240
    else:
        a = math.sin(theta) / theta
        half = 0.5 * theta
        d = (1 - half * math.cos(half) / math.sin(half)) / t2
    if theta < 0.75 * math.pi:
        wx, wy, wz = ax / a, ay / a, az / a
    else:  # near π sin θ loses the axis: read it from the symmetric part (kinematics.se3.log_so3)
        d0, d1, d2 = (r00 - cos_t) / (1 - cos_t), (r11 - cos_t) / (1 - cos_t), (r22 - cos_t) / (1 - cos_t)
        if d0 >= d1 and d0 >= d2:
            cx, cy, cz = d0, 0.5 * (r10 + r01) / (1 - cos_t), 0.5 * (r20 + r02) / (1 - cos_t)
        elif d1 >= d2:
            cx, cy, cz = 0.5 * (r01 + r10) / (1 - cos_t), d1, 0.5 * (r21 + r12) / (1 - cos_t)
        else:
            cx, cy, cz = 0.5 * (r02 + r20) / (1 - cos_t), 0.5 * (r12 + r21) / (1 - cos_t), d2
        norm = math.sqrt(cx * cx + cy * cy + cz * cz)
        sign = -1.0 if cx * ax + cy * ay + cz * az < 0 else 1.0
        wx, wy, wz = cx / norm * sign * theta, cy / norm * sign * theta, cz / norm * sign * theta
    # V⁻¹ p = p − ½ w × p + d w × (w × p)
    cx, cy, cz = wy * pz - wz * py, wz * px - wx * pz, wx * py - wy * px
    ccx, ccy, ccz = wy * cz - wz * cy, wz * cx - wx * cz, wx * cy - wy * cx
    e[0], e[1], e[2] = px - 0.5 * cx + d * ccx, py - 0.5 * cy + d * ccy, pz - 0.5 * cz + d * ccz
    e[3], e[4], e[5] = wx, wy, wz


@_jit
def _features(q, T, cols, trig, x):
    """Network inputs x (f,) at q from the link frames T (a layered network's J is the joint twists alone: no
    derivative of its inputs is needed). trig (n, H + 1, 2): workspace for
    sin h q_j, cos h q_j by the angle-addition recurrence (features.harmonics_of_joints' running product)."""
    n, H = q.shape[0], trig.shape[1] - 1
    for j in range(n):
        c, s = math.cos(q[j]), math.sin(q[j])
        trig[j, 0, 0], trig[j, 0, 1] = 0.0, 1.0
        for h in range(1, H + 1):
            sp, cp = trig[j, h - 1, 0], trig[j, h - 1, 1]
            trig[j, h, 0], trig[j, h, 1] = sp * c + cp * s, cp * c - sp * s
    for f in range(cols.shape[0]):
        op, j, order = cols[f, 0], cols[f, 1], cols[f, 2]
        if op == OP_Q:
            x[f] = q[j]
        elif op == OP_SIN:
            x[f] = trig[j, order, 0]
        elif op == OP_COS:
            x[f] = trig[j, order, 1]
        elif op == OP_GRAVITY:  # −R_link[2, axis]
            x[f] = -T[j, 2, order]
        else:
            x[f] = 0.0


@_jit
def _network(x, weights, layers, buf, out):
    """The network's folded layers (``Network._folded``: x @ Wt + b, tanh between) at one input x → out (N,).
    layers (L, 4): inputs, outputs, offset of Wt (inputs × outputs, row-major) and of b in ``weights``;
    buf (2, widest layer): workspace."""
    L = layers.shape[0]
    for li in range(L):
        m, k, wo, bo = layers[li, 0], layers[li, 1], layers[li, 2], layers[li, 3]
        g = out if li == L - 1 else buf[li % 2]
        for c in range(k):
            g[c] = weights[bo + c]
        for r in range(m):
            hr = x[r] if li == 0 else buf[(li - 1) % 2, r]
            base = wo + r * k
            for c in range(k):
                g[c] += hr * weights[base + c]
        if li < L - 1:
            for c in range(k):
                g[c] = math.tanh(g[c])


# Fused multiply-adds (contraction only: no reassociation, so the same input still gives the same bits): the series'
# sums are most of a hybrid correction's arithmetic.
@_jit(fastmath={"contract"})
def _series(q, T, runs, weights, rho, S, slope):
    """A one-layer network on ``harmonics:H``, ``gravity`` and ``q`` (the definition's linear series) at q: δρ into
    rho (6,) and, with ``slope``, S (6, n) = dδρ/dq without the gravity columns' part (as the definition's).

    weights: ``Network._folded``'s Wt (f, 6) row-major, then b. runs (R, 4): (RUN_HARMONICS, joint j, first column,
    H): columns sin h q_j, cos h q_j for h = 1 … H; (RUN_GRAVITY, link, first column, 3): −R_link[2, :];
    (RUN_Q, joint, column, 1). One pass: sin h q and cos h q by the angle-addition recurrence in registers (no
    table), δρ and each run's slope summed in scalars (every weight read once, no sum waiting on memory)."""
    F = (weights.shape[0] - 6) // 6
    r0, r1, r2 = weights[6 * F], weights[6 * F + 1], weights[6 * F + 2]  # the bias
    r3, r4, r5 = weights[6 * F + 3], weights[6 * F + 4], weights[6 * F + 5]
    if slope:
        S[:] = 0.0
    for k in range(runs.shape[0]):
        kind, j, o = runs[k, 0], runs[k, 1], 6 * runs[k, 2]
        if kind == RUN_HARMONICS:
            c, s = math.cos(q[j]), math.sin(q[j])
            sh, ch = s, c
            s0 = s1 = s2 = s3 = s4 = s5 = 0.0
            for h in range(1, runs[k, 3] + 1):
                # columns sin h q (row o) and cos h q (row o + 6); d/dq: h cos h q and −h sin h q
                a0, a1, a2 = weights[o], weights[o + 1], weights[o + 2]
                a3, a4, a5 = weights[o + 3], weights[o + 4], weights[o + 5]
                b0, b1, b2 = weights[o + 6], weights[o + 7], weights[o + 8]
                b3, b4, b5 = weights[o + 9], weights[o + 10], weights[o + 11]
                r0 += sh * a0 + ch * b0
                r1 += sh * a1 + ch * b1
                r2 += sh * a2 + ch * b2
                r3 += sh * a3 + ch * b3
                r4 += sh * a4 + ch * b4
                r5 += sh * a5 + ch * b5
                if slope:
                    ds, dc = h * ch, -h * sh
                    s0 += ds * a0 + dc * b0
                    s1 += ds * a1 + dc * b1
                    s2 += ds * a2 + dc * b2
                    s3 += ds * a3 + dc * b3
                    s4 += ds * a4 + dc * b4
                    s5 += ds * a5 + dc * b5
                sh, ch = sh * c + ch * s, ch * c - sh * s
                o += 12
            if slope:
                S[0, j] += s0
                S[1, j] += s1
                S[2, j] += s2
                S[3, j] += s3
                S[4, j] += s4
                S[5, j] += s5
        else:  # RUN_GRAVITY: x = −R_link[2, a] for a < 3; RUN_Q: x = q_j, whose slope is its weights
            for a in range(runs[k, 3]):
                x = -T[j, 2, a] if kind == RUN_GRAVITY else q[j]
                r0 += x * weights[o]
                r1 += x * weights[o + 1]
                r2 += x * weights[o + 2]
                r3 += x * weights[o + 3]
                r4 += x * weights[o + 4]
                r5 += x * weights[o + 5]
                if slope and kind == RUN_Q:
                    for b in range(6):
                        S[b, j] += weights[o + b]
                o += 6
    rho[0], rho[1], rho[2], rho[3], rho[4], rho[5] = r0, r1, r2, r3, r4, r5


@_jit
def _residual(qc, jacobian, r, J, ctx):
    """CalibratedRobot.residual at qc (n,) into r (6,) and, with ``jacobian``, J (6, n); ctx: the fixed arguments of
    one call (correct_one), target the nominal pose.

    mode NET_NONE: r = e, J the joint twists; NET_LAYERS: r = e − J δρ; NET_SERIES (a linear series): r = e − J δρ
    and J the Newton Jacobian J + J S + bracket (model._bracket). has_point: twists about ``point``
    (model._about_point).
    """
    target, point, has_point, model, mode, cols, weights, layers, T, x, work = ctx
    trig, buf, Jt, S, vec = work  # workspace: vec rows e, ρ, z, tail
    n = qc.shape[0]
    _walk(model, qc, T, Jt)
    e, rho, z, tail = vec[0], vec[1], vec[2], vec[3]
    _log_pose(target, T[n], e)
    rho[:] = 0.0
    if mode == NET_SERIES:
        _series(qc, T, cols, weights, rho, S, jacobian)  # cols: the series' runs
    elif mode == NET_LAYERS:
        _features(qc, T, cols, trig, x)
        _network(x, weights, layers, buf, rho)
    for a in range(6):
        acc = 0.0
        for j in range(n):
            acc += Jt[a, j] * rho[j]
        r[a] = e[a] - acc
    if jacobian:
        if mode == NET_SERIES:
            # bracket column i: ad(ξ_i) z_i with z_i = Σ_{j>i} δρ_j ξ_j − e/2 and ad(v, ω) = [[ω̂, v̂], [0, ω̂]]
            tail[:] = 0.0  # Σ_{j>i} δρ_j ξ_j, from the last joint back
            for i in range(n - 1, -1, -1):
                for a in range(6):
                    z[a] = tail[a] - 0.5 * e[a]
                vx, vy, vz, wx, wy, wz = Jt[0, i], Jt[1, i], Jt[2, i], Jt[3, i], Jt[4, i], Jt[5, i]
                for a in range(6):
                    acc = Jt[a, i]
                    for j in range(n):
                        acc += Jt[a, j] * S[j, i]
                    J[a, i] = acc
                J[0, i] += wy * z[2] - wz * z[1] + vy * z[5] - vz * z[4]
                J[1, i] += wz * z[0] - wx * z[2] + vz * z[3] - vx * z[5]
                J[2, i] += wx * z[1] - wy * z[0] + vx * z[4] - vy * z[3]
                J[3, i] += wy * z[5] - wz * z[4]
                J[4, i] += wz * z[3] - wx * z[5]
                J[5, i] += wx * z[4] - wy * z[3]
                for a in range(6):
                    tail[a] += rho[i] * Jt[a, i]
        else:
            for a in range(6):
                for j in range(n):
                    J[a, j] = Jt[a, j]
    if has_point:  # twists about the point: v + ω × p
        px, py, pz = point[0], point[1], point[2]
        r0, r1, r2 = r[4] * pz - r[5] * py, r[5] * px - r[3] * pz, r[3] * py - r[4] * px
        r[0] += r0
        r[1] += r1
        r[2] += r2
        if jacobian:
            for j in range(n):
                wx, wy, wz = J[3, j], J[4, j], J[5, j]
                J[0, j] += wy * pz - wz * py
                J[1, j] += wz * px - wx * pz
                J[2, j] += wx * py - wy * px


@_jit
def _lu(A, piv):
    """In-place LU factorisation with partial pivoting of a square A (LAPACK's getrf, unblocked)."""
    m = A.shape[0]
    for c in range(m):
        p, big = c, abs(A[c, c])
        for i in range(c + 1, m):
            if abs(A[i, c]) > big:
                p, big = i, abs(A[i, c])
        piv[c] = p
        if p != c:
            for k in range(m):
                A[c, k], A[p, k] = A[p, k], A[c, k]
        for i in range(c + 1, m):
            A[i, c] /= A[c, c]  # a zero pivot (singular A) gives inf/NaN: the step is judged failed
            f = A[i, c]
            for k in range(c + 1, m):
                A[i, k] -= f * A[c, k]


@_jit
def _lu_solve(A, piv, b, out):
    """out = A⁻¹ b from _lu's factors."""
    m = A.shape[0]
    for i in range(m):
        out[i] = b[i]
    for i in range(m):
        p = piv[i]
        if p != i:
            out[i], out[p] = out[p], out[i]
    for i in range(m):
        for k in range(i):
            out[i] -= A[i, k] * out[k]
    for i in range(m - 1, -1, -1):
        for k in range(i + 1, m):
            out[i] -= A[i, k] * out[k]
        out[i] /= A[i, i]


@_jit
def _cost(r, w):
    c = 0.0
    for a in range(6):
        c += (r[a] * w[a]) ** 2
    return c


@_jit
def _lm_step(jac, err, lam, A, rhs, piv, step):
    """solve.damped_step before its clip: step = (JᵀJ + λ μ I)⁻¹ Jᵀ r, μ the mean of JᵀJ's diagonal."""
    n = jac.shape[1]
    sq = 0.0
    for a in range(6):
        for j in range(n):
            sq += jac[a, j] * jac[a, j]
    mu = lam * sq / n
    for j in range(n):
        for k in range(n):
            acc = 0.0
            for a in range(6):
                acc += jac[a, j] * jac[a, k]
            A[j, k] = acc
        A[j, j] += mu
        acc = 0.0
        for a in range(6):
            acc += jac[a, j] * err[a]
        rhs[j] = acc
    _lu(A, piv)
    _lu_solve(A, piv, rhs, step)


@_jit
def _damped(q0, q_init, r0, J0, bound, has_bound, w, budget, tol, consts, ctx):
    """solve._damped for one row: damped steps from q_init (r0, J0 evaluated there), kept where they do not raise
    |W r|, Nielsen's λ rule, stopped below tol, at λ > LAMBDA_GIVE_UP or on a stall from half the budget."""
    damped_max, lam_min, lam_give_up, stall_window, stall_fall = consts[3], consts[5], consts[6], consts[7], consts[8]
    n = q0.shape[0]
    out = q_init.copy()
    err, jac = np.empty(6), np.empty((6, n))
    for a in range(6):
        err[a] = r0[a] * w[a]
        for j in range(n):
            jac[a, j] = J0[a, j] * w[a]
    cost = _cost(r0, w)
    lam, grow = consts[4], 2.0  # LAMBDA_START
    history = np.empty(budget + 1)
    history[0] = cost
    A, rhs, step, piv = np.empty((n, n)), np.empty(n), np.empty(n), np.empty(n, dtype=np.int64)
    cand, rc, Jc = np.empty(n), np.empty(6), np.empty((6, n))
    for i in range(1, budget + 1):
        _lm_step(jac, err, lam, A, rhs, piv, step)
        size = 0.0
        for j in range(n):
            s = min(max(step[j], -damped_max), damped_max)
            if has_bound:
                s = min(max(s, q0[j] - bound - out[j]), q0[j] + bound - out[j])
            step[j] = s
            size = max(size, abs(s))
        predicted = cost
        for a in range(6):
            m = err[a]
            for j in range(n):
                m -= jac[a, j] * step[j]
            predicted -= m * m
        for j in range(n):
            cand[j] = out[j] + step[j]
        _residual(cand, True, rc, Jc, ctx)
        cost_c = _cost(rc, w)
        kept = cost_c <= cost
        gain = (cost - cost_c) / predicted if predicted > 0 else 0.0
        if kept:
            for j in range(n):
                out[j] = cand[j]
            for a in range(6):
                err[a] = rc[a] * w[a]
                for j in range(n):
                    jac[a, j] = Jc[a, j] * w[a]
            cost = cost_c
            lam, grow = max(lam * max(1 / 3, 1 - (2 * gain - 1) ** 3), lam_min), 2.0
        else:
            lam, grow = lam * grow, 2 * grow
        history[i] = cost
        if size < tol or lam > lam_give_up:
            break
        if 2 * i >= budget and cost > stall_fall * history[max(i - int(stall_window), 0)]:
            break
    return out


# Relative width of the shell about the validity region's boundary where the kernel leaves the verdict to the
# definition: ValidityRegion.distance sums |x|² − 2 x·c + |c|² (rounding error ≈ n ε (|x|² + |c|²), ε = 2.2e-16)
# and this kernel |c − x|² (≈ n ε |c − x|²); 1e-12 is a hundredfold that for any arm.
_REGION_SHELL = 1e-12


@_jit
def _in_region(q, centres, scale, radius):
    """The validity region's ball test: (inside, sure). Inside when a centre is within the radius (the scaled
    |c − x|² ≤ radius²). sure is False when q lies within rounding of the boundary, where the definition's own
    distance (ValidityRegion.distance, to refuse and to bound), summed in another order, may judge it the other
    way: the caller then leaves the verdict to the definition."""
    n = q.shape[0]
    x = np.empty(n)
    xx = 0.0
    for j in range(n):
        x[j] = q[j] * scale[j]
        xx += x[j] * x[j]
    r2 = radius * radius
    # near the boundary |c| ≤ |x| + radius, so |x|² + |c|² ≤ 3 (|x|² + radius²): one slack for every centre
    slack = _REGION_SHELL * 3.0 * (xx + r2)
    sure = True
    for c in range(centres.shape[0]):  # any centre within the radius, stopping at the first surely within
        d2 = 0.0
        for j in range(n):
            d = centres[c, j] - x[j]
            d2 += d * d
        if d2 <= r2 - slack:
            return True, True
        if d2 <= r2 + slack:  # not NaN-safe on purpose: an overflowed |x|² (inf slack) is never sure
            sure = False
    return False, sure


@_jit
def _gauss_newton(q0, out, iterations, tol, consts, r, J, r0, J0, ctx):
    """solve.solve's Gauss-Newton mode for one row from q0 into out: full steps J⁻¹ r, judged by solve.verdict; once
    a step was below REUSE_BELOW the next reuse the kept J (its factors). r0, J0: the residual at q0 (where a failed
    row's damped mode starts). Returns True when the row failed."""
    n = q0.shape[0]
    gn_max, reuse_below, noise_floor = consts[0], consts[1], consts[2]
    LU, piv, step = np.empty((6, 6)), np.empty(6, dtype=np.int64), np.empty(n)
    target, y = np.empty(6), np.empty(6)
    for j in range(n):
        out[j] = q0[j]
    prev = -1.0  # no step yet
    for i in range(max(iterations, 1)):
        # settled: reuse the last J (solve's simplified Newton; n = 6 only: a redundant arm's least change moves
        # with J)
        fresh = n != 6 or not (prev >= 0.0 and prev < reuse_below)
        _residual(out, fresh, r, J, ctx)
        if i == 0:
            r0[:] = r
            J0[:] = J
        if n == 6:
            if fresh:
                LU[:] = J
                _lu(LU, piv)
            _lu_solve(LU, piv, r, step)
        else:  # n > 6: the step to the least total change, Jᵀ (J Jᵀ)⁻¹ (r + J (q − q0)) − (q − q0)
            for a in range(6):
                acc = r[a]
                for j in range(n):
                    acc += J[a, j] * (out[j] - q0[j])
                target[a] = acc
                for b in range(6):
                    acc = 0.0
                    for j in range(n):
                        acc += J[a, j] * J[b, j]
                    LU[a, b] = acc
            _lu(LU, piv)
            _lu_solve(LU, piv, target, y)
            for j in range(n):
                acc = 0.0
                for a in range(6):
                    acc += J[a, j] * y[a]
                step[j] = acc - (out[j] - q0[j])
        size = 0.0
        for j in range(n):
            size = max(size, abs(step[j]))
            if not math.isfinite(step[j]):
                size = np.nan
                break
        # solve.verdict
        if prev < 0.0:
            bad, done = not size <= gn_max, size < tol
        elif size < noise_floor:
            bad, done = False, True
        else:
            ratio = min(size / max(prev, 1e-300), 0.5)
            bad = not size <= min(gn_max, 0.5 * prev)
            done = size * ratio / (1 - ratio) < tol or size < 1e-3 * tol
        if bad:
            return True
        for j in range(n):
            out[j] += step[j]
        prev = size
        if done:
            break
    return False


@_jit
def correct_one(
    q0, out, nominal, model, mode, cols, weights, layers, H, width, w, ranges, centres, scale, radius,
    has_region, tcp, has_tcp, extrapolate, iterations, tol, budget, consts,
):  # fmt: skip
    """CalibratedRobot.correct(q0, method="newton") of one configuration into out (n,); returns DONE, or OUTSIDE
    when q0 is not finite, outside the ranges or outside the validity region without ``extrapolate``, or within
    rounding of the region's boundary (the caller then takes the batched path, which names what is wrong or, at
    the boundary, decides). consts: solve.py's (GN_MAX_STEP, REUSE_BELOW,
    NOISE_FLOOR, DAMPED_MAX_STEP, LAMBDA_START, LAMBDA_MIN, LAMBDA_GIVE_UP, STALL_WINDOW, STALL_FALL,
    MAX_CORRECTION)."""
    n = q0.shape[0]
    for j in range(n):
        # not finite, or outside the calibrated ranges (lo, hi with CalibratedRobot._ranges' 1e-12 margin: the
        # definition's comparisons on the same numbers)
        if not (math.isfinite(q0[j]) and (extrapolate or ranges[0, j] <= q0[j] <= ranges[1, j])):
            return OUTSIDE
    # The region decides both the refusal and, under extrapolate, the bound: outside the joint ranges too (the
    # region's balls reach beyond a learned fit's ranges, which are its data's). Near its boundary the definition
    # decides.
    in_region = True
    if has_region:
        in_region, sure = _in_region(q0, centres, scale, radius)
        if not sure:
            return OUTSIDE
    if not (extrapolate or in_region):
        return OUTSIDE
    # correct()'s bound: inside the validity region (every row without extrapolate, its own test with it)
    bounded = has_region and in_region
    bound = consts[9]
    T = np.empty((n + 1, 4, 4))
    _walk(nominal, q0, T, np.empty((6, n)))
    target = T[n].copy()
    point = np.zeros(3)
    if has_tcp:  # the TCP's nominal position: (T_target · tcp)[:3, 3]
        for a in range(3):
            point[a] = target[a, 0] * tcp[0, 3] + target[a, 1] * tcp[1, 3] + target[a, 2] * tcp[2, 3] + target[a, 3]
    # workspace: sin h q_j, cos h q_j (h ≤ H), two network layers, J's twists, the series' slope, vectors
    work = (np.empty((n, H + 1, 2)), np.empty((2, width)), np.empty((6, n)), np.empty((6, n)), np.empty((4, max(n, 6))))
    ctx = (target, point, has_tcp, model, mode, cols, weights, layers, T, np.empty(cols.shape[0]), work)
    r, J, r0, J0 = np.empty(6), np.empty((6, n)), np.empty(6), np.empty((6, n))
    failed = _gauss_newton(q0, out, iterations, tol, consts, r, J, r0, J0, ctx)
    # a Gauss-Newton answer beyond the box: damped from it clipped into the box when that is better
    if bounded and not failed and not np.all(np.abs(out - q0) <= bound):
        clipped = np.minimum(np.maximum(out, q0 - bound), q0 + bound)
        _residual(clipped, True, r, J, ctx)
        if _cost(r, w) < _cost(r0, w):
            out[:] = _damped(q0, clipped, r, J, bound, True, w, budget, tol, consts, ctx)
        else:
            failed = True
    if failed:
        out[:] = _damped(q0, q0, r0, J0, bound, bounded, w, budget, tol, consts, ctx)
    return DONE
