"""URScript export: a self-contained ``labcal_correct(q)`` that runs the compensator on a UR controller.

The generated file defines global constants (all prefixed ``lc_``) and functions; include it in a robot program
and call ``q_cmd = labcal_correct(q)`` with a target joint list q (rad), then ``movej(q_cmd, …)``.

What it computes (``method="newton"``, the default, matches :meth:`CalibratedRobot.correct`):

1. the nominal tool pose of q (the robot's own kinematics, local POE, written out as constant frames);
2. a fixed number (``iterations``, default 4) of Gauss-Newton steps from q_cmd = q on
   ``log(T_nominal(q) T_model(q_cmd)⁻¹) − J(q_cmd) δρ(q_cmd) = 0``: the identified frames' forward kinematics, the
   joint twists J, the network δρ (tanh hidden layers, normalisation folded into the weights) and a 6×6 solve by
   Gaussian elimination with partial pivoting — the same equations as the Python runtime, which stops adaptively
   where the script always runs ``iterations`` steps (four reach ≤ 1e-9 rad on non-singular configurations);
3. ``method="paper"`` instead emits eq. (24), q − δρ_a(q): one network evaluation, exact for the paper's method.

Not covered (say so where it matters): configurations outside the calibrated joint ranges stop the program
(``popup`` + ``halt``) — there is no ``extrapolate``; there is no Levenberg-Marquardt fallback, so near a singular
configuration the script returns whatever the fixed Gauss-Newton steps give (the Python runtime would damp them);
robots with fewer than 6 joints are supported without a network only (virtual joints need a QR decomposition),
robots with more than 6 not at all (a UR controller drives six);
the rotation logarithm assumes a residual rotation below π/2 (corrections are milliradians).

The emitted language is a small subset of URScript: ``def``/``end``, ``while``, ``if``/``elif``/``else``,
``local`` assignments, flat lists with integer indexing, ``+ - * /``, comparisons, ``and``/``or``/``not``,
and the built-ins sin, cos, sqrt, atan2, pow, popup and halt.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labcal import features as feature_lib
from labcal.compensator import CalibratedRobot
from labcal.export.zform import ZAxisForm
from labcal.robots import model_hash

BUILTINS = ("sin", "cos", "sqrt", "atan2", "pow", "popup", "halt")


def _num(x: float) -> str:
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"cannot write the non-finite number {x} into URScript")
    text = repr(x)
    return text if ("." in text or "e" in text or "n" in text) else text + ".0"


def _list(values) -> str:
    return "[" + ", ".join(_num(v) for v in np.asarray(values, dtype=float).ravel()) + "]"


def _bools(values) -> str:
    return "[" + ", ".join("True" if v else "False" for v in values) + "]"


def _zeros(m: int) -> str:
    return "[" + ", ".join(["0.0"] * m) + "]"


def _frames12(kin: ZAxisForm) -> np.ndarray:
    """A'_0 … A'_n as 3×4 row-major blocks (the implicit last row is 0 0 0 1)."""
    A = np.concatenate([kin.A0[None], kin.A_rest])
    return A[:, :3, :].reshape(-1)


def _mul_function() -> list[str]:
    terms = []
    for i in range(3):
        for col in range(4):
            expr = " + ".join(f"a[{4 * i + m}] * b[{4 * m + col}]" for m in range(3))
            if col == 3:
                expr += f" + a[{4 * i + 3}]"
            terms.append(expr)
    return ["def lc_mul(a, b):", "  return [" + ", ".join(terms) + "]", "end"]


def _chain_function(n: int) -> list[str]:
    m = 12 * (n + 1)
    g = []
    for k in range(4):
        g.append(f"c * A[o + {k}] - s * A[o + {4 + k}]")
    for k in range(4):
        g.append(f"s * A[o + {k}] + c * A[o + {4 + k}]")
    g += ["A[o + 8]", "A[o + 9]", "A[o + 10]", "A[o + 11] + lin[j] * q[j]"]
    return [
        "# frames T'_0 … T'_n of a chain (3×4 row-major blocks); the last block is the tool pose",
        "def lc_chain(A, lin, rev, q):",
        f"  local F = {_zeros(m)}",
        "  local i = 0",
        "  local j = 0",
        "  local c = 1.0",
        "  local s = 0.0",
        "  local o = 0",
        "  local b = 0",
        "  local G = [0.0]",
        "  local P = [0.0]",
        "  local R = [0.0]",
        "  while i < 12:",
        "    F[i] = A[i]",
        "    i = i + 1",
        "  end",
        f"  while j < {n}:",
        "    c = 1.0",
        "    s = 0.0",
        "    if rev[j]:",
        "      c = cos(q[j])",
        "      s = sin(q[j])",
        "    end",
        "    o = 12 * (j + 1)",
        "    b = 12 * j",
        "    G = [" + ", ".join(g) + "]",
        "    P = [" + ", ".join(f"F[b + {k}]" for k in range(12)) + "]",
        "    R = lc_mul(P, G)",
        "    i = 0",
        "    while i < 12:",
        "      F[o + i] = R[i]",
        "      i = i + 1",
        "    end",
        "    j = j + 1",
        "  end",
        "  return F",
        "end",
    ]


def _twists_function(n: int) -> list[str]:
    return [
        "# joint twists in the base frame, 6×n row-major (v, w): Ad(T'_j)(h_j e_z, e_z)",
        "def lc_twists(F, rev, pitch):",
        f"  local J = {_zeros(6 * n)}",
        "  local j = 0",
        "  local b = 0",
        "  local zx = 0.0",
        "  local zy = 0.0",
        "  local zz = 0.0",
        "  local px = 0.0",
        "  local py = 0.0",
        "  local pz = 0.0",
        f"  while j < {n}:",
        "    b = 12 * j",
        "    zx = F[b + 2]",
        "    zy = F[b + 6]",
        "    zz = F[b + 10]",
        "    px = F[b + 3]",
        "    py = F[b + 7]",
        "    pz = F[b + 11]",
        "    if rev[j]:",
        "      J[j] = py * zz - pz * zy + pitch[j] * zx",
        f"      J[{n} + j] = pz * zx - px * zz + pitch[j] * zy",
        f"      J[{2 * n} + j] = px * zy - py * zx + pitch[j] * zz",
        f"      J[{3 * n} + j] = zx",
        f"      J[{4 * n} + j] = zy",
        f"      J[{5 * n} + j] = zz",
        "    else:",
        "      J[j] = zx",
        f"      J[{n} + j] = zy",
        f"      J[{2 * n} + j] = zz",
        "    end",
        "    j = j + 1",
        "  end",
        "  return J",
        "end",
    ]


def _log_function() -> list[str]:
    return [
        "# twist (v, w) of the pose (dR, dp); residual rotations are small (series below 0.01 rad)",
        "def lc_log(dR, dp):",
        "  local ax = 0.5 * (dR[7] - dR[5])",
        "  local ay = 0.5 * (dR[2] - dR[6])",
        "  local az = 0.5 * (dR[3] - dR[1])",
        "  local th = atan2(sqrt(ax * ax + ay * ay + az * az), 0.5 * (dR[0] + dR[4] + dR[8] - 1.0))",
        "  local t2 = th * th",
        "  local a = 1.0",
        "  local bb = 0.5",
        "  local d = 0.0",
        "  if th < 0.01:",
        "    a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0))",
        "    d = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0",
        "  else:",
        "    a = sin(th) / th",
        "    bb = (1.0 - cos(th)) / t2",
        "    d = (1.0 - a / (2.0 * bb)) / t2",
        "  end",
        "  local wx = ax / a",
        "  local wy = ay / a",
        "  local wz = az / a",
        "  local cx = wy * dp[2] - wz * dp[1]",
        "  local cy = wz * dp[0] - wx * dp[2]",
        "  local cz = wx * dp[1] - wy * dp[0]",
        "  local ccx = wy * cz - wz * cy",
        "  local ccy = wz * cx - wx * cz",
        "  local ccz = wx * cy - wy * cx",
        "  return [dp[0] - 0.5 * cx + d * ccx, dp[1] - 0.5 * cy + d * ccy, dp[2] - 0.5 * cz + d * ccz, wx, wy, wz]",
        "end",
    ]


def _solve_function(n: int) -> list[str]:
    return [
        f"# solve M x = y for a {n}×{n} row-major M (Gaussian elimination, partial pivoting)",
        "def lc_solve(M, y):",
        f"  local A = {_zeros(n * n)}",
        f"  local x = {_zeros(n)}",
        "  local i = 0",
        "  local r = 0",
        "  local k = 0",
        "  local p = 0",
        "  local best = 0.0",
        "  local t = 0.0",
        "  local f = 0.0",
        f"  while i < {n * n}:",
        "    A[i] = M[i]",
        "    i = i + 1",
        "  end",
        "  i = 0",
        f"  while i < {n}:",
        "    x[i] = y[i]",
        "    i = i + 1",
        "  end",
        "  i = 0",
        f"  while i < {n}:",
        "    p = i",
        f"    best = lc_abs(A[i * {n} + i])",
        "    r = i + 1",
        f"    while r < {n}:",
        f"      if lc_abs(A[r * {n} + i]) > best:",
        f"        best = lc_abs(A[r * {n} + i])",
        "        p = r",
        "      end",
        "      r = r + 1",
        "    end",
        "    if p != i:",
        "      k = 0",
        f"      while k < {n}:",
        f"        t = A[i * {n} + k]",
        f"        A[i * {n} + k] = A[p * {n} + k]",
        f"        A[p * {n} + k] = t",
        "        k = k + 1",
        "      end",
        "      t = x[i]",
        "      x[i] = x[p]",
        "      x[p] = t",
        "    end",
        "    r = i + 1",
        f"    while r < {n}:",
        f"      f = A[r * {n} + i] / A[i * {n} + i]",
        "      k = i",
        f"      while k < {n}:",
        f"        A[r * {n} + k] = A[r * {n} + k] - f * A[i * {n} + k]",
        "        k = k + 1",
        "      end",
        "      x[r] = x[r] - f * x[i]",
        "      r = r + 1",
        "    end",
        "    i = i + 1",
        "  end",
        f"  i = {n - 1}",
        "  while i >= 0:",
        "    k = i + 1",
        f"    while k < {n}:",
        f"      x[i] = x[i] - A[i * {n} + k] * x[k]",
        "      k = k + 1",
        "    end",
        f"    x[i] = x[i] / A[i * {n} + i]",
        "    i = i - 1",
        "  end",
        "  return x",
        "end",
        "def lc_abs(v):",
        "  if v < 0.0:",
        "    return -v",
        "  end",
        "  return v",
        "end",
    ]


def _network_functions(robot: CalibratedRobot, kin: ZAxisForm) -> tuple[list[str], list[str]]:
    """(constant lines, function lines) of the feature map and the network forward pass lc_rho(q, F)."""
    net = robot.network
    n = robot.n
    Wt, bs = net._folded
    consts, lines = [], []
    # -- features -------------------------------------------------------------------------------------------
    parts: list[str] = []
    for name in net.features:
        if name == "q":
            parts += [f"q[{j}]" for j in range(n)]
        elif name in ("sincos", "sincos2"):
            sines, cosines = [], []
            for j in range(n):
                if not kin.revolute[j]:
                    sines.append(f"q[{j}]" if name == "sincos" else "0.0")
                    cosines.append("0.0")
                elif name == "sincos":
                    sines.append(f"sin(q[{j}])")
                    cosines.append(f"cos(q[{j}])")
                else:
                    sines.append(f"2.0 * sin(q[{j}]) * cos(q[{j}])")
                    cosines.append(f"cos(q[{j}]) * cos(q[{j}]) - sin(q[{j}]) * sin(q[{j}])")
            parts += sines + cosines
        elif name == "gravity":
            for j in range(1, n + 1):
                rows = [f"F[{12 * j + 8 + a}]" for a in range(3)]
                if kin.identity_C:
                    parts += [f"-{r}" for r in rows]
                else:
                    RC = kin.RC_T[j - 1]
                    for col in range(3):
                        parts.append("-(" + " + ".join(f"{rows[a]} * {_num(RC[a, col])}" for a in range(3)) + ")")
        else:
            kind = feature_lib.parse(name)
            if kind is None:
                raise ValueError(f"cannot export network feature {name!r} to URScript")
            H = kind[1]
            lo, hi = robot.model.limits[:, 0], robot.model.limits[:, 1]
            for j in range(n):
                theta = (
                    f"q[{j}]"
                    if kin.revolute[j]
                    else f"({_num(np.pi)} * (q[{j}] - {_num(lo[j])}) / {_num(hi[j] - lo[j])})"
                )
                for h in range(1, H + 1):
                    parts += [f"sin({h}.0 * {theta})", f"cos({h}.0 * {theta})"]
    f = len(parts)
    if f != Wt[0].shape[0]:
        raise ValueError(f"network expects {Wt[0].shape[0]} inputs, the features give {f}")
    lines += ["# network inputs (normalisation is folded into lc_W0 / lc_b0)", "def lc_features(q, F):"]
    lines += ["  return [" + ", ".join(parts) + "]", "end"]
    # -- layers ---------------------------------------------------------------------------------------------
    last = len(Wt) - 1
    for i, (W, b) in enumerate(zip(Wt, bs, strict=True)):
        nin, nout = W.shape
        consts.append(f"lc_W{i} = {_list(W.T)}")
        consts.append(f"lc_b{i} = {_list(b)}")
        lines += [
            f"def lc_layer{i}(x):",
            f"  local y = {_zeros(nout)}",
            "  local o = 0",
            "  local k = 0",
            "  local acc = 0.0",
            f"  while o < {nout}:",
            f"    acc = lc_b{i}[o]",
            "    k = 0",
            f"    while k < {nin}:",
            f"      acc = acc + lc_W{i}[o * {nin} + k] * x[k]",
            "      k = k + 1",
            "    end",
            "    y[o] = " + ("acc" if i == last else "lc_tanh(acc)"),
            "    o = o + 1",
            "  end",
            "  return y",
            "end",
        ]
    call = "lc_features(q, F)"
    for i in range(len(Wt)):
        call = f"lc_layer{i}({call})"
    lines += [
        "def lc_tanh(x):",
        "  if x > 20.0:",
        "    return 1.0",
        "  end",
        "  if x < -20.0:",
        "    return -1.0",
        "  end",
        f"  local e = pow({_num(np.e)}, 2.0 * x)",
        "  return (e - 1.0) / (e + 1.0)",
        "end",
        "# joint motion errors δρ(q) (6 values: actuated joints, then virtual joints)",
        "def lc_rho(q, F):",
        f"  return {call}",
        "end",
    ]
    return consts, lines


def urscript_text(
    robot: CalibratedRobot,
    *,
    method: str = "newton",
    iterations: int = 4,
    function_name: str = "labcal_correct",
    provenance: dict | None = None,
) -> str:
    """The URScript source of ``function_name(q)`` for this calibrated robot (see the module docstring)."""
    if method not in ("newton", "paper"):
        raise ValueError(f"urscript method must be 'newton' or 'paper', got {method!r}")
    if not function_name.isidentifier():
        raise ValueError(f"function name {function_name!r} is not an identifier")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    n = robot.n
    net = robot.network
    if robot.joint_map is not None:
        raise ValueError(
            "URScript export of a robot with a joint map (controller joints are not the model's joints) is not "
            "supported: UR controllers have no coupled or offset joints, so a map means this is not a UR arm; use "
            "the json/npz compensator, which converts controller joints"
        )
    if method == "paper" and net is None:
        raise ValueError("method 'paper' (eq. 24) needs a network; this calibration has none")
    if method == "paper" and (why := robot.network_only_error("paper")):
        raise ValueError(why)
    if n > 6:
        raise ValueError(
            f"URScript export of a {n}-joint robot is not supported (UR controllers drive 6 joints); "
            "use the json/npz compensator"
        )
    if net is not None and n < 6:
        raise ValueError(
            f"URScript export of a network for a {n}-joint robot is not supported (virtual joints); "
            "use the json/npz compensator"
        )
    kin, nom = ZAxisForm(robot.model), ZAxisForm(robot.nominal)
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]

    head = [
        f"# labcal compensator for {robot.nominal.name or 'robot'} — method {robot.method}, script: {method}",
        f"# nominal robot sha256 {model_hash(robot.nominal)}",
    ]
    head += [f"# {k}: {v}" for k, v in sorted((provenance or {}).items())]
    head += [
        f"# usage: q_cmd = {function_name}(q)   (q: {n} joint angles in rad, the pose you want the nominal model of)",
        "# generated by labcal.export.urscript; do not edit (the numbers are the calibration)",
        f"lc_lo = {_list(lo)}",
        f"lc_hi = {_list(hi)}",
        f"lc_A = {_list(_frames12(kin))}",
        f"lc_lin = {_list(kin.lin)}",
        f"lc_pitch = {_list(kin.pitch)}",
        f"lc_rev = {_bools(kin.revolute)}",
        f"lc_nA = {_list(_frames12(nom))}",
        f"lc_nlin = {_list(nom.lin)}",
        f"lc_nrev = {_bools(nom.revolute)}",
    ]
    funcs = _mul_function() + _chain_function(n) + _twists_function(n) + _log_function() + _solve_function(n)
    if net is not None:
        consts, net_lines = _network_functions(robot, kin)
        head += consts
        funcs += net_lines

    check = [
        "  local j = 0",
        f"  while j < {n}:",
        "    if q[j] < lc_lo[j] or q[j] > lc_hi[j]:",
        '      popup("labcal: joint outside the calibrated range", error=True, blocking=True)',
        "      halt",
        "    end",
        "    j = j + 1",
        "  end",
    ]
    main = [f"def {function_name}(q):", *check]
    if method == "paper":
        F = "lc_chain(lc_A, lc_lin, lc_rev, q)" if "gravity" in net.features else "[0.0]"
        main += [
            f"  local rho = lc_rho(q, {F})",
            "  return [" + ", ".join(f"q[{j}] - rho[{j}]" for j in range(n)) + "]",
            "end",
        ]
        return "\n".join(head + funcs + main) + "\n"

    last = 12 * n
    main += [
        "  local T = lc_chain(lc_nA, lc_nlin, lc_nrev, q)",
        "  local Rt = [" + ", ".join(f"T[{last + 4 * a + b}]" for a in range(3) for b in range(3)) + "]",
        "  local pt = [" + ", ".join(f"T[{last + 4 * a + 3}]" for a in range(3)) + "]",
        f"  local qc = [{', '.join(f'q[{j}]' for j in range(n))}]",
        "  local F = [0.0]",
        "  local J = [0.0]",
        "  local dR = [0.0]",
        "  local dp = [0.0]",
        "  local r = [0.0]",
        "  local st = [0.0]",
        "  local it = 0",
        f"  while it < {int(iterations)}:",
        "    F = lc_chain(lc_A, lc_lin, lc_rev, qc)",
        "    J = lc_twists(F, lc_rev, lc_pitch)",
    ]
    # dR = Rt Rmᵀ, dp = pt − dR pm
    dR = []
    for a in range(3):
        for b in range(3):
            dR.append(" + ".join(f"Rt[{3 * a + m}] * F[{last + 4 * b + m}]" for m in range(3)))
    main.append("    dR = [" + ", ".join(dR) + "]")
    dp = [
        f"pt[{a}] - (" + " + ".join(f"dR[{3 * a + m}] * F[{last + 4 * m + 3}]" for m in range(3)) + ")"
        for a in range(3)
    ]
    main.append("    dp = [" + ", ".join(dp) + "]")
    main.append("    r = lc_log(dR, dp)")
    if net is not None:
        main.append("    local rho = lc_rho(qc, F)")
        dy = [" + ".join(f"J[{6 * a + m}] * rho[{m}]" for m in range(6)) for a in range(6)]
        main.append("    r = [" + ", ".join(f"r[{a}] - ({dy[a]})" for a in range(6)) + "]")
    if n >= 6:
        main.append("    st = lc_solve(J, r)")
    else:
        L = float(robot.length_scale)
        w = [1.0 / L**2] * 3 + [1.0] * 3
        JtJ = [
            " + ".join(f"{_num(w[a])} * J[{a * n + i}] * J[{a * n + k}]" for a in range(6))
            for i in range(n)
            for k in range(n)
        ]
        Jtr = [" + ".join(f"{_num(w[a])} * J[{a * n + i}] * r[{a}]" for a in range(6)) for i in range(n)]
        main.append("    st = lc_solve([" + ", ".join(JtJ) + "], [" + ", ".join(Jtr) + "])")
    main += [
        f"    qc = [{', '.join(f'qc[{j}] + st[{j}]' for j in range(n))}]",
        "    it = it + 1",
        "  end",
        "  return qc",
        "end",
    ]
    return "\n".join(head + funcs + main) + "\n"


def write_urscript(robot: CalibratedRobot, path, provenance: dict | None = None, **options) -> Path:
    path = Path(path)
    path.write_text(urscript_text(robot, provenance=provenance, **options))
    return path
