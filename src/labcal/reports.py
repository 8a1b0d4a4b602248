"""Markdown reports with PNG plots (matplotlib, headless Agg backend) of the fits stored under a version.

For every fit: its metrics table (train / val / test, before / after: mean, RMS, p95, max in mm and degrees),
the position and orientation error of every configuration before and after (the paper's Fig. 5), the training
curve with the validation-stopping point when the fit trained a network (Fig. 4), and the identified local-POE
frame parameters with their standard deviations when it identified frames. Across fits: histograms of the
position error after calibration per method.

Example::

    from labcal.datasets import SessionStore
    write_session_report(SessionStore("sessions"), "20261122-031500-ur10-3f9a@v1", "report/")
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from labcal.calibration.metrics import prediction_errors
from labcal.calibration.observations import Observations
from labcal.compensator import from_payload

ROBOT_FILE, BEFORE_FILE = "robot.json", "before.json"


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _fit_data(store, ref: str, fit_id: str) -> dict:
    record = store.load_fit(ref, fit_id)
    meta = record.metadata
    robot, _ = from_payload(json.loads(record.read(ROBOT_FILE)), f"fit {fit_id}")
    before, _ = from_payload(json.loads(record.read(BEFORE_FILE)), f"fit {fit_id}")
    datasets = [store.load(i["ref"]) for i in record.inputs]
    split = meta.get("split")
    obs = Observations(
        q=np.concatenate([d.q for d in datasets]),
        points=np.concatenate([d.points for d in datasets]),
        targets=datasets[0].targets,
        frame=datasets[0].frame,
        split=np.array(split, dtype=object) if split else np.concatenate([d.split for d in datasets]).astype(object),
    )
    return {"fit_id": fit_id, "meta": meta, "robot": robot, "before": before, "obs": obs}


def _find(info, key):
    """The first value stored under key anywhere in a nested info dict (hybrid/auto nest their stages)."""
    if isinstance(info, dict):
        if key in info and info[key] is not None:
            return info[key]
        for value in info.values():
            found = _find(value, key)
            if found is not None:
                return found
    return None


def _md_metrics(metrics: dict) -> list[str]:
    cols = [f"pos {s} (mm)" for s in ("mean", "rms", "p95", "max")] + [
        f"ori {s} (°)" for s in ("mean", "rms", "p95", "max")
    ]
    lines = ["| split | n | | " + " | ".join(cols) + " |", "|---|---:|---|" + "---:|" * len(cols)]
    for split in ("train", "val", "test", "all"):
        if split not in metrics:
            continue
        for when in ("before", "after"):
            s = metrics[split][when]

            def f(key, scale, s=s):
                v = s.get(key)
                return "—" if v is None else f"{v * scale:.4f}"

            vals = [f(f"pos_{k}", 1e3) for k in ("mean", "rms", "p95", "max")]
            vals += [f(f"ori_{k}", 180 / np.pi) for k in ("mean", "rms", "p95", "max")]
            n = str(int(s.get("count") or 0)) if when == "before" else ""
            lines.append(f"| {split if when == 'before' else ''} | {n} | {when} | " + " | ".join(vals) + " |")
    return lines


def _plot_per_configuration(plt, data: dict, path: Path) -> None:
    obs = data["obs"]
    order = np.argsort([{"train": 0, "val": 1, "test": 2}.get(s, 3) for s in obs.split], kind="stable")
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
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_curve(plt, curve: dict, stopped_at, path: Path, title: str) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.semilogy(curve["train"], label="training")
    ax.semilogy(curve["val"], label="validation")
    if stopped_at is not None:
        ax.axvline(stopped_at, color="k", ls="--", lw=0.8, label=f"validation stop (iteration {stopped_at})")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_histograms(plt, fits: list[dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    first = fits[0]
    before = prediction_errors(first["before"], first["obs"])[0] * 1e3
    hi = float(np.max(before)) if before.size else 1.0
    bins = np.linspace(0, max(hi, 1e-6), 30)
    ax.hist(before, bins=bins, histtype="step", lw=1.5, label="before (registered nominal)")
    for data in fits:
        e = prediction_errors(data["robot"], data["obs"])[0] * 1e3
        ax.hist(e, bins=bins, histtype="step", lw=1.2, label=f"{data['robot'].method} ({data['fit_id']})")
    ax.set_xlabel("position error (mm), every configuration")
    ax.set_ylabel("configurations")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _parameter_lines(info: dict) -> list[str]:
    dz, std = _find(info, "delta_zeta"), _find(info, "std")
    if dz is None:
        return []
    dz = np.asarray(dz, dtype=float)
    std = np.asarray(std, dtype=float) if std is not None else np.full_like(dz, np.nan)
    names = ["vx (mm)", "vy (mm)", "vz (mm)", "ωx (mrad)", "ωy (mrad)", "ωz (mrad)"]
    lines = [
        "Identified frame corrections δζ_j = log(A_j,nominal⁻¹ A_j,identified) ± one standard deviation "
        "(— where not identifiable):",
        "",
        "| frame | " + " | ".join(names) + " |",
        "|---|" + "---:|" * 6,
    ]
    for j, (row, srow) in enumerate(zip(dz, std, strict=True)):
        cells = []
        for i, (v, s) in enumerate(zip(row, srow, strict=True)):
            scale = 1e3
            cells.append(f"{v * scale:.4f} ± {s * scale:.4f}" if np.isfinite(s) else f"{v * scale:.4f} ± —")
            del i
        label = f"A{j + 1}" if j < len(dz) - 1 else f"A{j + 1} (tool)"
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def write_session_report(store, ref: str, out_dir, fit_ids: list[str] | None = None) -> Path:
    """Write ``report.md`` and PNG plots for the fits of a version into out_dir; returns the report's path."""
    plt = _plt()
    r = store.resolve(ref)
    ids = fit_ids or [f.fit_id for f in store.list_fits(r)]
    if not ids:
        raise ValueError(f"{r} has no fits to report on: run `labcal fit {r}` first")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fits = [_fit_data(store, str(r), fid) for fid in ids]
    ds = store.load(r)
    lines = [
        f"# labcal calibration report — {r}",
        "",
        f"Robot model **{ds.robot.get('name')}** (sha256 `{ds.robot.get('hash', '')[:16]}…`), "
        f"{len(ds)} configurations, points in the {ds.frame} frame. Errors are the distance between the "
        "calibrated model's predicted tool pose and the pose fitted to the three measured targets "
        "(position, mm) and the angle between the "
        "orientations (degrees); *before* is the nominal model registered to the data.",
        "",
    ]
    for data in fits:
        meta, fid = data["meta"], data["fit_id"]
        lines += [
            f"## Fit {fid}: {meta.get('chosen', data['robot'].method)} "
            f"(asked: {meta.get('method')}, seed {meta.get('seed')})",
            "",
            f"Inputs: {', '.join(str(x) for x in (meta.get('inputs') or [])) or r}. Rows: "
            + ", ".join(f"{k} {v}" for k, v in (meta.get("rows") or {}).items())
            + ".",
            "",
            *_md_metrics(meta.get("metrics") or {}),
            "",
        ]
        png = f"errors-{fid}.png"
        _plot_per_configuration(plt, data, out / png)
        lines += [f"![error per configuration]({png})", ""]
        info = meta.get("info") or {}
        curve = _find(info, "curve")
        if curve and curve.get("train"):
            cpng = f"training-{fid}.png"
            _plot_curve(plt, curve, _find(info, "stopped_at"), out / cpng, f"network training ({fid})")
            lines += [f"![training curve]({cpng})", ""]
        kept = _find(info, "kept")
        if kept:
            lines += [f"Hybrid: kept **{kept}** (validation decides whether the network stage stays).", ""]
        cands = _find(info, "candidates")
        if isinstance(cands, dict):
            lines += [
                "Auto: validation mean position error "
                + ", ".join(f"{k} {v * 1e3:.4f} mm" for k, v in cands.items() if v is not None)
                + ".",
                "",
            ]
        lines += [*_parameter_lines(info), ""]
    hpng = "histogram.png"
    _plot_histograms(plt, fits, out / hpng)
    lines += ["## Position error after calibration, per method", "", f"![histograms]({hpng})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
