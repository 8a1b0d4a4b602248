"""No import circles inside labcal, counting imports inside functions too (issue 29).

A lazy import inside a function hides a circle from Python's start-up, not from a reader: the two modules still
depend on each other, and neither can be understood or tested without the other. The graph is built from the
source with :mod:`ast` (every ``import`` and ``from … import`` anywhere in a module, ``if TYPE_CHECKING`` blocks
excepted: they never run), an edge for each labcal module named; ``from package import name`` is an edge to the
submodule when ``name`` is one, else to the package's ``__init__``. A parent package imported implicitly (Python
runs ``labcal/x/__init__`` before ``labcal.x.y``) is not an edge: it is where a package lists its API.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"


def module_files(src: Path = SRC) -> dict[str, Path]:
    """Dotted module name → file, for every module of labcal."""
    out = {}
    for path in sorted((src / "labcal").rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.AST, module: str, is_package: bool) -> list[tuple[str, list[str]]]:
    """(imported module, names) of every import in the tree, outside ``if TYPE_CHECKING`` blocks."""
    found: list[tuple[str, list[str]]] = []
    skipped = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and _type_checking(node)
               for child in node.body for n in ast.walk(child)}  # fmt: skip
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found.extend((alias.name, []) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = module.split(".")
                if not is_package:
                    package = package[:-1]
                package = package[: len(package) - (node.level - 1)]
                base = ".".join(package + ([base] if base else []))
            found.append((base, [alias.name for alias in node.names]))
    return found


def import_graph(src: Path = SRC) -> dict[str, set[str]]:
    """module → the labcal modules it imports anywhere in its source."""
    files = module_files(src)
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        edges = set()
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for base, names in _imports(tree, module, path.name == "__init__.py"):
            if not base.startswith("labcal"):
                continue
            subs = [f"{base}.{name}" for name in names if f"{base}.{name}" in files]
            edges.update(subs)
            if len(subs) < len(names) or not names:
                while base not in files and "." in base:
                    base = base.rsplit(".", 1)[0]
                edges.add(base)
        edges.discard(module)
        graph[module] = edges
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted; sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def test_the_graph_sees_function_level_and_relative_imports(tmp_path):
    pkg = tmp_path / "labcal"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from labcal.sub.a import f\n")
    (pkg / "sub" / "a.py").write_text("def f():\n    from labcal.sub import b\n    return b\n")
    (pkg / "sub" / "b.py").write_text("from . import a\nfrom typing import TYPE_CHECKING\n"
                                      "if TYPE_CHECKING:\n    from labcal import sub\n")  # fmt: skip
    graph = import_graph(tmp_path)
    assert graph["labcal.sub.a"] == {"labcal.sub.b"}
    assert graph["labcal.sub.b"] == {"labcal.sub.a"}
    assert circles(graph) == [["labcal.sub.a", "labcal.sub.b"]]


def test_no_import_circle_inside_labcal():
    found = circles(import_graph())
    assert not found, "import circles (function-level imports included):\n" + "\n".join(" <-> ".join(c) for c in found)


if __name__ == "__main__":  # pragma: no cover - a report for a maintainer: python tests/test_import_circles.py
    for component in circles(import_graph()):
        print(" <-> ".join(component))
    raise SystemExit(pytest.main([__file__, "-q"]))
