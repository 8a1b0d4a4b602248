"""The paper's calibration method: a neural network learns the joint motion errors of an equivalent robot.

Eq. (16-22): a feed-forward network N(q, w) — inputs the nominal joint values (or features of them), tanh hidden
layer(s), N = max(n, 6) linear outputs — approximates the joint motion errors δρ(q) (n actuated + 6 − n virtual
joints; a redundant arm's n joints, δρ without self-motion, :mod:`labcal.calibration.equivalent`) of the equivalent
robot built on a *base* robot. Training data are the eq. (21) observations
``δρ_k = (P_k J_ρ,k)^+ δp_k`` of :mod:`labcal.calibration.equivalent`, after the condition filter.

Training, in torch (imported lazily), float64 and single-threaded so that the same data and seed give
bit-identical weights:

- inputs and outputs are standardised on the (kept) training rows; the loss is eq. (21) in standardised output
  units, ``E = Σ_k w_k ||(N(q_k) − δρ_k) / s||² / Σ_k w_k`` (w_k the condition weights, s the output scales), plus
  ``weight_decay · ||W||²`` over the weight matrices (not the biases) if asked; ``loss="task"`` uses eq. (20)
  instead, ``||δp_k − P_k J_ρ,k N(q_k)||²`` in metres (divided by the training RMS of δp);
- trainers: ``"lm"`` Levenberg-Marquardt on the full weight vector (Jacobian of the residuals by
  ``torch.func.jacfwd``, damped normal equations, Marquardt's μ × 10 / ÷ 10 rule), ``"adam"`` (full batch) and
  ``"gd"``, plain gradient descent (eq. 22);
- early stopping: after every iteration the loss on the early-stopping rows is evaluated — the caller's "val"
  rows if it gave any, else an inner split of the training rows (``stop_fraction``), so rows that later judge the
  network never steer it; the weights with the lowest early-stopping loss are kept, and training stops after
  ``patience`` iterations without improvement (the paper's Fig. 4);
- ``restarts`` random initialisations (normal, scaled by 1/√fan-in, the output layer by a further 0.01; seeded
  by (seed, restart) through numpy), the one with the lowest validation loss wins.

**Which loss.** The paper trains on eq. (21), the joint-space loss, and it is the default here to reproduce the
paper. Measured on the simulator it is the weaker choice: the δρ observations are noisy in very unequal amounts
along different joint-error directions (far more along the ill-conditioned ones), and an unweighted joint-space
fit spends its capacity on that noise. Eq. (20), ``loss="task"``, weights every direction by what it does to the
measured points — for isotropic tracker noise, the maximum-likelihood fit — and was much better in every
scenario measured. Example (fanuc-m1000ia, ``ErrorSpec.default()``, base = the local-POE fit, 200 train / 200
val, held-out mean position error 0.21 mm before the network): joint loss 0.33 mm (worse), task loss 0.12 mm.

**Fewer than three targets.** A row that sees one target, or two, or a line of them, fixes only 3 or 5 of the six
joint-error directions: its eq. (21) "observation" is the minimum-norm solution, the part of δρ the points see
(:mod:`labcal.calibration.equivalent`). A joint-space fit would learn that projection as if it were δρ, so when any
row is such a row the network is trained on eq. (20) — the points themselves — whatever ``loss`` says, and
``info["loss_note"]`` says so (measured on one-target UR10 data, the point loss was clearly better than the joint
loss on the minimum-norm observations; numbers in the issue-15 report). A redundant arm's rows (n > 6) with three
targets are minimum-norm too, but they lose only the self-motion, which moves no point (J_ρ δρ is the full
δρ's): the joint loss stays defined there.

Default size: one hidden layer of round(√(N f)) tanh nodes for f network inputs and N outputs — the paper's √(6n)
rule of thumb (the geometric mean of inputs and outputs), identical to it for the paper's ``features=("q",)`` on a
robot with at most six joints.

Example (slow-ish, so not a doctest)::

    robot, info = fit_ann(obs.with_splits(0.5, seed=0), CalibratedRobot(nominal, nominal), seed=0)
    robot.correct(q)                      # eq. (23-24) by default through a Newton solve
    info["observations"]["dropped"], info["stopped_at"], info["val_loss"]
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TypedDict, final

import numpy as np

from labcal import features as feature_lib
from labcal.calibration.equivalent import (
    MAX_CONDITION,
    SOFT_CONDITION,
    DroppedCause,
    FilterSummary,
    JointErrorObservations,
    equivalent_joints,
    joint_error_observations,
    learned_robot,
)
from labcal.calibration.observations import ObservationError, Observations
from labcal.compensator import CalibratedRobot, Network, input_features

TRAINERS = ("lm", "adam", "gd")
LOSSES = ("joint", "task")
# (max_iter, patience, learning rate) per trainer. LM converges in tens of iterations (the paper's Fig. 4: 11);
# first-order methods need thousands of full-batch steps.
_DEFAULTS = {"lm": (200, 6, None), "adam": (5000, 200, 1e-2), "gd": (20000, 500, 0.05)}
_MU0, _MU_MAX = 1e-3, 1e10
STOP_FRACTION = 0.25  # share of the training rows held back for early stopping when no "val" rows are given
MAX_ROWS = 2000  # training rows fed to the network at most (seeded subsample); cost is linear in them
MIN_TRAIN_ROWS = 8  # after the condition filter; fewer cannot constrain even the bias terms sensibly
MIN_STOP_ROWS = 3
_OUTPUT_INIT = 1e-2  # relative scale of the initial output-layer weights

ProgressFn = Callable[[int, int, float, float], None]


@final  # final: `"no_network" in info` tells NoNetworkInfo from it for the type checker
class ANNInfo(TypedDict):
    """:func:`fit_ann`'s info (saved with a fit)."""

    method: str
    observations: FilterSummary
    dropped_causes: list[DroppedCause]
    early_stopping: str
    subsampled_from: int
    max_condition: float | None
    soft_condition: float | None
    train_rows: int
    val_rows: int
    features: list[str]
    inputs: int
    hidden: list[int]
    weights: int
    trainer: str
    loss: str
    loss_note: str | None
    weight_decay: float
    max_iter: int
    patience: int
    lr: float | None
    seed: int
    restarts: int
    restart_val_losses: list[float]
    chosen_restart: int
    curve: dict[str, list[float]]
    stopped_at: int
    iterations: int
    train_loss: float
    val_loss: float
    export_max_abs_diff: float
    warnings: list[str]


