"""URScript export: the compensator as URScript a UR controller runs, in two deployable forms.

- **function file** (``urscript_text``, ``--format urscript``): global ``lc_`` constants and functions, ending in
  ``labcal_correct(q)``. Load it with a *Script* node in file mode under BeforeStart (so it runs once, before the
  first call), then
  ``q_cmd = labcal_correct(q)`` and ``movej(q_cmd, …)``.
- **program** (``urscript_program_text``, ``--format urscript-program``): the same definitions inside one
  ``def labcal_program(): … end`` for the primary/secondary script port (30001/30002). On its own it runs a self
  test (golden configurations of the export within :data:`FLOAT32_BOUND` of the Python runtime's q_cmd, and
  configurations near the wrist and elbow singularities within :data:`AGREEMENT`, see
  :func:`near_singular_self_test`) and says so with ``textmsg``; a caller may pass ``body`` lines (e.g. ``movej``) to
  run after.

What it computes (``method="newton"``, the default, matches :meth:`CalibratedRobot.correct`):

1. the nominal tool pose of q (the robot's own kinematics, local POE, written out as constant frames);
2. Gauss-Newton steps (``lc_attempt``, at most ``iterations``, default :data:`ITERATIONS`) from q_cmd = q on
   ``log(T_nominal(q) T_model(q_cmd)⁻¹) − J(q_cmd) δρ(q_cmd) = 0``: the identified frames' forward kinematics, the
   joint twists J, the network δρ (tanh hidden layers, normalisation folded into the weights) and a 6×6 solve by
   Gaussian elimination with partial pivoting — the same equations as the Python runtime, under the same verdict
   as its Gauss-Newton mode (:func:`labcal.compensator.solve.verdict`): a first step above ``GN_MAX_STEP``, a later
   one above half the previous (unless below :data:`CONVERGED_STEP`, i.e. rounding) or one that is not finite
   means a (near-)singular configuration;
3. it returns q_cmd only when the step that led to it is below :data:`CONVERGED_STEP`, the residual there is below
   :data:`RESIDUAL_TOL` (length-scaled, L1) and ``|q_cmd − q|`` is within ``max_correction`` (default
   :data:`MAX_CORRECTION`); a converged q_cmd takes the step at hand once more (r and J are computed), which in
   double precision brings it to rounding of ``correct()``'s answer. Otherwise ``labcal_correct`` writes the
   reason to the log (``textmsg``) and stops the program: ``popup`` naming the configuration, then ``halt``.
   Where ``correct()`` needs its damped fallback the script refuses instead of damping: there the damped answer
   is mostly a least-squares compromise with a residual left, which nothing in the script could check
   (``benchmarks/urscript_agreement.py`` counts both), and 24 damped steps would cost the controller another
   ~200 frames;
4. ``method="paper"`` instead emits eq. (24), q − δρ_a(q): one network evaluation, exact for the paper's method.

TCP. The model ends at tool0, the flange (robot and tool apart: the calibration's measurement tool is not part of
it, and the header names it). The script returns only converged Gauss-Newton answers, which put the calibrated
flange exactly at its nominal pose; every TCP rigidly attached to the flange is then at its nominal pose too, so
the answer is the same for every TCP, the controller's active one (``get_tcp_offset()``) included, and the script
needs none. A TCP changes :meth:`CalibratedRobot.correct` only where it damps (``tcp=``: the pose error is measured
at the TCP), which is exactly where the script refuses.

Whenever the script returns, its q_cmd is within :data:`AGREEMENT` of ``correct()`` in float64 and float32: the
last step below 1e-5 rad bounds the distance to the root of the residual *as computed*, and the computed residual
differs from the exact one by rounding δr, which moves the root by ``J_s⁻¹ δr``. Near the elbow ``‖J_s⁻¹‖∞``
(length-scaled) reaches 10³, and in float32 a step and a residual below 1e-5 left a q_cmd 1.1e-4 rad off (the real
UR10 fit, q = [1.6962, 0.7805, −0.0283, −1.0017, 1.5547, 0.5462]). So a six-joint script also computes
``‖J_s⁻¹‖∞`` (six solves with the J it has) and the machine epsilon ε of its arithmetic, and refuses where
``‖J_s⁻¹‖∞ · RESIDUAL_ROUNDING · ε > AGREEMENT`` (status −4).

Strings: every text the exporter writes into a comment or a string literal (robot name, method, provenance, popup
messages) goes through :func:`_text`, which keeps printable ASCII and writes every other character, the quote,
the backslash, ``%`` and ``#`` as %XX escapes, so no name or provenance value can end a comment or a string.
Rules the emitted script keeps (the tests check every emitted script with ``benchmarks/urscript_subset.py``):

- **List capacity.** Since PolyScope 5.15 a list can only be assigned to an existing list of greater or equal
  capacity, and a list literal's capacity is its length. Every list is created at its full size (``[0.0, …]`` of
  the length it will hold, or the result of a function whose returned list has that length) and only lists of
  the same length are assigned to it later.
- **Integer indexing.** Indices are int expressions (int literals and int variables under + − ×); a variable keeps
  the type of its first assignment (an int counter never receives a float).
- **Scope.** Every variable a function assigns is declared ``local`` (or is a parameter), so a user program's
  global of the same name (``i``, ``q`` …) is never overwritten; globals are the ``lc_``-prefixed constants.
- **Built-ins.** Only sin, cos, sqrt, atan2, pow, sync, popup, textmsg, str_cat, movej (and ``halt``); URScript has no
  ``exp`` or ``tanh`` (tanh is built from pow).
- **Statement budget.** The manual asks for ``sync()`` next to computation-heavy code (a thread that uses its
  whole 2 ms frame without one risks "Lost communication with Controller" and a protective stop). Each heavy
  phase (a chain, the twists, the features, each network layer, the solve) starts with ``sync()``; loops over
  joints or pivots call ``sync()`` every few iterations, and the network, written out straight (one feature
  column or up to :data:`TERMS_PER_STATEMENT` multiply-adds per statement, the folded weights as literals with
  exact zeros left out), calls it after each chunk of statements, so that at most ``statements_per_sync``
  statements run between two ``sync()`` calls (``tests/export/measure_urscript.py`` prints statements and syncs
  per call); the manual gives no number, so the default
  :data:`STATEMENTS_PER_SYNC` is a conservative choice: lower it if the controller reports a thread that used too
  much time, raise it for fewer frames per call. Each ``sync()`` costs one 2 ms frame, so a call takes at least
  2 ms × the number of syncs it executes.

Numbers: the script prints every constant with 17 significant digits, but the controller computes in 32-bit
floats. The float32 result differs from ``correct()`` by rounding, amplified by the configuration's conditioning:
within :data:`FLOAT32_BOUND` rad on configurations whose length-scaled joint Jacobian has a condition number
≤ 100 (the test evaluates every script in float32 and holds it to this bound; the exact double-precision
agreement holds only in double precision). The range and region checks compare with bounds moved inwards by their
own float32 rounding (:func:`_script_ranges`, :func:`_script_radius2`), so a controller never passes a
configuration ``correct()`` refuses; it stops in a thin band just inside instead (``benchmarks/urscript_boundary.py``).

Not covered (say so where it matters): configurations outside the calibrated joint ranges or outside the
calibration's validity region (farther than its radius from every stored configuration, joints scaled as in
:mod:`labcal.compensator.validity`: where ``correct()`` refuses without ``extrapolate``) stop the program
(``popup`` + ``halt``) — there is no ``extrapolate``; the region check loops over the stored configurations
(at most :data:`labcal.compensator.validity.MAX_CENTRES`), about (2n + 3) statements each, so it adds
``centres × (2n + 3) / (statements_per_sync / 2)`` sync frames (2 ms each) to a call; where the Python runtime
damps (near a singular configuration) the script stops instead; robots with fewer than 6 joints are supported
without a network only (virtual joints need a QR decomposition; their least-squares residual is not zero, so
only the step is checked), robots with more than 6 not at all (a UR controller drives six); the rotation logarithm
assumes a residual rotation below π/2 (corrections are milliradians).
"""

