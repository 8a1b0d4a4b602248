"""The names of the import and recording sanity checks (:mod:`labcal.datasets.sanity`) and what each catches.

Plain strings in a module of their own, so the command line can list them in its help (``--allow CHECK``) without
importing numpy and the kinematics behind the checks themselves.
"""

from __future__ import annotations

CHECKS: dict[str, str] = {
    "target-distances": "target distances match the targets file (unit slips, wrong or permuted targets file)",
    "target-outliers": "no single row's target distances are off the other rows' by more than 2 mm",
    "joint-limits": "joint values inside the robot file's limits (after its joint map)",
    "joint-span": "with --angle-unit deg, some joint moves more than 12.6° (catches radians read as degrees)",
    "nominal": "points within 25 mm (mean) of the nominal model's prediction (after frame registration)",
    "reach": "base-frame points within the robot's reach (catches tracker-frame data imported as base)",
    "duplicates": "at most half of the rows repeat an earlier pose (identical joints; every repeat is reported)",
    "few-poses": "at least 2 distinct poses per joint, the least a calibration can work with",
}
