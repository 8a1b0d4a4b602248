"""`labcal export` as a function: write a stored fit in one of the export formats, with provenance.

Order of checks, all before any work: the format, the output path (an existing file is refused without
``force``; a device, a symlink, a folder or a FIFO is refused even with ``force``; a missing or unwritable folder
is a one-line error), then the fit's warnings (refused without ``force``; a forced export records ``forced: true``
and the warnings in its provenance). Every writer goes through :mod:`labcal.atomicio` (temporary file in the same
folder, fsync, rename), so a reader never sees half a file and an interrupted export leaves the previous file
untouched.

Provenance names what was calibrated and with what: the session, fit and data hashes, and the serial numbers of
the arm (``arm_serial``: what the controller reported, else the session's unit id) and of the tracker
(``tracker_serial``) that the sessions' start documents recorded (``labcal session show``). Serials come from
devices: each is written as printable text (:func:`labcal.names.printable`), cut to 64 characters, and
every writer escapes it again for its own format.
"""

from __future__ import annotations

import os
import tempfile
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from labcal.atomicio import UnsafeTargetError, check_target, write_bytes
from labcal.cli.common import UserError, session_unit
from labcal.cli.ops.common import check_choice, robot_for
from labcal.cli.ops.fitting import info_warnings, load_stored_fit
from labcal.datasets import SessionStore
from labcal.names import printable
from labcal.robots.joint_map import JointMap

MAX_SERIAL = 64  # characters of a device's serial number written into an export (a confused device sends more)


def stored_warnings(meta: dict) -> list[dict]:
    """The blocking warnings of a stored fit: fit.json's ``warnings``, or for fits stored before the gates
    existed, the ones their stored diagnostics imply."""
    if "warnings" in meta:
        return list(meta.get("warnings") or [])
    return info_warnings(meta.get("info") or {}, meta.get("chosen"))


def check_output(out: str | Path, *, force: bool = False) -> Path:
    """Refuse an output path that cannot be written, or that exists (without force), before any work."""
    out = Path(out)
    parent = out.parent
    if out.is_dir() and not out.is_symlink():
        raise UserError(f"--out {printable(out)} is a folder: give a file name")
    if os.path.lexists(out):
        try:
            check_target(out)  # a device, a symlink, a FIFO: refused with or without --force
        except UnsafeTargetError as e:
            raise UserError(f"--out {printable(e)}") from None
    if not parent.is_dir():
        what = "is not a folder" if parent.exists() else "does not exist: create it first"
        raise UserError(f"output folder {parent} {what}")
    # Try it: os.access says yes to root and to a read-only mount, a file actually created does not lie.
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".probe", dir=parent)
    except OSError as e:
        raise UserError(f"output folder {parent} is not writable ({e.strerror}): choose another --out") from None
    os.close(fd)
    os.unlink(probe)
    if out.exists() and not force:
        raise UserError(f"{out} already exists: pass --force to replace it (the old file is replaced atomically)")
    return out


GEOMETRY_FORMATS = ("urdf", "ur-kinematics")


def joint_dynamics(spec) -> dict:
    """velocity / effort per joint from the robot file's [[joints]] tables (None where a joint has none), and the
    masses and centres of mass when the file gives any mass: the URDF export's inputs."""
    rows: list = []
    if spec.format == "toml" and spec.text:
        try:
            rows = tomllib.loads(spec.text).get("joints") or []
        except tomllib.TOMLDecodeError:
            rows = []
    n = spec.model.n
    rows = [r if isinstance(r, dict) else {} for r in rows] + [{}] * max(0, n - len(rows))
    out = {key: [rows[j].get(key) for j in range(n)] for key in ("velocity", "effort")}
    if np.any(np.asarray(spec.masses) > 0):
        out.update(masses=spec.masses, coms=spec.coms)
    return out


def _map_arrays(joint_map, n: int) -> np.ndarray:
    jm = joint_map if joint_map is not None else JointMap.identity(n)  # None: controller joints are model joints
    return np.concatenate([jm.matrix.ravel(), jm.offsets])


def _one_line(text: str) -> str:
    # URScript comments and URDF/XML comments take one line and no "--"; a device's text no control characters.
    return printable(text).replace("--", "- -")


def device_serials(store: SessionStore, refs: list[str]) -> dict[str, str]:
    """``arm_serial`` and ``tracker_serial`` of the sessions ``refs`` (their start documents: what the controller
    and the tracker reported, the arm's falling back to the session's unit id), as printable text; several
    sessions with different units give a comma-separated list; a serial nobody recorded is ``unknown`` (an
    imported CSV, a sim tracker), so a reader sees it is missing rather than forgotten.

    Example: ``{"arm_serial": "20185500001", "tracker_serial": "P7-04711"}``
    """
    arms, trackers = [], []
    for ref in refs:
        session = store.load(ref).manifest.get("session") or {}  # verified: a record names what it calibrated
        arms.append(((session.get("robot_driver") or {}).get("identity") or {}).get("serial") or session_unit(session))
        trackers.append(((session.get("tracker") or {}).get("identity") or {}).get("serial"))

    def listed(values: list) -> str:  # the distinct serials in order, as printable text
        given = (printable(v, MAX_SERIAL) for v in values if v is not None and str(v).strip())
        return ", ".join(dict.fromkeys(given)) or "unknown"

    return {"arm_serial": listed(arms), "tracker_serial": listed(trackers)}


