"""typer is pinned to the release labcal.cli.coercion and labcal.cli.helprender were written for: both reach into
typer's private modules to keep the light commands' start-up within budget (issue 29), so a typer that differs
fails here, with what to re-check, before it can change a value check or a help page unnoticed."""

from __future__ import annotations

import importlib.metadata
import tomllib
from pathlib import Path

from labcal.cli.coercion import WRITTEN_FOR_TYPER

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"

RECHECK = (
    "labcal.cli.coercion and labcal.cli.helprender were written for typer {want}, installed is {have}. Before moving "
    "the pin (pyproject.toml) and WRITTEN_FOR_TYPER together, re-check against the new typer: "
    "(1) typer.core._TyperParameter still calls self._runtime_param.coerce(value, param=, ctx=) and leaves "
    "_runtime_param None until then; typer._coercion.build_runtime_param and typer._param_types' "
    "choice_coercion_annotation, coerce_cli_choice, coerce_cli_path, routes_to_path keep their signatures and "
    "meaning (tests/cli/test_coercion.py compares every option's values with typer's own check); "
    "(2) typer.rich_utils still imports Markdown from rich.markdown and Traceback from rich.traceback by name and "
    "uses neither for rich-markup help (tests/cli/test_help_render.py); "
    "(3) typer._click.exceptions still holds ClickException, UsageError, NoArgsIsHelpError (cli/app.py); "
    "(4) whether an on/off flag still prints '<bool>' (helprender.hide_flag_type); "
    "(5) whether a new typer checks values without pydantic: then run benchmarks/cli_startup.py without both "
    "modules and drop them if the light commands stay within 0.35 s."
)


def test_installed_typer_is_the_one_the_patches_were_written_for():
    have = importlib.metadata.version("typer")
    assert have == WRITTEN_FOR_TYPER, RECHECK.format(want=WRITTEN_FOR_TYPER, have=have)


def test_pyproject_pins_that_typer_exactly():
    deps = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["project"]["dependencies"]
    typer_deps = [d for d in deps if d.split("==")[0].split(">")[0].split("<")[0].strip() == "typer"]
    assert typer_deps == [f"typer=={WRITTEN_FOR_TYPER}"], (
        f"pyproject.toml requires {typer_deps}: pin typer exactly to {WRITTEN_FOR_TYPER} (WRITTEN_FOR_TYPER in "
        "labcal.cli.coercion), or move both together after the re-checks listed in tests/cli/test_typer_pin.py"
    )
