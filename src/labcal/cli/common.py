"""Shared CLI pieces: the --store option, user-error handling (stderr, exit 2, no traceback; Ctrl-C exit 130),
tables, and the fit warnings every command shows the same way."""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

STORE_HELP = "Session store folder (default: $LABCAL_STORE, else ./sessions)."
StoreOption = typer.Option(None, "--store", help=STORE_HELP, show_default=False)
INTERRUPTED = 130  # exit code after Ctrl-C

# Piped output (files, CI logs, tests) gets room for the full metrics table instead of 80 columns.
out = Console(soft_wrap=True, highlight=False, width=None if sys.stdout.isatty() else 200)
err = Console(stderr=True, soft_wrap=True, highlight=False)


def user_errors(fn):
    """Turn the errors a user can fix into `error: …` on stderr and exit code 2, without a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from labcal.datasets import DatasetError

        try:
            return fn(*args, **kwargs)
        except typer.Exit:
            raise
        except KeyboardInterrupt:
            # The shell convention for SIGINT (128 + 2): scripts must not mistake an interrupted run for a
            # successful one. Whatever was recorded is already on disk (the journal is fsynced per measurement).
            err.print("interrupted (Ctrl-C)", markup=False)
            raise typer.Exit(INTERRUPTED) from None
        except (ValueError, DatasetError, OSError, KeyError, RuntimeError) as e:
            # OSError covers more than missing / forbidden files: a full disk or a read-only file system met
            # mid-write is a one-line error too, not a traceback.
            if isinstance(e, KeyError):
                msg = f"missing field {e}"
            elif isinstance(e, OSError) and e.strerror and not str(e).startswith("[Errno"):
                msg = str(e)
            elif isinstance(e, OSError) and e.strerror:
                msg = f"{e.strerror}: {e.filename}" if e.filename else e.strerror
            else:
                msg = str(e)
            err.print(f"error: {msg}", markup=False)
            raise typer.Exit(2) from None

    return wrapper


def store_of(store: Path | None):
    from labcal.cli.ops import open_store

    return open_store(store)


def mm(x) -> str:
    return "—" if x is None else f"{x * 1e3:.4f}"


def deg(x) -> str:
    return "—" if x is None else f"{x * 180 / 3.141592653589793:.4f}"


def metrics_table(metrics: dict, title: str) -> Table:
    """Rich table: split × (before, after) with mean / RMS / p95 / max position (mm) and orientation (deg) of the
    tool pose, and mean / p95 / max of the per-target point error (mm) beside it."""
    t = Table(title=title, title_justify="left")
    t.add_column("split")
    t.add_column("n", justify="right")
    t.add_column("")
    for stat in ("mean", "rms", "p95", "max"):
        t.add_column(f"pos {stat} mm", justify="right")
    for stat in ("mean", "rms", "p95", "max"):
        t.add_column(f"ori {stat} °", justify="right")
    for stat in ("mean", "p95", "max"):
        t.add_column(f"point {stat} mm", justify="right")
    for split in ("train", "val", "test", "all"):
        if split not in metrics:
            continue
        for when in ("before", "after"):
            s = metrics[split][when]
            p = (metrics[split].get("points") or {}).get(when) or {}
            t.add_row(
                split if when == "before" else "",
                str(int(s.get("count") or 0)) if when == "before" else "",
                when,
                *[mm(s.get(f"pos_{k}")) for k in ("mean", "rms", "p95", "max")],
                *[deg(s.get(f"ori_{k}")) for k in ("mean", "rms", "p95", "max")],
                *[mm(p.get(k)) for k in ("mean", "p95", "max")],
            )
    return t


def targets_table(metrics: dict, title: str = "per-target point error (mm): mean / p95 / max") -> Table | None:
    """Rich table: split × (before, after) × target of the point error (mm), or None if the metrics have none."""
    splits = [s for s in ("train", "val", "test", "all") if s in metrics and "points" in metrics[s]]
    if not splits:
        return None
    m = len(metrics[splits[0]]["points"]["after"].get("per_target") or [])
    t = Table(title=title, title_justify="left")
    t.add_column("split")
    t.add_column("")
    for i in range(m):
        t.add_column(f"t{i + 1} mean", justify="right")
        t.add_column(f"t{i + 1} p95", justify="right")
        t.add_column(f"t{i + 1} max", justify="right")
    for split in splits:
        for when in ("before", "after"):
            per = metrics[split]["points"][when].get("per_target") or []
            cells = [mm(p.get(k)) for p in per for k in ("mean", "p95", "max")]
            t.add_row(split if when == "before" else "", when, *cells)
    return t


def print_gates(gates: dict | None, *, what: str = "this fit", footer: bool = True) -> None:
    """Every blocking warning on stderr as `WARNING [code] message`, then the notes; nothing when clean."""
    gates = gates or {}
    warnings = gates.get("warnings") or []
    for w in warnings:
        err.print(f"WARNING [{w.get('code')}] {w.get('message')}", markup=False, style="bold yellow")
    for n in gates.get("notes") or []:
        err.print(f"note: {n}", markup=False)
    if warnings and footer:
        err.print(
            f"{what} has {len(warnings)} warning(s): `labcal export` refuses it unless --force is given",
            markup=False,
            style="bold yellow",
        )