from __future__ import annotations

import re

import numpy as np

from labcal import features as feature_lib
from labcal.compensator import CalibratedRobot, golden_configurations
from labcal.compensator.solve import GN_MAX_STEP, MAX_CORRECTION
from labcal.export.zform import ZAxisForm
from labcal.kinematics import se3
from labcal.kinematics.metric import scaled_condition
from labcal.robots import model_hash

STATEMENTS_PER_SYNC = 1000  # default budget of statements between two sync() calls (see the module docstring)
FLOAT32_BOUND = 2e-5  # rad: |script in float32 − correct()| on configurations with scaled condition ≤ 100
AGREEMENT = 1e-4  # rad: |script − correct()| wherever the script returns (float64 or float32)
ITERATIONS = 6  # Gauss-Newton steps at most (a converged call takes two or three)
CONVERGED_STEP = 1e-5  # rad: the last step must be below this (it bounds the distance to correct()'s answer)
RESIDUAL_TOL = 1e-5  # |r| (L1, translation over the length scale) at the returned q_cmd, in rad
# MAX_CORRECTION (solve's, 0.1 rad): a larger |q_cmd − q| is refused, the bound correct() itself keeps
# |δr|∞, the rounding left in the residual at the returned q_cmd, in machine epsilons ε. Measured as
# |J_s (q_cmd − correct())|∞ over the float32 answers of benchmarks/urscript_agreement.py (printed below its table):
# at most 3.8 ε over the three exports, then 4.19 ε once the 1,000 configurations of the validity region were
# added (issue 27), so the bound was raised from 4 to 5 ε: an assumption a measurement exceeded is no bound. The
# bound ‖J_s⁻¹‖∞ |δr|∞ assumes the worst alignment of δr; the errors measured were at most 2.0 ε ‖J_s⁻¹‖∞.
RESIDUAL_ROUNDING = 5.0
FLOAT32_EPS = 2.0**-23  # a controller's machine epsilon (lc_eps measures the script's own)
# The range and region checks compare with bounds moved inwards by the float32 rounding of the comparison, so that
# the controller never passes a configuration correct() refuses (benchmarks/urscript_boundary.py: with the bounds
# themselves, float32 passed configurations 1e-7 of the validity radius outside it, 1e-4 where a joint never moved,
# and 1e-8 past a joint's range).
RANGE_MARGIN = 2.0**-22  # relative (at least 1 rad or m): two float32 spacings of the bound, see _script_ranges
REGION_ROUNDING = 6.0  # |computed − exact| of e_j = q_j w_j − c_j in float32, in units of 2⁻²⁴ m_j: _script_radius2
SELF_TEST_COUNT = 4
SELF_TEST_OFFSETS = (0.05, 0.1, 0.2)  # rad from the wrist and elbow singularities: the self test's candidates
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _num(x: float) -> str:
    """A float literal URScript and the test interpreter both read as a float (always with a decimal point)."""
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"cannot write the non-finite number {x} into URScript")
    mantissa, e, exponent = repr(x).partition("e")  # a finite float's repr has a point unless it has an exponent
    return (mantissa if "." in mantissa else mantissa + ".0") + e + exponent


def _list(values) -> str:
    return "[" + ", ".join(_num(v) for v in np.asarray(values, dtype=float).ravel()) + "]"


def _zeros(m: int) -> str:
    return "[" + ", ".join(["0.0"] * m) + "]"


def _locals(value: str, *names: str) -> list[str]:
    """A function's declarations ``local name = value``, one line each (URScript declares one name per statement)."""
    return [f"  local {name} = {value}" for name in names]


def _chunk(statements: int) -> int:
    """Statements between two sync() calls in one chunk (``statements_per_sync`` given): half the budget, so that a
    chunk plus the straight-line code after it (up to the next phase's sync) stays within the budget."""
    if statements < 200:
        raise ValueError(f"statements_per_sync must be >= 200 (one joint's chain step needs ~60), got {statements}")
    return int(statements) // 2