def default_hidden(n_inputs: int, n_outputs: int = 6) -> int:
    """The paper's rule of thumb: round(√(outputs · inputs)) hidden nodes (at least 1); outputs: the equivalent
    robot's joint motion errors, max(n, 6)."""
    return max(1, round(math.sqrt(n_outputs * n_inputs)))


def _layer_shapes(n_in: int, hidden: tuple[int, ...], n_out: int = 6) -> list[tuple[int, int]]:
    sizes = [n_in, *hidden, n_out]
    return [(sizes[i + 1], sizes[i]) for i in range(len(sizes) - 1)]


def _init_params(shapes, seed: int, restart: int) -> np.ndarray:
    rng = np.random.default_rng([seed, restart])
    parts = []
    for idx, (o, i) in enumerate(shapes):
        # The output layer starts small, so the first network predicts ≈ the training mean and early stopping
        # falls back to that instead of to a random function (measured: much better held-out errors with 50
        # noisy configurations).
        scale = (_OUTPUT_INIT if idx == len(shapes) - 1 else 1.0) / math.sqrt(i)
        parts.append(rng.normal(0.0, scale, size=o * i))
        parts.append(rng.normal(0.0, scale, size=o))
    return np.concatenate(parts)


def _unflatten(theta, shapes):
    """Flat parameter vector → [(W (out, in), b (out,)), …] (views; numpy or torch)."""
    out, off = [], 0
    for o, i in shapes:
        W = theta[off : off + o * i].reshape(o, i)
        off += o * i
        out.append((W, theta[off : off + o]))
        off += o
    return out


def _weight_mask(shapes) -> np.ndarray:
    """True at the weight matrices' entries of a flat parameter vector (:func:`_unflatten`), False at the biases."""
    return np.concatenate([np.arange(o * i + o) < o * i for o, i in shapes])


def _forward(theta, x, shapes):
    """Torch forward pass on standardised inputs x (k, f) → standardised outputs (k, N). Same op order as Network."""
    import torch

    h = x
    layers = _unflatten(theta, shapes)
    for idx, (W, b) in enumerate(layers):
        h = h @ W.T + b
        if idx < len(layers) - 1:
            h = torch.tanh(h)
    return h


