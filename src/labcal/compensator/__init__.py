"""The compensator runtime: a calibrated robot model that predicts poses and corrects joint commands. Numpy only
(a single correction runs compiled when numba is installed: :mod:`labcal.compensator.kernel`).

- :mod:`~labcal.compensator.model`: :class:`CalibratedRobot` (identified frames + learned joint motion errors:
  ``predict_pose``, ``correct``), :class:`Network`, :func:`input_features` (the :mod:`labcal.features` registry);
- :mod:`~labcal.compensator.solve`: the one solver ``correct`` uses (Gauss-Newton with a damped fallback over a
  residual function);
- :mod:`~labcal.compensator.io`: export payloads, checksums, JSON / NPZ files, and :class:`Compensator`, the
  deployable form that loads and verifies an export.

Joints: :class:`CalibratedRobot` works in the robot model's joints. When the robot file declares a joint map
(controller joints ≠ model joints, :mod:`labcal.robots.joint_map`), the map travels in the export and
:class:`Compensator` takes and returns *controller* joints, converting at its edge.

This package imports numpy, labcal.features, labcal.kinematics and labcal.robots (for the model hash) only, so a
controller-side process can load an export without torch, scipy, pandas or any driver.

Example::

    >>> from labcal.robots import load as load_robot
    >>> nominal = load_robot("ur10").model
    >>> robot = CalibratedRobot(nominal=nominal, model=nominal)       # an uncalibrated robot
    >>> q = [0.1, -1.2, 1.0, -1.4, -1.5, 0.2]
    >>> float(abs(robot.correct(q) - q).max()) < 1e-12
    True
"""

from __future__ import annotations

from labcal.compensator.io import (
    CHECKED_FIELDS,
    GOLDEN_COUNT,
    GOLDEN_TOL_POSE,
    GOLDEN_TOL_Q,
    SCHEMA,
    SCHEMA_VERSION,
    Compensator,
    CompensatorFileError,
    field_checksums,
    from_payload,
    golden_configurations,
    load,
    read_payload,
    save,
    to_payload,
)
from labcal.compensator.model import CalibratedRobot, Network, input_features

__all__ = [
    "CHECKED_FIELDS",
    "GOLDEN_COUNT",
    "GOLDEN_TOL_POSE",
    "GOLDEN_TOL_Q",
    "SCHEMA",
    "SCHEMA_VERSION",
    "CalibratedRobot",
    "Compensator",
    "CompensatorFileError",
    "Network",
    "field_checksums",
    "from_payload",
    "golden_configurations",
    "input_features",
    "load",
    "read_payload",
    "save",
    "to_payload",
]
