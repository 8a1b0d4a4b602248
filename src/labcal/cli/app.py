"""The `labcal` command line (typer). Thin: every command parses its arguments and calls library functions.

Quick start::

    labcal demo                                  # no hardware: simulate, fit every method, export, report
    labcal session new --robot ur10 --robot-driver sim --tracker-driver sim --targets t.toml --poses 60
    labcal fit SESSION --method auto
    labcal export SESSION --format json --out ur10.json
    labcal evaluate FIT --data HELDOUT_SESSION       # score held-out data with a stored fit

Exit codes (every command): 0 ok; 1 a verification failure (``session verify`` found damage, a recording ended
failed or paused, a refit failed); 2 a usage or input error (one ``error: …`` line on stderr); 130 interrupted.

Importing this module must stay light (no pandas, pyarrow, torch, scipy, matplotlib): ``labcal --help``, shell
completion and ``labcal session list`` run on it alone. Command modules import their heavy machinery inside the
command functions; ``tests/cli/test_scripting.py`` checks it.
"""

from __future__ import annotations

import signal
import sys

import typer
from typer._click import exceptions as click_exceptions  # typer vendors click; its exceptions live here
from typer.core import TyperGroup

from labcal.cli import coercion, helprender, session
from labcal.cli.common import TERMINATED_BY, interruption
from labcal.cli.demo import demo
from labcal.cli.evaluate import evaluate
from labcal.cli.export import export
from labcal.cli.filter import filter_program
from labcal.cli.fit import fit
from labcal.cli.refit import refit
from labcal.cli.report import report


class _LabcalGroup(TyperGroup):
    """The root command: a usage error (bad option value, unknown option, missing argument) is ONE line on stderr,
    `error: …`, exit 2 — the same shape as the commands' own input errors, so scripts and people read one format.
    Typer would print a framed multi-line panel instead."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        # Before any value is checked: typer's own checks import pydantic, which the light paths must not need.
        coercion.install(self)
        if _shows_help(self, sys.argv[1:] if args is None else list(args)):
            helprender.import_help_renderer()
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click_exceptions.NoArgsIsHelpError as e:
            # `labcal session` alone: the help (rich has already printed it; plain click hands it over), exit 2
            if e.format_message().strip():
                sys.stdout.write(e.format_message() + "\n")
            sys.exit(e.exit_code)
        except click_exceptions.ClickException as e:
            sys.stderr.write(f"error: {_one_line(e)}\n")
            sys.exit(e.exit_code)
        except typer.Abort:
            sys.stderr.write("aborted\n")
            sys.exit(1)
        # Non-standalone mode hands back a typer.Exit's code (or the command's return value, None for all ours).
        sys.exit(rv if isinstance(rv, int) and not isinstance(rv, bool) else 0)


def _shows_help(group, argv: list[str]) -> bool:
    """Whether these arguments print a help: --help anywhere, or nothing after a command group (`labcal session`).
    Only decides whether to import the help renderer early (the lighter way); a wrong guess costs time, not output."""
    if not argv or "--help" in argv:
        return True
    command = group
    for word in argv:
        command = None if word.startswith("-") else (getattr(command, "commands", None) or {}).get(word)
        if command is None:
            return False
    return hasattr(command, "commands")


def _one_line(e: click_exceptions.ClickException) -> str:
    """`Invalid value for '--method': 'x' is not one of 'local-poe', … (see labcal fit --help)` on one line."""
    msg = " ".join(e.format_message().replace("Value error, ", "").split())
    ctx = getattr(e, "ctx", None)
    if isinstance(e, click_exceptions.UsageError) and ctx is not None:
        msg += f" (see {ctx.command_path} --help)"
    return msg


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            v = version("labcal")
        except PackageNotFoundError:  # run from a source tree that is not installed
            from labcal import __version__ as v
        print(f"labcal {v}")
        raise typer.Exit(0)


app = typer.Typer(
    name="labcal",
    cls=_LabcalGroup,
    help="Calibrate serial robots from tracker measurements of one or more target points.\n\n"
    "Examples:\n\n  labcal demo\n\n  labcal session list\n\n  labcal fit SESSION --method hybrid\n\n"
    "  labcal export SESSION --format urscript --out labcal_correct.script\n\n"
    "  labcal evaluate FIT --data heldout.csv --targets t.toml --length-unit mm\n\n"
    "  labcal filter poses.csv --calibration ur10.json --out corrected.csv\n\n"
    "  labcal refit --robot ur10 --since 2026-11-01 --method auto --jobs 4\n\n"
    "  labcal report SESSION --out report/\n\n"
    "  labcal session list --json | jq '.sessions[].session'\n\n"
    "Exit codes: 0 ok, 1 verification failure (damaged data, a failed or paused recording), 2 usage or input "
    "error, 130 interrupted.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=True,
)


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", is_eager=True, callback=_version, help="Print labcal's version and exit."
    ),
) -> None:
    """Calibrate serial robots from tracker measurements of one or more target points."""


app.add_typer(session.app, name="session")
app.command("fit")(fit)
app.command("refit")(refit)
app.command("export")(export)
app.command("filter")(filter_program)
app.command("report")(report)
app.command("evaluate")(evaluate)
app.command("demo")(demo)


def _terminate(signum: int, _frame) -> None:
    # A supervisor's SIGTERM or a closed terminal's SIGHUP takes Ctrl-C's path: the robot is stopped and the
    # journal's stop record written (by default Python would die on the spot, the move in progress running on).
    TERMINATED_BY.append(signum)  # for commands that report an interrupted run themselves (session new / resume)
    raise KeyboardInterrupt(signum)


def main() -> None:
    """Console-script entry point. Ctrl-C outside a command's own handling exits 130 (128 + SIGINT), not 0/1;
    SIGTERM and SIGHUP are handled as Ctrl-C is and exit 143 / 129."""
    for signum in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _terminate)
    try:
        app()
    except KeyboardInterrupt as e:
        message, code = interruption(e)
        print(message, file=sys.stderr)
        sys.exit(code)


if __name__ == "__main__":
    main()
