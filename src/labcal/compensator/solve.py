"""The compensator's one solver: Gauss-Newton with a damped (Levenberg-Marquardt) fallback, over a residual function.

:func:`solve` finds q with ``r(q) = 0`` (or ``|W r(q)|`` least, for fewer than six joints) for a batch of rows at
once, given a function that returns the residual r (m, 6) and the joint twists J (m, 6, n) at m configurations:

- **Gauss-Newton** first, from q0, with the full step ``J⁻¹ r`` (least squares in the metric W for n < 6; for
  a redundant arm, n > 6, the step to the least total change ``|q − q0|`` of the linearised problem, so q − q0
  has no self-motion: :func:`gauss_newton_step`). A row stops when its estimated distance to the solution,
  ``|step| ρ / (1 − ρ)`` with ρ the ratio of its last two steps (linear convergence), is below ``tol``, or when a
  step is below :data:`NOISE_FLOOR` (rounding: a tol below it cannot be reached). A row *fails* when its steps
  stop contracting (a step more than half the previous one), are not finite, or exceed :data:`GN_MAX_STEP`: a
  (near-)singular configuration. For n = 6, after a step below :data:`REUSE_BELOW` the next one reuses J: the
  residual is asked for r alone (``jacobian=False``) and may skip J, which moved by less than its own
  approximation error and is much of a residual's cost (the simplified Newton method; its zero is still r = 0,
  whereas a least-squares step's zero, and a redundant arm's least change, move with J). A J the residual returns
  anyway is not used, so that one configuration steps with the inverse of J it kept: a product, where a solve
  costs numpy's wrapper around one small LAPACK call.
- The failed rows then start over from q0 in **damped** mode: steps ``(JᵀJ + λ μ I)⁻¹ Jᵀ r`` in the length-scaled
  metric W (μ the mean of JᵀJ's diagonal), clipped to :data:`DAMPED_MAX_STEP`, kept only where they do not raise
  ``|W r|``. λ follows the gain ratio ϱ of a kept step (actual over predicted fall of ``|W r|²``): it is multiplied
  by ``max(1/3, 1 − (2ϱ − 1)³)``, and by 2, 4, 8 … after refused steps in a row (Nielsen's rule, which wastes
  fewer evaluations than tenfold jumps). A row stops when its last step (kept or refused) was below ``tol`` or λ
  passed 1e6 (no step helps), and, once it has taken half of ``damped_iterations``, when its last 4 steps did not
  halve its cost: a row on its way to an exact solution (whose cost falls by orders of magnitude per step near
  the end) finishes, while one settling into a least-squares minimum with a residual left, where the cost hardly
  moves any more, stops. All stop after ``damped_iterations`` steps. So near a singularity the answer is never
  worse than q0, and a call's worst case is bounded. For a redundant arm each damped step is the least one of its
  own linear model (the ``λ μ |s|²`` term), not of the total change, so a damped row (near a singularity, or
  beyond ``max_correction``) may move along the self-motion: there the best reachable pose uses it (removing that
  part of such an answer raises its pose error), and the pose is not reached exactly anyway.

Both modes are one loop each over the same residual function, so a single configuration (k = 1) takes exactly the
path a batch takes. This is the definition: :mod:`labcal.compensator.kernel` takes the same steps for one
configuration in compiled code (tested against this module with a batch of one).

Example (six "joints" whose twists are the unit twists, so r = target − q)::

    >>> target = np.array([[0.1, -0.2, 0.3, 0.0, 0.0, 0.0]])
    >>> def residual(q, rows, jacobian=True):
    ...     J = np.broadcast_to(np.eye(6), (len(rows), 6, 6)).copy()
    ...     return target[rows] - q, J
    >>> solve(residual, np.zeros((1, 6))).round(12) + 0.0
    array([[ 0.1, -0.2,  0.3,  0. ,  0. ,  0. ]])
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

GN_MAX_STEP = 0.3  # rad: a full Gauss-Newton step this large means a (near-)singular configuration
REUSE_BELOW = 1e-4  # rad: after a step this small J has moved by less than its approximation error
# rad: a step this small that does not contract is rounding (J⁻¹ amplifies the residual's last bits), not a
# singularity: the row has converged as far as floating point allows, whatever tol asked for
NOISE_FLOOR = 1e-12
DAMPED_MAX_STEP = 0.02  # rad per damped step: corrections are milliradians, so larger steps mean a singularity
LAMBDA_START, LAMBDA_MIN, LAMBDA_GIVE_UP = 1e-6, 1e-12, 1e6
DAMPED_BUDGET = 24  # damped steps per call at most, by default
# rad: the largest |q_cmd − q| a fitted compensator's correction returns (``solve(max_correction=…)``), the URScript's
# refusal bound (export.urscript.MAX_CORRECTION). Calibration corrections are milliradians; a Gauss-Newton answer
# beyond it is an ill-conditioned configuration (q5 ≈ 0, an elbow stretched) turning the wrist to fix micro-radians
# of orientation, so that row is solved again in the damped mode confined to this box: the best compromise within it,
# never worse than q (issue 27).
MAX_CORRECTION = 0.1
STALL_WINDOW, STALL_FALL = 4, 0.5  # after half its budget a row stops when 4 steps did not halve its cost
_ONES6 = np.ones(6)

#: residual(q (m, n), rows (m,) indices into the batch, jacobian=True) → (r (m, 6), J (m, 6, n)); with
#: ``jacobian=False`` J may be None (the solver reuses its last). The first evaluation is always at q0 for every
#: row, with J (a residual may have prepared that one).
Residual = Callable[..., tuple[np.ndarray, np.ndarray | None]]


def gauss_newton_step(
    r: np.ndarray, J: np.ndarray, weights: np.ndarray | None, change: np.ndarray | None = None
) -> np.ndarray:
    """(m, 6) residuals, (m, 6, n) Jacobians → (m, n) full steps: J⁻¹ r (n = 6), least squares in diag(weights)
    (n < 6), or for n > 6 the step to the minimum-norm *total* change: with ``change`` (m, n) the change made so far
    (q − q0), ``Jᵀ (J Jᵀ)⁻¹ (r + J change) − change`` (without it, change = 0: ``Jᵀ (J Jᵀ)⁻¹ r``). NaN rows where J
    is singular.

    Why the total: a redundant arm reaches the pose along a whole self-motion manifold, and the correction must
    be its point nearest q0 (the elbow the user commanded stays where it was). Minimum-norm steps from wherever the
    iteration stands add up to a change whose self-motion part grows with the square of the correction (each
    step's row space is that of a different J); this step solves the linearised problem for the total change
    afresh at every iterate, so the fixed point has r = 0 and q − q0 in the row space of J there (no self-motion),
    the first-order condition of ``min |q − q0|`` on the manifold.

    Example (one row, J = [I₆ | e₁]: joints 1 and 7 move the same way)::

        >>> J = np.hstack([np.eye(6), np.eye(6)[:, :1]])[None]
        >>> r = np.array([[0.2, 0, 0, 0, 0, 0]])
        >>> gauss_newton_step(r, J, None).round(12).tolist()           # half of it on each of joints 1 and 7
        [[0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1]]
        >>> change = np.array([[0.2, 0, 0, 0, 0, 0, 0.0]])             # the pose reached, by joint 1 alone:
        >>> gauss_newton_step(np.zeros((1, 6)), J, None, change).round(12).tolist()  # share it out (self-motion)
        [[-0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1]]
    """
    n = J.shape[2]
    if weights is not None:
        r, J = r * weights, J * weights[:, None]
    try:
        if n == 6:
            if len(J) == 1:  # numpy's stacked solve costs more per call than the 2-D one (a control loop's case)
                return np.linalg.solve(J[0], r[0])[None]
            return np.linalg.solve(J, r[:, :, None])[:, :, 0]
        Jt = J.transpose(0, 2, 1)
        if n > 6:
            if change is None:
                return (Jt @ np.linalg.solve(J @ Jt, r[:, :, None]))[:, :, 0]
            target = r + (J @ change[:, :, None])[:, :, 0]  # the linearised pose change from q0 still to be made
            return (Jt @ np.linalg.solve(J @ Jt, target[:, :, None]))[:, :, 0] - change
        return np.linalg.solve(Jt @ J, Jt @ r[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        if len(J) == 1:
            return np.full((1, n), np.nan)
    # numpy's stacked solve refuses the whole stack for one singular matrix: row by row, only those rows fail
    return np.concatenate(
        [
            gauss_newton_step(r[i : i + 1], J[i : i + 1], None, None if change is None else change[i : i + 1])
            for i in range(len(J))
        ]
    )


def damped_step(r: np.ndarray, J: np.ndarray, lam: np.ndarray | float) -> np.ndarray:
    """(m, 6) weighted residuals, (m, 6, n) weighted Jacobians, (m,) λ (a float for m = 1) → (m, n) clipped
    Levenberg-Marquardt steps."""
    n = J.shape[2]
    if len(J) == 1:  # one row (a control loop's call): the 2-D products and solve cost less per call
        J1 = J[0]
        lam1 = lam if isinstance(lam, float) else float(np.ravel(lam)[0])
        # mean of JᵀJ's diagonal: trace(JᵀJ) is the sum of J's squares
        step = np.linalg.solve(J1.T @ J1 + (lam1 * float(np.vdot(J1, J1)) / n) * np.eye(n), J1.T @ r[0])
        return np.minimum(np.maximum(step, -DAMPED_MAX_STEP), DAMPED_MAX_STEP)[None]
    JtJ = np.einsum("kai,kaj->kij", J, J)
    mean_diag = (np.trace(JtJ, axis1=1, axis2=2) / n)[:, None, None]
    rhs = np.einsum("kai,ka->ki", J, r)[..., None]
    step = np.linalg.solve(JtJ + (np.asarray(lam)[:, None, None] * mean_diag) * np.eye(n), rhs)[..., 0]
    return np.minimum(np.maximum(step, -DAMPED_MAX_STEP), DAMPED_MAX_STEP)


def solve(
    residual: Residual,
    q0: np.ndarray,
    *,
    iterations: int = 10,
    tol: float = 1e-11,
    weights: np.ndarray | None = None,
    damped_iterations: int | None = None,
    max_correction: float | None = None,
) -> np.ndarray:
    """(k, n) start q0 → (k, n) solutions of ``residual(q) = 0`` (module docstring: the two modes).

    weights: (6,) the metric W of the damped mode, and of Gauss-Newton's least squares for n < 6. iterations:
    Gauss-Newton steps per row (at least 1); damped_iterations: damped steps (default :data:`DAMPED_BUDGET`).
    max_correction: a bound on ``max |q − q0|`` (e.g. :data:`MAX_CORRECTION`): a Gauss-Newton answer beyond it is
    solved again in the damped mode, whose steps stay within it (None: no bound).
    """
    n = q0.shape[1]
    w = _ONES6 if weights is None else np.asarray(weights, dtype=float)
    rows = _Rows(q0, tol)
    # A step with an older J still heads for r = 0; a least-squares step's zero moves with J, and so does a
    # redundant arm's least total change (its self-motion is J's null space at the answer): n = 6 only
    reuse = n == 6
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):  # a singular J gives a NaN step
        for i in range(max(iterations, 1)):
            q, active = rows.active()
            fresh = not (reuse and rows.settled())
            r, J = residual(q, active, fresh)
            J = rows.jacobians(J if fresh else None)  # the last one kept once settled, even if the residual has one
            if i == 0:  # every row's, at q0: where a failed row's damped mode starts (_Rows writes into its J later)
                at_q0 = r, J.copy()
            if not rows.advance(rows.step(r, J, w if n < 6 else None)):
                break
        # Rows still contracting after the iteration budget keep their Gauss-Newton result; failed rows start over.
        out, failed = rows.out, np.flatnonzero(rows.bad)
        budget = DAMPED_BUDGET if damped_iterations is None else int(damped_iterations)
        if max_correction is not None:
            far = np.setdiff1d(np.flatnonzero(~(np.abs(out - q0).max(axis=1) <= max_correction)), failed)
            if far.size:
                # A Gauss-Newton answer beyond the box: the damped mode starts from it clipped into the box (the
                # best compromise is usually near it) when that is better than q0, else from q0 with the failed rows.
                lo, hi = q0[far] - max_correction, q0[far] + max_correction
                clipped = np.minimum(np.maximum(out[far], lo), hi)
                r, J = residual(clipped, far)
                assert J is not None  # called with jacobian=True (Residual's contract)
                cost_clip = np.sum((r * w) ** 2, axis=1)
                cost_q0 = np.sum((at_q0[0][far] * w) ** 2, axis=1)
                better = cost_clip < cost_q0
                if better.any():
                    rows_b = far[better]
                    out[rows_b] = _damped(
                        residual, q0[rows_b], rows_b, w, budget, tol, (r[better], J[better]), max_correction,
                        clipped[better],
                    )  # fmt: skip
                failed = np.union1d(failed, far[~better])
        if failed.size:
            start = (at_q0[0][failed], at_q0[1][failed])
            out[failed] = _damped(residual, q0[failed], failed, w, budget, tol, start, max_correction)
    return out


class _Rows:
    """The Gauss-Newton state of a batch: every row's q, last step size, last Jacobian and fate, advanced by
    :func:`verdict`."""

    def __init__(self, q0: np.ndarray, tol: float) -> None:
        self.out, self.tol, self.q0 = q0.copy(), tol, q0
        self.prev: np.ndarray | None = None  # (k,) last step sizes, after the first step
        self.J: np.ndarray | None = None  # (k, 6, n) the Jacobians of the last full steps
        self.bad = np.zeros(len(q0), dtype=bool)
        self.rows = np.arange(len(q0))  # rows still iterating

    def _everyone(self) -> bool:
        return self.rows.size == len(self.out)  # the common case: no gathers and scatters

    def active(self) -> tuple[np.ndarray, np.ndarray]:
        """(q of the rows still iterating, their indices)."""
        return (self.out if self._everyone() else self.out[self.rows]), self.rows

    def settled(self) -> bool:
        """True when every row still iterating took a last step below REUSE_BELOW (its J can be reused)."""
        return self.prev is not None and bool((self.prev[self.rows] < REUSE_BELOW).all())

    def jacobians(self, new: np.ndarray | None) -> np.ndarray:
        """Keep the Jacobians ``new`` of the rows still iterating and return them; for None, the ones kept."""
        if new is None:
            assert self.J is not None  # the first call (at q0) always brings new Jacobians
            return self.J if self._everyone() else self.J[self.rows]
        if self._everyone():
            self.J = new
        else:
            assert self.J is not None  # rows thin out only after a first full step
            self.J[self.rows] = new
        return new

    def step(self, r: np.ndarray, J: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
        """The steps of the rows still iterating, from r and the kept J (n > 6: towards the least total change)."""
        if J.shape[2] <= 6:
            return gauss_newton_step(r, J, weights)
        q, rows = self.active()
        return gauss_newton_step(r, J, weights, q - (self.q0 if self._everyone() else self.q0[rows]))

    def advance(self, step: np.ndarray) -> bool:
        """Judge and apply one step of the rows still iterating; False when none is left."""
        rows, everyone = self.rows, self._everyone()
        size = np.abs(step).max(axis=1)
        prev = None if self.prev is None else (self.prev if everyone else self.prev[rows])
        bad, done = verdict(size, prev, self.tol)
        if bad.any():
            step[bad] = 0.0
            self.bad[rows[bad]] = True
        if everyone:
            self.out += step
            self.prev = size
        else:
            self.out[rows] += step
            assert self.prev is not None  # rows thin out only after a first full step
            self.prev[rows] = size
        stop = bad | done
        if stop.any():
            self.rows = rows[~stop]
        return self.rows.size > 0


def verdict(size: np.ndarray, prev: np.ndarray | None, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton rule, (failed, converged) as (m,) bool arrays, after steps of max-norm ``size`` (m,) that
    followed ones of max-norm ``prev`` (None: the first step). See the module docstring (the URScript exporter and
    :mod:`labcal.compensator._jit` write it for one row in their languages)."""
    if prev is None:  # no previous step: ρ = 1/2, so the estimated distance is the step itself
        return ~(size <= GN_MAX_STEP), size < tol
    ratio = np.minimum(size / np.maximum(prev, 1e-300), 0.5)
    floor = size < NOISE_FLOOR
    bad = ~(size <= np.minimum(GN_MAX_STEP, 0.5 * prev)) & ~floor
    return bad, (size * ratio / (1 - ratio) < tol) | (size < 1e-3 * tol) | floor


def _damped(
    residual: Residual,
    q0: np.ndarray,
    rows: np.ndarray,
    w: np.ndarray,
    budget: int,
    tol: float,
    start=None,
    bound: float | None = None,
    q_init: np.ndarray | None = None,
):
    """The damped mode from q0 (m, n) for the batch rows ``rows``: steps kept only where they do not raise |W r|.

    A row stops when its last step (kept or refused) was below tol (the cost cannot fall further in floating
    point), when λ passed LAMBDA_GIVE_UP, or, from half its budget on, when its last STALL_WINDOW steps did not
    lower its cost by STALL_FALL; all stop after the budget. A row keeps its best q. start: (r, J) at q0 when the
    caller has them (the Gauss-Newton mode's first evaluation), else evaluated here. bound: steps stay within
    ``|q − q0| ≤ bound`` (None: no bound). q_init: where the steps start (within the bound; default q0), with
    ``start`` evaluated there.
    """
    box = math.inf if bound is None else bound
    out = (q0 if q_init is None else q_init).copy()
    r, J = residual(out, rows) if start is None else start
    err, jac = r * w, J * w[:, None]
    cost = np.sum(err * err, axis=1)
    lam, grow = np.full(len(out), LAMBDA_START), np.full(len(out), 2.0)
    going = np.ones(len(out), dtype=bool)
    history = np.empty((budget + 1, len(out)))  # every row's best cost after each step
    history[0] = cost
    for i in range(1, budget + 1):
        step = damped_step(err, jac, lam)
        if bound is not None:
            step = np.clip(step, q0 - box - out, q0 + box - out)
        step[~going] = 0.0
        model = err - np.einsum("kai,ki->ka", jac, step)  # the linear model's residual after the step
        predicted = cost - np.sum(model * model, axis=1)
        cand = out + step
        r, J = residual(cand, rows)
        err_c, jac_c = r * w, J * w[:, None]
        cost_c = np.sum(err_c * err_c, axis=1)
        ok = (cost_c <= cost) & going
        gain = np.where(predicted > 0, (cost - cost_c) / np.where(predicted > 0, predicted, 1.0), 0.0)
        out[ok], err[ok], jac[ok], cost[ok] = cand[ok], err_c[ok], jac_c[ok], cost_c[ok]
        lam, grow = (
            np.where(ok, np.maximum(lam * np.maximum(1 / 3, 1 - (2 * gain - 1) ** 3), LAMBDA_MIN), lam * grow),
            np.where(ok, 2.0, 2 * grow),
        )
        history[i] = cost
        going &= ~((np.abs(step).max(axis=1) < tol) | (lam > LAMBDA_GIVE_UP))
        if 2 * i >= budget:
            going &= ~(cost > STALL_FALL * history[max(i - STALL_WINDOW, 0)])
        if not going.any():
            break
    return out
