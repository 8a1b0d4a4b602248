"""labcal.cli.coercion: option values checked without pydantic give what typer's own (pydantic) check gives — the
same value of the same type, or the same error — for every option of the app and the values a user may type."""

from __future__ import annotations

import typing
from pathlib import Path

import pytest
import typer.main
from typer._click import Context
from typer._coercion import build_runtime_param

from labcal.cli.app import app
from labcal.cli.coercion import PlainCoercion, install

SAMPLES = {
    str: ["abc", "", " x ", "ünï", "--json", "0"],
    int: ["0", "7", "-3", "007", "+5", " 5", "5 ", "5_000", "1.0", "1e3", "abc", "", "-", "99999999999999999999", 3],
    float: ["0.5", "-1", "0", "1e3", "1E-2", "2.5e+1", ".5", "5.", "nan", "inf", "1_0.5", " 1", "abc", "", 2, 0.25],
    Path: ["a/b", "", ".", "~/x", "/tmp", "-", Path("x")],
    bool: [True, False, "true", "0", "no", ""],
}


def commands(root=None):
    """(command path, click command) for every command of the app."""
    root = root or typer.main.get_command(app)
    out, todo = [], [("labcal", root)]
    while todo:
        path, cmd = todo.pop()
        out.append((path, cmd))
        todo += [(f"{path} {n}", c) for n, c in (getattr(cmd, "commands", None) or {}).items()]
    return out


def cases():
    for path, cmd in commands():
        for param in cmd.params:
            annotation = param.type_descriptor.annotation
            if typing.get_origin(annotation) is typing.Literal:
                choices = typing.get_args(annotation)
                values = [*choices, *(c.upper() for c in choices), "bogus", ""]
            elif typing.get_origin(annotation) is list:
                values = [("a", "b"), ["x"], (), "one"]
            else:
                values = SAMPLES[annotation]
            for v in values:
                yield pytest.param(cmd, param, v, id=f"{path} {param.name} {v!r}")


def outcome(check, value, param, ctx):
    try:
        v = check.coerce(value, param=param, ctx=ctx)
    except Exception as e:
        return ("error", type(e).__name__, str(getattr(e, "message", e)))
    return ("value", type(v).__name__, repr(v))  # repr: NaN equals NaN


@pytest.mark.parametrize("cmd, param, value", list(cases()))
def test_plain_check_agrees_with_typers(cmd, param, value):
    ctx = Context(cmd, info_name=cmd.name)
    plain = outcome(PlainCoercion(param.type_descriptor), value, param, ctx)
    typers = outcome(build_runtime_param(param.type_descriptor), value, param, ctx)
    assert plain == typers


def test_every_option_type_of_the_app_is_sampled():
    kinds = {p.type_descriptor.annotation for _, c in commands() for p in c.params}
    plain = {k for k in kinds if typing.get_origin(k) not in (typing.Literal, list)}
    assert plain <= set(SAMPLES), f"add samples for {plain - set(SAMPLES)}"


def test_install_reaches_every_parameter_and_the_help_options():
    """If typer renames the hook, install would silently do nothing: pydantic would be back on every path."""
    root = typer.main.get_command(app)
    install(root)
    for _, cmd in commands(root):
        for p in cmd.params:
            assert isinstance(p._runtime_param, PlainCoercion), (cmd.name, p.name)
        ctx = Context(cmd, info_name=cmd.name)
        assert isinstance(cmd.get_help_option(ctx)._runtime_param, PlainCoercion)
