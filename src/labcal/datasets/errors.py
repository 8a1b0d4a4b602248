"""Errors raised by :mod:`labcal.datasets`. Every one says which file, row, column or value is at fault."""

from __future__ import annotations

from labcal.tomlschema import SchemaError


class DatasetError(Exception):
    """Base class of every error raised by the session store and the importers."""


class InvalidId(DatasetError, ValueError):
    """A session id, version name, fit id or reference string is malformed or unsafe as a path name."""


class UnknownSession(DatasetError, LookupError):
    """The reference names a session that is not in the store."""


class UnknownVersion(DatasetError, LookupError):
    """The reference names a version (or fit) that the session does not have."""


class DatasetCorrupted(DatasetError):
    """Stored bytes no longer match their recorded sha256 (or a file is missing / unexpected).

    ``problems`` lists one human-readable line per fault.
    """

    def __init__(self, message: str, problems: list[str] | None = None) -> None:
        super().__init__(message)
        self.problems = list(problems or [])


class JournalError(DatasetError):
    """A journal document is invalid, or the journal is in the wrong state for the operation."""


class JournalCorrupted(JournalError):
    """A journal line other than a torn (unfinished) last write cannot be parsed."""


class TargetsError(DatasetError, SchemaError):
    """A targets file or targets array is invalid (count, numbers, unit, coincident or collinear points). A
    :class:`~labcal.tomlschema.SchemaError` (so a ValueError) too: the targets file is checked by the one TOML
    validator."""


class ImportFormatError(DatasetError, ValueError):
    """An input file for import is malformed. ``row`` is the 1-based data row (header not counted),
    ``line`` the 1-based line in the file, ``column`` the column name; each may be None."""

    def __init__(
        self,
        message: str,
        *,
        path: str | None = None,
        row: int | None = None,
        line: int | None = None,
        column: str | None = None,
    ) -> None:
        where = []
        if path is not None:
            where.append(str(path))
        if row is not None:
            where.append(f"data row {row}" + (f" (line {line} of the file)" if line is not None else ""))
        elif line is not None:
            where.append(f"line {line}")
        if column is not None:
            where.append(f"column {column!r}")
        super().__init__(f"{', '.join(where)}: {message}" if where else message)
        self.path = path
        self.row = row
        self.line = line
        self.column = column


class MappingError(DatasetError, SchemaError):
    """A column-mapping TOML file is invalid (unknown key, wrong type, inconsistent options)."""
