"""Code size of labcal: lines per area, the longest functions, and the largest classes by method count.

Lines are non-blank, non-comment source lines (docstrings count: they are read too); a second total leaves the
docstrings out (issue 29's measure: 24,009 on 3fc465f, before that issue). Run it on two trees to set a
restructuring's before and after side by side. The test doubles (``fakes/src/labcal_fakes``, the labcal-fakes
distribution beside the package) get a line of their own, outside the product count:

    python benchmarks/code_size.py                       # this checkout's src/labcal (and fakes/src/labcal_fakes)
    python benchmarks/code_size.py --src /tmp/before/src/labcal --top 5
"""

from __future__ import annotations

import argparse
import ast
import io
import tokenize
from collections import Counter
from pathlib import Path


def code_lines(text: str) -> int:
    return sum(1 for line in text.splitlines() if line.strip() and not line.strip().startswith("#"))


def code_lines_without_docstrings(text: str, tree: ast.AST) -> int:
    """Lines holding a token that is not a comment, a docstring or layout."""
    docs: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.body:
            first = node.body[0]
            if (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            ):
                docs.update(range(first.lineno, first.end_lineno + 1))
    layout = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER}
    lines: set[int] = set()
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type not in layout:
            lines.update(range(tok.start[0], tok.end[0] + 1))
    return len(lines - docs)


def functions(tree: ast.AST, module: str) -> list[tuple[int, str]]:
    """(length in lines, qualified name) of every function and method."""
    out = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                out.append((child.end_lineno - child.lineno + 1, f"{module}:{name}"))
                visit(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")

    visit(tree, "")
    return out


def classes(tree: ast.AST, module: str) -> list[tuple[int, str]]:
    """(number of methods, qualified name) of every class."""
    return [
        (sum(isinstance(b, ast.FunctionDef | ast.AsyncFunctionDef) for b in node.body), f"{module}:{node.name}")
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--src", type=Path, default=Path(__file__).resolve().parents[1] / "src" / "labcal")
    ap.add_argument("--top", type=int, default=5, help="how many of the longest functions and largest classes")
    args = ap.parse_args(argv)
    per_area: Counter = Counter()
    funcs, klasses = [], []
    without_docstrings = 0
    for path in sorted(args.src.rglob("*.py")):
        rel = path.relative_to(args.src)
        text = path.read_text()
        area = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        per_area[area] += code_lines(text)
        tree = ast.parse(text)
        without_docstrings += code_lines_without_docstrings(text, tree)
        funcs += functions(tree, str(rel))
        klasses += classes(tree, str(rel))
    print(f"code lines in {args.src}: {sum(per_area.values())} ({without_docstrings} without docstrings)")
    for area, n in sorted(per_area.items(), key=lambda kv: -kv[1]):
        print(f"  {area:14s} {n:6d}")
    fakes = args.src.parents[1] / "fakes" / "src" / "labcal_fakes"  # src/labcal -> the checkout -> its fakes
    if fakes.is_dir():  # checkouts from before the fakes left the package have none
        texts = [path.read_text() for path in sorted(fakes.rglob("*.py"))]
        with_docs = sum(code_lines(text) for text in texts)
        without = sum(code_lines_without_docstrings(text, ast.parse(text)) for text in texts)
        print(
            f"labcal-fakes (test doubles, separate distribution; not in the product count), {fakes}: "
            f"{with_docs} ({without} without docstrings)"
        )
    print(f"longest functions (lines), of {len(funcs)}:")
    for n, name in sorted(funcs, reverse=True)[: args.top]:
        print(f"  {n:4d}  {name}")
    print("largest classes (methods):")
    for n, name in sorted(klasses, reverse=True)[: args.top]:
        print(f"  {n:4d}  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
