"""Every command's --help: an on/off flag shows no type (typer printed `<bool>` beside each, as if it took a value),
while options that take a value keep theirs."""

from __future__ import annotations

import typer
from cli_testutil import invoke

from labcal.cli.app import app


def command_paths(command, prefix=()) -> list[tuple[str, ...]]:
    paths = [prefix]
    for name, sub in sorted((getattr(command, "commands", None) or {}).items()):
        paths += command_paths(sub, (*prefix, name))
    return paths


def test_no_help_shows_a_type_beside_a_flag(monkeypatch):
    monkeypatch.setenv("COLUMNS", "120")
    paths = command_paths(typer.main.get_command(app))
    assert ("fit",) in paths and ("session", "new") in paths
    for path in paths:
        r = invoke(*path, "--help")
        assert r.exit_code == 0, (path, r.stdout + r.stderr)
        assert "--help" in r.stdout
        assert "<bool>" not in r.stdout, f"labcal {' '.join(path)} --help:\n{r.stdout}"
    fit = invoke("fit", "--help").stdout
    assert "<int>" in fit and "<float>" in fit and "<path>" in fit, "options with a value keep their type"
    assert any(line.strip("│ ").startswith("--json ") and "Print" in line for line in fit.splitlines())
