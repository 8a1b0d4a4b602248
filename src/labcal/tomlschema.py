"""One declarative validator for labcal's TOML files (robots, device profiles, targets, import mappings).

A schema is a :class:`Table` of :class:`Key` s. Each key states its kind, whether it is required, its default,
its shape (for lists), its unit (shown in messages) and its allowed values; keys a table does not declare are
refused with a did-you-mean, because in a hand-written file an unknown key is almost always a typo that would
otherwise be silently ignored. :func:`validate` returns the document with defaults filled in and numbers as
floats; every error names the file, the table and the key::

    >>> POINT = Table({"unit": Key("str", choices=("m", "mm"), default="m"),
    ...                "points": Key("vectors", shape=(None, 3), unit="in unit", required=True)})
    >>> validate({"unit": "mm", "points": [[0, 0, 1]]}, POINT, source="t.toml")
    {'unit': 'mm', 'points': [[0.0, 0.0, 1.0]]}
    >>> validate({"units": "mm", "points": [[0, 0, 1]]}, POINT, source="t.toml")
    Traceback (most recent call last):
    ...
    labcal.tomlschema.SchemaError: t.toml: unknown key 'units' (did you mean 'unit'?); allowed: points, unit

Kinds: ``str``, ``int``, ``bool``, ``number`` (a finite int or float; TOML booleans are not numbers), ``vector``
(a list of numbers; ``shape=(3,)``), ``vectors`` (a list of lists of numbers, ``shape=(rows, cols)``, ``None`` =
any count), ``strings`` (a list of strings, ``shape=(n,)`` or ``None``), ``table`` (a nested :class:`Table`),
``tables`` (an array of tables, each checked against ``table``), ``any`` (no check). ``shape`` entries may be
names (``"n"``) bound by the caller through ``dims``. Semantic checks that need more than one key (a lower
limit below an upper one, a regex's groups) stay with the loader; it raises them through :func:`fail` so that
they read the same.

Pure standard library: this module sits below every layer that reads a file.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

MISSING: Any = object()
KINDS = ("str", "int", "bool", "number", "vector", "vectors", "strings", "table", "tables", "any")


class SchemaError(ValueError):
    """A file does not follow its schema; the message names the file, the table and the key.

    ``source`` is the file, ``path`` the dotted key path (``joints[2].alpha``; empty for the whole document).
    """

    def __init__(self, message: str, source: str = "", path: str = ""):
        super().__init__(message)
        self.source = source
        self.path = path


@dataclass(frozen=True)
class Key:
    """One key of a table.

    ``check(value) -> phrase | None`` adds a rule of its own after the type check; the phrase follows the key's
    path in the message (``"must not be zero"`` → ``joints[4].axis must not be zero``). ``expect`` replaces the
    generated description of the kind in type errors (``"[lo, hi] numbers"``). ``doc`` says what the key means,
    for a reader of the schema.
    """

    kind: str
    required: bool = False
    default: Any = MISSING
    choices: tuple | None = None
    shape: tuple | None = None
    unit: str = ""
    table: Table | None = None
    min_items: int = 0
    check: Callable[[Any], str | None] | None = None
    expect: str = ""
    doc: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Key kind must be one of {KINDS}, got {self.kind!r}")
        if self.kind in ("table", "tables") and self.table is None:
            raise ValueError(f"a {self.kind!r} key needs its table schema")


@dataclass(frozen=True)
class Table:
    """A table's keys; ``name`` is how messages call it when it is the whole document (e.g. "robot file")."""

    keys: Mapping[str, Key] = field(default_factory=dict)
    name: str = ""


E = TypeVar("E", bound=SchemaError)


def fail(source: str, path: str, message: str, error: type[E] = SchemaError) -> E:  # type: ignore[assignment]
    """The error for ``path`` in ``source``: ``"arm.toml: joints[2].alpha must be …"`` (raise it)."""
    where = f"{source}: " if source else ""
    return error(f"{where}{path + ' ' if path else ''}{message}", source, path)


