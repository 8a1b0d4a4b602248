"""Markdown reports with PNG plots (matplotlib, headless Agg backend) of the fits stored under a version.

At the top: every fit's blocking warnings (the ones `labcal export` refuses without --force) and notes. For every
fit: its warnings again, what its targets let it claim about orientation (one target point: none; targets on a
line: not the rotation about it; three targets in some poses only: on those poses), its metrics table (train /
val / test, before / after: mean, RMS, p95, max in mm and degrees, and the per-target point error beside the pose
error), the per-target point residuals (table and plot),
the position and orientation error of every configuration before and after (the paper's Fig. 5), the training
curve with the validation-stopping point when the fit trained a network (Fig. 4), the identified local-POE frame
parameters — with ± one standard deviation only where a parameter is identifiable on its own, "—" where it is
not, and the identifiable combinations of the others with their standard deviations — and the evaluations stored
for the fit (``labcal evaluate``). Across fits: histograms of the position error after calibration per method.

When fewer than three non-collinear targets are seen in some pose (split table ``"primary": "points"``), the
per-target point errors are the primary figures: their table comes first and the pose columns are marked as
covering only the poses that fix a pose.

Example::

    from labcal.datasets import SessionStore
    write_session_report(SessionStore("sessions"), "20261122-031500-ur10-3f9a@v1", "report/")
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from labcal.calibration.metrics import observability, point_errors, prediction_errors, split_table
from labcal.calibration.observations import pooled
from labcal.calibration.tool import tool_lines
from labcal.compensator import from_payload
from labcal.datasets.errors import DatasetError
from labcal.kinematics.metric import parameter_weights

# A stored fit's files (labcal.cli.ops.fitting.run_fit writes them): the fitted robot and the registered nominal
# (the "before" of every metric), as compensator payloads.
ROBOT_FILE, BEFORE_FILE = "robot.json", "before.json"


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _fit_data(store, ref: str, fit_id: str, load_obs=None) -> dict:
    """A fit's record, robots and data. load_obs(refs) → Observations (the CLI passes its loader, which converts
    controller joints to model joints); without it the versions are pooled as stored."""
    record = store.load_fit(ref, fit_id)
    meta = record.metadata
    robot, _ = from_payload(json.loads(record.read(ROBOT_FILE)), f"fit {fit_id}")
    before, _ = from_payload(json.loads(record.read(BEFORE_FILE)), f"fit {fit_id}")
    refs = [i["ref"] for i in record.inputs]
    stored = load_obs(refs) if load_obs is not None else pooled([store.load(r) for r in refs])
    split = meta.get("split")
    split = np.array(split, dtype=object) if split and len(split) == stored.k else stored.split
    obs = dataclasses.replace(stored, split=split, group=None)
    return {"fit_id": fit_id, "meta": meta, "robot": robot, "before": before, "obs": obs}


def _owner(info, key):
    """The first dict anywhere in a nested info dict that holds key (the stage that trained a curve)."""
    if isinstance(info, dict):
        if info.get(key) is not None:
            return info
        for value in info.values():
            found = _owner(value, key)
            if found is not None:
                return found
    return None


def _find(info, key):
    """The first value stored under key anywhere in a nested info dict (hybrid/auto nest their stages)."""
    return (_owner(info, key) or {}).get(key)


SPLITS = ("train", "val", "test", "all")
POSE_STATS, POINT_STATS = ("mean", "rms", "p95", "max"), ("mean", "p95", "max")


def split_rows(metrics: dict, length, angle) -> list[tuple]:
    """The rows of a split table's error tables, split × (before, after), as the report and `labcal fit` /
    `labcal evaluate` print them: (the split, on its before row only; the pose count, on the before row only;
    before / after; the position stats, the orientation stats and the point stats as text). ``length`` and ``angle``
    format a value in m and in rad."""
    rows = []
    for split in (s for s in SPLITS if s in metrics):
        for when in ("before", "after"):
            s = metrics[split][when]  # NaN: no pose in these rows (fewer than three targets seen)
            p = (metrics[split].get("points") or {}).get(when) or {}
            lead, n = (split, str(int(s.get("count") or 0))) if when == "before" else ("", "")
            pos, ori = [length(s.get(f"pos_{k}")) for k in POSE_STATS], [angle(s.get(f"ori_{k}")) for k in POSE_STATS]
            rows.append((lead, n, when, pos, ori, [length(p.get(k)) for k in POINT_STATS]))
    return rows


def target_rows(metrics: dict, length) -> list[tuple[str, str, list[list[str]]]]:
    """The per-target point error rows, split × (before, after): (the split, on its before row only; before /
    after; mean, p95, max of every target as text, through ``length``); none when the metrics have no point errors."""
    splits = [s for s in SPLITS if s in metrics and "points" in metrics[s]]
    return [
        (split if when == "before" else "", when,
         [[length(t.get(k)) for k in POINT_STATS] for t in metrics[split]["points"][when].get("per_target") or []])
        for split in splits
        for when in ("before", "after")
    ]  # fmt: skip


def _md_row(cells) -> str:
    return "| " + " | ".join(cells) + " |"


def _md_table(head: list[str], align: str, rows) -> list[str]:
    """A Markdown table: the header (an empty name as ``| |``), the alignment line (``align``: "l" or "r" per column)
    and the rows."""
    header = "".join(f"| {name} " if name else "| " for name in head) + "|"
    return [header, "|" + "".join("---:|" if a == "r" else "---|" for a in align), *map(_md_row, rows)]


def _md_metrics(metrics: dict) -> list[str]:
    cols = [f"pos {s} (mm)" for s in POSE_STATS] + [f"ori {s} (°)" for s in POSE_STATS]
    cols += [f"point {s} (mm)" for s in POINT_STATS]
    rows = split_rows(metrics, _mm, lambda v: _mm(v, 180 / np.pi))
    cells = [[lead, n, when, *pos, *ori, *pts] for lead, n, when, pos, ori, pts in rows]
    return _md_table(["split", "n", "", *cols], "lrl" + "r" * len(cols), cells)


def _save(plt, fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _split_order(obs) -> np.ndarray:
    """Row order for the per-configuration plots: train, then val, then test (stable within each)."""
    return np.argsort([{"train": 0, "val": 1, "test": 2}.get(s, 3) for s in obs.split], kind="stable")


def _plot_per_configuration(plt, data: dict, path: Path) -> None:
    obs = data["obs"]
    order = _split_order(obs)
    p0, o0 = prediction_errors(data["before"], obs)
    p1, o1 = prediction_errors(data["robot"], obs)
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    x = np.arange(obs.k)
    for ax, b, a, unit, scale in (
        (axes[0], p0, p1, "position error (mm)", 1e3),
        (axes[1], o0, o1, "orientation error (°)", 180 / np.pi),
    ):
        ax.plot(x, b[order] * scale, "o-", ms=3, lw=0.8, label="before")
        ax.plot(x, a[order] * scale, "s-", ms=3, lw=0.8, label="after")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
    splits = obs.split[order]
    for s in ("val", "test"):
        idx = np.flatnonzero(splits == s)
        if idx.size:
            for ax in axes:
                ax.axvline(idx[0] - 0.5, color="k", lw=0.6, ls="--")
            axes[0].text(idx[0], axes[0].get_ylim()[1] * 0.95, s, va="top", fontsize=8)
    axes[0].legend()
    axes[1].set_xlabel("configuration (train, then val, then test)")
    axes[0].set_title(f"{data['robot'].method}: error per configuration before/after calibration")
    _save(plt, fig, path)


LOSS_LABELS = {
    # Both losses of labcal.calibration.ann are dimensionless: squared errors divided by a scale of the training rows.
    "joint": "loss, dimensionless: weighted mean of (joint-space error / output scale)² (eq. 21)",
    "task": "loss, dimensionless: weighted mean of (point error / training RMS)² (eq. 20)",
}


def loss_axis_label(loss: str | None) -> str:
    """The y-axis label of a training curve: what the loss measures and its unit, for info["loss"]."""
    return LOSS_LABELS.get(str(loss), "loss, dimensionless (squared error over a scale of the training rows)")


def _plot_curve(plt, curve: dict, stopped_at, path: Path, title: str, loss: str | None = None) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.semilogy(curve["train"], label="training")
    ax.semilogy(curve["val"], label="validation")
    if stopped_at is not None:
        ax.axvline(stopped_at, color="k", ls="--", lw=0.8, label=f"validation stop (iteration {stopped_at})")
    ax.set(xlabel="iteration", title=title)
    ax.set_ylabel(loss_axis_label(loss), fontsize=8)
    ax.legend()
    ax.grid(alpha=0.3)
    _save(plt, fig, path)


def histogram_bins(samples: list[np.ndarray]) -> np.ndarray:
    """Bin edges (mm) for the error histograms: log-spaced over the range of all samples, as many as numpy's "auto"
    rule chooses for the pooled log10 errors.

    Errors before and after calibration differ by orders of magnitude (3 mm vs 0.07 mm), so linear bins sized for
    the before-errors (0.25 mm) put every calibrated method in one bar; on a log axis with at least 8 bins a decade
    methods that differ by a few tens of percent fall in different bins. samples: 1-D arrays of errors in mm
    (non-finite and non-positive values ignored).

    >>> histogram_bins([np.array([0.05, 0.07, 0.09]), np.array([2.0, 3.0, 5.0])])[[0, -1]]
    array([0.05, 5.  ])
    """
    pooled = np.concatenate([np.asarray(x, dtype=float).ravel() for x in samples] or [np.zeros(0)])
    pooled = pooled[np.isfinite(pooled) & (pooled > 0)]
    if pooled.size == 0:
        return np.geomspace(1e-3, 1.0, 11)
    lo, hi = float(pooled.min()), float(pooled.max())
    if hi <= lo * (1 + 1e-9):
        lo, hi = lo / 1.5, hi * 1.5  # one distinct value: a bar around it
    span = (np.log10(lo), np.log10(hi))
    auto = len(np.histogram_bin_edges(np.log10(pooled), bins="auto", range=span)) - 1
    # at least 8 bins a decade: a factor 1.33 per bin, so a method 30 % better than another sits a bin lower
    return np.logspace(*span, max(auto, math.ceil(8 * (span[1] - span[0])), 1) + 1)


def _position_errors_mm(model, obs) -> np.ndarray:
    """Position errors (mm) of the poses that have one (a pose that saw fewer than three targets has none)."""
    e = prediction_errors(model, obs)[0] * 1e3
    return e[np.isfinite(e)]


def _plot_histograms(plt, fits: list[dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    before = _position_errors_mm(fits[0]["before"], fits[0]["obs"])
    after = [_position_errors_mm(data["robot"], data["obs"]) for data in fits]
    bins = histogram_bins([before, *after])
    ax.hist(before, bins=bins, histtype="step", lw=1.5, label="before (registered nominal)")
    for data, e in zip(fits, after, strict=True):
        ax.hist(e, bins=bins, histtype="step", lw=1.2, label=f"{data['robot'].method} ({data['fit_id']})")
    ax.set(xscale="log", xlabel="position error (mm, log scale), every configuration", ylabel="configurations")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    _save(plt, fig, path)


def _mm(v, scale: float = 1e3) -> str:
    return "—" if v is None or not np.isfinite(v) else f"{v * scale:.4f}"


def _md_targets(metrics: dict) -> list[str]:
    """Per-target point error table (mm): split × before/after × target mean / p95 / max."""
    rows = target_rows(metrics, _mm)
    if not rows:
        return []
    head = [f"t{i + 1} {k} (mm)" for i in range(len(rows[1][2])) for k in POINT_STATS]
    return [
        "Per-target point error: distance between each measured target and its predicted position (a targets file "
        "that does not match the data shows here, not in the pose error):",
        "",
        *_md_table(
            ["split", "", *head],
            "ll" + "r" * len(head),
            [[lead, when, *(c for t in per for c in t)] for lead, when, per in rows],
        ),
    ]


def _plot_targets(plt, data: dict, path: Path) -> None:
    """Point error of every target and configuration after calibration (solid) and before (faint)."""
    obs = data["obs"]
    order = _split_order(obs)
    d0 = point_errors(data["before"], obs)[order] * 1e3
    d1 = point_errors(data["robot"], obs)[order] * 1e3
    fig, ax = plt.subplots(figsize=(9, 4))
    x = np.arange(obs.k)
    for i in range(d1.shape[1]):
        (line,) = ax.plot(x, d1[:, i], "o-", ms=3, lw=0.8, label=f"t{i + 1} after")
        ax.plot(x, d0[:, i], ":", lw=0.8, color=line.get_color(), alpha=0.6, label=f"t{i + 1} before")
    ax.set(yscale="log", xlabel="configuration (train, then val, then test)", ylabel="point error (mm)")
    ax.set_title(f"{data['robot'].method}: per-target point error before/after calibration")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=3)
    _save(plt, fig, path)


def observability_lines(obs_info: dict | None, data=None) -> list[str]:
    """What orientation accuracy the fit can and cannot claim, from the fit's stored ``observability`` (15.3), or
    from the data when the fit was stored before it existed (``data``: Observations, or None)."""
    if not obs_info and data is not None:
        obs_info = observability(data)
    if not obs_info:
        return []
    level = obs_info.get("orientation")
    head = {"measured": "measured", "partial": "partly measured", "none": "not measured"}.get(str(level), str(level))
    lines = [
        f"**Orientation accuracy: {head}.** {obs_info.get('claim', '')} ({obs_info.get('targets')} target(s), "
        f"{obs_info.get('geometry')}; {obs_info.get('rows_with_pose')} of {obs_info.get('rows')} poses fix a full "
        "pose.)",
    ]
    words = obs_info.get("unobservable") or []
    if words:
        lines += ["", "Not determined by these data (no accuracy can be claimed for them):", ""]
        lines += [f"- {w}" for w in words]
    return lines


def _primary(metrics: dict) -> str:
    """ "points" when any split says the per-target point errors are the figures to quote, else "pose"."""
    return "points" if any(isinstance(m, dict) and m.get("primary") == "points" for m in metrics.values()) else "pose"


def _warning_lines(meta: dict, fit_id: str, *, heading: bool = True) -> list[str]:
    warnings, who = meta.get("warnings"), f"fit {fit_id}: " if heading else ""
    old = f"- fit {fit_id}: stored before fit warnings were recorded; `labcal export` re-derives them."
    lines = [old] if warnings is None else []
    lines += [f"- **WARNING [{w.get('code')}]** {who}{w.get('message')}" for w in warnings or []]
    return lines + [f"- note: {who}{n}" for n in meta.get("notes") or []]


def _chosen_info(info: dict, chosen: str | None) -> dict:
    """The diagnostics of the model that was kept (auto keeps every candidate's info under its name)."""
    if isinstance(info, dict) and isinstance(info.get("candidates"), dict) and chosen in info:
        return info[chosen] or {}
    return info


IDENTIFIABLE_LEVERAGE = 1e-6  # share of a parameter's unit vector inside the null space below which it is identified


def _covariance(lp: dict, data: dict) -> np.ndarray | None:
    """Parameter covariance (p × p, SI units) of the local-POE identification, recomputed from the fit's rows at the
    identified model (σ² (JᵀJ)⁺ on the identified rank): fits do not store it."""
    from labcal.calibration.local_poe import _residual_and_jacobian, fitting_rows

    try:
        obs, robot = data["obs"], data["robot"]
        estimate_base = obs.frame == "tracker"
        frames = list(range(1 if estimate_base else 0, robot.model.n + 1))
        rows = fitting_rows(obs)
        r, J = _residual_and_jacobian(
            robot.measurement_model,
            robot.T_tracker_base,
            obs.q[rows],
            obs.targets,
            obs.points[rows],
            frames,
            estimate_base,
        )
        L = float(lp.get("length_scale") or robot.length_scale)
        scale = parameter_weights(J.shape[1] // 6, L)
        lam, V = np.linalg.eigh((J * scale).T @ (J * scale))
        rank = int(lp["rank"])
        Vk, lk = V[:, -rank:], lam[-rank:]
        sigma2 = float(r @ r) / max(r.size - rank, 1)
        return sigma2 * (scale[:, None] * (Vk / lk) @ Vk.T * scale[None, :])
    except Exception:  # an optional refinement: without it the combinations show no σ
        return None


def _measurement_tool_lines(lp: dict | None) -> list[str]:
    """Robot and tool apart: the identified measurement tool (± σ) against the robot file's tool, when identified."""
    if lp is None or lp.get("measurement_tool") is None:
        return []
    X = np.asarray(lp["measurement_tool"], dtype=float)
    std = lp.get("measurement_tool_std")
    std = None if std is None else np.array([np.nan if v is None else v for v in std], dtype=float)
    body = tool_lines(X, std)
    return [
        "**Measurement tool** (identified apart from the robot; the robot's model ends at tool0, so a tool change "
        "keeps the calibration):",
        "",
        *[f"    {line}" for line in body],
        "",
    ]


def _parameter_lines(lp: dict | None, data: dict) -> list[str]:
    """The local-POE stage's frame corrections (lp: its diagnostics, None when the fit has none) with σ where
    identifiable, the identifiable combinations of the others and the directions the data do not determine."""
    if lp is None:
        return []
    dz = np.asarray(lp["delta_zeta"], dtype=float)
    std = np.asarray(lp["std"], dtype=float) if lp.get("std") is not None else np.full_like(dz, np.nan)
    labels = list(lp.get("param_labels") or [])
    null = np.asarray(lp.get("null_space") or np.zeros((len(labels), 0)), dtype=float)
    n1 = dz.shape[0]
    estimate_base = bool(labels) and labels[-1].startswith("T_tracker_base")
    frames = list(range(n1 - len(labels) // 6 + (1 if estimate_base else 0), n1)) if labels else list(range(n1))
    identified = np.zeros((n1, 6), bool)
    leverage = scale = Vn = None
    if labels and null.ndim == 2 and null.shape[0] == len(labels):
        scale = parameter_weights(len(labels) // 6, float(lp.get("length_scale") or 1.0))
        Vn = null / scale[:, None]  # back to the orthonormal basis of the scaled problem
        leverage = np.sum(Vn * Vn, axis=1)
        identified[frames] = leverage[: 6 * len(frames)].reshape(-1, 6) < IDENTIFIABLE_LEVERAGE  # base params last
    else:
        identified = np.isfinite(std)
    names = ["vx (mm)", "vy (mm)", "vz (mm)", "ωx (mrad)", "ωy (mrad)", "ωz (mrad)"]
    rank, need = lp.get("rank"), lp.get("expected_rank")
    lines = []
    if rank is not None:
        lines += [
            f"Local POE identified numerical rank **{rank}** (identifiable at most: {need}; {len(labels)} frame "
            f"parameters, so {len(labels) - int(rank)} directions are not identified"
            + (" — **fewer than the model allows: the poses do not excite every direction**" if need and rank < need
               else "")
            + ").",
            "",
        ]  # fmt: skip
    lines += [
        "Identified frame corrections δζ_j = log(A_j,nominal⁻¹ A_j,identified) ± one standard deviation, for "
        "parameters identifiable on their own; **—** marks a parameter that is not identifiable on its own (its "
        "value depends on an arbitrary choice inside the null space; only the combinations listed below are "
        "determined by the data):",
        "",
    ]

    def cell(v: float, sd: float, j: int, i: int) -> str:
        if not np.isfinite(sd) and j not in frames:
            return "in T_tracker_base" if estimate_base else "not estimated"
        return f"{v * 1e3:.4f} ± {sd * 1e3:.4f}" if identified[j, i] and np.isfinite(sd) else "—"

    rows = [
        [f"A{j + 1}" if j < n1 - 1 else f"A{j + 1} (tool)"]
        + [cell(v, sd, j, i) for i, (v, sd) in enumerate(zip(row, srow, strict=True))]
        for j, (row, srow) in enumerate(zip(dz, std, strict=True))
    ]
    lines += _md_table(["frame", *names], "l" + "r" * len(names), rows)
    if leverage is not None:
        lines += ["", *_combination_lines(lp, data, dz, frames, labels, leverage, scale, Vn)]
    dirs = lp.get("null_directions") or []
    if dirs:
        lines += ["", "Directions the data do not determine (largest components):", ""]
        lines += [f"- {d}" for d in dirs]
    return lines


def _combination_lines(lp, data, dz, frames, labels, leverage, scale, null) -> list[str]:
    """The identifiable combinations of the parameters that are not identifiable on their own, with σ (scale: the
    parameter weights, null: the null space in the orthonormal basis of the scaled problem, as _parameter_lines)."""
    S = np.flatnonzero(leverage >= IDENTIFIABLE_LEVERAGE)
    if S.size == 0:
        return ["Every parameter is identifiable on its own."]
    U, sv, _ = np.linalg.svd(null[S], full_matrices=True)
    d = int(np.sum(sv > 1e-9))
    B = U[:, d:].T  # rows: coefficient vectors (scaled coordinates) orthogonal to the null space
    if B.shape[0] == 0:
        return ["No combination of the parameters marked — is determined by the data."]
    import scipy.linalg

    _, _, piv = scipy.linalg.qr(B, pivoting=True)
    pivots = piv[: B.shape[0]]
    C = np.linalg.solve(B[:, pivots], B)  # each row: 1 at its pivot, 0 at the other pivots
    x = np.zeros(len(labels))
    x[: 6 * len(frames)] = dz[frames].ravel()
    cov = _covariance(lp, data)
    units = ("mm", "mm", "mm", "mrad", "mrad", "mrad")
    lines = [
        "Identifiable combinations of the parameters marked — (first order; coefficients in SI units, value in "
        "the unit of the leading parameter; Aj = frame j, A" + str(len(dz)) + " = tool; the five largest terms):",
        "",
        "| combination | value ± σ |",
        "|---|---:|",
    ]
    short = [_short_label(x, len(dz)) for x in labels]
    for row, p in zip(C, pivots, strict=True):
        a = np.zeros(len(labels))
        a[S] = row / scale[S] * scale[S[p]]  # scaled → SI coefficients, leading coefficient 1
        rel = np.zeros(len(labels))
        rel[S] = row / row[p]  # scaled coordinates (angles × reach): comparable sizes across units
        # Terms below 1e-3 of the leading one (in the scaled metric) change the value by less than its rounding.
        order = [S[p]] + [int(i) for i in np.argsort(-np.abs(rel)) if i != S[p] and abs(rel[i]) > 1e-3]
        terms = [short[order[0]]] + [f"{a[i]:+.3g}·{short[i]}" for i in order[1:5]]
        more = len(order) - 5
        text = " ".join(terms) + (f" … (+{more} terms)" if more > 0 else "")
        value = float(a @ x) * 1e3
        sd = float(np.sqrt(max(a @ cov @ a, 0.0))) * 1e3 if cov is not None and cov.shape == (len(a), len(a)) else None
        unit = units[S[p] % 6]
        lines.append(f"| {text} | {value:.4f} ± {'—' if sd is None else f'{sd:.4f}'} {unit} |")
    return lines


def _short_label(label: str, n_frames: int) -> str:
    """'frame A_3 (before joint 3) wy' → 'A3 ωy'; 'tool frame A_{n+1} vz' → 'A7 vz'; T_tracker_base → 'Tb'."""
    import re

    axis = label.rsplit(" ", 1)[-1].replace("w", "ω")
    if label.startswith("T_tracker_base"):
        return f"Tb {axis}"
    if label.startswith("tool frame"):
        return f"A{n_frames} {axis}"
    m = re.match(r"frame A_(\d+)", label)
    return f"A{m.group(1)} {axis}" if m else label


def _evaluation_lines(store, ref: str, fit_id: str) -> list[str]:
    """The stored `labcal evaluate` results of a fit (SessionStore.list_evaluations)."""
    docs = store.list_evaluations(ref, fit_id)
    if not docs:
        return []
    head = ["evaluation", "data", "rows", "pos mean before (mm)", "pos mean after (mm)", "point mean after (mm)",
            "point p95 after (mm)", "point max after (mm)"]  # fmt: skip
    rows = []
    for d in docs:
        m = (d.get("metrics") or {}).get("all") or {}
        pts = (m.get("points") or {}).get("after") or {}
        data = d.get("data") or {}
        rows.append([
            f"{d.get('evaluation_id')}{' (corrupt)' if d.get('corrupt') else ''}", str(data.get("ref", "?")),
            str(data.get("rows", "?")), _mm((m.get("before") or {}).get("pos_mean")),
            _mm((m.get("after") or {}).get("pos_mean")), *[_mm(pts.get(k)) for k in POINT_STATS],
        ])  # fmt: skip
    text = "Evaluations on other data (`labcal evaluate`; only T_tracker_base is fitted on tracker-frame data):"
    return [text, "", *_md_table(head, "llrrrrrr", rows)]


def _cv_lines(cv) -> list[str]:
    if not isinstance(cv, dict) or not cv.get("errors"):
        return []
    parts = []
    for name, errs in cv["errors"].items():
        e = np.asarray([x for x in (errs or []) if x is not None], dtype=float)
        if e.size:
            parts.append(f"{name} {e.mean() * 1e3:.4f} ± {e.std() * 1e3:.4f} mm ({e.size} folds)")
        else:
            parts.append(f"{name}: no fold could be scored")
    lines = [
        f"Cross-validation ({cv.get('folds')} folds, {cv.get('scheme')}; {cv.get('metric') or 'mean error'}): "
        f"mean ± spread over the folds per candidate: {'; '.join(parts)}. Chosen: **{cv.get('chosen')}**.",
        "",
    ]
    for name, why in (cv.get("failures") or {}).items():
        lines += [f"- {name} failed on a fold: {why}"]
    return [*lines, ""] if cv.get("failures") else lines


def held_out_worse(metrics: dict, where: str) -> list[str]:
    """Warning texts for held-out figures that calibration made worse than before (the registered nominal).

    metrics: a split table (``{"test": {"before": …, "after": …, "points": …}, …}``); the held-out splits (val,
    test) are compared, or "all" for data the fit never saw (``labcal evaluate``; where names them). One text per
    split whose mean point error or mean position error grew.

    >>> m = {"test": {"before": {"pos_mean": 0.003}, "after": {"pos_mean": 0.004}}}
    >>> held_out_worse(m, "the fit's")
    ["the fit's test split: mean position error 3.0000 → 4.0000 mm"]
    """
    found = []
    splits = ("all",) if where != "the fit's" else ("val", "test")
    for split in splits:
        table = metrics.get(split)
        if not isinstance(table, dict):
            continue
        points = table.get("points") or {}
        before, after = table.get("before") or {}, table.get("after") or {}
        pairs = [
            ("mean point error", (points.get("before") or {}).get("mean"), (points.get("after") or {}).get("mean")),
            ("mean position error", before.get("pos_mean"), after.get("pos_mean")),
        ]
        worse = [
            f"{what} {b * 1e3:.4f} → {a * 1e3:.4f} mm"
            for what, b, a in pairs
            if isinstance(b, int | float) and isinstance(a, int | float) and np.isfinite(a) and np.isfinite(b) and a > b
        ]
        if worse:
            label = f"{where} {split} split" if split != "all" else where
            found.append(f"{label}: {', '.join(worse)}")
    return found


def _held_out_lines(store, ref: str, data: dict, metrics: dict, *, heading: bool = True) -> list[str]:
    """Report warnings (not stored with the fit) where a fit does worse than no calibration on data it did not fit."""
    fid, method = data["fit_id"], data["meta"].get("chosen") or data["robot"].method
    found = held_out_worse(metrics, "the fit's")
    for doc in store.list_evaluations(ref, fid):
        if doc.get("corrupt"):
            continue
        seen = (doc.get("data") or {}).get("ref", "?")
        found += held_out_worse(doc.get("metrics") or {}, f"evaluation {doc.get('evaluation_id')} on {seen}")
    who = f"fit {fid} ({method}): " if heading else ""
    return [
        f"- **WARNING [worse-than-before]** {who}held-out error is worse after calibration than before — {text}; "
        "do not use this fit to correct the robot"
        for text in found
    ]


def _device_text(device: dict, what: str, unit: object = None) -> str:
    """'arm serial 2018… (UR10, software 5.11.0), ur driver' from a device's block of a manifest (its identity dict
    and driver); says so when no serial was reported, and names a recorded ``unit`` that is not the serial."""
    identity = device.get("identity") or {}
    serial = identity.get("serial")
    extra = [f"{k} {identity[k]}" for k in ("model", "software", "firmware", "version") if identity.get(k)]
    text = f"{what}: serial not reported" if serial in (None, "") else f"{what} serial **{serial}**"
    text += f" ({', '.join(extra)})" if extra else ""
    if unit not in (None, "") and str(unit) != str(serial):
        text += f", recorded as unit {unit}"
    return text + (f", {device['driver']} driver" if device.get("driver") else "")


def device_line(session: dict) -> str:
    """The units a version was measured with, from its manifest's ``session`` block (as `labcal session show`).

    >>> device_line({"robot_driver": {"driver": "ur", "identity": {"serial": "20185500001", "model": "UR10"}},
    ...              "tracker": {"driver": "serial", "identity": {"serial": "P9-01234"}}, "metadata": {}})
    'arm serial **20185500001** (model UR10), ur driver; tracker serial **P9-01234**, serial driver'
    """
    arm = _device_text(session.get("robot_driver") or {}, "arm", (session.get("metadata") or {}).get("unit"))
    return f"{arm}; {_device_text(session.get('tracker') or {}, 'tracker')}"


def _devices_of(store, refs: list[str]) -> list[str]:
    """One line per distinct set of units among the versions refs (a pooled fit may span several arms)."""
    lines: list[str] = []
    for r in refs:
        try:
            line = device_line(store.load(r).manifest.get("session") or {})
        except (ValueError, OSError, DatasetError):
            line = "units unknown (the version cannot be read)"
        entry = f"{line} ({r})"
        if not any(e.startswith(line + " (") for e in lines):
            lines.append(entry)
    return lines


def _metrics_of(data: dict) -> dict:
    """A fit's split table as stored, recomputed for fits stored before point errors were."""
    metrics = data["meta"].get("metrics") or {}
    if not any("points" in m for m in metrics.values() if isinstance(m, dict)):
        metrics = split_table(data["before"], data["robot"], data["obs"])
    return metrics


def write_session_report(store, ref: str, out_dir, fit_ids: list[str] | None = None, load_obs=None) -> Path:
    """Write ``report.md`` and PNG plots for the fits of a version into out_dir; returns the report's path.

    load_obs(refs) → Observations reads a fit's input versions (the CLI passes its loader, which converts controller
    joints to model joints); default: the versions as stored.
    """
    plt = _plt()
    r = store.resolve(ref)
    ids = fit_ids or [f.fit_id for f in store.list_fits(r)]
    if not ids:
        raise ValueError(f"{r} has no fits to report on: run `labcal fit {r}` first")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fits, unreadable = [], []
    for fid in ids:
        try:
            fits.append(_fit_data(store, str(r), fid, load_obs))
        except (ValueError, OSError, DatasetError) as e:  # a fit written by another labcal version, or damaged
            if fit_ids:
                raise
            unreadable.append(f"- fit {fid} is left out: it cannot be read ({e})")
    if not fits:
        raise ValueError(f"no fit of {r} can be read:\n" + "\n".join(unreadable))
    lines = _intro_lines(r, store.load(r))
    metrics_of = {data["fit_id"]: _metrics_of(data) for data in fits}
    lines += _warnings_section(store, r, fits, metrics_of, unreadable)
    for data in fits:
        lines += _fit_section(store, r, data, metrics_of[data["fit_id"]], plt, out)
    hpng = "histogram.png"
    _plot_histograms(plt, fits, out / hpng)
    lines += ["## Position error after calibration, per method", "", f"![histograms]({hpng})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path


def _intro_lines(r, ds) -> list[str]:
    """The report's title and what its errors are."""
    return [
        f"# labcal calibration report — {r}",
        "",
        f"Robot model **{ds.robot.get('name')}** (sha256 `{ds.robot.get('hash', '')[:16]}…`), "
        f"{len(ds)} configurations, points in the {ds.frame} frame. Errors are the distance between each "
        "measured target point and its prediction (point, mm), and — in poses where at least three "
        "non-collinear targets were seen — the distance between the calibrated model's predicted tool pose and "
        "the pose fitted to the measured targets (position, mm) and the angle between the orientations "
        "(degrees); *before* is the nominal model registered to the data.",
        "",
        f"Measured with: {device_line(ds.manifest.get('session') or {})}.",
        "",
    ]


def _warnings_section(store, r, fits: list[dict], metrics_of: dict, unreadable: list[str]) -> list[str]:
    """Every fit's warnings and held-out notes up front, the fits left out, and what `labcal export` refuses."""
    summary = [line for data in fits for line in _warning_lines(data["meta"], data["fit_id"])]
    summary += [line for data in fits for line in _held_out_lines(store, str(r), data, metrics_of[data["fit_id"]])]
    blocked = [d["fit_id"] for d in fits if (d["meta"].get("warnings") or [])]
    lines = ["## Warnings", ""]
    if unreadable:
        lines += [*unreadable, ""]
    if summary:
        lines += [*summary, ""]
        if blocked:
            lines += [
                f"`labcal export` refuses {', '.join(blocked)} unless `--force` (a forced export records the "
                "warnings in its provenance).",
                "",
            ]
    else:
        lines += ["None: no fit in this report has warnings or notes.", ""]
    return lines


def _fit_section(store, r, data: dict, metrics: dict, plt, out: Path) -> list[str]:
    """One fit: heading, its warnings, inputs and what the data let it claim, error tables (the primary figures
    first), cross-validation, plots, what it kept, its parameters and its stored evaluations."""
    meta, fid = data["meta"], data["fit_id"]
    lines = [
        f"## Fit {fid}: {meta.get('chosen', data['robot'].method)} "
        f"(asked: {meta.get('method')}, seed {meta.get('seed')})",
        "",
    ]
    own = _warning_lines(meta, fid, heading=False) + _held_out_lines(store, str(r), data, metrics, heading=False)
    if own:
        lines += [*own, ""]
    inputs = [str(x) for x in (meta.get("inputs") or [])]
    rows = ", ".join(f"{k} {v}" for k, v in (meta.get("rows") or {}).items())
    lines += [f"Inputs: {', '.join(inputs) or r}. Rows: {rows}.", ""]
    if inputs and inputs != [str(r)]:
        lines += ["Units of the inputs:", "", *[f"- {line}" for line in _devices_of(store, inputs)], ""]
    claim = observability_lines(meta.get("observability"), data["obs"])
    if claim:
        lines += [*claim, ""]
    tables = [_md_metrics(metrics), _md_targets(metrics)]
    if _primary(metrics) == "points":
        # Fewer than three targets seen somewhere: the points are what was measured, so they lead (15.3).
        lines += [
            "Primary figures: the per-target point errors (fewer than three non-collinear targets were seen in "
            "some poses). The pose columns of the table after them cover only the poses that fix a full pose "
            "(n = their count; — when none does).",
            "",
        ]
        tables.reverse()
    lines += [*tables[0], "", *tables[1], ""]
    lines += [*_cv_lines(meta.get("cv"))]
    lines += _fit_plots(plt, data, out)
    info = meta.get("info") or {}
    lines += _choice_lines(info)
    lp = _owner(_chosen_info(info, meta.get("chosen")), "delta_zeta")  # the local-POE stage, if any
    lines += [*_parameter_lines(lp, data), "", *_measurement_tool_lines(lp)]
    return [*lines, *_evaluation_lines(store, str(r), fid), ""]


def _fit_plots(plt, data: dict, out: Path) -> list[str]:
    """A fit's plots written into out (errors per configuration, per target, the training curve if it has one)
    and the lines that show them."""
    fid = data["fit_id"]
    png = f"errors-{fid}.png"
    _plot_per_configuration(plt, data, out / png)
    lines = [f"![error per configuration]({png})", ""]
    tpng = f"targets-{fid}.png"
    _plot_targets(plt, data, out / tpng)
    lines += [f"![per-target point error]({tpng})", ""]
    trained = _owner(data["meta"].get("info") or {}, "curve")  # the stage that trained a network, if one did
    if trained and trained["curve"].get("train"):
        cpng = f"training-{fid}.png"
        title = f"network training ({fid})"
        _plot_curve(plt, trained["curve"], trained.get("stopped_at"), out / cpng, title, trained.get("loss"))
        lines += [f"![training curve]({cpng})", ""]
    return lines


def _choice_lines(info: dict) -> list[str]:
    """What a hybrid kept and what auto compared, when the fit says."""
    lines = []
    kept = _find(info, "kept")
    if kept:
        lines += [
            f"Hybrid: kept **{kept}** (cross-validation decides which learned stage, if any, stays).",
            "",
        ]
    cands = _find(info, "candidates")
    if isinstance(cands, dict):
        lines += [
            "Auto: validation mean position error "
            + ", ".join(f"{k} {v * 1e3:.4f} mm" for k, v in cands.items() if isinstance(v, int | float))
            + ".",
            "",
        ]
    return lines
