"""Run the URScript subset labcal emits, by a strict line-by-line translation to Python.

Every line must match one statement form of the subset (def/end, while, if/elif/else, local/plain/indexed
assignment, return, popup/halt, comments); expressions may only use names, numbers, strings, + - * /, comparisons,
and/or/not, parentheses, list literals and integer indexing. Anything else (Python-only syntax such as slices,
comprehensions, ** or attribute access) is rejected, so a script that passes here uses only URScript constructs.
"""

from __future__ import annotations

import math
import re

_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
_STATEMENTS = [
    re.compile(rf"^def {_NAME}\(({_NAME}(, {_NAME})*)?\):$"),
    re.compile(r"^end$"),
    re.compile(r"^(while|if|elif) (?P<e>.+):$"),
    re.compile(r"^else:$"),
    re.compile(rf"^(local )?{_NAME} = (?P<e>.+)$"),
    re.compile(rf"^{_NAME}\[(?P<i>[^\]]+)\] = (?P<e>.+)$"),
    re.compile(r"^return (?P<e>.+)$"),
    re.compile(r'^popup\("[^"]*", error=True, blocking=True\)$'),
    re.compile(r"^halt$"),
]
_TOKEN = re.compile(
    r'\s*(?:(?P<num>\d+\.\d*(?:e[-+]?\d+)?|\d+(?:e[-+]?\d+)?)|(?P<name>[A-Za-z_]\w*)|(?P<op><=|>=|==|!=|[-+*/<>()\[\],=])|(?P<str>"[^"]*"))'
)
_KEYWORDS = {"and", "or", "not", "True", "False"}
ALLOWED_CALLS = {"sin", "cos", "sqrt", "atan2", "pow", "popup"}


class Halted(Exception):
    """The script executed ``halt`` (after a popup)."""


def _check_expression(expr: str, where: str) -> None:
    pos = 0
    while pos < len(expr):
        m = _TOKEN.match(expr, pos)
        if not m or m.end() == pos:
            raise SyntaxError(f"{where}: not in the URScript subset: {expr[pos:]!r}")
        if m.group("op") == "=" and not re.search(r"(error|blocking)=$", expr[: m.end()]):
            raise SyntaxError(f"{where}: assignment inside an expression")
        pos = m.end()
    if "**" in expr or "//" in expr or "%" in expr or " for " in expr or ":" in expr:
        raise SyntaxError(f"{where}: Python-only syntax in {expr!r}")


def translate(script: str) -> str:
    out = []
    for number, raw in enumerate(script.splitlines(), start=1):
        line = raw.split("#", 1)[0].rstrip() if '"' not in raw else raw.rstrip()
        body = line.strip()
        if not body:
            continue
        where = f"line {number}"
        for pattern in _STATEMENTS:
            m = pattern.match(body)
            if m:
                break
        else:
            raise SyntaxError(f"{where}: statement not in the URScript subset: {body!r}")
        for group in ("e", "i"):
            if group in pattern.groupindex and m.group(group) is not None:
                _check_expression(m.group(group), where)
        indent = line[: len(line) - len(line.lstrip())]
        if body == "end":
            continue
        if body == "halt":
            out.append(f"{indent}raise Halted()")
            continue
        if body.startswith("local "):
            body = body[len("local ") :]
        out.append(indent + body)
    return "\n".join(out) + "\n"


def _popup(message, error=False, blocking=False):
    print("popup:", message)


def _pow(base, exponent):
    try:
        return math.pow(base, exponent)
    except OverflowError:
        return math.inf


def load(script: str) -> dict:
    """Translate and execute the script's top level; returns its namespace (functions and lc_ constants)."""
    code = translate(script)
    names = {"sin": math.sin, "cos": math.cos, "sqrt": math.sqrt, "atan2": math.atan2, "pow": _pow}
    names.update({"popup": _popup, "Halted": Halted, "__builtins__": {}})
    exec(compile(code, "<urscript>", "exec"), names)
    return names