@contextmanager
def _deterministic_torch(seed: int):
    """Single thread and a seeded global RNG; restores the caller's thread count and RNG state.

    Single-threaded float64 CPU kernels give the same bits on every run, which is what bit-identical fits need.
    (``torch.use_deterministic_algorithms`` is not switched on: it changes nothing for these CPU operations and
    its first call imports torch's compiler stack, about 3 s — measured, issue 13.7.)
    """
    import torch

    threads = torch.get_num_threads()
    rng_state = torch.get_rng_state()
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    try:
        yield torch
    finally:
        torch.set_num_threads(threads)
        torch.set_rng_state(rng_state)


class _Problem:
    """The least-squares problem of one split: residual vector r(θ) with loss ||r||² (weight decay separate)."""

    def __init__(self, torch, x, y, w, A=None, b=None):
        self.torch = torch
        self.x = torch.as_tensor(x, dtype=torch.float64)
        self.y = None if y is None else torch.as_tensor(y, dtype=torch.float64)
        wn = np.asarray(w, float) / np.sum(w)
        self.sqrt_w = torch.as_tensor(np.sqrt(wn), dtype=torch.float64)[:, None]
        self.A = None if A is None else torch.as_tensor(A, dtype=torch.float64)
        self.b = None if b is None else torch.as_tensor(b, dtype=torch.float64)

    def residual(self, theta, shapes):
        out = _forward(theta, self.x, shapes)
        if self.A is None:
            r = out - self.y
        else:
            r = self.b - self.torch.einsum("kab,kb->ka", self.A, out)
        return (r * self.sqrt_w).reshape(-1)

    def jacobian(self, theta, shapes):
        """Jacobian of :meth:`residual` for one hidden layer, written out (d tanh = 1 − tanh²).

        torch.func.jacfwd pushes every weight's tangent through the network separately; with ~100 weights and
        thousands of rows that was ~90 % of a hybrid fit (issue 13.7). Checked against jacfwd in the tests.
        """
        torch = self.torch
        (W1, b1), (W2, _) = _unflatten(theta, shapes)
        x = self.x
        k, f = x.shape
        hidden, outs = W1.shape[0], W2.shape[0]
        a = torch.tanh(x @ W1.T + b1)  # (k, H)
        slope = W2[None, :, :] * (1.0 - a * a)[:, None, :]  # (k, N, H): d out / d pre-activation
        # B: d residual / d out per row, (k, m, N) — the weighted identity (eq. 21) or −√w A (eq. 20). The blocks
        # of d residual / d θ are formed from it directly, never the (k, 6, P) Jacobian of the outputs.
        if self.A is None:
            B = torch.diag_embed(self.sqrt_w.expand(k, outs))
        else:
            B = -self.sqrt_w[:, :, None] * self.A
        m = B.shape[1]
        C = torch.bmm(B, slope)  # (k, m, H)
        blocks = [
            (C[:, :, :, None] * x[:, None, None, :]).reshape(k, m, hidden * f),  # W1, row-major
            C,  # b1
            (B[:, :, :, None] * a[:, None, None, :]).reshape(k, m, outs * hidden),  # W2
            B,  # b2
        ]
        return torch.cat(blocks, dim=2).reshape(k * m, -1)


@dataclass(frozen=True)
class _Job:
    """One training problem: layer shapes, the training and early-stopping problems, and the options."""

    shapes: list
    train: _Problem
    val: _Problem
    options: _Settings


