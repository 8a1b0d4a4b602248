"""The examples in labcal's docstrings run, and print what they say they print.

Every module of ``src/labcal`` and of its test doubles (``fakes/src/labcal_fakes``) whose source holds a ``>>>``
example is one test: its docstring examples run with :mod:`doctest` (whitespace-normalised, ``...`` allowed), in a
copy of the module's globals, with temporary files under pytest's ``tmp_path``. Worked examples that only
illustrate (they need a session store or a recorded journal that a docstring cannot hold) are listed in
``ILLUSTRATIONS`` with the reason, and the list is itself checked so that it cannot go stale.
"""

from __future__ import annotations

import doctest
import importlib
import tempfile
from pathlib import Path

import pytest

import labcal
import labcal_fakes

OPTIONFLAGS = doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS

PACKAGE_DIRS = [Path(labcal.__file__).parent, Path(labcal_fakes.__file__).parent]

# Docstrings (doctest names) whose ``>>>`` lines illustrate a call in a ``::`` block and are not run: the reason
# is what the example would need.
ILLUSTRATIONS = {
    "labcal.cli.ops.refit": "needs a session store with recorded ur10 sessions",
    "labcal.datasets.documents": "needs a recorded measurement document (the JSON shown above it)",
}


def _module_name(path: Path, package_dir: Path) -> str:
    parts = path.relative_to(package_dir.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules_with_examples() -> list[str]:
    return sorted(
        _module_name(path, package_dir)
        for package_dir in PACKAGE_DIRS
        for path in package_dir.rglob("*.py")
        if ">>>" in path.read_text(encoding="utf-8")
    )


MODULES = _modules_with_examples()


def _doctests(module_name: str) -> list[doctest.DocTest]:
    module = importlib.import_module(module_name)
    # The module's own docstrings only (exclude_empty drops the ones without examples).
    found = doctest.DocTestFinder(exclude_empty=True).find(module, module_name)
    return [test for test in found if test.examples]


def _run(tests: list[doctest.DocTest]) -> tuple[doctest.TestResults, str]:
    """Run the doctests; return (failed, attempted) and doctest's report of the failures."""
    runner = doctest.DocTestRunner(optionflags=OPTIONFLAGS)
    report: list[str] = []
    for test in tests:
        runner.run(test, out=report.append, clear_globs=True)
    return runner.summarize(verbose=False), "".join(report)


@pytest.fixture
def temp_files_in(tmp_path, monkeypatch):
    """Examples that write files use ``tempfile.mkdtemp()``: send those under pytest's tmp_path."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    return tmp_path


@pytest.mark.parametrize("module_name", MODULES)
def test_docstring_examples_run(module_name, temp_files_in):
    tests = [test for test in _doctests(module_name) if test.name not in ILLUSTRATIONS]
    if not tests:
        pytest.skip(f"{module_name}: its only examples are illustrations ({ILLUSTRATIONS.get(module_name)})")
    results, report = _run(tests)
    assert results.attempted > 0, f"{module_name} has '>>>' in its source but doctest found no example"
    assert results.failed == 0, f"{results.failed} of {results.attempted} examples in {module_name} fail:\n{report}"


@pytest.mark.parametrize("name", sorted(ILLUSTRATIONS))
def test_listed_illustrations_still_exist(name):
    """An entry of ILLUSTRATIONS names a docstring that still holds examples (else the entry must go)."""
    module_name = name if name in MODULES else name.rsplit(".", 1)[0]
    assert name in {test.name for test in _doctests(module_name)}, f"{name} has no '>>>' example any more"


def test_a_wrong_example_fails_the_runner():
    """The runner and its flags report a wrong output, and an exception, as failures (nothing is swallowed)."""
    parser = doctest.DocTestParser()
    wrong_output = parser.get_doctest(">>> 1 + 1\n3\n", {}, "wrong_output", "<test>", 0)
    raises = parser.get_doctest(">>> undefined_name\n", {}, "raises", "<test>", 0)
    results, report = _run([wrong_output, raises])
    assert (results.failed, results.attempted) == (2, 2)
    assert "Expected:\n    3\nGot:\n    2" in report
    assert "NameError" in report
