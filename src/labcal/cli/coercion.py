"""Option values checked without importing pydantic, for the values a command line actually carries.

typer checks every parameter value through a pydantic TypeAdapter it builds on first use — even an option that
was not given, and the ``--help`` flag itself — and importing pydantic costs about as much as the rest of
`labcal session list` or `labcal fit --help`. :func:`install` gives each parameter of the command tree a check
that does what typer's adapter does for the common cases (a missing value; a string for a ``str`` or ``Path``
option; an integer or a decimal number written plainly; a ``Literal`` choice; repeated strings) and hands every
other value, and every value it would refuse, to typer's own check. So a bad value's error message, and any type
not listed here, stay exactly typer's.

``tests/cli/test_coercion.py`` compares the two on the types and values labcal's options use, and fails if a new
typer no longer has the hook used here (then :func:`install` does nothing and typer checks everything itself).

Why typer's private modules at all (issue 29): without this module and :mod:`labcal.cli.helprender`, typer 0.29
imports pydantic and builds a TypeAdapter for every parameter of a command, ``--help`` included, and the light
commands took 0.34-0.45 s here (1.4-2.0x; benchmarks/results/cli_startup.txt), over their 0.35 s budget; typer has
no public way to check a value without pydantic. So typer is pinned exactly (pyproject.toml) to
:data:`WRITTEN_FOR_TYPER`, and ``tests/cli/test_typer_pin.py`` fails on any other typer with the list of what to
re-check before the pin moves.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

# The typer release whose private modules (typer._coercion, typer._param_types, typer.core's ``_runtime_param``,
# typer.rich_utils' imports, typer._click) this module and labcal.cli.helprender were written for and tested on.
WRITTEN_FOR_TYPER = "0.29.2"

# Only spellings whose meaning cannot differ between Python and pydantic; anything else goes to pydantic.
_INT = re.compile(r"-?[0-9]{1,18}\Z")
_FLOAT = re.compile(r"-?[0-9]{1,15}(\.[0-9]{1,15})?([eE]-?[0-9]{1,2})?\Z")
_DEFER = object()  # "not one of the plain cases": typer's own check decides
_UNSET = object()


class PlainCoercion:
    """One parameter's check. Duck-types typer's ``RuntimeParam`` (typer calls ``coerce`` only)."""

    __slots__ = ("_descriptor", "_plain", "_typer")

    def __init__(self, descriptor: Any) -> None:
        self._descriptor = descriptor
        self._typer = None
        self._plain = _UNSET  # made for the parameters that get a value: most of the tree's never do

    def coerce(self, value: Any, param: Any, ctx: Any) -> Any:
        multi = param.multiple or param.nargs == -1
        if value is None:  # as typer's RuntimeParam.coerce, before it builds an adapter
            return () if multi else None
        if self._plain is _UNSET:
            self._plain = _plain_check(self._descriptor)
        if self._plain is not None and not (multi and isinstance(value, str)):
            try:
                out = self._plain(value, param, ctx)
            except Exception:  # refused: typer's check raises its own error for it
                out = _DEFER
            if out is not _DEFER:
                return out
        return self.typer_check().coerce(value, param=param, ctx=ctx)

    def typer_check(self) -> Any:
        if self._typer is None:
            from typer._coercion import build_runtime_param

            self._typer = build_runtime_param(self._descriptor)
        return self._typer


def _plain_check(descriptor: Any):
    """The check of the plain cases of this parameter's type, or None when every value goes to typer."""
    from typing import get_args, get_origin

    from typer._param_types import choice_coercion_annotation, coerce_cli_choice, coerce_cli_path, routes_to_path

    annotation, info = descriptor.annotation, descriptor.parameter_info
    if descriptor.file_annotation is not None or info.parser is not None:
        return None
    if info.min is not None or info.max is not None:
        return None

    if annotation is str or annotation is bool:
        return lambda v, param, ctx: v if isinstance(v, annotation) else _DEFER
    if annotation is int or annotation is float:
        # an int is a float too, a float not an int; a bool (an int to Python) is neither
        accepted, spelling = (int, _INT) if annotation is int else (int | float, _FLOAT)

        def to_number(v, param, ctx):
            if isinstance(v, accepted) and not isinstance(v, bool):
                return annotation(v)
            return annotation(v) if isinstance(v, str) and spelling.match(v) else _DEFER

        return to_number
    if get_origin(annotation) is list and get_args(annotation) == (str,):

        def to_strings(v, param, ctx):
            return list(v) if isinstance(v, list | tuple) and all(isinstance(x, str) for x in v) else _DEFER

        return to_strings
    choice = choice_coercion_annotation(annotation, info)
    if choice is not None:
        choices, case_sensitive = choice
        return lambda v, param, ctx: coerce_cli_choice(v, choices=choices, case_sensitive=case_sensitive, ctx=ctx)
    if isinstance(annotation, type) and issubclass(annotation, Path) and routes_to_path(annotation, info):
        if info.path_type is not None:
            return None

        def to_path(v, param, ctx):
            if isinstance(v, str) and v and "\0" not in v:
                v = annotation(v)
            if not isinstance(v, annotation):
                return _DEFER
            return coerce_cli_path(v, info, path_type=annotation, param=param, ctx=ctx)

        return to_path
    return None


def install(command: Any) -> None:
    """Give every parameter of ``command`` and its subcommands a :class:`PlainCoercion` (those typer has not yet
    given its own check), the ``--help`` option too. Does nothing on a typer without the ``_runtime_param`` hook."""
    for param in command.params:
        _give(param)
    if not getattr(command, "_labcal_plain_help", False) and hasattr(command, "get_help_option"):
        # click makes the --help option on first use, from the context's option names: give it the check then.
        made_by = command.get_help_option

        def get_help_option(ctx):
            option = made_by(ctx)
            if option is not None:
                _give(option)
            return option

        command.get_help_option = get_help_option
        command._labcal_plain_help = True
    for sub in (getattr(command, "commands", None) or {}).values():
        install(sub)


def _give(param: Any) -> None:
    # The walk over every parameter (the lazily made --help too) also settles how a flag shows in the help.
    from labcal.cli.helprender import hide_flag_type

    hide_flag_type(param)
    if getattr(param, "_runtime_param", False) is None and hasattr(param, "type_descriptor"):
        param._runtime_param = PlainCoercion(param.type_descriptor)