def _train_one(torch, job: _Job, theta0: np.ndarray, restart: int):
    """One initialisation. Returns (best θ (np), curve train, curve val, best iteration, iterations run)."""
    shapes, train, val, opts = job.shapes, job.train, job.val, job.options
    wmask = torch.as_tensor(_weight_mask(shapes))
    sqrt_wd = math.sqrt(opts.weight_decay)

    def full_residual(theta):
        r = train.residual(theta, shapes)
        if opts.weight_decay > 0:
            r = torch.cat([r, sqrt_wd * theta[wmask]])
        return r

    def losses(theta):
        with torch.no_grad():
            rt = full_residual(theta)
            rv = val.residual(theta, shapes)
            return float(rt @ rt), float(rv @ rv)

    theta = torch.as_tensor(theta0, dtype=torch.float64).clone()
    tr, va = losses(theta)
    curve_t, curve_v = [tr], [va]
    best_theta, best_val, best_it = theta.clone(), va, 0
    opts.progress(restart, 0, tr, va)
    if opts.trainer == "lm":
        step = _lm_step(torch, job, full_residual, wmask, sqrt_wd, theta.numel())
    else:
        step = _gradient_step(torch, opts, full_residual, theta)
    it = 0
    for it in range(1, opts.max_iter + 1):
        stepped = step(theta)
        if stepped is None:  # no damping lowers the loss: a (local) minimum
            break
        theta = stepped
        tr, va = losses(theta)
        curve_t.append(tr)
        curve_v.append(va)
        opts.progress(restart, it, tr, va)
        if not (math.isfinite(tr) and math.isfinite(va)):
            break
        if va < best_val:
            best_theta, best_val, best_it = theta.clone(), va, it
        elif it - best_it >= opts.patience:
            break
    return best_theta.numpy().copy(), curve_t, curve_v, best_it, it


def _lm_step(torch, job: _Job, full_residual, wmask, sqrt_wd: float, size: int):
    """Levenberg-Marquardt: a function θ → the next θ (the damping μ carried between calls), None when no
    damping lowers the loss."""
    shapes, train, weight_decay = job.shapes, job.train, job.options.weight_decay
    if len(shapes) == 2:  # one hidden layer: the Jacobian in closed form

        def jac(theta):
            J = train.jacobian(theta, shapes)
            if weight_decay > 0:
                J = torch.cat([J, sqrt_wd * torch.eye(theta.numel(), dtype=theta.dtype)[wmask]])
            return J
    else:
        jac = torch.func.jacfwd(full_residual)  # few weights, many residuals: forward mode
    mu = _MU0
    eye = torch.eye(size, dtype=torch.float64)

    def step(theta):
        nonlocal mu
        r = full_residual(theta).detach()
        J = jac(theta).detach()
        g, H = J.T @ r, J.T @ J
        cost = float(r @ r)
        while mu <= _MU_MAX:
            cand = theta + torch.linalg.solve(H + mu * eye, -g)
            with torch.no_grad():
                rc = full_residual(cand)
            if float(rc @ rc) < cost:
                mu = max(mu * 0.1, 1e-15)
                return cand
            mu *= 10.0
        return None

    return step


def _gradient_step(torch, opts: _Settings, full_residual, theta0):
    """Adam or plain gradient descent: a function θ → the next θ (the optimiser's state carried between calls)."""
    param = torch.nn.Parameter(theta0.clone())
    opt = torch.optim.Adam([param], lr=opts.lr) if opts.trainer == "adam" else torch.optim.SGD([param], lr=opts.lr)

    def step(_theta):
        opt.zero_grad()
        r = full_residual(param)
        (r @ r).backward()
        opt.step()
        return param.detach().clone()

    return step


