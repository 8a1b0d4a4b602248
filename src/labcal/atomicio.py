"""Atomic replacement of output files: an export or a filtered program is either whole or not there.

Everything labcal writes for a user (compensator files, URScript, URDF, ROS YAML, filtered programs) goes
through :func:`write_text` or :func:`write_bytes`. The data are written to a temporary file in the same folder,
flushed and fsynced, and renamed over the target, so a full disk or a kill leaves the old file (or none), never a
program cut after 245 of 3,000 ``movej`` lines. Only a regular file is ever replaced: a device node, a symlink, a
folder or a FIFO at the target is refused (``--force`` or not), because renaming over ``/dev/null`` as root would
replace the device with a file, and writing through a symlink would land the export somewhere the user did not
name.

Example::

    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "robot.script"
    >>> write_text(p, "def f():\\n  return 1\\nend\\n")
    >>> p.read_text().splitlines()[0]
    'def f():'
"""

from __future__ import annotations

import contextlib
import os
import stat
from pathlib import Path

__all__ = ["UnsafeTargetError", "check_target", "fsync_dir", "write_all", "write_bytes", "write_text"]


# What a path that is not a regular file is, for the message that refuses it.
_KINDS = (
    (stat.S_ISLNK, "a symbolic link"),
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISCHR, "a device"),
    (stat.S_ISBLK, "a device"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
)


class UnsafeTargetError(ValueError):
    """The output path names something other than a regular file (or a new name in an existing folder)."""


def check_target(path: str | os.PathLike) -> Path:
    """Refuse an output path that is not a regular file or a free name in an existing folder.

    Returns the path. Raises :class:`UnsafeTargetError` with one line naming the path and what it is.
    """
    path = Path(path)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        parent = path.parent
        if not parent.is_dir():
            raise UnsafeTargetError(f"{path}: its folder {parent} does not exist") from None
        return path
    except OSError as e:
        raise UnsafeTargetError(f"{path}: cannot be inspected ({e.strerror or e})") from None
    if stat.S_ISREG(st.st_mode):
        return path
    kind = next((what for test, what in _KINDS if test(st.st_mode)), "not a regular file")
    raise UnsafeTargetError(f"{path} is {kind}; labcal only writes regular files - name a file path instead")


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, fsync, rename), replacing only a
    regular file. A failure (disk full, permission) leaves the previous file untouched and no temp file behind;
    the error names ``path``."""
    path = check_target(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{os.urandom(4).hex()}")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        if path.exists():  # keep the permissions the user gave the file it replaces
            os.chmod(tmp, stat.S_IMODE(os.lstat(path).st_mode))
        check_target(path)  # a symlink or device swapped in meanwhile is still refused
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise OSError(e.errno, f"cannot write {path}: {e.strerror or e}") from None
    fsync_dir(path.parent)


def write_all(fd: int, data: bytes) -> None:
    """``os.write`` until every byte of ``data`` is written (one call may write only part)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def fsync_dir(path: Path) -> None:
    """Make the directory entries of ``path`` durable (no-op where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> None:
    """:func:`write_bytes` for text (UTF-8 by default)."""
    write_bytes(path, text.encode(encoding))