def input_file_problem(path: str | Path) -> str | None:
    """Why ``path`` cannot be read as an input file, as the end of a sentence (None: a regular file, or a link to one).

    A device such as ``/dev/zero`` never ends and a FIFO blocks until someone writes: both are refused by name
    instead of being read (or called missing).

    >>> input_file_problem("/dev/zero")
    'is a device, not a file: name the file itself'
    """
    import os
    import stat

    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "not found (check the path and the current folder)"
    except OSError as e:
        return f"cannot be opened ({e.strerror or e})"
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "is a folder, not a file: name the file inside it"
    if stat.S_ISFIFO(mode):
        return "is a FIFO (named pipe), not a file: save the data to a regular file first"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "is a device, not a file: name the file itself"
    return "is not a regular file (a socket?): name a regular file"


def decode_text(data: bytes, path: str | Path, error: type[Exception], what: str = "file") -> str:
    """UTF-8 text of ``data`` (a byte order mark, as Windows editors write, is accepted and dropped); bytes that are
    not UTF-8 raise ``error`` naming the line and column and how to convert the file."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        start = exc.start + (3 if data.startswith(b"\xef\xbb\xbf") else 0)
        line = data[:start].count(b"\n") + 1
        column = start - (data.rfind(b"\n", 0, start) + 1) + 1
        bad = data[start : start + 1].hex()
        name = Path(path).name
        raise error(
            f"{path}: line {line}, column {column}: byte 0x{bad} is not UTF-8 (the {what} was saved in another "
            f"encoding, e.g. Latin-1 or Windows-1252): save it as UTF-8, e.g. `iconv -f latin1 -t utf-8 {name} > "
            f"utf8-{name}`"
        ) from None


def read_toml(path: str | Path, error: type[SchemaError] = SchemaError, what: str = "file") -> dict:
    """Parse a TOML file; an unreadable file or bad TOML raises ``error`` naming the file (and the line)."""
    path = Path(path)
    why = input_file_problem(path)
    if why is not None:
        raise error(f"{path}: cannot read {what}: it {why}", str(path))
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror or exc}", str(path)) from exc
    text = decode_text(data, path, error, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}", str(path)) from exc


def is_number(value: Any) -> bool:
    """A finite int or float; True/False are not numbers here, although Python's bool is an int."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def positive(value: float) -> str | None:
    """A :attr:`Key.check`: the number must be > 0 (a rate, a timeout, a tolerance)."""
    return None if value > 0 else f"must be > 0, got {value}"


def non_negative(value: float) -> str | None:
    """A :attr:`Key.check`: the number must be >= 0 (a mass, a retry count, a delay)."""
    return None if value >= 0 else f"must be >= 0, got {value}"


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def _shape(key: Key, dims: Mapping[str, int]) -> tuple[int | None, int | None]:
    """The key's shape with named dimensions bound (None: any count), padded to two entries."""
    shape = [dims.get(s) if isinstance(s, str) else s for s in key.shape or ()]
    return (*shape, None, None)[:2]  # type: ignore[return-value]


#: The kinds of one value: the test a value passes and how a message names the kind.
_PLAIN: dict[str, tuple[Callable[[Any], bool], str]] = {
    "str": (lambda v: isinstance(v, str), "a string"),
    "int": (lambda v: isinstance(v, int) and not isinstance(v, bool), "an integer"),
    "bool": (lambda v: isinstance(v, bool), "true or false"),
    "number": (is_number, "a finite number"),
}


def _expected(key: Key, dims: Mapping[str, int]) -> str:
    unit = f" ({key.unit})" if key.unit else ""
    if key.expect:
        return key.expect + unit
    rows, cols = _shape(key, dims)
    if key.kind in _PLAIN:
        return _PLAIN[key.kind][1] + unit
    if key.kind == "vector":
        return (f"a list of {_plural(rows, 'number')}" if rows is not None else "a list of numbers") + unit
    if key.kind == "vectors":
        inner = _plural(cols, "number") if cols is not None else "numbers"
        return (f"{rows} rows of {inner}" if rows is not None else f"a list of rows of {inner}") + unit
    # strings (a table, an array of tables or any value is never of the wrong kind here: validate checks them)
    return f"a list of {_plural(rows, 'string')}" if rows is not None else "a list of strings"


def _numbers(value: Any, n: int | None) -> bool:
    return isinstance(value, list) and (n is None or len(value) == n) and all(is_number(x) for x in value)


