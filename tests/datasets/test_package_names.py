"""labcal.datasets' public names: the lazy table, the imports type checkers read, and what each name resolves to."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import labcal.datasets as datasets


def _type_checking_imports() -> dict[str, set[str]]:
    """module → names of the ``if TYPE_CHECKING:`` imports of the package's ``__init__``."""
    tree = ast.parse(Path(datasets.__file__).read_text(encoding="utf-8"))
    block = next(n for n in tree.body if isinstance(n, ast.If) and ast.unparse(n.test) == "TYPE_CHECKING")
    out: dict[str, set[str]] = {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.level == 1
        out.setdefault(str(node.module), set()).update(a.name for a in node.names)
    return out


def test_the_lazy_table_and_the_type_checking_imports_name_the_same_things():
    table: dict[str, set[str]] = {}
    for name, module in datasets._LAZY.items():
        table.setdefault(module, set()).add(name)
    assert table == _type_checking_imports()
    assert sorted(datasets.__all__) == sorted(datasets._LAZY) and len(set(datasets.__all__)) == len(datasets.__all__)


def test_every_public_name_is_the_object_of_its_module_and_listed_by_dir():
    for name, module in datasets._LAZY.items():
        assert getattr(datasets, name) is getattr(importlib.import_module(f"labcal.datasets.{module}"), name)
    assert set(datasets.__all__) <= set(dir(datasets))


def test_an_unknown_name_is_an_attribute_error_naming_it():
    try:
        datasets.no_such_name  # noqa: B018
    except AttributeError as e:
        assert "no_such_name" in str(e)
    else:
        raise AssertionError("no AttributeError")


def test_importing_the_package_and_the_store_loads_no_pandas():
    code = "import sys, labcal.datasets as d; d.SessionStore; print('pandas' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
