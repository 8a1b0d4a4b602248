"""Names and labels that end up in exports: what a robot, joint, method or serial number may be called.

A robot file's ``name`` and joint names, a compensator file's model names, a session's serial numbers all reach
files that other programs read: a URScript program (where a line break in a comment starts a statement the
controller runs), ur_description's YAML (where it starts a key), a URDF (where a control character makes the XML
ill-formed), and the terminal (where ``ESC [`` sequences recolour or rewrite what the user sees). So a name is
checked where it enters labcal (robot files at load, compensator files at load), and every writer still quotes or
escapes what it writes, as a second wall.

A name: 1 to 64 ASCII letters, digits and ``_ - . + /``, starting with a letter or a digit (the built-ins'
``ur10``, ``fanuc-m1000ia``, ``shoulder_pan_joint``, URDF-style ``arm/joint_1``). Nothing of that can start a
statement, a key or a markup sequence anywhere labcal writes it. A label (a serial number, a message): printable
text on one line; :func:`printable` turns anything else into a visible, escaped form for output.

Example::

    >>> name_problem("ur10") is None
    True
    >>> name_problem("ur10\\nmovej([0, 0, 0, 0, 0, 0])").split(", got ")[1]
    "'ur10\\\\nmovej([0, 0, 0, 0, 0, 0])'"
    >>> printable("SN\\x1b[31m42")
    'SN\\\\x1b[31m42'
"""

from __future__ import annotations

import re

MAX_NAME = 64
MAX_LABEL = 200  # characters of a device-reported label (serial, model) written into an export
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+/-]{0,63}")
NAME_RULE = f"1 to {MAX_NAME} letters, digits or _ - . + / starting with a letter or digit"


def name_problem(value: object) -> str | None:
    """None for a valid name, else the phrase saying what is wrong (for a message that names the field)."""
    if isinstance(value, str) and _NAME.fullmatch(value):
        return None
    shown = repr(value) if len(repr(value)) <= 120 else repr(value)[:117] + "..."
    return f"must be {NAME_RULE}, got {shown}"


def duplicate(names) -> tuple[int, int] | None:
    """(first index, repeated index) of the first name that appears twice, else None."""
    seen: dict = {}
    for i, name in enumerate(names):
        if name in seen:
            return seen[name], i
        seen[name] = i
    return None


def printable(value: object, limit: int | None = None) -> str:
    """``value`` as one printable line: whitespace runs become one blank, other control and format characters
    (ESC, bidi overrides, NUL …) their backslash escapes, so nothing written can move a cursor or start a line.
    limit: cut to that many characters (marked with ``...``)."""
    one_line = " ".join(str(value).split())
    text = "".join(ch if ch.isprintable() else ch.encode("unicode_escape").decode("ascii") for ch in one_line)
    if limit is not None and len(text) > limit:
        text = text[: max(0, limit - 3)] + "..."
    return text


def label_problem(value: object, limit: int = MAX_LABEL) -> str | None:
    """None for a printable one-line string of at most ``limit`` characters, else what is wrong."""
    if not isinstance(value, str):
        return f"must be a string, got {type(value).__name__}"
    if len(value) > limit:
        return f"must be at most {limit} characters, got {len(value)}"
    if not value.isprintable():
        return f"must be printable text on one line (no control characters), got {printable(value, 120)!r}"
    return None


__all__ = ["MAX_NAME", "NAME_RULE", "duplicate", "label_problem", "name_problem", "printable"]
