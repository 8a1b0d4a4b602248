"""labcal.cli.helprender: `--help` renders the same with the stand-ins for rich.markdown and rich.traceback as with
the real modules, and the real modules are what later imports get."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

RUN = "import sys; from labcal.cli.app import main; sys.argv = ['labcal', *sys.argv[1:]]; main()"


def help_text(argv: list[str], *, preload_real: bool) -> str:
    # Importing the real modules first leaves import_help_renderer nothing to stand in for.
    code = ("import rich.markdown, rich.traceback; " if preload_real else "") + RUN
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "COLUMNS": "100"})  # fmt: skip
    assert r.returncode == (2 if "--help" not in argv else 0), r.stderr  # a group alone: its help, exit 2
    assert "Usage: labcal" in r.stdout
    return r.stdout


@pytest.mark.parametrize(
    "argv",
    [["--help"], ["session", "--help"], ["session", "list", "--help"], ["fit", "--help"], ["export", "--help"],
     ["filter", "--help"], ["session"]],
)  # fmt: skip
def test_help_is_the_same_with_the_stand_ins(argv):
    assert help_text(argv, preload_real=False) == help_text(argv, preload_real=True)


def test_later_imports_get_the_real_modules():
    code = (
        "import sys\n"
        "from labcal.cli.helprender import import_help_renderer\n"
        "import_help_renderer()\n"
        "assert 'rich.markdown' not in sys.modules and 'rich.traceback' not in sys.modules\n"
        "import typer.rich_utils as ru\n"
        "import rich.markdown, rich.traceback\n"
        "assert rich.markdown.Markdown.__module__ == 'rich.markdown', rich.markdown.Markdown\n"
        "md = ru.Markdown('*x*')\n"
        "assert type(md) is rich.markdown.Markdown and isinstance(md, ru.Markdown)\n"
        "assert ru.Traceback.from_exception is not None\n"
        "print('ok')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"
