"""Shared CLI pieces: the --store option, user-error handling (stderr, exit 2, no traceback), tables."""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

STORE_HELP = "Session store folder (default: $LABCAL_STORE, else ./sessions)."
StoreOption = typer.Option(None, "--store", help=STORE_HELP, show_default=False)

# Piped output (files, CI logs, tests) gets room for the full metrics table instead of 80 columns.
out = Console(soft_wrap=True, highlight=False, width=None if sys.stdout.isatty() else 160)
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
        except (ValueError, DatasetError, FileNotFoundError, PermissionError, KeyError, RuntimeError) as e:
            msg = str(e) if not isinstance(e, KeyError) else f"missing field {e}"
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
    """Rich table: split × (before, after) with mean / RMS / p95 / max position (mm) and orientation (deg)."""
    t = Table(title=title, title_justify="left")
    t.add_column("split")
    t.add_column("n", justify="right")
    t.add_column("")
    for stat in ("mean", "rms", "p95", "max"):
        t.add_column(f"pos {stat} mm", justify="right")
    for stat in ("mean", "rms", "p95", "max"):
        t.add_column(f"ori {stat} °", justify="right")
    for split in ("train", "val", "test", "all"):
        if split not in metrics:
            continue
        for when in ("before", "after"):
            s = metrics[split][when]
            t.add_row(
                split if when == "before" else "",
                str(int(s.get("count") or 0)) if when == "before" else "",
                when,
                *[mm(s.get(f"pos_{k}")) for k in ("mean", "rms", "p95", "max")],
                *[deg(s.get(f"ori_{k}")) for k in ("mean", "rms", "p95", "max")],
            )
    return t
