"""`labcal export` as a function: write a stored fit in one of the export formats, with provenance.

Order of checks, all before any work: the format, the output path (an existing file is refused without
``force``; a missing or unwritable folder is a one-line error), then the fit's warnings (refused without
``force``; a forced export records ``forced: true`` and the warnings in its provenance). The file is written to a
temporary file in the same folder and moved into place with ``os.replace``, so a reader never sees half a file and
an interrupted export leaves the previous file untouched.
"""

from __future__ import annotations

import os
import tempfile
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from labcal.cli.ops.common import UserError, robot_for
from labcal.cli.ops.fitting import info_warnings, load_stored_fit
from labcal.datasets import SessionStore
from labcal.robots.joint_map import JointMap


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
    if out.is_dir():
        raise UserError(f"--out {out} is a folder: give a file name")
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


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _one_line(text: str) -> str:
    # URScript comments and URDF/XML comments take one line and no "--".
    return " ".join(str(text).split()).replace("--", "- -")


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

    if fmt not in FORMATS:
        raise UserError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
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
    provenance = {
        "session": stored.ref,
        "fit_id": stored.fit_id,
        "inputs": ", ".join(i["ref"] for i in record.inputs),
        "data_sha256": ", ".join(i["manifest_sha256"] for i in record.inputs),
        "method": stored.robot.method,
    }
    if warnings:
        provenance["forced"] = True
        if fmt in ("json", "npz"):
            provenance["warnings"] = [{"code": w.get("code"), "message": w.get("message")} for w in warnings]
        else:
            provenance["warnings"] = _one_line(" | ".join(f"[{w.get('code')}] {w.get('message')}" for w in warnings))
    # Same folder ⇒ same file system ⇒ os.replace is atomic. The temporary name keeps the suffix the writers check.
    options = dict(options or {})
    if fmt == "urdf":
        # Unknown effort/velocity: written as 0 with a note in the file and a warning, unless the caller refuses.
        options = {"unknown_dynamics": "zero", **joint_dynamics(spec), **options}
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=out.suffix, dir=out.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        try:
            export(stored.robot, fmt, tmp, provenance, **options)
        except ValueError as e:
            raise UserError(f"fit {stored.fit_id} cannot be exported as {fmt}: {e}") from None
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; an export gets the mode a plain write would
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if on_warning is not None and fmt in GEOMETRY_FORMATS and options.get("geometry_only"):
        from labcal.export.learned import dropped_learned_term

        dropped = dropped_learned_term(stored.robot)
        if dropped is not None:
            on_warning(f"--geometry-only: {out} leaves out the learned term: {dropped.describe()}")
    dynamics = (options.get("velocity") or []) + (options.get("effort") or [])
    if on_warning is not None and fmt == "urdf" and (not dynamics or None in dynamics):
        on_warning(
            f"{out}: the robot file gives no joint effort/velocity, written as 0 (add 'velocity' and 'effort' to its "
            "[[joints]] tables, or pass --unknown-dynamics refuse to stop instead)"
        )
    return out
