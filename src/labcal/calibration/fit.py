"""One entry point for every calibration method: split the data, fit, measure.

Methods (:data:`METHODS`):

- ``nominal``: the registered nominal (only T_tracker_base estimated, for tracker-frame data) — the baseline;
- ``local-poe``: model-based identification of the frame errors (:mod:`labcal.calibration.local_poe`);
- ``ann``: the paper's method — equivalent robot + network on the registered nominal
  (:mod:`labcal.calibration.ann`);
- ``hybrid``: local POE, then the network on the identified robot, kept only if it helps on validation;
- ``auto``: fits local-poe, ann and hybrid and keeps the lowest validation mean position error; a tie (within
  1e-12 m) goes to the simpler model, in the order local-poe, hybrid, ann (hybrid without its network *is*
  local POE; the paper's ANN has the least structure).

ann and hybrid learn the six joint motion errors of the equivalent robot, so they need a robot with at most 6 joints;
for a redundant arm (n > 6) they are refused and auto fits local-poe alone.

Unassigned rows are split into train / val with ``obs.with_splits(val_fraction, seed)``; rows already labelled
keep their label, and "test" rows are never fitted on. Same data and seed ⇒ bit-identical parameters.

Example::

    >>> from labcal.robots import load
    >>> from labcal.simulation import ErrorSpec, simulate
    >>> spec = load("scara4"); actual = simulate(spec, ErrorSpec.paper(), seed=1)
    >>> rng = np.random.default_rng(0)
    >>> q = rng.uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(40, 4))
    >>> targets = np.array([[0.05, 0, 0], [0, 0.05, 0], [-0.04, -0.03, 0.01]])
    >>> obs = Observations(q, actual.measure(q, targets, rng), targets)
    >>> result = fit(obs, spec.model, "local-poe")
    >>> result.n_train, result.n_val, result.metrics["val"]["after"]["pos_mean"] < 1e-4
    (20, 20, True)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from labcal.calibration.hybrid import fit_hybrid, validation_error
from labcal.calibration.local_poe import fit_local_poe, register
from labcal.calibration.metrics import prediction_errors, split_table, summarize
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics.poe import LocalPOEModel

METHODS = ("nominal", "local-poe", "ann", "hybrid", "auto")
_SIMPLICITY = ("local-poe", "hybrid", "ann")  # tie-break order for auto
_TIE = 1e-12  # m


@dataclass(frozen=True, eq=False)
class FitResult:
    """The outcome of :func:`fit`.

    method: what was asked; chosen: what was fitted (differs only for "auto"); robot: the calibrated robot;
    before: the registered nominal; metrics: ``split_table(before, robot, obs)`` (per split, before/after);
    info: method diagnostics (for auto: ``candidates`` {method: val error m} and each candidate's info);
    seed; n_train / n_val / n_test: row counts; fit_seconds: wall time per fitted method; obs: the split data.
    """

    method: str
    chosen: str
    robot: CalibratedRobot
    before: CalibratedRobot
    metrics: dict
    info: dict
    seed: int
    n_train: int
    n_val: int
    n_test: int
    fit_seconds: dict = field(default_factory=dict)
    obs: Observations | None = None


def _split_table(before: CalibratedRobot, after: CalibratedRobot, obs: Observations) -> dict:
    """metrics.split_table, skipping absent splits before selecting them.

    Observations.subset of zero rows raises at the moment (reshape of an empty array), so a data set without
    test rows would fail in split_table; once that is fixed this reduces to split_table.
    """
    if all(np.any(obs.split == s) for s in ("train", "val", "test")):
        return split_table(before, after, obs)
    table = {}
    for name in ("train", "val", "test", "all"):
        mask = np.ones(obs.k, bool) if name == "all" else obs.split == name
        if not mask.any():
            continue
        part = obs.subset(mask)
        table[name] = {
            "before": summarize(*prediction_errors(before, part)),
            "after": summarize(*prediction_errors(after, part)),
        }
    return table


def _ann(obs, base, seed, options):
    from labcal.calibration.ann import fit_ann  # torch is imported only when a network is fitted

    return fit_ann(obs, base, seed=seed, **options)


def fit(
    obs: Observations,
    nominal: LocalPOEModel,
    method: str = "auto",
    *,
    seed: int = 0,
    val_fraction: float = 0.5,
    progress: Callable[[str], None] | None = None,
    local_poe_options: dict | None = None,
    **options,
) -> FitResult:
    """Fit one method (or choose one with "auto") and measure it against the registered nominal.

    options: keyword options of the method's fitting function — ``fit_local_poe`` for "local-poe", ``fit_ann``
    for "ann", "hybrid" and "auto" (their network stage); ``local_poe_options`` go to the local-POE stage of
    "hybrid" and "auto"; ``stage2`` and ``series_options`` go to the hybrid only (see ``fit_hybrid``).
    progress: optional callable receiving one status line per step.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    obs.check_robot(nominal.n)
    say = progress or (lambda _msg: None)
    obs = obs.with_splits(val_fraction, seed)
    counts = {s: int(np.sum(obs.split == s)) for s in ("train", "val", "test")}
    if counts["train"] == 0:
        raise ValueError("no training rows: every row is labelled val or test")
    if method in ("hybrid", "ann") and nominal.n > 6:
        raise ValueError(
            f"method {method!r} learns the six joint motion errors of the equivalent robot (eq. 12-14), which needs a "
            f"robot with at most 6 joints; {nominal.name!r} has {nominal.n}: use local-poe"
        )
    if method in ("hybrid", "auto", "ann") and counts["val"] == 0:
        raise ValueError(f"method {method!r} needs validation rows: use val_fraction > 0 or label some rows 'val'")
    lp_opts = dict(local_poe_options or {})
    hybrid_opts = {key: options.pop(key) for key in ("stage2", "series_options") if key in options}
    seconds: dict[str, float] = {}

    say("registering the nominal model")
    t0 = time.perf_counter()
    before, reg_info = register(obs, nominal)
    seconds["nominal"] = time.perf_counter() - t0

    def timed(name, fn):
        say(f"fitting {name}")
        t = time.perf_counter()
        out = fn()
        seconds[name] = time.perf_counter() - t
        return out

    info: dict
    if method == "nominal":
        robot, info, chosen = before, {"register": reg_info}, "nominal"
    elif method == "local-poe":
        robot, info = timed("local-poe", lambda: fit_local_poe(obs, nominal, **{**lp_opts, **options}))
        chosen = "local-poe"
    elif method == "ann":
        robot, info = timed("ann", lambda: _ann(obs, before, seed, options))
        chosen = "ann"
    elif method == "hybrid":
        robot, info = timed(
            "hybrid",
            lambda: fit_hybrid(
                obs, nominal, seed=seed, local_poe_options=lp_opts, progress=say, **hybrid_opts, **options
            ),
        )
        chosen = "hybrid"
    else:
        stage1 = timed("local-poe", lambda: fit_local_poe(obs, nominal, **lp_opts))
        cands = {"local-poe": stage1}
        if nominal.n > 6:
            say(f"auto: ann and hybrid need a robot with at most 6 joints ({nominal.name!r} has {nominal.n})")
        else:
            cands["ann"] = timed("ann", lambda: _ann(obs, before, seed, options))
            cands["hybrid"] = timed(
                "hybrid",
                lambda: fit_hybrid(obs, nominal, seed=seed, stage1=stage1, progress=say, **hybrid_opts, **options),
            )
            seconds["hybrid"] += seconds["local-poe"]  # the hybrid's first stage was shared
        errors = {name: validation_error(r, obs) for name, (r, _) in cands.items()}
        best = min(errors.values())
        chosen = next(name for name in _SIMPLICITY if name in errors and errors[name] <= best + _TIE)
        robot = cands[chosen][0]
        info = {"candidates": errors, **{name: i for name, (_, i) in cands.items()}}
        say("auto: validation mean position error " + ", ".join(f"{m} {e * 1e3:.4f} mm" for m, e in errors.items()))
        say(f"auto: chose {chosen}")
    metrics = _split_table(before, robot, obs)
    return FitResult(
        method=method,
        chosen=chosen,
        robot=robot,
        before=before,
        metrics=metrics,
        info=info,
        seed=seed,
        n_train=counts["train"],
        n_val=counts["val"],
        n_test=counts["test"],
        fit_seconds=seconds,
        obs=obs,
    )
