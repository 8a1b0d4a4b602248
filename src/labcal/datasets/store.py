"""The session store: sessions, immutable versions, verification and fits.

Layout::

    <store>/<session-id>/
        journal.jsonl                 append-only documents of recorded runs (absent for imported sessions)
        v001/                         an immutable version
            measurements.parquet      the measurements table (read-only file)
            manifest.json             metadata, units, sha256 of every data file, its own sha256 (read-only)
            fits/<fit-id>/            fits that read this version (added later; NOT part of the version's hash)
                fit.json              inputs (refs + hashes), caller's metadata, sha256 of each fit file
                ...                   the caller's files (model weights, metrics, exports)
        v002/ …                       parent = v001: all rows of v001 plus the new ones
        versions.jsonl                one line per version ever published (name, manifest sha256): so a deleted
                                      version is reported, not silently forgotten

The default store is ``$LABCAL_STORE`` if set, else ``./sessions`` relative to the current directory.

A version is written into a hidden temporary directory inside the session, every file fsynced and made
read-only (0o444), then renamed to ``vNNN`` in one step, so it either exists complete or not at all. The same
holds for a whole imported session and for a fit. Hidden ``.tmp-*`` directories left by a crash are ignored.
The ``fits/`` folder of a version is the only thing that may change after the version was written: adding a
fit never touches the version's data files or manifest, and ``verify`` ignores ``fits/``.

Each version stands on its own manifest: :meth:`SessionStore.verify` checks only the version's own files against its
own hashes, so damage elsewhere (the journal, another version) never makes an intact version unusable. What spans
the session (the journal against the part of it each version sealed, the start document, versions listed in
``versions.jsonl`` or named as a parent but gone, a journal gone) is :meth:`SessionStore.check_session`;
:meth:`SessionStore.check_before_recording` runs both over the whole session before a recording command moves the
robot. Entries that labcal did not write (a copied ``ID (copy)`` folder, ``.DS_Store``, ``Thumbs.db``, ``*~``) are
listed as foreign (:meth:`SessionStore.foreign_entries`, :attr:`VerifyReport.notes`) and skipped, never fatal.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.atomicio import write_bytes

from ._util import (
    READ_ONLY,
    canonical_json,
    fsync_dir,
    iso,
    json_lines,
    jsonable,
    make_dirs_durable,
    make_temp_dir,
    publish_dir,
    remove_tree,
    sha256_bytes,
    sha256_file,
    software_versions,
    utc_now,
    write_all,
    write_file_durable,
)
from .errors import DatasetCorrupted, DatasetError, JournalCorrupted, UnknownSession, UnknownVersion
from .ids import _ID_RE, Ref, new_fit_id, new_session_id, parse_ref, parse_version, validate_id, version_name
from .schema import SCHEMA_VERSION, column_units, joint_columns, normalize_table, spread_columns, target_columns

MEASUREMENTS = "measurements.parquet"
MANIFEST = "manifest.json"
FITS = "fits"
FIT_JSON = "fit.json"
# V/fits/.evaluations/<fit id>/<evaluation id>.json: `labcal evaluate` results, beside the sealed fit folders (a fit's
# folder never changes after save_fit), each a self-hashed JSON document like fit.json.
EVALUATIONS = ".evaluations"
_VERSION_DIR = re.compile(r"^v(\d{3,6})$")
#: The session's list of published versions (append-only JSON lines: version, manifest sha256, parent).
VERSIONS_LOG = "versions.jsonl"
# Files that operating systems, file managers and editors drop into any folder they touch: foreign, never fatal.
_OS_FILES = frozenset({".DS_Store", "Thumbs.db", "desktop.ini", ".directory", "Icon\r", ".localized"})


def is_os_or_editor_file(name: str) -> bool:
    """True for the litter of file managers and editors (``.DS_Store``, ``Thumbs.db``, ``._x``, ``x~``, ``.x.swp``):
    foreign in the store, reported as such and skipped, never a reason to refuse a version."""
    return (
        name in _OS_FILES
        or name.startswith(("._", ".#", ".~lock."))
        or name.endswith(("~", ".swp", ".swo", ".bak", ".orig"))
    )


# journal and documents are imported where they are used: an empty store, a listing of imported sessions and
# `labcal --help` need neither (schema imports numpy and pandas only in its functions). The journal's file name is
# all a listing needs; tests/cli/test_scripting.py checks it is journal.JOURNAL_NAME.
JOURNAL_NAME = "journal.jsonl"

if TYPE_CHECKING:
    import numpy as np
    import pandas as pd

    from .documents import MeasurementDoc, SessionHeader, StartDoc
    from .journal import Journal, JournalContents


class StoreWriteError(DatasetError, OSError):
    """Writing to the session store failed (read-only, full, permissions). A DatasetError, so the CLI prints its one
    line, and still an OSError, so callers that handle OS errors keep working; the original error is chained."""


def _writes(what: str):
    """Turn an OS error while writing (read-only store, full disk, permissions) into one DatasetError line that
    names the store and the operation, instead of a traceback. Nothing half-written is left visible: every write
    goes to a hidden temporary folder first (see the module docstring)."""

    def decorate(fn):
        @functools.wraps(fn)
        def wrapper(self, *args, **kwargs):
            try:
                return fn(self, *args, **kwargs)
            except DatasetError:
                raise
            except OSError as e:
                import errno

                where = f" ({e.filename})" if getattr(e, "filename", None) else ""
                fix = (
                    "free space on its disk, or set --store or LABCAL_STORE to a folder on another disk"
                    if e.errno in (errno.ENOSPC, errno.EDQUOT)
                    else "is it read-only or full? set --store or LABCAL_STORE to a writable folder"
                )
                raise StoreWriteError(
                    f"cannot {what} in the session store {self.root}: {e.strerror or e}{where} ({fix}); nothing "
                    "half-written was left"
                ) from e

        return wrapper

    return decorate


def default_root() -> Path:
    """``$LABCAL_STORE`` if set and non-empty, else ``./sessions`` (relative to the current directory)."""
    env = os.environ.get("LABCAL_STORE")
    return Path(env) if env else Path.cwd() / "sessions"


# --------------------------------------------------------------------------------------------------------------
# Self-hashed JSON: the file's bytes are the canonical dump, and it carries the sha256 of its other content.


def _content_sha256(obj: dict, key: str) -> str:
    """What a self-hashed document holds under ``key``: the sha256 of the canonical JSON of its other fields."""
    return sha256_bytes(canonical_json({k: v for k, v in obj.items() if k != key}).encode("utf-8"))


def _dump_sealed(obj: dict, key: str) -> bytes:
    return canonical_json({**obj, key: _content_sha256(obj, key)}, indent=2).encode("utf-8")


def _write_sealed(folder: Path, files: Mapping[str, bytes], doc: dict, name: str, key: str) -> dict:
    """Write ``files`` (name → bytes) into ``folder``, then ``doc`` as the file ``name`` with what every labcal
    record carries (schema version, creation time, software, sha256 and size of each file), self-hashed under
    ``key``: a version's manifest, a fit's fit.json. Every file fsynced and read-only; returns the record written."""
    for file, data in sorted(files.items()):
        write_file_durable(folder / file, data)
    listed = {file: {"sha256": sha256_bytes(data), "bytes": len(data)} for file, data in files.items()}
    common = {"schema_version": SCHEMA_VERSION, "created": iso(utc_now()), "software": software_versions()}
    sealed = _dump_sealed({**doc, **common, "files": listed}, key)
    write_file_durable(folder / name, sealed)
    return json.loads(sealed)


def _load_sealed(data: bytes, key: str, name: str) -> tuple[dict | None, list[str]]:
    try:
        obj = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        return None, [f"{name}: not valid JSON any more ({type(e).__name__}: {e})"]
    if not isinstance(obj, dict) or key not in obj:
        return None, [f"{name}: has no {key!r} field"]
    problems = []
    actual = _content_sha256(obj, key)
    if actual != obj[key]:
        problems.append(f"{name}: content sha256 mismatch: expected {obj[key]}, actual {actual}")
    elif canonical_json(obj, indent=2).encode("utf-8") != data:
        problems.append(f"{name}: bytes differ from the canonical form written (formatting was changed)")
    return obj, problems


# --------------------------------------------------------------------------------------------------------------
# Result types


@dataclass(frozen=True)
class Dataset:
    """One loaded version. ``table`` is the measurements table (see :mod:`labcal.datasets.schema`)."""

    ref: str
    table: pd.DataFrame
    manifest: dict

    @property
    def n_joints(self) -> int:
        return int(self.manifest["session"]["robot"]["n_joints"])

    @property
    def robot(self) -> dict:
        """{"name", "hash", "n_joints"} of the robot model the data were taken with, plus "text" and "format" (the
        robot file itself) for data recorded or imported since versions store it (``cli.ops.common.robot_for``)."""
        return dict(self.manifest["session"]["robot"])

    @property
    def frame(self) -> str:
        """ "base" or "tracker": the frame of :attr:`points`."""
        return self.manifest["session"]["frame"]

    @property
    def targets(self) -> np.ndarray:
        """(m, 3) m: the target points in the tool frame, row i = target t(i+1)."""
        import numpy as np

        return np.asarray(self.manifest["session"]["targets"], dtype=np.float64).reshape(-1, 3)

    @property
    def n_targets(self) -> int:
        """m: the number of targets (the length of the manifest's targets list)."""
        return len(self.manifest["session"]["targets"])

    @property
    def q(self) -> np.ndarray:
        """(k, n) rad: joint positions as the controller reported them (controller joints; the robot file's joint
        map converts them to model joints: ``labcal.cli.ops.common.load_observations``)."""
        return self.table[joint_columns(self.n_joints)].to_numpy(dtype=float)

    @property
    def points(self) -> np.ndarray:
        """(k, m, 3) m: measured targets; ``points[:, i]`` is target t(i+1), all NaN where it was not seen."""
        m = self.n_targets
        return self.table[list(target_columns(m))].to_numpy(dtype=float).reshape(-1, m, 3)

    @property
    def seen(self) -> np.ndarray:
        """(k, m) bool: target t(i+1) was seen in the row (``points[r, i]`` is finite)."""
        import numpy as np

        return ~np.isnan(self.points).all(axis=2)

    @property
    def split(self) -> np.ndarray:
        """(k,) str: "train", "val", "test" or "" (unassigned)."""
        return self.table["split"].to_numpy(dtype=str)

    @property
    def pose(self) -> np.ndarray:
        """(k,) int: plan index (or import row) of each measurement."""
        return self.table["pose"].to_numpy(dtype="int64")

    @property
    def spread(self) -> np.ndarray | None:
        """(k, m) m tracker spread per target (NaN where not seen or unknown), or None if the version has none."""
        cols = list(spread_columns(self.n_targets))
        if not all(c in self.table.columns for c in cols):
            return None
        return self.table[cols].to_numpy(dtype=float)

    @property
    def units(self) -> dict[str, str]:
        return dict(self.manifest["units"])

    def __len__(self) -> int:
        return len(self.table)


@dataclass(frozen=True)
class VerifyReport:
    """Result of :meth:`SessionStore.verify` (one version) or :meth:`SessionStore.check_session` (what spans the
    session; ``ref`` is then the session id). ``problems`` has one line per fault (empty = intact); ``notes`` lists
    foreign entries (OS and editor files) that were skipped and do not make the result bad."""

    ref: str
    problems: list[str]
    checked: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def raise_if_bad(self) -> None:
        if self.problems:
            raise DatasetCorrupted(
                f"{self.ref} is corrupted ({len(self.problems)} problem(s)):\n  " + "\n  ".join(self.problems),
                self.problems,
            )


@dataclass(frozen=True)
class SealResult:
    """Result of :meth:`SessionStore.seal`: ``ref`` of the new version (or of the latest if none was made)."""

    ref: str | None
    created: bool
    rows_added: int
    message: str


@dataclass(frozen=True)
class VersionInfo:
    name: str
    rows: int
    created: str
    source: str
    parent: str | None
    fits: int


@dataclass(frozen=True)
class SessionInfo:
    session_id: str
    robot: dict
    frame: str
    status: str
    versions: list[VersionInfo]
    measurements: int | None  # journal measurement documents (valid + rejected), None without a journal
    warnings: list[str]

    @property
    def rows(self) -> int:
        """Rows in the latest version (0 if none)."""
        return self.versions[-1].rows if self.versions else 0


@dataclass(frozen=True)
class FitRecord:
    """A stored fit: ``ref`` is the version it is stored under; ``meta`` the content of fit.json."""

    fit_id: str
    ref: str
    path: Path
    meta: dict

    @property
    def inputs(self) -> list[dict]:
        return list(self.meta["inputs"])

    @property
    def metadata(self) -> dict:
        return dict(self.meta["metadata"])

    @property
    def files(self) -> list[str]:
        return sorted(self.meta["files"])

    def read(self, name: str) -> bytes:
        """Bytes of one fit file, checked against its recorded sha256."""
        if name not in self.meta["files"]:
            raise UnknownVersion(f"fit {self.fit_id} has no file {name!r}; it has {self.files}")
        data = (self.path / name).read_bytes()
        expected = self.meta["files"][name]["sha256"]
        if sha256_bytes(data) != expected:
            raise DatasetCorrupted(
                f"fit {self.fit_id}: {name}: sha256 mismatch: expected {expected}, actual {sha256_bytes(data)}"
            )
        return data


# --------------------------------------------------------------------------------------------------------------


def _parquet_bytes(table: pd.DataFrame) -> bytes:
    import pyarrow as pa
    import pyarrow.parquet as pq

    buf = pa.BufferOutputStream()
    pq.write_table(pa.Table.from_pandas(table, preserve_index=False), buf, compression="zstd")
    return buf.getvalue().to_pybytes()


def _read_parquet(data: bytes) -> pd.DataFrame:
    import pyarrow.parquet as pq

    return pq.read_table(io.BytesIO(data)).to_pandas()


@contextlib.contextmanager
def _publishing(parent: Path, prefix: str, final: Path) -> Iterator[Path]:
    """A fresh hidden temporary folder in ``parent`` to fill, renamed to ``final`` when the block ends; removed
    instead if the block or the rename fails, so ``final`` appears complete or not at all."""
    tmp = make_temp_dir(parent, prefix)
    try:
        yield tmp
        publish_dir(tmp, final)
    except BaseException:
        remove_tree(tmp)
        raise


def _plan_summary(plan: Sequence[Any]) -> dict:
    """Length and sha256 of a plan (JSON types: as read from a journal)."""
    return {"length": len(plan), "sha256": sha256_bytes(canonical_json(list(plan)).encode("utf-8"))}


def with_robot_record(meta: dict) -> dict:
    """``meta`` with the robot file's text in ``meta["robot"]`` when the caller handed the record elsewhere.

    Importers may pass ``RobotSpec.record()`` (name, hash, n_joints, text, format) either as ``meta["robot"]`` or
    inside the user metadata as ``meta["metadata"]["robot"]``; either way the manifest's ``session.robot`` ends up
    holding the text, which is what makes a version refittable without the robot file. A record of another model
    (different hash) is refused rather than silently attached.
    """
    robot = meta["robot"]
    user = dict(meta.get("metadata") or {})
    record = user.pop("robot", None)  # stored once, in session.robot
    if not isinstance(record, Mapping) or not record.get("text"):
        return meta
    if record.get("hash") not in (None, robot.get("hash")):
        raise DatasetError(
            f"the robot record passed in the metadata (hash {str(record.get('hash'))[:12]}…) is not the model the "
            f"data are labelled with ({robot.get('name')!r}, hash {str(robot.get('hash'))[:12]}…)"
        )
    robot = {**{str(key): jsonable(value) for key, value in record.items()}, **robot}  # the labels win
    return {**meta, "robot": robot, "metadata": user}


def session_meta_from_start(start: StartDoc) -> dict:
    """The ``session`` block of a manifest, from a journal's start document: what describes the session (robot,
    targets, frame, devices, units of the extra fields, metadata) and a summary of the plan."""
    doc = start.to_json()
    keep = ("session_id", "robot", "targets", "frame", "tracker", "robot_driver", "extra_units", "metadata")
    return {**{k: doc[k] for k in keep}, "targets_unit": "m", "plan": _plan_summary(start.plan)}


_ID_TIME = re.compile(r"^(\d{4})(\d{2})(\d{2})-(\d{2})(\d{2})(\d{2})-")


def started_at(info: SessionInfo) -> str:
    """ISO-8601 UTC start of a session ("" if unknown): its id's time prefix, else its first version's creation.

    >>> started_at(SessionInfo("20261122-031500-ur10-3f9a", {}, "base", "done", [], None, []))
    '2026-11-22T03:15:00'
    """
    match = _ID_TIME.match(info.session_id)
    if match:
        return "{}-{}-{}T{}:{}:{}".format(*match.groups())
    return info.versions[0].created if info.versions else ""


class SessionStore:
    """A folder of sessions. ``root`` defaults to :func:`default_root` (``$LABCAL_STORE`` or ``./sessions``)."""

    def __init__(self, root: str | Path | None = None) -> None:
        self.root = Path(root) if root is not None else default_root()

    def __repr__(self) -> str:
        return f"SessionStore({str(self.root)!r})"

    # ---------------------------------------------------------------------------------------------- sessions
    def session_dir(self, session_id: str) -> Path:
        return self.root / validate_id(session_id)

    def session_ids(self) -> list[str]:
        """All session ids, sorted (ids start with their UTC creation time, so this is chronological).

        Only folders whose name is a valid session id and that hold a journal, a version or a versions log count;
        anything else (``ID (copy)``, ``.DS_Store``, stray files) is foreign: see :meth:`foreign_entries`."""
        return sorted(p.name for p in self._root_entries() if _session_folder_problem(p) is None)

    def _root_entries(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        # labcal's own hidden temporary folders (an import interrupted before its rename) are not entries at all
        return [p for p in self.root.iterdir() if not p.name.startswith(".tmp-")]

    def foreign_entries(self) -> list[tuple[str, str]]:
        """(name, why) of every entry of the store folder that is not a session: skipped by listings, never fatal.

        Example: a folder copied by a file manager, ``20261122-031500-ur10-3f9a (copy)``, gives ``("… (copy)", "not a
        session id (…): a copy? rename it to a new id to use it as a session")``."""
        entries = sorted(self._root_entries(), key=lambda q: q.name)
        return [(p.name, why) for p in entries if (why := _session_folder_problem(p)) is not None]

    def require_root(self) -> None:
        """Raise :class:`UnknownSession` with one clear line when the store folder does not exist."""
        if not self.root.is_dir():
            what = "is not a folder" if self.root.exists() else "does not exist"
            raise UnknownSession(f"no session store at {self.root} ({what}; set --store or LABCAL_STORE)")

    def _require_session(self, session_id: str) -> Path:
        d = self.session_dir(session_id)
        if not d.is_dir():
            self.require_root()
            known = self.session_ids()
            hint = f"; known sessions: {', '.join(known[-20:])}" if known else "; the store is empty"
            raise UnknownSession(
                f"no session {session_id!r} in store {self.root}{_did_you_mean(session_id, known)}{hint}"
            )
        return d

    def versions(self, session_id: str) -> list[int]:
        """Version numbers of a session, ascending."""
        d = self._require_session(session_id)
        return sorted(int(m.group(1)) for p in d.iterdir() if p.is_dir() and (m := _VERSION_DIR.match(p.name)))

    def resolve(self, ref: str | Ref) -> Ref:
        """Check a reference against the store and return it with a concrete version number.

        Raises :class:`UnknownSession` / :class:`UnknownVersion` listing what is available.
        """
        r = parse_ref(ref)
        versions = self.versions(r.session_id)
        available = ", ".join(version_name(v) for v in versions) or "none"
        if r.version is None:
            if not versions:
                raise UnknownVersion(
                    f"session {r.session_id!r} has no versions yet (seal its journal first); available: none"
                )
            return Ref(r.session_id, versions[-1])
        if r.version not in versions:
            raise UnknownVersion(
                f"session {r.session_id!r} has no version {version_name(r.version)}; available: {available}"
            )
        return r

    def version_dir(self, ref: str | Ref) -> Path:
        return self._located(ref)[1]

    def _located(self, ref: str | Ref) -> tuple[Ref, Path]:
        """The resolved reference (:meth:`resolve`) and its version folder."""
        r = self.resolve(ref)
        return r, self.session_dir(r.session_id) / version_name(r.version)  # type: ignore[arg-type]

    @_writes("create a session")
    def create_session(self, header: SessionHeader) -> Journal:
        """Create a session folder and its journal (start document of ``header`` written and fsynced); return the
        open :class:`Journal` (close it when done).

        ``header.robot``: the model's full record (``RobotSpec.record()``, with the file text) is stored in the start
        document and so in every version sealed from it, which makes the session refittable without the file.
        ``header.session_id``: None = a new id from the robot name and the time.
        """
        from .journal import Journal

        session_id = validate_id(header.session_id) if header.session_id else new_session_id(str(header.robot["name"]))
        make_dirs_durable(self.root)
        d = self.root / session_id
        try:
            d.mkdir()
        except FileExistsError:
            raise DatasetError(f"session {session_id!r} already exists in {self.root}") from None
        fsync_dir(self.root)
        try:
            return Journal.create(d / JOURNAL_NAME, header, session_id=session_id)
        except BaseException:
            # Nothing was written (or the start document failed): leave no empty session behind.
            with contextlib.suppress(OSError):
                (d / JOURNAL_NAME).unlink(missing_ok=True)
                d.rmdir()
            raise

    def open_journal(self, session_id: str) -> Journal:
        """Open a session's journal for appending (resume); repairs a torn last line."""
        from .journal import Journal

        return Journal.open(self._require_session(session_id) / JOURNAL_NAME)

    def read_journal(self, session_id: str) -> JournalContents:
        from .journal import read_journal

        return read_journal(self._require_session(session_id) / JOURNAL_NAME)

    def session_meta(self, session_id: str) -> dict:
        """The session's metadata block (robot, targets, frame, tracker …) from its journal or latest version."""
        d = self._require_session(session_id)
        if (d / JOURNAL_NAME).exists():
            start = self.read_journal(session_id).start
            if start is not None:
                return session_meta_from_start(start)
        versions = self.versions(session_id)
        if not versions:
            raise DatasetError(f"session {session_id!r} has neither a readable journal nor a version")
        return self.manifest(Ref(session_id, versions[-1]))["session"]

    def show(self, session_id: str) -> SessionInfo:
        """Summary of one session: robot, frame, status, versions (rows, source, parent, fits)."""
        d = self._require_session(session_id)
        warnings: list[str] = []
        status, n_meas = "imported", None
        if (d / JOURNAL_NAME).exists():
            contents = self.read_journal(session_id)
            status, n_meas = contents.status, len(contents.measurements)
            warnings += contents.warnings
        infos = []
        for v in self.versions(session_id):
            vdir = d / version_name(v)
            try:
                m = json.loads((vdir / MANIFEST).read_text(encoding="utf-8"))
                nfits = sum(p.is_dir() and not p.name.startswith(".") for p in (vdir / FITS).glob("*"))
                infos.append(
                    VersionInfo(version_name(v), int(m["row_count"]), m["created"], m["source"], m["parent"], nfits)
                )
            except (OSError, ValueError, KeyError) as e:
                warnings.append(f"{version_name(v)}: unreadable manifest ({e}); run verify")
                infos.append(VersionInfo(version_name(v), 0, "?", "?", None, 0))
        try:
            meta = self.session_meta(session_id)
            robot, frame = meta["robot"], meta["frame"]
        except (DatasetError, OSError, ValueError, KeyError) as e:
            warnings.append(f"no readable session metadata: {e}")
            robot, frame = {}, "?"
        return SessionInfo(session_id, robot, frame, status, infos, n_meas, warnings)

    def list_sessions(self) -> list[SessionInfo]:
        """:meth:`show` for every session, oldest first: by the UTC start time in the id, or for an id without one
        (e.g. the shipped ``example``, which sorted after every dated id) by its first version's creation."""
        return sorted((self.show(s) for s in self.session_ids()), key=started_at)

    # ---------------------------------------------------------------------------------------------- versions
    def manifest(self, ref: str | Ref) -> dict:
        """The manifest of a version (not verified; use :meth:`verify` or :meth:`load` for that)."""
        return json.loads((self.version_dir(ref) / MANIFEST).read_text(encoding="utf-8"))

    def verify(self, ref: str | Ref) -> VerifyReport:
        """Recompute every hash of a version; report missing, extra and changed files precisely."""
        r, vdir = self._located(ref)
        if not (vdir / MANIFEST).is_file():
            return VerifyReport(str(r), [f"{MANIFEST}: missing"])
        manifest, problems = _load_sealed((vdir / MANIFEST).read_bytes(), "manifest_sha256", MANIFEST)
        checked = [MANIFEST]
        if manifest is None:
            return VerifyReport(
                str(r), [f"{m} (the data files cannot be checked without it)" for m in problems], checked
            )
        if manifest.get("ref") != str(r):
            problems.append(f"{MANIFEST}: belongs to {manifest.get('ref')!r}, found as {str(r)!r}")
        listed = dict(manifest.get("files") or {})
        _check_files(vdir, listed, "", problems, checked)
        notes: list[str] = []
        for p in sorted(vdir.iterdir()):
            if p.name in listed or p.name == MANIFEST or (p.name == FITS and p.is_dir()):
                continue
            kind = "directory" if p.is_dir() else "file"
            if is_os_or_editor_file(p.name):
                notes.append(f"{p.name}: foreign {kind} (operating system or editor), skipped")
                continue
            problems.append(f"{p.name}: extra {kind} not listed in the manifest")
        # The journal is not part of the version: the version holds its own copy of every measurement it sealed,
        # so damage to the journal must never make it unusable (check_session reports the journal).
        return VerifyReport(str(r), problems, checked, notes)

    def check_session(self, session_id: str) -> VerifyReport:
        """What spans the versions of a session: the journal against the part of it each version sealed, the
        start document, versions gone (listed in the versions log, a gap in the numbering) and the journal gone.

        Each version's own files are :meth:`verify`'s; ``ref`` of the report is the session id. Foreign entries
        of the session folder are notes. One line per problem, naming the file, the line or version, and the fix.
        """
        d = self._require_session(session_id)
        problems: list[str] = []
        checked: list[str] = []
        notes = _foreign_entry_notes(d)
        versions = self.versions(session_id)
        manifests: dict[int, dict | None] = {}
        for v in versions:
            try:
                manifests[v] = json.loads((d / version_name(v) / MANIFEST).read_text(encoding="utf-8"))
            except (OSError, ValueError):
                manifests[v] = None  # the version's own verify says why
        last = versions[-1] if versions else 0
        gap = f"{version_name(last)} exists and versions are numbered in order" if last else ""
        missing = {v: gap for v in range(1, last) if v not in manifests}
        log = d / VERSIONS_LOG
        if log.is_file():
            checked.append(VERSIONS_LOG)
            _check_versions_log(log, manifests, missing, problems, notes)
        for v, why in sorted(missing.items()):
            problems.append(
                f"{version_name(v)}: missing ({why}): restore {d / version_name(v)} from a backup; the other versions "
                "stand on their own"
            )
        sealed = [(v, m["provenance"]["journal"]) for v, m in manifests.items()
                  if m and isinstance((m.get("provenance") or {}).get("journal"), dict)]  # fmt: skip
        jpath = d / JOURNAL_NAME
        if not jpath.exists():
            if sealed:
                problems.append(
                    f"{JOURNAL_NAME}: missing ({version_name(sealed[0][0])} was sealed from it): restore it from a "
                    "backup; the versions keep their own copies of the measurements (fit them as they are), but the "
                    "session cannot be resumed or sealed again"
                )
            return VerifyReport(session_id, problems, checked, notes)
        contents = self.read_journal(session_id)
        checked.append(JOURNAL_NAME)
        problems += _journal_problems(session_id, jpath, contents, sealed, manifests)
        return VerifyReport(session_id, problems, checked, notes)

    def check_before_recording(self, session_id: str) -> None:
        """Verify the whole session before a recording command moves the robot: every version's own files, the
        journal (against what each version sealed), the start document, versions or journal gone.

        Raises :class:`DatasetCorrupted` with one line naming the first problem, how many more there are and the fix,
        so a resume never drives the plan only to find at the end that the result cannot be sealed."""
        reports = [self.verify(Ref(session_id, v)) for v in self.versions(session_id)]
        reports.append(self.check_session(session_id))
        problems = [f"{r.ref}: {p}" if r.ref != session_id else p for r in reports for p in r.problems]
        if not problems:
            return
        n_more = len(problems) - 1
        more = f" (and {n_more} more: `labcal session verify {session_id}` lists them)" if n_more else ""
        bad_version = next((r.ref for r in reports[:-1] if r.problems), None)
        fix = ""
        if bad_version is not None and not reports[-1].problems:
            fix = (f"; restore {self.version_dir(bad_version)} from a backup (the other versions stand on their own), "
                   "or record the remaining poses in a new session")  # fmt: skip
        raise DatasetCorrupted(
            f"session {session_id} is damaged; nothing was moved: {problems[0]}{more}{fix}", problems
        )

    def verify_fits(self, ref: str | Ref) -> VerifyReport:
        """Check every fit stored under a version (the version's own :meth:`verify` leaves ``fits/`` out).

        Per fit: fit.json's own sha256 and canonical bytes, the sha256 of every file it lists, missing and unlisted
        files, and that each input version's manifest is still the one the fit read. One line per problem.
        """
        r, vdir = self._located(ref)
        fits_dir = vdir / FITS
        problems: list[str] = []
        checked: list[str] = []
        notes: list[str] = []
        for p in sorted(fits_dir.glob("*")):  # none without a fits/ folder
            if p.name.startswith("."):  # the temporary folder of an interrupted save_fit, never published
                continue
            where = f"{FITS}/{p.name}"
            if is_os_or_editor_file(p.name):
                kind = "folder" if p.is_dir() else "file"
                notes.append(f"{where}: foreign {kind} (operating system or editor), skipped")
                continue
            if not p.is_dir():
                problems.append(f"{where}: extra file in {FITS}/ (a fit is a folder)")
                continue
            if not (p / FIT_JSON).is_file():
                problems.append(f"{where}/{FIT_JSON}: missing (the fit's files cannot be checked without it)")
                continue
            meta, mp = _load_sealed((p / FIT_JSON).read_bytes(), "fit_sha256", f"{where}/{FIT_JSON}")
            problems += mp
            checked.append(f"{where}/{FIT_JSON}")
            if meta is None:
                continue
            files = dict(meta.get("files") or {})
            _check_files(p, files, f"{where}/", problems, checked)
            for fp in sorted(p.iterdir()):
                if fp.name != FIT_JSON and fp.name not in files:
                    kind = "directory" if fp.is_dir() else "file"
                    problems.append(f"{where}/{fp.name}: extra {kind} not listed in {FIT_JSON}")
            for inp in meta.get("inputs") or []:
                try:
                    current = self.manifest(inp["ref"]).get("manifest_sha256")
                except (DatasetError, OSError, ValueError, KeyError) as e:
                    problems.append(f"{where}: input {inp.get('ref')!r} cannot be read ({type(e).__name__}: {e})")
                    continue
                if current != inp.get("manifest_sha256"):
                    problems.append(
                        f"{where}: input {inp['ref']} is not the data the fit read (manifest sha256 "
                        f"{inp.get('manifest_sha256')} when fitted, {current} now)"
                    )
        for ep in sorted((fits_dir / EVALUATIONS).glob("*/*.json")):
            where = f"{FITS}/{EVALUATIONS}/{ep.parent.name}/{ep.name}"
            checked.append(where)
            problems += _load_sealed(ep.read_bytes(), "evaluation_sha256", where)[1]
            if not (fits_dir / ep.parent.name / FIT_JSON).is_file():
                problems.append(f"{where}: evaluates fit {ep.parent.name}, which is not stored under {r}")
        return VerifyReport(str(r), problems, checked, notes)

    def load(self, ref: str | Ref) -> Dataset:
        """Load a version after verifying its hashes; raises :class:`DatasetCorrupted` on any mismatch."""
        r, vdir = self._located(ref)
        self.verify(r).raise_if_bad()
        manifest = json.loads((vdir / MANIFEST).read_text(encoding="utf-8"))
        data = (vdir / MEASUREMENTS).read_bytes()
        # Hash the very bytes we parse, so a change after verify() cannot slip through.
        expected = manifest["files"][MEASUREMENTS]["sha256"]
        if sha256_bytes(data) != expected:
            raise DatasetCorrupted(f"{r}: {MEASUREMENTS} changed while loading", [f"{MEASUREMENTS}: changed"])
        table = _read_parquet(data)
        if list(table.columns) != manifest["columns"] or len(table) != manifest["row_count"]:
            raise DatasetCorrupted(f"{r}: table columns/rows disagree with the manifest")
        return Dataset(str(r), table, manifest)

    def _write_version(
        self,
        where: Path,
        session_id: str,
        parent_ds: Dataset | None,
        rows: pd.DataFrame,
        meta: dict,
        *,
        source: str,
        provenance: dict,
        journal_seq_through: int,
    ) -> str:
        """Publish the version after ``parent_ds`` (None: v001) in the session folder ``where``: the parent's rows
        plus ``rows``, checked (:func:`~labcal.datasets.schema.normalize_table`), and its manifest (``meta`` is its
        ``session`` block). Written into a temporary folder, then renamed; returns the new ``SESSION@vNNN``."""
        import pandas as pd

        table = rows if parent_ds is None else pd.concat([parent_ds.table, rows], ignore_index=True)
        table = normalize_table(table, int(meta["robot"]["n_joints"]), len(meta["targets"]))
        parent = None if parent_ds is None else parse_ref(parent_ds.ref).version
        name = version_name((parent or 0) + 1)
        manifest = {
            "kind": "labcal.dataset.version",
            "session_id": session_id,
            "version": name,
            "ref": f"{session_id}@{name}",
            "parent": version_name(parent) if parent else None,
            "source": source,
            "session": meta,
            "row_count": len(table),
            "columns": list(table.columns),
            "units": column_units(
                list(table.columns), {f"x_{k}": u for k, u in (meta.get("extra_units") or {}).items()}
            ),
            "journal_seq_through": journal_seq_through,
            "provenance": jsonable(provenance),
        }
        with _publishing(where, name, where / name) as tmp:
            written = _write_sealed(tmp, {MEASUREMENTS: _parquet_bytes(table)}, manifest, MANIFEST, "manifest_sha256")
        # After the rename: a crash in between leaves a complete version the log does not list yet, which
        # check_session notes; the other order would list a version that was never published.
        _log_version(where, name, written["manifest_sha256"], manifest["parent"])
        return f"{session_id}@{name}"

    def _check_compatible(self, session_id: str, meta: dict, new: dict) -> None:
        """Refuse to mix data of another robot, target set or frame into a session."""
        import numpy as np

        a, b = meta, new
        if a["robot"]["n_joints"] != b["robot"]["n_joints"] or a["robot"]["hash"] != b["robot"]["hash"]:
            raise DatasetError(
                f"session {session_id!r} was recorded with robot {a['robot']}; the new data are for {b['robot']}"
            )
        if a["frame"] != b["frame"]:
            raise DatasetError(f"session {session_id!r} has points in the {a['frame']} frame, new data in {b['frame']}")
        ta, tb = np.asarray(a["targets"], dtype=float), np.asarray(b["targets"], dtype=float)
        if ta.shape != tb.shape or not np.allclose(ta, tb, rtol=0, atol=1e-9):
            raise DatasetError(f"session {session_id!r} has targets {a['targets']}, new data {b['targets']}")

    @_writes("write a new version")
    def append_rows(self, session_id: str, rows: pd.DataFrame, meta: dict, *, source: str, provenance: dict) -> str:
        """Make a new version of an existing session: all rows of the latest version plus ``rows``.

        ``meta`` describes the new rows (same robot hash, n_joints, frame and targets as the session).
        Returns the new ref ``SESSION@vNNN``.
        """
        d = self._require_session(session_id)
        versions = self.versions(session_id)
        session = self.session_meta(session_id)
        meta = with_robot_record(meta)
        self._check_compatible(session_id, session, meta)
        parent_ds = self.load(Ref(session_id, versions[-1])) if versions else None
        through = int(parent_ds.manifest.get("journal_seq_through", 0)) if parent_ds is not None else 0
        merged = {**session, "extra_units": {**meta.get("extra_units", {}), **session.get("extra_units", {})}}
        return self._write_version(
            d, session_id, parent_ds, rows, merged, source=source, provenance=provenance, journal_seq_through=through
        )

    @_writes("write the imported session")
    def create_imported_session(
        self, rows: pd.DataFrame, meta: dict, *, source: str, provenance: dict, session_id: str | None = None
    ) -> str:
        """Create a session holding only ``v001`` (no journal), atomically: it appears complete or not at all."""
        session_id = validate_id(session_id) if session_id else new_session_id(meta["robot"]["name"])
        meta = with_robot_record({**meta, "session_id": session_id})
        make_dirs_durable(self.root)
        final = self.root / session_id
        if final.exists():
            raise DatasetError(f"session {session_id!r} already exists in {self.root}")
        with _publishing(self.root, f"session-{session_id}", final) as tmp:
            return self._write_version(
                tmp, session_id, None, rows, meta, source=source, provenance=provenance, journal_seq_through=0
            )

    @_writes("seal the journal into a version")
    def seal(self, session_id: str, *, valid_prefix: bool = False) -> SealResult:
        """Make a new version from the journal's valid measurements not yet in a version.

        If there is nothing new, no version is made (``created=False``, message says so). Unreadable journal
        lines that are not a torn last write make sealing fail (:class:`JournalCorrupted`), unless
        ``valid_prefix``: then only the documents before the first corrupt line are sealed, and the version's
        provenance lists every line left out (line number and why). The journal itself is never changed.

        Damage inside the part of the journal that the latest version already sealed (a corrupt line, changed
        bytes, a damaged start document) does not touch that version, which keeps its own copy: with
        ``valid_prefix`` the measurements recorded after that part are sealed (up to the first corrupt line after
        it), the session metadata taken from the version's manifest, and the damage recorded in the provenance.
        """
        d = self._require_session(session_id)
        jpath = d / JOURNAL_NAME
        contents = self.read_journal(session_id)
        versions = self.versions(session_id)
        parent_ds = self.load(Ref(session_id, versions[-1])) if versions else None  # its own files only
        latest = parent_ds.ref if parent_ds is not None else None
        through = int(parent_ds.manifest.get("journal_seq_through", 0)) if parent_ds is not None else 0
        damage, sealed_bytes, sealed_lines = _sealed_part_damage(jpath, contents, parent_ds, latest)
        old = [ln for ln in contents.corrupt_lines if ln <= sealed_lines]
        tail = [ln for ln in contents.corrupt_lines if ln > sealed_lines]
        if old and damage is None:  # cannot happen with intact bytes, but a line judged corrupt is damage all the same
            damage = f"line(s) {old} of the part sealed into {latest} cannot be read"
        if not valid_prefix:
            _refuse_damaged_journal(session_id, contents, contents.size < sealed_bytes, latest, damage, tail)
        meta = _seal_session_meta(session_id, contents, parent_ds, damage)
        first_bad = tail[0] if tail else None
        measurements, skipped = _measurements_to_seal(
            contents, sealed_lines if damage is not None else 0, old, tail, latest
        )
        new = [m for m in measurements if m.seq > through and m.valid]
        if not new:
            where = f"since {latest}" if latest else "in the journal"
            why = f"; {damage}, and {latest} keeps its own copy" if damage else ""
            return SealResult(latest, False, 0, f"nothing new to seal {where} (no new valid measurements){why}")
        seq_through = max(m.seq for m in measurements)
        provenance = {
            "journal": {
                "seq_through": seq_through,
                "bytes": contents.size,
                "sha256": sha256_file(jpath, limit=contents.size),
                "new_seqs": [m.seq for m in new],
                "warnings": contents.warnings,
            }
        }
        if skipped or damage is not None:
            provenance["journal"]["valid_prefix"] = {
                "through_line": (first_bad - 1) if first_bad is not None else max(contents.document_lines),
                "skipped": skipped,
                **({"sealed_part_damage": damage} if damage is not None else {}),
            }
        rows = journal_rows(new, int(meta["robot"]["n_joints"]), len(meta["targets"]))
        ref = self._write_version(
            d,
            session_id,
            parent_ds,
            rows,
            meta,
            source="journal",
            provenance=provenance,
            journal_seq_through=seq_through,
        )
        left_out = f"; left out {len(skipped)} journal line(s) from line {skipped[0]['line']} on" if skipped else ""
        if damage is not None:
            left_out += f" ({damage}: sealed only what was recorded after it)"
        return SealResult(ref, True, len(new), f"sealed {len(new)} new measurement(s) into {ref}{left_out}")

    # ---------------------------------------------------------------------------------------------- fits
    @_writes("store the fit")
    def save_fit(
        self,
        refs: str | Ref | Sequence[str | Ref],
        files: Mapping[str, bytes | str],
        metadata: Mapping[str, Any],
        *,
        fit_id: str | None = None,
    ) -> FitRecord:
        """Store a fit under the (first) version it read, atomically.

        ``refs``: the input version(s); a fit pooling several versions is stored under the first and records
        all of them. ``files``: file name → bytes (or text, stored UTF-8), e.g. model weights. ``metadata``:
        JSON-able (method, seed, metrics …). fit.json records each input's resolved ref, manifest sha256 and
        data sha256, plus the sha256 of every fit file. Inputs are verified first.
        """
        inputs = []
        for ref in [refs] if isinstance(refs, str | Ref) else refs:
            r = self.resolve(ref)
            self.verify(r).raise_if_bad()
            m = self.manifest(r)
            inputs.append(
                {
                    "ref": str(r),
                    "manifest_sha256": m["manifest_sha256"],
                    "files": {k: v["sha256"] for k, v in m["files"].items()},
                    "row_count": m["row_count"],
                }
            )
        if not inputs:
            raise DatasetError("a fit needs at least one input version")
        under, vdir = self._located(inputs[0]["ref"])
        fit_id = validate_id(fit_id, "fit id") if fit_id else new_fit_id()
        for name in files:
            validate_id(name, "fit file name")
            if name == FIT_JSON:
                raise DatasetError(f"{FIT_JSON} is reserved for labcal's own record of the fit")
        fits_dir = vdir / FITS
        make_dirs_durable(fits_dir)
        if (fits_dir / fit_id).exists():
            raise DatasetError(f"fit {fit_id!r} already exists under {under}")
        data = {name: c.encode("utf-8") if isinstance(c, str) else bytes(c) for name, c in files.items()}
        meta = {
            "kind": "labcal.fit",
            "fit_id": fit_id,
            "stored_under": str(under),
            "inputs": inputs,
            "metadata": jsonable(dict(metadata)),
        }
        with _publishing(fits_dir, fit_id, fits_dir / fit_id) as tmp:
            written = _write_sealed(tmp, data, meta, FIT_JSON, "fit_sha256")
        return FitRecord(fit_id, str(under), fits_dir / fit_id, written)

    @_writes("store the evaluation")
    def save_evaluation(self, ref: str | Ref, fit_id: str, doc: Mapping[str, Any]) -> tuple[str, Path]:
        """Store one evaluation of fit fit_id (stored under ref); returns (evaluation id, path).

        The document is written like fit.json: canonical, self-hashed (``evaluation_sha256``), durable
        (:func:`labcal.atomicio.write_bytes`: temp file, fsync, rename, fsync of the folder) and read-only. The id is
        the UTC time plus six hex digits.
        """
        r, vdir = self._located(ref)
        if not (vdir / FITS / validate_id(fit_id) / FIT_JSON).is_file():
            raise DatasetError(f"{r} has no fit {fit_id!r} to store an evaluation under")
        folder = vdir / FITS / EVALUATIONS / fit_id
        make_dirs_durable(folder)
        eval_id = new_fit_id()
        path = folder / f"{eval_id}.json"
        write_bytes(path, _dump_sealed({**jsonable(dict(doc)), "evaluation_id": eval_id}, "evaluation_sha256"))
        os.chmod(path, READ_ONLY)
        return eval_id, path

    def list_evaluations(self, ref: str | Ref, fit_id: str) -> list[dict]:
        """The stored evaluations of a fit, oldest first; one that fails its own hash has ``corrupt: True``."""
        folder = self.version_dir(ref) / FITS / EVALUATIONS / fit_id
        out = []
        for p in sorted(folder.glob("*.json")):
            doc, problems = _load_sealed(p.read_bytes(), "evaluation_sha256", p.name)
            out.append({**(doc or {"evaluation_id": p.stem}), **({"corrupt": True} if problems else {})})
        return out

    def list_fits(self, ref: str | Ref) -> list[FitRecord]:
        """Fits stored under a version, oldest first (fit.json checked, fit files not read)."""
        r, vdir = self._located(ref)
        return [
            self.load_fit(r, p.name, check_files=False)
            for p in sorted((vdir / FITS).glob("*"))  # none without a fits/ folder
            if not p.name.startswith(".") and not is_os_or_editor_file(p.name)
        ]

    def load_fit(self, ref: str | Ref, fit_id: str, *, check_files: bool = True) -> FitRecord:
        """Load a fit's record, verifying fit.json (and, by default, every fit file's sha256)."""
        r, vdir = self._located(ref)
        path = vdir / FITS / validate_id(fit_id, "fit id")
        if not (path / FIT_JSON).is_file():
            known = sorted(p.name for p in path.parent.glob("*") if not p.name.startswith("."))  # none: no folder
            raise UnknownVersion(
                f"{r} has no fit {fit_id!r}{_did_you_mean(fit_id, known)}; available: {', '.join(known) or 'none'}"
            )
        meta, problems = _load_sealed((path / FIT_JSON).read_bytes(), "fit_sha256", f"fit {fit_id}/{FIT_JSON}")
        if meta is not None and check_files:
            _check_files(path, meta.get("files", {}), f"fit {fit_id}/", problems, [])
        if problems or meta is None:
            raise DatasetCorrupted(f"fit {fit_id} under {r} is corrupted:\n  " + "\n  ".join(problems), problems)
        return FitRecord(fit_id, str(r), path, meta)

    def find_fit(self, fit_id: str) -> FitRecord:
        """Find a fit by id anywhere in the store."""
        validate_id(fit_id, "fit id")
        self.require_root()
        for s in self.session_ids():
            for v in self.versions(s):
                if (self.session_dir(s) / version_name(v) / FITS / fit_id / FIT_JSON).is_file():
                    return self.load_fit(Ref(s, v), fit_id)
        known = [p.parent.name for s in self.session_ids() for p in self.session_dir(s).glob(f"v*/{FITS}/*/{FIT_JSON}")]
        raise UnknownVersion(f"no fit {fit_id!r} in store {self.root}{_did_you_mean(fit_id, known)}")


def _check_files(folder: Path, listed: Mapping[str, dict], where: str, problems: list[str], checked: list[str]) -> None:
    """Each file ``listed`` (name → {"sha256": …}) in ``folder`` against its sha256: a line in ``problems`` for each
    one missing or changed, the name of each one read in ``checked``; ``where`` prefixes the names."""
    for name, info in sorted(listed.items()):
        if not (folder / name).is_file():
            problems.append(f"{where}{name}: missing (expected sha256 {info.get('sha256')})")
            continue
        actual = sha256_file(folder / name)
        checked.append(f"{where}{name}")
        if actual != info.get("sha256"):
            problems.append(f"{where}{name}: sha256 mismatch: expected {info.get('sha256')}, actual {actual}")


def _foreign_entry_notes(session_dir: Path) -> list[str]:
    """A note per entry of a session folder that labcal did not write (skipped by the checks)."""
    return [
        f"{p.name}: foreign {'folder' if p.is_dir() else 'file'} (not written by labcal), skipped"
        for p in sorted(session_dir.iterdir())
        if not (p.name in (JOURNAL_NAME, VERSIONS_LOG) or p.name.startswith(".tmp-"))
        and not (p.is_dir() and _VERSION_DIR.match(p.name))
    ]


def _check_versions_log(
    log: Path, manifests: dict[int, dict | None], missing: dict[int, str], problems: list[str], notes: list[str]
) -> None:
    """The versions log against the version folders (``manifests``: version → its manifest, None if unreadable):
    adds to missing the published versions that are gone, to problems a damaged log or a manifest that is not the
    published one, to notes the versions it does not list."""
    entries, log_problems, log_notes = _read_versions_log(log.read_bytes())
    problems += log_problems
    notes += log_notes
    logged = set()
    for e in entries:
        try:
            v = parse_version(e["version"])
        except DatasetError:
            problems.append(f"{VERSIONS_LOG}: names an invalid version {e['version']!r}")
            continue
        logged.add(v)
        if v not in manifests:
            missing[v] = f"published {e.get('time', '?')}, listed in {VERSIONS_LOG}"
        elif (man := manifests[v]) is not None and man.get("manifest_sha256") != e.get("manifest_sha256"):
            problems.append(
                f"{version_name(v)}/{MANIFEST}: not the manifest that was published (sha256 "
                f"{e.get('manifest_sha256')} in {VERSIONS_LOG}, {man.get('manifest_sha256')} now): "
                f"restore {version_name(v)} from a backup"
            )
    for v in manifests:
        if v not in logged:
            notes.append(
                f"{version_name(v)}: not listed in {VERSIONS_LOG} (written by an older labcal, or a seal "
                "interrupted after the version was complete)"
            )


def _handled_damage(sealed: list[tuple[int, dict]]) -> tuple[dict[int, str], dict[int, str]]:
    """Damage a later `seal --valid-prefix` already sealed around (and recorded), where running it again adds
    nothing: (journal line → the version that skipped it, version whose sealed part changed → the later version)."""
    handled: dict[int, str] = {}
    handled_prefix: dict[int, str] = {}
    for v, info in sealed:
        vp = info.get("valid_prefix") or {}
        for skip in vp.get("skipped") or []:
            if isinstance(skip, dict) and isinstance(skip.get("line"), int):
                handled.setdefault(skip["line"], version_name(v))
        if vp.get("sealed_part_damage"):
            for w, _ in sealed:
                if w < v:
                    handled_prefix.setdefault(w, version_name(v))
    return handled, handled_prefix


def _journal_problems(
    session_id: str, jpath: Path, contents, sealed: list[tuple[int, dict]], manifests: dict[int, dict | None]
) -> list[str]:
    """The journal's problems: its start document, its corrupt lines (with the fix that applies where each lies)
    and the parts sealed into versions that changed or were cut off since."""
    problems = []
    cmd = f"`labcal session seal {session_id} --valid-prefix`"
    keep = "the versions keep their own copies and stay usable"
    if contents.start is None:
        fix = (f"{keep}; {cmd} seals what was recorded after the damage" if sealed else
               "no version holds a copy of it: restore the journal from a backup")  # fmt: skip
        problems.append(f"{JOURNAL_NAME}: line 1: the start document is damaged or missing: {fix}")
    through = max((int(info.get("bytes", 0)) for _, info in sealed), default=0)
    sealed_lines = _lines_in(jpath, through)
    handled, handled_prefix = _handled_damage(sealed)
    after = "record the remaining poses in a new session"
    for ln in contents.corrupt_lines:
        if ln == 1 and contents.start is None:
            continue  # the start document: said above, with the fix that applies to it
        why = contents.corrupt_reasons.get(ln, "corrupt")
        if ln in handled:
            fix = f"left out and recorded by {handled[ln]}'s seal --valid-prefix; {keep}; {after}"
        elif ln <= sealed_lines:
            fix = f"it lies in the part already sealed: {keep}; {cmd} seals what was recorded after that part"
        else:
            fix = f"{cmd} seals the measurements before it and records what it left out"
        problems.append(f"{JOURNAL_NAME}: line {ln}: {why}: {fix}")
    damaged = []
    for v, info in sealed:
        n = int(info.get("bytes", 0))
        if contents.size < n:
            what = (
                f"shorter ({contents.size} bytes) than when {version_name(v)} was sealed ({n} bytes): its end was "
                f"cut off; {keep}; record the remaining poses in a new session"
            )
            damaged.append((v, what))
        elif sha256_file(jpath, limit=n) != info.get("sha256"):
            fix = (f"recorded by {handled_prefix[v]}'s seal --valid-prefix; {after}" if v in handled_prefix
                   else f"{cmd} seals what was recorded after them")  # fmt: skip
            what = f"the first {n} bytes, sealed into {version_name(v)}, changed since it was sealed; {keep}; {fix}"
            damaged.append((v, what))
    if damaged:
        v, what = damaged[0]
        also = [version_name(w) for w, _ in damaged[1:]]
        also_text = f" (so did the parts sealed into {', '.join(also)})" if also else ""
        problems.append(f"{JOURNAL_NAME}: {what}{also_text}")
        if contents.start is not None and (man := manifests.get(v)):
            if session_meta_from_start(contents.start) != man.get("session"):
                problems.append(
                    f"{JOURNAL_NAME}: line 1: the start document differs from the copy in {version_name(v)}'s "
                    f"manifest; the versions use their own copy"
                )
    return problems


def _sealed_part_damage(
    jpath: Path, contents, parent_ds: Dataset | None, latest: str | None
) -> tuple[str | None, int, int]:
    """(what happened to the part of the journal the latest version sealed, or None; that part's size in bytes;
    the journal lines in that part that are still there)."""
    pj = ((parent_ds.manifest.get("provenance") or {}).get("journal") if parent_ds is not None else None) or {}
    sealed_bytes = int(pj.get("bytes", 0))
    damage = None
    if sealed_bytes and contents.size < sealed_bytes:
        damage = f"the journal is shorter ({contents.size} bytes) than when {latest} was sealed ({sealed_bytes})"
    elif sealed_bytes and sha256_file(jpath, limit=sealed_bytes) != pj.get("sha256"):
        damage = f"the first {sealed_bytes} bytes of the journal, sealed into {latest}, changed since"
    return damage, sealed_bytes, _lines_in(jpath, min(sealed_bytes, contents.size))


def _refuse_damaged_journal(
    session_id: str, contents, truncated: bool, latest: str | None, damage: str | None, tail: list[int]
) -> None:
    """Without --valid-prefix: :class:`JournalCorrupted` for damage to the sealed part, then for corrupt lines
    after it, each with the fix."""
    cmd = f"`labcal session seal {session_id} --valid-prefix`"
    if damage is not None:
        fix = ("nothing recorded after it can be placed: record the remaining poses in a new session" if truncated
               else f"{cmd} seals the measurements recorded after it and records the damage")  # fmt: skip
        raise JournalCorrupted(
            f"journal of {session_id!r}: {damage}; {latest} keeps its own copy of those measurements and stays "
            f"usable; refusing to seal ({fix})"
        )
    if tail:
        reasons = contents.corrupt_reasons
        why = "; ".join(f"line {ln}: {reasons.get(ln, 'corrupt')}" for ln in tail)
        raise JournalCorrupted(
            f"journal of {session_id!r} has corrupt line(s) {tail} ({why}); refusing to seal ({cmd} seals the "
            f"measurements before line {tail[0]} and records what it left out)"
        )


def _seal_session_meta(session_id: str, contents, parent_ds: Dataset | None, damage: str | None) -> dict:
    """The session metadata of the new version: the latest version's verified copy when the sealed part is
    damaged, else the journal's start document."""
    if damage is not None and parent_ds is not None:
        return dict(parent_ds.manifest["session"])  # the version's verified copy of the start document
    if contents.start is not None:
        return session_meta_from_start(contents.start)
    raise JournalCorrupted(
        f"journal of {session_id!r}: line 1, the start document, is damaged or missing and no version holds "
        "a copy of it: the measurements cannot be tied to their robot and targets; restore the journal "
        "from a backup"
    )


def _measurements_to_seal(
    contents, after: int, old: list[int], tail: list[int], latest: str | None
) -> tuple[list[MeasurementDoc], list[dict]]:
    """(the measurement documents after journal line ``after`` and before the first corrupt line after it, the
    journal lines left out with why, by line)."""
    from .documents import MeasurementDoc

    reasons = contents.corrupt_reasons
    first_bad = tail[0] if tail else None
    skipped: list[dict] = [
        {"line": ln, "reason": f"{reasons.get(ln, 'corrupt')} (in the part sealed into {latest}, which keeps its "
                               "own copy)"}
        for ln in old
    ]  # fmt: skip
    skipped += [{"line": ln, "reason": reasons.get(ln, "corrupt")} for ln in tail]
    measurements: list[MeasurementDoc] = []
    for ln, doc in zip(contents.document_lines, contents.documents, strict=True):
        if doc["type"] != "measurement" or ln <= after:
            continue
        if first_bad is not None and ln > first_bad:
            # after an unexplained corruption the order and completeness of the later documents cannot be trusted
            skipped.append(
                {"line": ln, "seq": doc["seq"], "pose_index": doc["pose_index"], "status": doc["status"],
                 "reason": f"after the corrupt line {first_bad}"}
            )  # fmt: skip
            continue
        measurements.append(MeasurementDoc.from_json(doc))
    skipped.sort(key=lambda x: x["line"])
    return measurements, skipped


def _lines_in(path: Path, n: int) -> int:
    """The number of lines that lie (at least partly) in the first ``n`` bytes of ``path``."""
    if n <= 0:
        return 0
    with open(path, "rb") as f:
        head = f.read(n)
    return head.count(b"\n") + (0 if head.endswith(b"\n") else 1)


def _log_version(session_dir: Path, name: str, manifest_sha256: str, parent: str | None) -> None:
    """Append the published version to the session's versions log (one fsynced line)."""
    entry = {"version": name, "manifest_sha256": manifest_sha256, "parent": parent, "time": iso(utc_now())}
    line = canonical_json(entry)
    path = session_dir / VERSIONS_LOG
    created = not path.exists()
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        # After a crash mid-append the last line is unfinished (read as a note). Appended to, it would join this entry
        # into one unreadable line in the middle: a problem that blocks every later recording, and this entry lost.
        # So an unreadable tail is cut off (its version then reads as "not listed", the note for a seal interrupted
        # after the version was complete); a readable one only gets its newline.
        size = os.fstat(fd).st_size
        tail = os.pread(fd, size, 0).rsplit(b"\n", 1)[-1] if size else b""
        data = (line + "\n").encode("utf-8")
        if tail:
            entries, _, _ = _read_versions_log(tail + b"\n")
            if entries:
                data = b"\n" + data
            else:
                os.ftruncate(fd, size - len(tail))
        write_all(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    if created:
        fsync_dir(session_dir)


def _read_versions_log(data: bytes) -> tuple[list[dict], list[str], list[str]]:
    """(entries, problems, notes) of a versions log; an unfinished last line (a crash mid-append) is a note."""
    entries: list[dict] = []
    problems: list[str] = []
    notes: list[str] = []
    unfinished = data.count(b"\n") + 1 if data and not data.endswith(b"\n") else 0  # its last line, if unterminated
    for i, doc, _ in json_lines(data):
        if isinstance(doc, dict) and isinstance(doc.get("version"), str):
            entries.append(doc)
        elif i == unfinished:
            notes.append(f"{VERSIONS_LOG}: line {i} unfinished (an interrupted write), ignored")
        else:
            problems.append(f"{VERSIONS_LOG}: line {i} unreadable")
    return entries, problems, notes


def _session_folder_problem(p: Path) -> str | None:
    """Why the store entry ``p`` is not a session folder, or None if it is one."""
    name = p.name
    if is_os_or_editor_file(name):
        return "a file of the operating system or an editor"
    if not p.is_dir():
        return "a file, not a session folder"
    if not _ID_RE.match(name) or ".." in name:
        return (
            "not a session id (letters, digits, '.', '_', '-'): a copy of a session? rename it to a new id to use it "
            "as one"
        )
    try:
        labcal = any(c.name in (JOURNAL_NAME, VERSIONS_LOG) or _VERSION_DIR.match(c.name) for c in p.iterdir())
    except OSError as e:
        return f"cannot be read ({e.strerror or e})"
    return None if labcal else "a folder without a journal or a version"


def _did_you_mean(name: str, known: Sequence[str]) -> str:
    """``"; did you mean X?"`` for the closest known id (a typo in a long id), else ""."""
    import difflib

    close = difflib.get_close_matches(name, known, n=1, cutoff=0.8)
    return f"; did you mean {close[0]!r}?" if close else ""


def journal_rows(measurements: Sequence[MeasurementDoc], n_joints: int, n_targets: int = 3) -> pd.DataFrame:
    """Measurement documents → table rows (q from q_actual, falling back to q_commanded).

    A target written as ``null`` (not seen) becomes NaN in its three columns and its spread.
    """
    import numpy as np
    import pandas as pd

    recs = []
    for m in measurements:
        q = m.q
        rec: dict[str, Any] = {"pose": m.pose_index}
        rec.update({f"q{j + 1}": float(q[j]) for j in range(n_joints)})
        points = m.points_array()
        if points is None or len(points) != n_targets:
            have = "no points" if points is None else f"{len(points)} target(s)"
            raise JournalCorrupted(f"measurement seq {m.seq} is valid but has {have}; the session has {n_targets}")
        rec.update(zip(target_columns(n_targets), points.ravel().tolist(), strict=True))
        rec["split"] = m.split or ""
        spread = m.spread
        for i, c in enumerate(spread_columns(n_targets)):
            rec[c] = float(spread[i]) if spread is not None and spread[i] is not None else np.nan
        rec["timestamp"] = float(m.time)
        for k, v in m.extra.items():
            rec[f"x_{k}"] = np.nan if v is None else v
        recs.append(rec)
    table = pd.DataFrame.from_records(recs)
    table["pose"] = table["pose"].astype(np.int64)
    return table


def load_version(store: SessionStore | str | Path | None, ref: str | Ref) -> Dataset:
    """Load ``SESSION[@vN]`` from ``store`` (a SessionStore or its root folder), verifying its hashes."""
    return (store if isinstance(store, SessionStore) else SessionStore(store)).load(ref)
