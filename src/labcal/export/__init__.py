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

from pathlib import Path

from labcal.compensator import CalibratedRobot
from labcal.compensator import save as save_compensator

FORMATS = ("json", "npz", "urscript", "urscript-program", "urdf", "ur-kinematics")
SUFFIXES = {
    "json": ".json",
    "npz": ".npz",
    "urscript": ".script",
    "urscript-program": ".script",
    "urdf": ".urdf",
    "ur-kinematics": ".yaml",
}


def export(robot: CalibratedRobot, fmt: str, path, provenance: dict | None = None, **options) -> Path:
    """Write robot in format fmt (json | npz | urscript | urdf) to path; returns the path written.

    json/npz: the compensator file (path must end in .json / .npz); urscript: the function file with
    ``labcal_correct(q)`` for a Script node, urscript-program: the ``def`` program for the script port (options of
    both: method, iterations, function_name, statements_per_sync); urdf: the identified frames (options: velocity,
    effort, masses, coms, ur_names, geometry_only, unknown_dynamics); ur-kinematics: ur_description's calibration
    YAML (option: geometry_only).
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if fmt in ("json", "npz"):
        if path.suffix.lower() != SUFFIXES[fmt]:
            raise ValueError(f"a {fmt} export must be written to a path ending in {SUFFIXES[fmt]}, got {path.name!r}")
        return save_compensator(robot, path, provenance)
    if fmt == "urscript":
        from labcal.export.urscript import write_urscript

        return write_urscript(robot, path, provenance, **options)
    if fmt == "urscript-program":
        from labcal.export.urscript import write_urscript_program

        return write_urscript_program(robot, path, provenance, **options)
    if fmt == "ur-kinematics":
        from labcal.export.ros import write_ur_kinematics

        return write_ur_kinematics(robot, path, provenance, **options)
    if fmt == "urdf":
        from labcal.export.urdf import write_urdf

        return write_urdf(robot, path, provenance, **options)
    # a name added to FORMATS without its branch here must not fall through to another format's writer
    raise NotImplementedError(f"export format {fmt!r} is listed in FORMATS but has no writer in export.export()")


__all__ = ["FORMATS", "SUFFIXES", "export"]