def _check_kind(key: Key, value: Any, dims: Mapping[str, int]) -> Any:
    """The value converted (numbers to float), or MISSING when it is not of the key's kind."""
    kind = key.kind
    rows, cols = _shape(key, dims)
    if kind in _PLAIN:
        if not _PLAIN[kind][0](value):
            return MISSING
        return float(value) if kind == "number" else value
    if kind == "vector":
        return [float(x) for x in value] if _numbers(value, rows) else MISSING
    if kind == "vectors":
        ok = isinstance(value, list) and (rows is None or len(value) == rows) and all(_numbers(r, cols) for r in value)
        return [[float(x) for x in r] for r in value] if ok else MISSING
    if kind == "strings":
        ok = isinstance(value, list) and (rows is None or len(value) == rows)
        return list(value) if ok and all(isinstance(s, str) for s in value) else MISSING
    return value  # any, and table / tables: checked by the caller


def _unknown(data: Mapping, table: Table, source: str, path: str, error: type[SchemaError]) -> None:
    unknown = [k for k in data if k not in table.keys]
    if not unknown:
        return
    allowed = sorted(table.keys)
    key = unknown[0]
    close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    where = path or table.name
    others = f" (and {', '.join(map(repr, unknown[1:]))})" if len(unknown) > 1 else ""
    message = f"unknown key {key!r}{others}{hint}; allowed: {', '.join(allowed)}"
    prefix = f"{source}: " if source else ""
    raise error(f"{prefix}{where + ': ' if where else ''}{message}", source, f"{path}.{key}" if path else key)


def validate(
    data: Any,
    table: Table,
    *,
    source: str = "",
    path: str = "",
    error: type[SchemaError] = SchemaError,
    dims: Mapping[str, int] | None = None,
) -> dict:
    """Check ``data`` (a parsed TOML table) against ``table``; return a copy with defaults filled in.

    Numbers come back as floats, lists of numbers as lists of floats; keys without a value and without a default
    are left out. Raises ``error`` (a :class:`SchemaError`) for the first problem, naming ``source`` and the key.
    """
    dims = dims or {}
    if not isinstance(data, dict):
        raise fail(source, path or table.name, f"must be a table, got {data!r}", error)
    _unknown(data, table, source, path, error)
    out: dict = {}
    for name, key in table.keys.items():
        where = f"{path}.{name}" if path else name
        if name not in data and key.required:
            raise fail(source, where, "is missing (required)", error)
        if name not in data and key.default is MISSING:
            continue
        # An absent key takes its default through the same checks (an absent table gets its own keys' defaults).
        value = data.get(name, key.default)
        if key.kind == "table":
            assert key.table is not None
            out[name] = validate(value, key.table, source=source, path=where, error=error, dims=dims)
            continue
        if key.kind == "tables":
            assert key.table is not None
            if not isinstance(value, list) or len(value) < key.min_items:
                need = "one" if key.min_items == 1 else str(key.min_items)
                what = f"needs at least {need} [[{where}]] table" if key.min_items else "must be an array of tables"
                raise fail(source, where, f"{what}, got {value!r}", error)
            out[name] = [
                validate(row, key.table, source=source, path=f"{where}[{i}]", error=error, dims=dims)
                for i, row in enumerate(value, start=1)
            ]
            continue
        converted = _check_kind(key, value, dims)
        if converted is MISSING:
            raise fail(source, where, f"must be {_expected(key, dims)}, got {value!r}", error)
        if key.choices is not None and converted not in key.choices:
            options = ", ".join(repr(c) for c in key.choices)
            close = difflib.get_close_matches(str(converted), [str(c) for c in key.choices], n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close and isinstance(converted, str) else ""
            raise fail(source, where, f"must be one of {options}, got {value!r}{hint}", error)
        if key.check is not None and (problem := key.check(converted)):
            raise fail(source, where, problem, error)
        out[name] = converted
    return out


__all__ = [
    "MISSING",
    "Key",
    "SchemaError",
    "Table",
    "decode_text",
    "fail",
    "input_file_problem",
    "is_number",
    "non_negative",
    "positive",
    "read_toml",
    "validate",
]
