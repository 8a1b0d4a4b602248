"""The `labcal` command line (typer). Thin: every command parses its arguments and calls library functions.

Quick start::

    labcal demo                                  # no hardware: simulate, fit every method, export, report
    labcal session new --robot ur10 --robot-driver sim --tracker-driver sim --targets t.toml --poses 60
    labcal fit SESSION --method auto
    labcal export SESSION --format json --out ur10.json
    labcal evaluate FIT --data HELDOUT_SESSION       # score held-out data with a stored fit
"""

from __future__ import annotations

import sys

import typer

from labcal.cli import bench, session
from labcal.cli.common import INTERRUPTED
from labcal.cli.demo import demo
from labcal.cli.evaluate import evaluate
from labcal.cli.export import export
from labcal.cli.filter import filter_program
from labcal.cli.fit import fit
from labcal.cli.report import report

app = typer.Typer(
    name="labcal",
    help="Calibrate serial robots from tracker measurements of one or more target points.\n\n"
    "Examples:\n\n  labcal demo\n\n  labcal session list\n\n  labcal fit SESSION --method hybrid\n\n"
    "  labcal export SESSION --format urscript --out labcal_correct.script\n\n"
    "  labcal evaluate FIT --data heldout.csv --targets t.toml --length-unit mm\n\n"
    "  labcal filter poses.csv --calibration ur10.json --out corrected.csv\n\n"
    "  labcal report SESSION --out report/",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
app.add_typer(session.app, name="session")
app.add_typer(bench.app, name="bench")
app.command("fit")(fit)
app.command("export")(export)
app.command("filter")(filter_program)
app.command("report")(report)
app.command("evaluate")(evaluate)
app.command("demo")(demo)


def main() -> None:
    """Console-script entry point. Ctrl-C outside a command's own handling exits 130 (128 + SIGINT), not 0/1."""
    try:
        app()
    except KeyboardInterrupt:
        print("interrupted (Ctrl-C)", file=sys.stderr)
        sys.exit(INTERRUPTED)


if __name__ == "__main__":
    main()
