"""Session ids, version names, fit ids and ``SESSION@vN`` references.

A session id is sortable and readable: ``YYYYMMDD-HHMMSS-<robot>-<4 hex>`` in UTC, e.g.
``20261122-031500-ur10-3f9a``. Any id given by a user must be a safe single path component: letters, digits,
``.``, ``_`` and ``-`` only, not starting with ``.`` or ``-``, at most 100 characters, and no ``@`` (reserved
for references). Versions are ``v001``, ``v002`` …; fit ids are ``YYYYMMDD-HHMMSS-ffffff-<6 hex>`` (UTC, with
microseconds) so they sort by creation time.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ._util import random_hex, utc_now
from .errors import InvalidId

_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
_VERSION_RE = re.compile(r"^v(\d{1,6})$")


def validate_id(value: str, what: str = "session id") -> str:
    """Return ``value`` if it is a safe path component for an id, else raise :class:`InvalidId`."""
    if not isinstance(value, str) or not _ID_RE.match(value) or value in {".", ".."} or ".." in value:
        raise InvalidId(
            f"invalid {what} {value!r}: use 1-100 letters, digits, '.', '_' or '-', starting with a letter "
            "or digit (no '/', '@', spaces or '..')"
        )
    return value


def robot_slug(robot_name: str) -> str:
    """A short lowercase path-safe form of a robot name (``"UR10e (lab 2)"`` → ``"ur10e-lab-2"``)."""
    slug = re.sub(r"[^a-z0-9]+", "-", str(robot_name).lower()).strip("-")
    return (slug[:24].rstrip("-")) or "robot"


def new_session_id(robot_name: str) -> str:
    """A new sortable session id: UTC time, robot slug and 4 random hex digits."""
    return f"{utc_now():%Y%m%d-%H%M%S}-{robot_slug(robot_name)}-{random_hex(4)}"


def new_fit_id() -> str:
    """A new fit id, sortable by creation time (microsecond resolution) and unique (6 random hex)."""
    return f"{utc_now():%Y%m%d-%H%M%S-%f}-{random_hex(6)}"


def version_name(number: int) -> str:
    if not isinstance(number, int) or number < 1:
        raise InvalidId(f"version numbers start at 1, got {number!r}")
    return f"v{number:03d}"


def parse_version(text: str) -> int:
    """``"v3"`` / ``"v003"`` → 3."""
    m = _VERSION_RE.match(text or "")
    if not m or int(m.group(1)) < 1:
        raise InvalidId(f"invalid version {text!r}: expected 'v' and a number >= 1, e.g. v1 or v003")
    return int(m.group(1))


@dataclass(frozen=True)
class Ref:
    """A parsed reference: ``session_id`` and a version number, or None for "the latest"."""

    session_id: str
    version: int | None = None

    def __str__(self) -> str:
        return self.session_id if self.version is None else f"{self.session_id}@{version_name(self.version)}"


def parse_ref(text: str | Ref) -> Ref:
    """Parse ``SESSION``, ``SESSION@vN`` or ``SESSION@v00N`` (syntax only; see ``SessionStore.resolve``)."""
    if isinstance(text, Ref):
        return text
    if not isinstance(text, str) or not text.strip():
        raise InvalidId(f"empty or non-string reference {text!r}; expected SESSION or SESSION@vN")
    text = text.strip()
    if text.count("@") > 1:
        raise InvalidId(f"invalid reference {text!r}: at most one '@' (SESSION@vN)")
    session, _, version = text.partition("@")
    validate_id(session)
    return Ref(session, parse_version(version) if "@" in text else None)