def _every(chunk: int, cost: int) -> int:
    """Iterations of a loop whose body runs at most ``cost`` statements that fit in one chunk (≥ 1)."""
    return max(1, chunk // max(1, cost))


def _counter(indent: str, name: str, every: int, trips: int) -> list[str]:
    """Lines that call sync() after every ``every`` iterations of a loop (none when the loop fits in one chunk)."""
    if every >= trips:
        return []
    return [
        f"{indent}{name} = {name} + 1",
        f"{indent}if {name} >= {every}:",
        f"{indent}  sync()",
        f"{indent}  {name} = 0",
        f"{indent}end",
    ]


def _frames12(kin: ZAxisForm) -> np.ndarray:
    """A'_0 … A'_n as 3×4 row-major blocks (the implicit last row is 0 0 0 1)."""
    A = np.concatenate([kin.A0[None], kin.A_rest])
    return A[:, :3, :].reshape(-1)


def _mul_function() -> list[str]:
    """lc_mul(a, b): the product of two 3×4 blocks (rotation and translation; the last column adds a's)."""
    terms = [
        " + ".join(f"a[{4 * i + m}] * b[{4 * m + col}]" for m in range(3)) + (f" + a[{4 * i + 3}]" if col == 3 else "")
        for i in range(3)
        for col in range(4)
    ]
    return ["def lc_mul(a, b):", "  return [" + ", ".join(terms) + "]", "end"]


def _chain_function(revolute, chunk: int) -> list[str]:
    """lc_chain(A, lin, q): the frames T'_0 … T'_n, written out joint by joint (the joint types are the same for
    the nominal and the identified model, so they are known here)."""
    n = len(revolute)
    body = _Straight(chunk)
    body.add("local c = 1.0")
    body.add("local s = 0.0")
    body.add(f"local G = {_zeros(12)}")
    body.add("local T0 = [" + ", ".join(f"A[{k}]" for k in range(12)) + "]")
    for j in range(n):
        o = 12 * (j + 1)
        if revolute[j]:
            body.add(f"c = cos(q[{j}])")
            body.add(f"s = sin(q[{j}])")
            g = [f"c * A[{o + k}] - s * A[{o + 4 + k}]" for k in range(4)]
            g += [f"s * A[{o + k}] + c * A[{o + 4 + k}]" for k in range(4)]
        else:
            g = [f"A[{o + k}]" for k in range(8)]
        g += [f"A[{o + 8}]", f"A[{o + 9}]", f"A[{o + 10}]", f"A[{o + 11}] + lin[{j}] * q[{j}]"]
        body.add("G = [" + ", ".join(g) + "]")
        body.add(f"local T{j + 1} = lc_mul(T{j}, G)", 2)
    body.add("return [" + ", ".join(f"T{j}[{k}]" for j in range(n + 1) for k in range(12)) + "]")
    return [
        "# frames T'_0 … T'_n of a chain (3×4 row-major blocks); the last block is the tool pose",
        "def lc_chain(A, lin, q):",
        *body.lines,
        "end",
    ]


def _twists_function(n: int) -> list[str]:
    return [
        "# joint twists in the base frame, 6×n row-major (v, w): Ad(T'_j)(h_j e_z, e_z)",
        "def lc_twists(F, rev, pitch):",
        "  sync()",
        f"  local J = {_zeros(6 * n)}",
        *_locals("0", "j", "b"),
        *_locals("0.0", "zx", "zy", "zz", "px", "py", "pz"),
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


def _solve_function(n: int, chunk: int) -> list[str]:
    # One pivot column: search (4 per row) and swap (4 per column + 5); then each row below it (8 + 3 per column).
    every = _every(chunk, 10 + 8 * n)
    row_every = _every(chunk, 8 + 3 * n)
    back_every = _every(chunk, 6 + 3 * n)
    return [
        f"# solve M x = y for a {n}×{n} row-major M (Gaussian elimination, partial pivoting)",
        "def lc_solve(M, y):",
        "  sync()",
        f"  local A = {_zeros(n * n)}",
        f"  local x = {_zeros(n)}",
        *_locals("0", "i", "r", "k", "p", "cnt", "rc"),
        *_locals("0.0", "best", "t", "f"),
        "  A = [" + ", ".join(f"M[{k}]" for k in range(n * n)) + "]",
        "  x = [" + ", ".join(f"y[{k}]" for k in range(n)) + "]",
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
        *_counter("      ", "rc", row_every, n - 1),
        "    end",
        "    i = i + 1",
        *_counter("    ", "cnt", every, n),
        "  end",
        "  sync()",
        "  cnt = 0",
        f"  i = {n - 1}",
        "  while i >= 0:",
        "    k = i + 1",
        f"    while k < {n}:",
        f"      x[i] = x[i] - A[i * {n} + k] * x[k]",
        "      k = k + 1",
        "    end",
        f"    x[i] = x[i] / A[i * {n} + i]",
        "    i = i - 1",
        *_counter("    ", "cnt", back_every, n),
        "  end",
        "  return x",
        "end",
        *_abs_function(),
    ]


def _abs_function() -> list[str]:
    return [
        "def lc_abs(v):",
        "  if v < 0.0:",
        "    return -v",
        "  end",
        "  return v",
        "end",
    ]


def _column_expression(col: feature_lib.Column, kin: ZAxisForm) -> str:
    """The URScript expression of one feature column (the registry's recipe; F: the chain's frames at q)."""
    if col.op == "q":
        return f"q[{col.joint}]"
    if col.op == "zero":
        return "0.0"
    if col.op in ("sin", "cos"):
        theta = f"q[{col.joint}]"
        if col.stroke is not None:
            lo, hi = col.stroke
            theta = f"({_num(np.pi)} * (q[{col.joint}] - {_num(lo)}) / {_num(hi - lo)})"
        arg = theta if col.order == 1 else f"{col.order}.0 * {theta}"
        return f"{col.op}({arg})"
    if col.op == "gravity":
        # −(row 2 of R_link): lc_chain's block ``link`` is that frame in the z-axis form (times C_link⁻¹ back).
        rows = [f"F[{12 * col.link + 8 + a}]" for a in range(3)]
        if kin.identity_C:
            return f"-{rows[col.axis]}"
        RC = kin.RC_T[col.link - 1]
        return "-(" + " + ".join(f"{rows[a]} * {_num(RC[a, col.axis])}" for a in range(3)) + ")"
    raise ValueError(f"feature column {col.op!r} has no URScript form")


TERMS_PER_STATEMENT = 8  # multiply-adds written into one statement of a network layer
_TANH_COST = 6  # statements of one lc_tanh call (the call, two tests, pow, return)


class _Straight:
    """Straight-line function body: a statement count since the last sync(), and a sync() before a statement
    that would take it past one chunk of the budget (so a chunk plus what follows the function stays within it)."""

    def __init__(self, chunk: int) -> None:
        self.chunk = chunk
        self.lines = ["  sync()"]  # each such body is a phase of its own
        self.count = 0

    def add(self, line: str, cost: int = 1) -> None:
        if self.count + cost > self.chunk:
            self.lines.append("  sync()")
            self.count = 0
        self.lines.append("  " + line)
        self.count += cost


def _network_functions(robot: CalibratedRobot, kin: ZAxisForm, chunk: int) -> list[str]:
    """Function lines of the feature map and the network forward pass lc_rho(q, F).

    Both are written out straight (one feature column, or up to TERMS_PER_STATEMENT multiply-adds of a layer, per
    statement; the folded weights as literals, exact zeros left out — a joint series' weights are mostly zeros),
    so the statement count is known here and sync() is placed exactly where the budget needs it.
    """
    net = robot.network
    Wts, bs = net._folded  # the layers acting on raw features and giving δρ directly (transposed)
    Ws = [Wt.T for Wt in Wts]
    joint_types, limits = robot.model.joint_types, robot.model.limits
    columns = [col for name in net.features for col in feature_lib.get(name).columns(joint_types, limits)]
    parts = [_column_expression(col, kin) for col in columns]
    if len(parts) != Ws[0].shape[1]:
        raise ValueError(f"network expects {Ws[0].shape[1]} inputs, the features give {len(parts)}")
    body = _Straight(chunk)
    body.add(f"local x = {_zeros(len(parts))}")
    for k, expr in enumerate(parts):
        body.add(f"x[{k}] = {expr}")
    body.add("return x")
    lines = ["# network inputs (the normalisation is folded into the first layer's weights)", "def lc_features(q, F):"]
    lines += [*body.lines, "end"]
    last = len(Ws) - 1
    for i, (W, b) in enumerate(zip(Ws, bs, strict=True)):
        nout, _ = W.shape
        body = _Straight(chunk)
        body.add(f"local y = {_zeros(nout)}")
        body.add("local acc = 0.0")
        for o in range(nout):
            terms = [f"{_num(W[o, k])} * x[{k}]" for k in np.flatnonzero(W[o])]
            chunks = [terms[c : c + TERMS_PER_STATEMENT] for c in range(0, len(terms), TERMS_PER_STATEMENT)]
            body.add(f"acc = {' + '.join([_num(b[o]), *chunks[0]]) if chunks else _num(b[o])}")
            for more in chunks[1:]:
                body.add(f"acc = acc + {' + '.join(more)}")
            if i == last:
                body.add(f"y[{o}] = acc")
            else:
                body.add(f"y[{o}] = lc_tanh(acc)", 1 + _TANH_COST)
        body.add("return y")
        lines += [f"def lc_layer{i}(x):", *body.lines, "end"]
    call = "lc_features(q, F)"
    for i in range(len(Ws)):
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
    return lines


def _check_exportable(
    robot: CalibratedRobot, method: str, iterations: int, function_name: str, max_correction: float
) -> None:
    if method not in ("newton", "paper"):
        raise ValueError(f"urscript method must be 'newton' or 'paper', got {method!r}")
    if not _IDENTIFIER.fullmatch(function_name) or function_name.startswith("lc_"):
        raise ValueError(f"function name {function_name!r} is not an ASCII identifier outside the lc_ prefix")
    if isinstance(iterations, bool) or not isinstance(iterations, int | np.integer) or iterations < 1:
        raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
    if not (isinstance(max_correction, int | float) and 0 < max_correction <= GN_MAX_STEP):
        raise ValueError(f"max_correction must be a number of rad in (0, {GN_MAX_STEP}], got {max_correction!r}")
    n, net = robot.n, robot.network
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
    if n > 6 or (net is not None and n < 6):
        what, why = (
            (f"a {n}-joint robot", "UR controllers drive 6 joints")
            if n > 6
            else (f"a network for a {n}-joint robot", "virtual joints")
        )
        raise ValueError(f"URScript export of {what} is not supported ({why}); use the json/npz compensator")


def _definitions(
    robot: CalibratedRobot, method: str, iterations: int, function_name: str, chunk: int, max_correction: float
) -> tuple[list[str], list[str]]:
    """(constant lines, function lines) of the compensator, ending with ``function_name(q)``."""
    n, net = robot.n, robot.network
    kin, nom = ZAxisForm(robot.model), ZAxisForm(robot.nominal)
    if not np.array_equal(kin.revolute, nom.revolute):
        raise ValueError("the identified model's joint types differ from the nominal robot's")
    lo, hi = _script_ranges(robot)
    consts = [
        f"lc_lo = {_list(lo)}",
        f"lc_hi = {_list(hi)}",
        f"lc_A = {_list(_frames12(kin))}",
        f"lc_lin = {_list(kin.lin)}",
        f"lc_pitch = {_list(kin.pitch)}",
        f"lc_rev = [{', '.join(str(bool(v)) for v in kin.revolute)}]",
        f"lc_nA = {_list(_frames12(nom))}",
        f"lc_nlin = {_list(nom.lin)}",
    ]
    funcs = (
        _mul_function()
        + _chain_function(kin.revolute, chunk)
        + _twists_function(n)
        + _log_function()
        + _solve_function(n, chunk)
    )
    if net is not None:
        funcs += _network_functions(robot, kin, chunk)
    region = robot.validity
    if region is not None:
        consts += [f"lc_vc{j} = {_list(region.centres[:, j])}" for j in range(n)]
        consts.append(f"lc_vr2 = {_num(_script_radius2(region)[0])}")
        funcs += _region_function(region, chunk)

    head = _correct_head(robot, function_name)
    if method == "paper":
        F = "lc_chain(lc_A, lc_lin, q)" if "gravity" in net.features else _zeros(12 * (n + 1))
        main = [f"  local rho = lc_rho(q, {F})", "  return [" + ", ".join(f"q[{j}] - rho[{j}]" for j in range(n)) + "]"]
        return consts, [*funcs, *head, *main, "end"]
    attempt = _attempt_function(robot, kin, iterations, max_correction)
    return consts, funcs + attempt + head + _correct_refusals(n, iterations, max_correction)


def _region_function(region, chunk: int) -> list[str]:
    """lc_region_d2(q): the squared scaled distance from q to the nearest centre of the validity region
    (:class:`labcal.compensator.validity.ValidityRegion`: joint j scaled by its weight, centres stored scaled)."""
    count, n = region.centres.shape
    squares = [  # d = Σ_j (q_j w_j − c_j)², one joint after the other
        (f"    e = q[{j}] * {_num(w)} - lc_vc{j}[c]", "    d = d + e * e" if j else "    d = e * e")
        for j, w in enumerate(region.weights)
    ]
    return [
        "def lc_region_d2(q):",
        "  sync()",
        "  local best = -1.0",
        *_locals("0.0", "d", "e"),
        *_locals("0", "c", "s"),
        f"  while c < {count}:",
        *(line for pair in squares for line in pair),
        "    if best < 0.0 or d < best:",
        "      best = d",
        "    end",
        "    c = c + 1",
        *_counter("    ", "s", _every(chunk, 2 * n + 3), count),
        "  end",
        "  return best",
        "end",
    ]


def _script_ranges(robot: CalibratedRobot, margins: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) the script compares q with: the calibrated ranges, each bound b moved inwards by RANGE_MARGIN ·
    max(|b|, 1), at least two float32 spacings of b. Rounding to float32 is monotone and moves a number by at most
    half a spacing, so a q past b stays past the rounded literal: the controller refuses every q correct() refuses,
    and the script refuses a band that thin just inside (float64: 1.5e-6 rad at ±2π, 2.4e-7 within ±1)."""
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    m = margins * RANGE_MARGIN
    return lo + m * np.maximum(np.abs(lo), 1.0), hi - m * np.maximum(np.abs(hi), 1.0)


def _script_radius2(region) -> tuple[float, float]:
    """(the radius² ``lc_region_d2`` is compared with, D): below every squared distance correct() refuses, by the
    rounding of both sides; D bounds the float32 script's error in the distance.

    correct() (float64, ε = 2⁻⁵³) sums |x|² − 2 x·c + |c|² (x = q w): off by at most (n + 5) 2ε (‖x‖ + ‖c‖)²,
    sqrt and comparison included, so it refuses only where the exact squared distance exceeds r2 below.
    The script (float32, u = 2⁻²⁴) computes e_j = q_j w_j − c_j with at most 3u|x_j| (q, w, their product) +
    u|c_j| + u|e_j| (c, the difference) ≤ REGION_ROUNDING u m_j, m_j = max |c_j| + radius bounding |x_j|, |c_j|
    and |e_j| within a ball (the 6th u absorbs the second-order terms); so its ‖e‖ is off by at most D =
    REGION_ROUNDING u ‖m‖, and the sum of n squares by a factor (1 ± n u). Comparing with (√r2 − D)² (1 − (n + 2) u)
    (the literal's own rounding included) refuses every q correct() refuses. The compared radius is smaller than the
    region's by 5.6e-6 of it for the real UR10 fit of benchmarks/urscript_agreement.py, 1.8e-6 for the simulated
    ones and 7.5e-4 where a joint never moved (scaled by 1 / MIN_SPREAD: 4,740 units), as
    ``benchmarks/urscript_boundary.py`` prints; the script stops in that shell just inside the region.
    """
    n = region.centres.shape[1]
    reach = np.abs(region.centres).max(axis=0) + region.radius  # m_j
    outer = 2.0 * float(np.linalg.norm(region.centres, axis=1).max()) + region.radius  # bounds ‖x‖ + ‖c‖
    r2 = region.radius**2 - (n + 5) * 2.0**-52 * outer**2
    slack = REGION_ROUNDING * 2.0**-24 * float(np.linalg.norm(reach))
    return max(np.sqrt(max(r2, 0.0)) - slack, 0.0) ** 2 * (1.0 - (n + 2) * 2.0**-24), slack


def _correct_head(robot: CalibratedRobot, function_name: str) -> list[str]:
    """function_name(q)'s opening: stop the program where ``correct()`` refuses without ``extrapolate``, at a joint
    outside its calibrated range or a configuration outside the validity region (within :func:`_script_ranges`,
    :func:`_script_radius2`)."""
    lines = [
        f"def {function_name}(q):",
        "  local j = 0",
        f"  while j < {robot.n}:",
        "    if not (lc_lo[j] <= q[j] and q[j] <= lc_hi[j]):",
        f'      textmsg("{_text("labcal: joint outside the calibrated range, q = ")}", q)',
        f'      popup(str_cat("{_text("labcal: joint outside the calibrated range, stopped at q = ")}", q), '
        "error=True, blocking=True)",
        "      halt",
        "    end",
        "    j = j + 1",
        "  end",
    ]
    if robot.validity is None:
        return lines
    head = "labcal: configuration outside the validity region of the calibration (no data near it), stopped at q = "
    return [
        *lines,
        "  if not (lc_region_d2(q) <= lc_vr2):",
        f'    textmsg("{_text(head)}", q)',
        f'    popup(str_cat("{_text(head)}", q), error=True, blocking=True)',
        "    halt",
        "  end",
    ]


def _attempt_function(robot: CalibratedRobot, kin: ZAxisForm, iterations: int, max_correction: float) -> list[str]:
    """lc_attempt(q) → [q_cmd…, status]: Gauss-Newton from q_cmd = q with correct()'s rules and a final check.

    status 1.0: converged (last step below CONVERGED_STEP, residual below RESIDUAL_TOL, correction within
    max_correction); −1.0: correction too large; −2.0: not converged in ``iterations`` steps; −3.0: a step too large,
    not contracting or not finite (a (near-)singular configuration, where correct() would damp); −4.0 (six joints):
    ``‖J_s⁻¹‖∞ · RESIDUAL_ROUNDING · ε`` above AGREEMENT (the arithmetic's rounding could move q_cmd that far).
    """
    n = robot.n
    err, solve = _attempt_error_and_solve(robot)
    lines = _attempt_locals(n) + _attempt_residual(n, robot.network is not None)
    lines += _attempt_step(n, err, solve, iterations)
    lines += _attempt_verdict(n, max_correction)
    lines += _amax_function(n)
    if n >= 6:
        lines += _inv_norm_function(n, float(robot.length_scale)) + _eps_function()
    return lines


def _attempt_locals(n: int) -> list[str]:
    """lc_attempt's opening: the nominal target pose (Rt, pt), its locals, and the head of the Newton loop."""
    last = 12 * n
    return [
        "def lc_attempt(q):",
        "  local T = lc_chain(lc_nA, lc_nlin, q)",
        "  local Rt = [" + ", ".join(f"T[{last + 4 * a + b}]" for a in range(3) for b in range(3)) + "]",
        "  local pt = [" + ", ".join(f"T[{last + 4 * a + 3}]" for a in range(3)) + "]",
        f"  local qc = [{', '.join(f'q[{j}]' for j in range(n))}]",
        f"  local F = {_zeros(12 * (n + 1))}",
        f"  local J = {_zeros(6 * n)}",
        f"  local dR = {_zeros(9)}",
        f"  local dp = {_zeros(3)}",
        *_locals(_zeros(6), "r", "rho"),
        f"  local st = {_zeros(n)}",
        "  local it = 0",
        *_locals("0.0", "size", "prev", "tot", "err", "status"),
        "  while status == 0.0:",
        "    F = lc_chain(lc_A, lc_lin, qc)",
        "    J = lc_twists(F, lc_rev, lc_pitch)",
    ]


def _attempt_residual(n: int, learned: bool) -> list[str]:
    """The residual r of one Newton step: log of the pose error, less J ρ(q) when there is a learned term."""
    last = 12 * n
    # dR = Rt Rmᵀ, dp = pt − dR pm
    dR = [" + ".join(f"Rt[{3 * a + k}] * F[{last + 4 * b + k}]" for k in range(3)) for a in range(3) for b in range(3)]
    lines = ["    dR = [" + ", ".join(dR) + "]"]
    dp = [
        f"pt[{a}] - (" + " + ".join(f"dR[{3 * a + k}] * F[{last + 4 * k + 3}]" for k in range(3)) + ")"
        for a in range(3)
    ]
    lines.append("    dp = [" + ", ".join(dp) + "]")
    lines.append("    r = lc_log(dR, dp)")
    if learned:
        lines.append("    rho = lc_rho(qc, F)")
        dy = [" + ".join(f"J[{6 * a + k}] * rho[{k}]" for k in range(6)) for a in range(6)]
        lines.append("    r = [" + ", ".join(f"r[{a}] - ({dy[a]})" for a in range(6)) + "]")
    return lines


def _attempt_error_and_solve(robot: CalibratedRobot) -> tuple[str, str]:
    """(the residual size expression, the step's solve statement): square J solved directly, fewer joints in least
    squares."""
    n = robot.n
    if n >= 6:
        # the residual in the length-scaled metric (L1, so that a NaN anywhere makes every test below false)
        scale = 1.0 / float(robot.length_scale)
        err = " + ".join(f"lc_abs(r[{a}])" + (f" * {_num(scale)}" if a < 3 else "") for a in range(6))
        return err, "      st = lc_solve(J, r)"
    # least squares: the residual at the solution is not zero, its projection is the step (checked below)
    L = float(robot.length_scale)
    w = [1.0 / L**2] * 3 + [1.0] * 3
    JtJ = [
        " + ".join(f"{_num(w[a])} * J[{a * n + i}] * J[{a * n + k}]" for a in range(6))
        for i in range(n)
        for k in range(n)
    ]
    Jtr = [" + ".join(f"{_num(w[a])} * J[{a * n + i}] * r[{a}]" for a in range(6)) for i in range(n)]
    return "0.0", "      st = lc_solve([" + ", ".join(JtJ) + "], [" + ", ".join(Jtr) + "])"


def _attempt_step(n: int, err: str, solve: str, iterations: int) -> list[str]:
    """The rest of the Newton loop: the convergence test, the step and correct()'s verdict on it."""
    return [
        f"    err = {err}",
        f"    if it > 0 and prev < {_num(CONVERGED_STEP)} and err < {_num(RESIDUAL_TOL)}:",
        "      status = 1.0",
        f"    elif it >= {int(iterations)}:",
        "      status = -2.0",
        "    end",
        # a converged q_cmd still takes the step at hand (r and J are computed; the solve is cheap next to them):
        # in double precision it takes the answer from within CONVERGED_STEP² to rounding of correct()'s
        "    if status >= 0.0:",
        solve,
        "      size = lc_amax(st)",
        "      tot = " + " + ".join(f"lc_abs(st[{j}])" for j in range(n)),
        # correct()'s Gauss-Newton verdict (solve.verdict): a first step above GN_MAX_STEP, a later one above half
        # the previous, or one that is not finite fails; below CONVERGED_STEP a step is rounding, not divergence
        f"      if not (size <= {_num(GN_MAX_STEP)} and tot <= {_num(n * GN_MAX_STEP)}):",
        "        status = -3.0",
        f"      elif it > 0 and size > 0.5 * prev and size >= {_num(CONVERGED_STEP)}:",
        "        status = -3.0",
        "      else:",
        f"        qc = [{', '.join(f'qc[{j}] + st[{j}]' for j in range(n))}]",
        "        prev = size",
        "        it = it + 1",
        "      end",
        "    end",
        "  end",
    ]


def _attempt_verdict(n: int, max_correction: float) -> list[str]:
    """After the loop: refuse a correction above max_correction (and, six joints, one rounding could move), return."""
    lines = [
        "  if status > 0.0:",
        f"    st = [{', '.join(f'qc[{j}] - q[{j}]' for j in range(n))}]",
        f"    if not (lc_amax(st) <= {_num(max_correction)}):",
        "      status = -1.0",
        "    end",
        "  end",
    ]
    if n >= 6:
        # The returned q_cmd differs from correct()'s root by J_s⁻¹ δr (plus the last step squared, negligible),
        # δr being the rounding in the residual the last step solved for, so a small step and residual bound the
        # joint error only together with ‖J_s⁻¹‖∞ (J_s: the length-scaled J). Near the elbow ‖J_s⁻¹‖∞ reaches 10³
        # while |δr|∞ reaches ~4 ε in float32 (ε = 2⁻²³): 1e-4 rad off with step and residual below 1e-5. Refuse where
        # ‖J_s⁻¹‖∞ · RESIDUAL_ROUNDING · ε could exceed AGREEMENT; ε is measured at run time (float32 on a
        # controller: ‖J_s⁻¹‖∞ ≤ 210, every configuration of scaled condition ≤ 100 passes; float64: ~never).
        lines += [
            "  if status > 0.0:",
            f"    if not (lc_inv_norm(J) * {_num(RESIDUAL_ROUNDING)} * lc_eps() <= {_num(AGREEMENT)}):",
            "      status = -4.0",
            "    end",
            "  end",
        ]
    return [*lines, f"  return [{', '.join(f'qc[{j}]' for j in range(n))}, status]", "end"]


def _amax_function(n: int) -> list[str]:
    return [
        "def lc_amax(v):",
        "  local out = 0.0",
        "  local j = 0",
        f"  while j < {n}:",
        "    if lc_abs(v[j]) > out:",
        "      out = lc_abs(v[j])",
        "    end",
        "    j = j + 1",
        "  end",
        "  return out",
        "end",
    ]


def _inv_norm_function(n: int, length_scale: float) -> list[str]:
    w = [length_scale] * 3 + [1.0] * (n - 3)
    return [
        "# ‖J_s⁻¹‖∞ of the length-scaled J_s = diag(1/L, 1/L, 1/L, 1, 1, 1) J: the largest row sum of",
        "# |J⁻¹ diag(L, L, L, 1, 1, 1)|, column by column (J x = L e_k for a translation, e_k for a rotation)",
        "def lc_inv_norm(J):",
        f"  local w = {_list(w)}",
        *_locals(_zeros(n), "e", "c", "s"),
        "  local k = 0",
        f"  while k < {n}:",
        f"    e = {_zeros(n)}",
        "    e[k] = w[k]",
        "    c = lc_solve(J, e)",
        f"    s = [{', '.join(f's[{j}] + lc_abs(c[{j}])' for j in range(n))}]",
        "    k = k + 1",
        "  end",
        "  return lc_amax(s)",
        "end",
    ]


def _eps_function() -> list[str]:
    return [
        "# the arithmetic's machine epsilon (2^-23 on a controller computing in float32, 2^-52 in float64)",
        "def lc_eps():",
        "  sync()",
        "  local u = 1.0",
        "  while 1.0 + 0.5 * u > 1.0:",
        "    u = 0.5 * u",
        "  end",
        "  return u",
        "end",
    ]


def _correct_refusals(n: int, iterations: int, max_correction: float) -> list[str]:
    """The rest of function_name(q) after :func:`_correct_head`: lc_attempt, and popup + halt for every status but
    converged."""
    reasons = [
        (-3.5, "labcal: too near a singular configuration for the controller's float precision, no command for q = "),
        (-2.5, "labcal: Newton steps diverge (near a singular configuration), no command for q = "),
        (-1.5, f"labcal: no convergence in {int(iterations)} Newton steps, no command for q = "),
        (None, f"labcal: correction larger than {max_correction:g} rad, no command for q = "),
    ]
    lines = [
        "  local out = lc_attempt(q)",
        f"  if out[{n}] < 0.5:",
        f'    textmsg("{_text("labcal: no command, status ")}", out[{n}])',
    ]
    for k, (below, message) in enumerate(reasons):
        test = "else" if below is None else f"{'elif' if k else 'if'} out[{n}] < {_num(below)}"
        lines += [f"    {test}:", f'      popup(str_cat("{_text(message)}", q), error=True, blocking=True)']
    lines += [
        "    end",
        "    halt",
        "  end",
        f"  return [{', '.join(f'out[{j}]' for j in range(n))}]",
        "end",
    ]
    return lines


def _header(robot: CalibratedRobot, method: str, provenance: dict | None, usage: str) -> list[str]:
    name = _text(robot.nominal.name or "robot")
    head = [
        f"# labcal compensator for {name} - method {_text(robot.method)}, script: {_text(method)}",
        f"# nominal robot sha256 {model_hash(robot.nominal)}",
    ]
    if robot.measurement_tool is not None:
        X = robot.measurement_tool
        pose6 = [*X[:3, 3], *se3.log_so3(X[:3, :3])]
        head += [
            "# robot and tool apart: the model ends at tool0 (the flange); the calibration's measurement tool in tool0 "
            "(x y z m, rotation vector rad; not corrected, not part of the robot): " + " ".join(_num(v) for v in pose6),
            "# TCP: the q_cmd returned is the same for every TCP (the controller's active get_tcp_offset() included)",
        ]
    head += [f"# {_text(k)}: {_text(v)}" for k, v in sorted((provenance or {}).items(), key=lambda kv: str(kv[0]))]
    head += [usage, "# generated by labcal.export.urscript; do not edit (the numbers are the calibration)"]
    return head


# Characters written as themselves into a URScript comment or string literal: printable ASCII without the quote,
# the backslash (a string escape in some readers), the percent sign (the escape below) and '#' (a comment).
_PLAIN = frozenset(chr(c) for c in range(0x20, 0x7F)) - set("\"\\%#'")


def _text(value) -> str:
    """Any value as text that stays inside one URScript comment or string literal: runs of whitespace become one
    space, and every character outside :data:`_PLAIN` is written as the %XX escapes of its UTF-8 bytes (readable,
    reversible, and free of quotes, backslashes and line breaks of any kind).

    >>> _text('ur10\\nmovej([0, 0], a=3)\\n#"x"')
    'ur10 movej([0, 0], a=3) %23%22x%22'
    """
    flat = re.sub(r"\s+", " ", str(value))
    return "".join(ch if ch in _PLAIN else "".join(f"%{b:02X}" for b in ch.encode("utf-8")) for ch in flat)


def urscript_text(
    robot: CalibratedRobot,
    *,
    method: str = "newton",
    iterations: int = ITERATIONS,
    function_name: str = "labcal_correct",
    provenance: dict | None = None,
    statements_per_sync: int = STATEMENTS_PER_SYNC,
    max_correction: float = MAX_CORRECTION,
) -> str:
    """The function file: constants and ``function_name(q)`` for a Script node (see the module docstring)."""
    _check_exportable(robot, method, iterations, function_name, max_correction)
    consts, funcs = _definitions(robot, method, iterations, function_name, _chunk(statements_per_sync), max_correction)
    usage = (
        f"# usage: a Script node in file mode under BeforeStart loads this once; then q_cmd = {function_name}(q)   "
        f"(q: {robot.n} joint angles in rad, the pose you want the nominal model of)"
    )
    return "\n".join(_header(robot, method, provenance, usage) + consts + funcs) + "\n"


def urscript_program_text(
    robot: CalibratedRobot,
    *,
    method: str = "newton",
    iterations: int = ITERATIONS,
    function_name: str = "labcal_correct",
    provenance: dict | None = None,
    statements_per_sync: int = STATEMENTS_PER_SYNC,
    max_correction: float = MAX_CORRECTION,
    program_name: str = "labcal_program",
    body: list[str] | None = None,
    self_test: bool = True,
) -> str:
    """The ``def`` program for the script port: definitions, a self test, then ``body`` (lines, unindented).

    The self test corrects the export's first golden configurations and halts with a popup when the controller's
    q_cmd differs from the Python runtime's by more than :data:`FLOAT32_BOUND` (a wrong file, or a controller that
    computes differently from what this export assumes).
    """
    _check_exportable(robot, method, iterations, function_name, max_correction)
    if not _IDENTIFIER.fullmatch(program_name):
        raise ValueError(f"program name {program_name!r} is not an ASCII identifier")
    consts, funcs = _definitions(robot, method, iterations, function_name, _chunk(statements_per_sync), max_correction)
    usage = f"# usage: send this file to the controller's script port (30002); it runs {program_name}()"
    lines = [f"def {program_name}():", *("  " + line for line in consts + funcs)]
    if self_test:
        golden = self_test_configurations(robot)
        near = near_singular_self_test(robot, golden, max_correction)
        q = np.concatenate([golden, near])
        bounds = [FLOAT32_BOUND] * len(golden) + [AGREEMENT] * len(near)
        expected = robot.correct(q, method=method)
        n = robot.n
        lines += [
            "  # self test: the Python runtime's q_cmd at a few configurations (the last near the wrist and elbow",
            "  # singularities), within the float32 bound (near the singularities: the agreement bound)",
            f"  lc_tq = {_list(q)}",
            f"  lc_tx = {_list(expected)}",
            f"  lc_tb = {_list(bounds)}",
            f"  lc_tin = {_zeros(n)}",
            f"  lc_tout = {_zeros(n)}",
            "  lc_ti = 0",
            "  lc_tj = 0",
            f"  while lc_ti < {len(q)}:",
            "    lc_tin = [" + ", ".join(f"lc_tq[lc_ti * {n} + {j}]" for j in range(n)) + "]",
            f"    lc_tout = {function_name}(lc_tin)",
            "    lc_tj = 0",
            f"    while lc_tj < {n}:",
            f"      if not (lc_abs(lc_tout[lc_tj] - lc_tx[lc_ti * {n} + lc_tj]) <= lc_tb[lc_ti]):",
            '        popup(str_cat("labcal: self test failed (this controller does not reproduce the export) at q = ", '
            "lc_tin), error=True, blocking=True)",
            "        halt",
            "      end",
            "      lc_tj = lc_tj + 1",
            "    end",
            "    lc_ti = lc_ti + 1",
            "  end",
            '  textmsg("labcal: compensator self test passed")',
        ]
    lines += ["  " + line for line in body or []]
    lines.append("end")
    return "\n".join(_header(robot, method, provenance, usage) + lines) + "\n"


def self_test_configurations(robot: CalibratedRobot, count: int = SELF_TEST_COUNT) -> np.ndarray:
    """(count, n) well-conditioned configurations where the script must answer: the compensator's golden
    configurations, or for a robot with a validity region the best-conditioned of samples of it inside the joint
    ranges (the golden ones span the joint ranges, where the script stops outside the region)."""
    region = robot.validity
    if region is None:
        return golden_configurations(robot)[:count]
    cand = region.sample(64 * count, np.random.default_rng(0))
    cand = cand[_passes(robot, cand)]
    J = robot.model.equivalent_jacobian(cand, length_scale=robot.length_scale)
    return cand[np.argsort(scaled_condition(J, robot.length_scale), kind="stable")[:count]]


def near_singular_self_test(robot: CalibratedRobot, golden: np.ndarray, max_correction: float) -> np.ndarray:
    """(k, n) configurations of the program's self test near a UR arm's singularities (none unless six joints).

    For the wrist (q5) and then the elbow (q3): a golden configuration with that joint moved to ±0.05 rad (else ±0.1,
    ±0.2: the first of :data:`SELF_TEST_OFFSETS` that qualifies), inside its range, where the plain Gauss-Newton
    steps of ``correct()`` converge (no damped fallback) to a correction within half of ``max_correction``: a
    configuration the script must return, so that a controller which refuses it or computes it differently fails
    the self test.
    """
    if robot.n != 6:
        return np.zeros((0, robot.n))
    out = []
    values = [sign * v for v in SELF_TEST_OFFSETS for sign in (1.0, -1.0)]
    for joint in (4, 2):
        q = np.tile(golden, (len(values), 1))
        q[:, joint] = np.repeat(values, len(golden))
        q = q[_passes(robot, q)]  # where the script answers
        full = robot.correct(q)
        undamped = robot.correct(q, iterations=ITERATIONS, damped_iterations=0)
        ok = (np.max(np.abs(full - undamped), axis=1) < 1e-9) & (np.max(np.abs(full - q), axis=1) <= max_correction / 2)
        # and one the script's precision check accepts in float32, with a factor 2 to spare (its J is float32)
        ok &= _inv_norm(robot, full) * RESIDUAL_ROUNDING * FLOAT32_EPS <= AGREEMENT / 2
        out.append(q[ok][:1])  # the first that qualifies, if any
    return np.concatenate(out)


def _passes(robot: CalibratedRobot, q: np.ndarray) -> np.ndarray:
    """(k,) whether (k, n) configurations pass the script's range and region checks in float32 for sure: inside
    its ranges by another margin, and inside its radius by another D (its own rounding, :func:`_script_radius2`)."""
    lo, hi = _script_ranges(robot, margins=2)
    ok = np.all((lo <= q) & (q <= hi), axis=1)
    if (region := robot.validity) is None:
        return ok
    r2, slack = _script_radius2(region)
    return ok & (region.distance(q) <= np.sqrt(r2) - 2 * slack)


def _inv_norm(robot: CalibratedRobot, q: np.ndarray) -> np.ndarray:
    """(k,) ‖J_s⁻¹‖∞ at (k, 6) configurations, as ``lc_inv_norm`` computes it (J_s: the length-scaled Jacobian)."""
    J = robot.model.equivalent_jacobian(q)
    w = np.array([float(robot.length_scale)] * 3 + [1.0] * 3)
    with np.errstate(all="ignore"):  # a NaN fails the caller's test as inf does
        return np.abs(np.linalg.inv(J) * w).sum(axis=2).max(axis=1)  # J⁻¹ diag(L, L, L, 1, 1, 1) = J_s⁻¹
