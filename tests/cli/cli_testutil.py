"""What the CLI tests share: a typer runner on the app, the demo's targets (and the same with t1 and t2 swapped)."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from labcal.cli.app import app

TARGETS = 'unit = "mm"\npoints = [[120.0, 0.0, 60.0], [-60.0, 100.0, 60.0], [-60.0, -100.0, 90.0]]\n'
SWAPPED = 'unit = "mm"\npoints = [[-60.0, 100.0, 60.0], [120.0, 0.0, 60.0], [-60.0, -100.0, 90.0]]\n'
runner = CliRunner()


def invoke(*args, store: Path | None = None):
    """Run `labcal ARGS [--store STORE]` in-process; returns typer's Result (stdout, stderr, exit_code)."""
    argv = [str(a) for a in args] + (["--store", str(store)] if store is not None else [])
    return runner.invoke(app, argv)


def last_line(result) -> str:
    return result.stdout.strip().splitlines()[-1]