def format_options(
    fmt: str, *, geometry_only: bool, ur_names: bool, unknown_dynamics: str, statements_per_sync: int
) -> dict:
    """The options of `labcal export` that apply to the format (the writer's keyword arguments)."""
    if fmt in ("urdf", "ur-kinematics"):
        options: dict = {"geometry_only": geometry_only}
        if fmt == "urdf":
            options.update(ur_names=ur_names, unknown_dynamics=unknown_dynamics)
        return options
    if fmt in ("urscript", "urscript-program"):
        return {"statements_per_sync": statements_per_sync}
    return {}


def export_fit(
    store: SessionStore,
    ref: str,
    fmt: str,
    out: str | Path,
    fit_id: str | None = None,
    *,
    force: bool = False,
    options: dict | None = None,
    on_warning: Callable[[str], None] | None = None,
) -> Path:
    """Write a stored fit in one of labcal.export.FORMATS, with provenance (session, fit id, data hashes).

    options: the format's options (urdf: geometry_only, ur_names, unknown_dynamics — default "zero" here, with a
    warning; ur-kinematics: geometry_only;
    urscript / urscript-program: statements_per_sync, iterations). For urdf the robot file's joint velocity,
    effort, masses and centres of mass are added. on_warning receives what the user must know about the file
    written (a learned term left out by --geometry-only, with its size).

    Raises UserError when the output exists (without force), its folder is missing or read-only, the fit has
    warnings (without force), or the format cannot hold this calibration (the message says why and what to use).
    """
    from labcal.export import FORMATS, SUFFIXES, export

    check_choice("--format", fmt, FORMATS)
    out = check_output(out, force=force)
    if fmt in ("json", "npz") and out.suffix.lower() != SUFFIXES[fmt]:
        raise UserError(f"a {fmt} export must be written to a path ending in {SUFFIXES[fmt]}, got {out.name!r}")
    stored = load_stored_fit(store, ref, fit_id)
    record = store.load_fit(stored.ref, stored.fit_id, check_files=False)
    spec = robot_for(store.load(stored.inputs[0]).robot)
    if not np.array_equal(_map_arrays(stored.robot.joint_map, spec.model.n), _map_arrays(spec.joint_map, spec.model.n)):
        # The compensator converts controller joints through the map it carries: one that lost its map (or carries
        # another robot's) would correct the wrong joints.
        raise UserError(
            f"fit {stored.fit_id} does not carry the joint map of the robot its data were recorded with: "
            f"refit {stored.inputs[0]} with this labcal"
        )
    warnings = stored_warnings(stored.meta)
    if warnings and not force:
        listed = "; ".join(f"[{w.get('code')}] {w.get('message')}" for w in warnings)
        raise UserError(
            f"fit {stored.fit_id} has {len(warnings)} warning(s) and is not exported: {listed}. "
            "Fix the data or the fit, or pass --force to export it anyway (recorded in the export's provenance)"
        )
    provenance = _provenance(store, stored, record, fmt, warnings)
    options = dict(options or {})
    if fmt == "urdf":
        # Unknown effort/velocity: written as 0 with a note in the file and a warning, unless the caller refuses.
        options = {"unknown_dynamics": "zero", **joint_dynamics(spec), **options}
    # The writer works in a private folder beside --out, and only its finished file is copied into place (through
    # atomicio: temp + fsync + rename, regular files only), so not even a writer that fails halfway touches --out.
    with tempfile.TemporaryDirectory(prefix=f".{out.name}.", dir=out.parent, ignore_cleanup_errors=True) as work:
        try:
            written = export(stored.robot, fmt, Path(work) / out.name, provenance, **options)
        except ValueError as e:
            raise UserError(f"fit {stored.fit_id} cannot be exported as {fmt}: {printable(e)}") from None
        try:
            write_bytes(out, Path(written).read_bytes())
        except UnsafeTargetError as e:  # swapped in since check_output
            raise UserError(f"--out {printable(e)}") from None
    if on_warning is not None:
        _warn_about_written(out, fmt, stored.robot, options, on_warning)
    return out


def _provenance(store: SessionStore, stored, record, fmt: str, warnings: list[dict]) -> dict:
    """What an export records of where it came from: session, fit, input data and their hashes, devices, and a
    forced export's warnings."""
    provenance = {
        "session": stored.ref,
        "fit_id": stored.fit_id,
        "inputs": ", ".join(i["ref"] for i in record.inputs),
        "data_sha256": ", ".join(i["manifest_sha256"] for i in record.inputs),
        "method": stored.robot.method,
        **device_serials(store, [i["ref"] for i in record.inputs]),
    }
    if warnings:
        provenance["forced"] = True
        if fmt in ("json", "npz"):
            provenance["warnings"] = [
                {"code": printable(w.get("code")), "message": printable(w.get("message"))} for w in warnings
            ]
        else:
            provenance["warnings"] = _one_line(" | ".join(f"[{w.get('code')}] {w.get('message')}" for w in warnings))
    return provenance


def _warn_about_written(out: Path, fmt: str, robot, options: dict, on_warning: Callable[[str], None]) -> None:
    """What the user must know about the file written: a learned term --geometry-only left out (with its size),
    joint effort/velocity written as 0."""
    if fmt in GEOMETRY_FORMATS and options.get("geometry_only"):
        from labcal.export.learned import dropped_learned_term

        dropped = dropped_learned_term(robot)
        if dropped is not None:
            on_warning(f"--geometry-only: {out} leaves out the learned term: {dropped.describe()}")
    dynamics = (options.get("velocity") or []) + (options.get("effort") or [])
    if fmt == "urdf" and (not dynamics or None in dynamics):
        on_warning(
            f"{out}: the robot file gives no joint effort/velocity, written as 0 (add 'velocity' and 'effort' to its "
            "[[joints]] tables, or pass --unknown-dynamics refuse to stop instead)"
        )
