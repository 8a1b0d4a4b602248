"""typer's rich help renderer, imported without the two rich renderers it imports but never uses for labcal.

``typer.rich_utils`` formats ``--help``. At import it also pulls in ``rich.markdown`` (with markdown-it and pygments)
and ``rich.traceback``, which together cost more than rendering the help: typer uses the first only for help text
in markdown mode (labcal's is rich markup) and the second only for pretty tracebacks (labcal turns them off).
:func:`import_help_renderer` imports ``typer.rich_utils`` with those two names bound to stand-ins that load the real
class on first use, so the help is the same and a later ``import rich.markdown`` gets the real module.

``tests/cli/test_help_render.py`` checks that the help text is identical either way and that the real modules are
importable afterwards. It relies on typer.rich_utils' imports, a private detail: typer is pinned for it and for
:mod:`labcal.cli.coercion` (whose docstring says why; ``tests/cli/test_typer_pin.py``).

:func:`hide_flag_type` keeps a flag's type out of its help line: typer 0.29 prints ``<bool>`` beside every on/off
flag (``--json <bool>``, ``--help <bool>``), which reads as if the flag took a value.
"""

from __future__ import annotations

import importlib
import sys
import types

# module → the class typer.rich_utils imports from it
_DEFERRED = {"rich.markdown": "Markdown", "rich.traceback": "Traceback"}


class _Deferred(type):
    """The metaclass of a stand-in: calling it, reading its attributes or an isinstance check load the real class."""

    _module: str

    def real(cls) -> type:
        return getattr(importlib.import_module(cls._module), cls.__name__)

    def __call__(cls, *args, **kwargs):
        return cls.real()(*args, **kwargs)

    def __getattr__(cls, name: str):
        return getattr(cls.real(), name)

    def __instancecheck__(cls, obj) -> bool:
        return isinstance(obj, cls.real())


def import_help_renderer() -> None:
    """Import ``typer.rich_utils`` now, with stand-ins for the renderers labcal does not use (no-op if imported)."""
    if "typer.rich_utils" in sys.modules:
        return
    stubs = {}
    for module, name in _DEFERRED.items():
        if module in sys.modules:
            continue
        stub = types.ModuleType(module, "labcal stand-in while typer.rich_utils is imported")
        setattr(stub, name, _Deferred(name, (), {"_module": module}))
        stubs[module] = stub
    sys.modules.update(stubs)
    try:
        import typer.rich_utils  # noqa: F401
    except Exception:  # typer imports it again when it renders help, and reports what is wrong itself
        sys.modules.pop("typer.rich_utils", None)
    finally:
        for module, stub in stubs.items():
            if sys.modules.get(module) is stub:
                del sys.modules[module]


def hide_flag_type(param) -> None:
    """Show no type beside an on/off flag in the help (typer shows ``<bool>``); a flag given a metavar keeps it.

    typer prints the metavar in place of the type when there is one, so an empty metavar prints nothing; a flag takes
    no value, so click never prints its metavar anywhere else.
    """
    if getattr(param, "is_flag", False) and getattr(param, "metavar", "") is None:
        param.metavar = ""
