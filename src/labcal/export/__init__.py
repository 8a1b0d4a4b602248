"""Exports of a calibrated robot: the compensator (JSON/NPZ), URScript (function file or program), a calibrated URDF,
ur_description's calibration YAML.

A robot whose file declares a joint map (controller joints ≠ model joints) exports only as json/npz: the
compensator converts controller joints, while a URScript function or a URDF has no place for the map and would be
fed the controller's joints, so both refuse it with a message saying so.

Numpy only (import-linter: "The compensator runtime is numpy-only"). Example::

    from labcal.export import export
    export(fit.robot, "json", "ur10.json", provenance={"session": "S@v001", "fit_id": "…"})
"""

from __future__ import annotations

import importlib
from pathlib import Path

from labcal.atomicio import write_text
from labcal.compensator import CalibratedRobot
from labcal.compensator import save as save_compensator

# format → (suffix, module and function giving the file's text from (robot, provenance=…, **options)); json and npz
# are the compensator's own files (no text writer). export() dispatches on this table alone, so no format is listed
# without its writer. Writers are imported when used: `import labcal.export` stays light.
_WRITERS: dict[str, tuple[str, tuple[str, str] | None]] = {
    "json": (".json", None),
    "npz": (".npz", None),
    "urscript": (".script", ("labcal.export.urscript", "urscript_text")),
    "urscript-program": (".script", ("labcal.export.urscript", "urscript_program_text")),
    "urdf": (".urdf", ("labcal.export.urdf", "urdf_text")),
    "ur-kinematics": (".yaml", ("labcal.export.ros", "ur_kinematics_text")),
}
FORMATS = tuple(_WRITERS)
SUFFIXES = {fmt: suffix for fmt, (suffix, _) in _WRITERS.items()}


def export(robot: CalibratedRobot, fmt: str, path, provenance: dict | None = None, **options) -> Path:
    """Write robot in format fmt (json | npz | urscript | urdf) to path; returns the path written.

    json/npz: the compensator file (path must end in .json / .npz); urscript: the function file with
    ``labcal_correct(q)`` for a Script node, urscript-program: the ``def`` program for the script port (options of
    both: method, iterations, function_name, statements_per_sync); urdf: the identified frames (options: velocity,
    effort, masses, coms, ur_names, geometry_only, unknown_dynamics); ur-kinematics: ur_description's calibration
    YAML (option: geometry_only). Every file is written atomically (:mod:`labcal.atomicio`): whole or absent,
    never over a device or a symbolic link.
    """
    path = Path(path)
    if fmt not in _WRITERS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    suffix, writer = _WRITERS[fmt]
    if writer is None:  # json / npz: the compensator's own files
        if path.suffix.lower() != suffix:
            raise ValueError(f"a {fmt} export must be written to a path ending in {suffix}, got {path.name!r}")
        return save_compensator(robot, path, provenance)
    module, function = writer
    text = getattr(importlib.import_module(module), function)(robot, provenance=provenance, **options)
    write_text(path, text)
    return path


__all__ = ["FORMATS", "SUFFIXES", "export"]