def _standardise(a: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    mean = np.average(a, axis=0, weights=weights)
    scale = np.sqrt(np.average((a - mean) ** 2, axis=0, weights=weights))
    # A constant input (a joint held still, a gravity component fixed by the first axis) carries no information.
    scale = np.where(scale > 1e-12 * np.maximum(1.0, np.abs(mean)), scale, 1.0)
    return mean, scale


def _check_hidden(hidden, n_in: int, n_out: int = 6) -> tuple[int, ...]:
    if hidden is None:
        return (default_hidden(n_in, n_out),)
    layers = (hidden,) if isinstance(hidden, int | np.integer) else tuple(hidden)
    if not layers or any(not isinstance(h, int | np.integer) or h < 1 for h in layers):
        raise ValueError(f"hidden must be a positive int or a non-empty sequence of them, got {hidden!r}")
    return tuple(int(h) for h in layers)


class NetworkDataError(ObservationError):
    """Too few usable rows for the network after the condition filter; ``causes`` as
    :meth:`~labcal.calibration.equivalent.JointErrorObservations.causes` returns them."""

    def __init__(self, message: str, causes: list[DroppedCause]) -> None:
        super().__init__(message)
        self.causes = causes


def _inner_split(kept: np.ndarray, units: np.ndarray, fraction: float, seed: int) -> dict[str, np.ndarray]:
    """Early-stopping rows drawn from the training rows: whole units, about ``fraction`` of the rows, seeded."""
    target = max(MIN_STOP_ROWS, round(fraction * kept.size))
    val = np.zeros(kept.size, bool)
    for u in np.random.default_rng([seed, 15485863]).permutation(np.unique(units)):
        if val.sum() >= target or (~val).sum() - np.sum(units == u) < 1:
            break
        val |= units == u
    return {"train": kept[~val], "val": kept[val]}


def _check_rows(rows: dict, jeo, fit_rows: np.ndarray, causes: list[DroppedCause]) -> None:
    n_tr, n_va = rows["train"].size, rows["val"].size
    if n_tr >= MIN_TRAIN_ROWS and n_va >= MIN_STOP_ROWS:
        return
    dropped = int(np.sum(~jeo.kept))
    if dropped:
        why = "; ".join(f"{c['cause']}: {c['rows']} rows" for c in causes)
        why = f"{dropped} dropped by the condition filter — {why}); measure more configurations away from them"
    else:
        why = "none dropped by the condition filter); measure more distinct configurations"
    raise NetworkDataError(
        f"too few rows for the network: {n_tr} training and {n_va} early-stopping rows remain, it needs at least "
        f"{MIN_TRAIN_ROWS} and {MIN_STOP_ROWS} ({int(fit_rows.sum())} training rows given, {why}",
        causes,
    )


def check_features(features) -> tuple[str, ...]:
    """The network input names as a tuple, refused unless the feature registry (:mod:`labcal.features`, which the
    runtime and the exporters use) knows every one of them: whatever the compensator computes (``q``, ``sincos``,
    ``gravity``, ``harmonics:H`` …) trains here, and nothing it cannot compute is ever trained."""
    names = (features,) if isinstance(features, str) else tuple(features)
    unknown = [name for name in names if not isinstance(name, str) or not feature_lib.is_feature(name)]
    if not names or unknown:
        raise ValueError(
            f"features must be a non-empty sequence of network inputs ({', '.join(feature_lib.NAMES)}), "
            f"got {features!r}" + (f": unknown {', '.join(map(repr, unknown))}" if unknown else "")
        )
    return names


def fit_ann(
    obs: Observations,
    base: CalibratedRobot,
    *,
    seed: int = 0,
    hidden: int | tuple[int, ...] | None = None,
    features: tuple[str, ...] = ("q",),
    trainer: str = "lm",
    restarts: int = 3,
    max_condition: float | None = MAX_CONDITION,
    soft_condition: float | None = SOFT_CONDITION,
    weight_decay: float = 0.0,
    loss: str = "joint",
    max_iter: int | None = None,
    patience: int | None = None,
    lr: float | None = None,
    progress: ProgressFn | None = None,
    stop_fraction: float = STOP_FRACTION,
    max_rows: int | None = MAX_ROWS,
) -> tuple[CalibratedRobot, ANNInfo]:
    """Fit the joint motion errors of ``base``'s equivalent robot with a neural network (paper eq. 16-22).

    obs: the network is trained on the "train" and unassigned rows; "test" rows are ignored. Early stopping
    uses the "val" rows when there are any (the caller chose them), else an inner split of the training rows:
    ``stop_fraction`` of them (whole :meth:`~Observations.units`, seeded), so that rows a caller uses to judge
    the network (cross-validation, a hold-out) never steer its training. ``max_rows``: at most this many
    (seeded random) training rows feed the network — its cost is linear in them and a network of ~100 weights
    gains nothing measurable beyond a few thousand (None: all). Rows the condition filter drops are reported
    with their cause (``info["dropped_causes"]``); when fewer than :data:`MIN_TRAIN_ROWS` training or
    :data:`MIN_STOP_ROWS` early-stopping rows remain, :class:`NetworkDataError` names the cause.
    base: a network-free robot — the nominal
    one for the paper's method, an identified local-POE robot for the hybrid. hidden: nodes per hidden layer (an
    int or a tuple for several layers; default round(√(N f)) for f inputs and N = max(n, 6) outputs). features:
    network inputs, see :func:`labcal.compensator.input_features`. trainer: "lm" | "adam" | "gd". max_condition /
    soft_condition: the condition filter of :func:`labcal.calibration.equivalent.joint_error_observations`. loss:
    "joint" (eq. 21) or "task" (eq. 20). max_iter / patience / lr: trainer defaults if None. progress: called as
    progress(restart, iteration, train_loss, val_loss).

    Returns the calibrated robot (model = base.model, method "ann") and an info dict: observation filter summary
    (dropped count and reasons, condition statistics), hidden, features, trainer, per-restart validation losses,
    the chosen restart, its training curve and stopping point, train/val loss, and warnings.
    """
    obs.check_robot(base.n)
    features = check_features(features)
    # Refuse unknown trainers and losses and impossible counts; fill in the trainer's defaults.
    if trainer not in TRAINERS:
        raise ValueError(f"trainer must be one of {TRAINERS}, got {trainer!r}")
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    if int(restarts) < 1:
        raise ValueError(f"restarts must be >= 1, got {restarts}")
    if not weight_decay >= 0.0:
        raise ValueError(f"weight_decay must be >= 0, got {weight_decay}")
    d_iter, d_pat, d_lr = _DEFAULTS[trainer]
    max_iter = d_iter if max_iter is None else int(max_iter)
    patience = d_pat if patience is None else int(patience)
    lr = d_lr if lr is None else float(lr)
    if max_iter < 1 or patience < 1:
        raise ValueError(f"max_iter and patience must be >= 1, got {max_iter}, {patience}")
    if not 0.0 < stop_fraction < 1.0:
        raise ValueError(f"stop_fraction must be in (0, 1), got {stop_fraction}")
    if max_rows is not None and int(max_rows) < MIN_TRAIN_ROWS:
        raise ValueError(f"max_rows must be >= {MIN_TRAIN_ROWS} or None, got {max_rows}")
    settings = _Settings(
        trainer, weight_decay, max_iter, patience, lr, progress or (lambda *_: None),
        features, hidden, loss, int(restarts), seed, max_condition, soft_condition, stop_fraction, max_rows,
    )  # fmt: skip
    return _fit_network(obs, base, settings)


@dataclass(frozen=True)
class _Settings:
    """fit_ann's checked options, the trainer's defaults resolved."""

    trainer: str
    weight_decay: float
    max_iter: int
    patience: int
    lr: float | None
    progress: ProgressFn
    features: tuple[str, ...]
    hidden: int | tuple[int, ...] | None
    loss: str
    restarts: int
    seed: int
    max_condition: float | None
    soft_condition: float | None
    stop_fraction: float
    max_rows: int | None


def _fit_network(obs: Observations, base: CalibratedRobot, opts: _Settings) -> tuple[CalibratedRobot, ANNInfo]:
    """fit_ann after its options are checked: observations, rows, training, the exported network, its info."""
    used = obs.subset(np.isin(obs.split, ["train", "", "val"]))
    if used.k == 0:
        raise NetworkDataError(f"no training rows: all {obs.k} rows are labelled 'test'", [])
    jeo = joint_error_observations(used, base, max_condition=opts.max_condition, soft_condition=opts.soft_condition)
    loss, loss_note = _loss_for(jeo, used.k, opts.loss)
    causes = jeo.causes(base) if not jeo.kept.all() else []
    rows, stopping, n_subsampled = _training_rows(used, jeo, causes, opts.seed, opts.stop_fraction, opts.max_rows)
    warnings: list[str] = []
    if obs.frame == "tracker" and np.allclose(base.T_tracker_base, np.eye(4)):
        warnings.append("tracker-frame data with an identity T_tracker_base: register the base first (hybrid)")
    data = _Scaled.of(jeo, input_features(jeo.q, opts.features, base.model), rows["train"])
    n_out = equivalent_joints(base.n)
    shapes = _layer_shapes(data.x.shape[1], _check_hidden(opts.hidden, data.x.shape[1], n_out), n_out)
    n_params = sum(o * i + o for o, i in shapes)
    if n_params > n_out * rows["train"].size:
        warnings.append(
            f"the network has {n_params} weights for {n_out * rows['train'].size} training numbers: expect over-fitting"
        )
    runs, val_losses, best = _train_restarts(jeo, data, rows, shapes, loss, opts)
    theta, curve_t, curve_v, stopped_at, iterations = runs[best]
    network = _network(theta, shapes, opts.features, data)
    export_diff = _export_difference(network, jeo.q[rows["train"]], base)
    info: ANNInfo = {
        "method": "ann",
        "observations": jeo.summary(),
        "dropped_causes": causes,
        "early_stopping": stopping,
        "subsampled_from": n_subsampled,
        "max_condition": opts.max_condition,
        "soft_condition": opts.soft_condition,
        "train_rows": int(rows["train"].size),
        "val_rows": int(rows["val"].size),
        "features": list(opts.features),
        "inputs": int(data.x.shape[1]),
        "hidden": list(network.hidden),
        "weights": n_params,
        "trainer": opts.trainer,
        "loss": loss,
        "loss_note": loss_note,
        "weight_decay": opts.weight_decay,
        "max_iter": opts.max_iter,
        "patience": opts.patience,
        "lr": opts.lr,
        "seed": opts.seed,
        "restarts": opts.restarts,
        "restart_val_losses": val_losses,
        "chosen_restart": best,
        "curve": {"train": curve_t, "val": curve_v},
        "stopped_at": int(stopped_at),
        "iterations": int(iterations),
        "train_loss": float(curve_t[stopped_at]),
        "val_loss": float(curve_v[stopped_at]),
        "export_max_abs_diff": export_diff,
        "warnings": warnings,
    }
    return learned_robot(base, network, used.q, "ann"), info


def _loss_for(jeo: JointErrorObservations, k: int, loss: str) -> tuple[str, str | None]:
    """The loss these observations define, and a note when it is not the one asked for."""
    if not (jeo.partial and loss == "joint") or jeo.rank is None:  # partial: the rank is known
        return loss, None
    # Where a row's points see fewer than six joint-error directions its eq. (21) "observation" is only the
    # part of δρ they see (minimum norm), not δρ: a joint-space fit would learn that projection. Eq. (20)
    # compares the network with the points themselves, so it is the one loss these data define.
    return "task", (
        f"{int(np.sum(jeo.rank < 6))} of {k} rows see fewer than six joint-error directions (fewer than "
        "three non-collinear targets): trained on the point loss of eq. (20) instead of eq. (21)"
    )


def _training_rows(
    used: Observations,
    jeo: JointErrorObservations,
    causes: list[DroppedCause],
    seed: int,
    stop_fraction: float,
    max_rows: int | None,
) -> tuple[dict[str, np.ndarray], str, int]:
    """The training and early-stopping rows (the caller's "val" rows, else an inner split), at most ``max_rows``
    training rows (seeded); how early stopping is done; the training row count before subsampling (0: none)."""
    fit_rows = np.isin(used.split, ["train", ""])
    if np.any(used.split == "val"):
        stopping = "the 'val' rows"
        rows = {"train": np.flatnonzero(fit_rows & jeo.kept), "val": np.flatnonzero((used.split == "val") & jeo.kept)}
    else:
        stopping = f"an inner split ({stop_fraction:.0%} of the training rows)"
        kept = np.flatnonzero(fit_rows & jeo.kept)
        rows = _inner_split(kept, used.units()[kept], stop_fraction, seed)
    _check_rows(rows, jeo, fit_rows, causes)
    n_subsampled = 0
    if max_rows is not None and rows["train"].size > int(max_rows):
        n_subsampled = int(rows["train"].size)
        pick = np.random.default_rng([seed, 104729]).choice(rows["train"].size, int(max_rows), replace=False)
        rows["train"] = np.sort(rows["train"][pick])
        cap = max(int(max_rows) // 2, MIN_STOP_ROWS)
        if rows["val"].size > cap:
            pick = np.random.default_rng([seed, 130363]).choice(rows["val"].size, cap, replace=False)
            rows["val"] = np.sort(rows["val"][pick])
    return rows, stopping, n_subsampled


@dataclass(frozen=True)
class _Scaled:
    """The network's standardised inputs x and joint-error targets y (rows the filter dropped: y = 0), and the
    means and scales that undo it, taken from the training rows."""

    x: np.ndarray
    y: np.ndarray
    in_mean: np.ndarray
    in_scale: np.ndarray
    out_mean: np.ndarray
    out_scale: np.ndarray

    @classmethod
    def of(cls, jeo: JointErrorObservations, feats: np.ndarray, tr: np.ndarray) -> _Scaled:
        in_mean, in_scale = _standardise(feats[tr])
        out_mean, out_scale = _standardise(jeo.delta_rho[tr], jeo.weight[tr])  # noisy rows count less
        y = np.zeros_like(jeo.delta_rho)
        ok = np.all(np.isfinite(jeo.delta_rho), axis=1)
        y[ok] = (jeo.delta_rho[ok] - out_mean) / out_scale
        return cls((feats - in_mean) / in_scale, y, in_mean, in_scale, out_mean, out_scale)


def _problem(torch, jeo: JointErrorObservations, data: _Scaled, idx: np.ndarray, tr: np.ndarray, loss: str):
    """The training problem of rows idx: eq. (21) on the standardised joint errors, or eq. (20) on the points."""
    if loss == "joint":
        return _Problem(torch, data.x[idx], data.y[idx], jeo.weight[idx])
    # eq. (20) on standardised outputs: δp − PJ (s ⊙ N + m), scaled to unit RMS on the training rows.
    if jeo.seen is None:
        unit = math.sqrt(np.mean(jeo.delta_p[tr] ** 2)) or 1.0
    else:  # over the coordinates the rows measured (unseen targets are zero rows)
        unit = math.sqrt(np.sum(jeo.delta_p[tr] ** 2) / (3.0 * np.sum(jeo.seen[tr]))) or 1.0
    A = jeo.PJ[idx] * data.out_scale / unit
    b = (jeo.delta_p[idx] - jeo.PJ[idx] @ data.out_mean) / unit
    return _Problem(torch, data.x[idx], None, jeo.weight[idx], A, b)


def _train_restarts(
    jeo: JointErrorObservations,
    data: _Scaled,
    rows: dict[str, np.ndarray],
    shapes,
    loss: str,
    options: _Settings,
) -> tuple[list, list[float], int]:
    """Every restart trained; their validation losses and the best one. Raises if every restart diverged."""
    tr, va, seed = rows["train"], rows["val"], options.seed
    runs = []
    with _deterministic_torch(seed) as torch:
        job = _Job(shapes, _problem(torch, jeo, data, tr, tr, loss), _problem(torch, jeo, data, va, tr, loss), options)
        for r in range(options.restarts):
            runs.append(_train_one(torch, job, _init_params(shapes, seed, r), r))
    val_losses = [float(run[2][run[3]]) for run in runs]
    finite = [v if math.isfinite(v) else math.inf for v in val_losses]
    best = int(np.argmin(finite))
    if not math.isfinite(finite[best]):
        raise RuntimeError("every training restart diverged (non-finite loss); lower lr or use trainer='lm'")
    return runs, val_losses, best


def _network(theta: np.ndarray, shapes, features: tuple[str, ...], data: _Scaled) -> Network:
    """The trained weights as the exported network."""
    layers = _unflatten(theta, shapes)
    return Network(
        features=features,
        weights=tuple(np.array(W) for W, _ in layers),
        biases=tuple(np.array(b) for _, b in layers),
        in_mean=data.in_mean,
        in_scale=data.in_scale,
        out_mean=data.out_mean,
        out_scale=data.out_scale,
    )


def _export_difference(network: Network, q: np.ndarray, base: CalibratedRobot) -> float:
    """The largest difference between the exported network and the torch model on q; raises beyond round-off:
    the export must be the trained model, not an approximation of it."""
    check = torch_predict(network, q, base.model)
    export_diff = float(np.max(np.abs(check - network(q, base.model))))
    if not export_diff <= 1e-12 * max(1.0, float(np.max(np.abs(check)))):
        raise RuntimeError(f"exported network differs from the torch model by {export_diff:.3g}")
    return export_diff


def torch_predict(network: Network, q: np.ndarray, model) -> np.ndarray:
    """(k, n) joints → (k, N) δρ computed by the torch forward pass of the training code from a Network's
    weights (float64). Used to verify that an export reproduces the trained model."""
    feats = input_features(q, network.features, model)
    x = (feats - network.in_mean) / network.in_scale
    shapes = [W.shape for W in network.weights]
    theta = np.concatenate(
        [np.concatenate([W.ravel(), b]) for W, b in zip(network.weights, network.biases, strict=True)]
    )
    with _deterministic_torch(0) as torch:
        out = _forward(torch.as_tensor(theta), torch.as_tensor(x), shapes).numpy()
    return out * network.out_scale + network.out_mean
