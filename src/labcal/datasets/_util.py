"""Small file-system and hashing helpers shared by the store, the journal and the importers.

Durability rule used everywhere: a file is complete once it has been written, flushed and fsynced, and its
*name* is durable once the directory holding it has been fsynced. New things appear by ``os.rename`` of a
finished temporary directory, so a reader never sees a half-written version, session or fit.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import json
import math
import os
import shutil
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from labcal.atomicio import fsync_dir, write_all

READ_ONLY = 0o444

# hashlib (it loads OpenSSL) and secrets are imported by the helpers that hash and make ids, which listing an empty
# store never calls.


def sha256_bytes(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path, limit: int | None = None) -> str:
    """sha256 of a file (or of its first ``limit`` bytes), read in chunks."""
    import hashlib

    h = hashlib.sha256()
    remaining = sys.maxsize if limit is None else limit
    with open(path, "rb") as f:
        while remaining > 0 and (chunk := f.read(min(1 << 20, remaining))):
            h.update(chunk)
            remaining -= len(chunk)
    return h.hexdigest()


def canonical_json(obj: Any, *, indent: int | None = None) -> str:
    """Deterministic JSON (sorted keys, no NaN) so that equal content gives equal bytes and hashes."""
    if indent is None:
        return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False, ensure_ascii=False)
    return json.dumps(obj, sort_keys=True, indent=indent, allow_nan=False, ensure_ascii=False) + "\n"


def json_lines(data: bytes) -> Iterator[tuple[int, Any, str | None]]:
    """(line number from 1, document, None) for each non-blank line of JSON-lines ``data`` that is JSON, (line
    number, None, why) for one that is not: the journal's and the versions log's reader."""
    for i, raw in enumerate(data.split(b"\n"), start=1):
        if raw.strip():
            try:
                doc = json.loads(raw.decode("utf-8"))
            except ValueError as e:  # UnicodeDecodeError and json.JSONDecodeError are ValueErrors
                yield i, None, f"unreadable ({type(e).__name__})"
                continue
            yield i, doc, None


def utc_now() -> _dt.datetime:
    return _dt.datetime.now(_dt.UTC)


def iso(t: _dt.datetime) -> str:
    return t.isoformat(timespec="microseconds").replace("+00:00", "Z")


def random_hex(n: int) -> str:
    import secrets

    return secrets.token_hex((n + 1) // 2)[:n]


def make_dirs_durable(path: Path) -> None:
    """``path.mkdir(parents=True, exist_ok=True)``, and the name of every folder it created made durable (its parent
    fsynced): files fsynced inside a folder whose own entry never reached the disk are lost with it."""
    created = list(itertools.takewhile(lambda p: not p.exists(), (path, *path.parents)))
    path.mkdir(parents=True, exist_ok=True)
    for p in reversed(created):
        fsync_dir(p.parent)


def write_file_durable(path: Path, data: bytes) -> None:
    """Write a new file (must not exist), fsync it, and make it read-only.

    An error of ``write`` or ``fsync`` (a full disk: ENOSPC, a quota, an I/O error) carries no file name of its own;
    it is re-raised with ``path`` as its filename, so the one-line message names the file that could not be written.
    """
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        write_all(fd, data)
        os.fsync(fd)
    except OSError as e:
        if e.filename is None:
            raise OSError(e.errno, e.strerror or str(e), str(path)) from e
        raise
    finally:
        os.close(fd)
    os.chmod(path, READ_ONLY)


def make_temp_dir(parent: Path, prefix: str) -> Path:
    """A fresh hidden directory in ``parent`` (same file system, so a later rename is atomic). Its 8 random hex
    digits make the name unique; were it taken, ``mkdir`` fails (FileExistsError) rather than reuse the folder."""
    p = parent / f".tmp-{prefix}-{random_hex(8)}"
    p.mkdir()
    return p


def remove_tree(path: Path) -> None:
    """Remove a (temporary) tree, including files we made read-only."""
    if not path.exists():
        return

    def onerror(func, p, _exc):
        os.chmod(p, 0o700 if os.path.isdir(p) else 0o600)
        func(p)

    if sys.version_info >= (3, 12):
        shutil.rmtree(path, onexc=onerror)
    else:  # pragma: no cover
        shutil.rmtree(path, onerror=onerror)


def publish_dir(tmp: Path, final: Path) -> None:
    """Atomically rename a finished temporary directory to its final name; fail if the name is taken."""
    fsync_dir(tmp)
    if final.exists():
        raise FileExistsError(f"{final} already exists")
    # os.rename would replace an *empty* existing directory on POSIX; the check above and the non-empty
    # temp dir make a concurrent writer fail with ENOTEMPTY/EEXIST instead of silently winning.
    os.rename(tmp, final)
    fsync_dir(final.parent)


def software_versions() -> dict[str, str]:
    """Versions of the software that produced a document (labcal, Python and the data libraries; scipy when loaded)."""
    import importlib

    import labcal

    out = {"labcal": getattr(labcal, "__version__", "unknown"), "python": sys.version.split()[0]}
    for name in ("numpy", "pandas", "pyarrow"):
        out[name] = importlib.import_module(name).__version__
    if (scipy := sys.modules.get("scipy")) is not None:
        out["scipy"] = scipy.__version__
    return out


def jsonable(obj: Any, *, finite: bool = False) -> Any:
    """Convert numpy arrays/scalars and tuples inside ``obj`` to plain JSON types (floats kept exact).

    ``finite=True`` turns NaN and ±inf into None, for reports whose statistics may be undefined (the import
    checks'); documents keep them, so that :func:`canonical_json` refuses a NaN instead of storing a null. (The
    compensator's ``io._canonical`` differs on purpose: every number a float, so a payload hashes alike as JSON
    and NPZ; the CLI's ``plain`` writes any other object as its text.)
    """
    import numpy as np

    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), finite=finite)
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, finite=finite) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v, finite=finite) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if finite and isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
