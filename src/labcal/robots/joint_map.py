"""Controller joints vs model joints: a linear map declared by the robot file.

Some controllers report joints that are not the kinematic model's joint angles: an elbow measured from the
horizontal (so the model's elbow angle is J2 + J3), a reversed sign, a zero offset. The robot file declares the
map once and every edge of labcal converts through it::

    q_model = M · q_controller + b          q_controller = M⁻¹ · (q_model − b)

Recorded and imported data keep the controller joints as the controller gave them; the calibration works in model
joints; the compensator takes and returns controller joints.

Example (a coupled elbow, 3 joints)::

    >>> jm = JointMap(np.array([[1, 0, 0], [0, 1, 0], [0, 1, 1.0]]), np.zeros(3))
    >>> jm.to_model(np.array([0.0, 0.5, -0.2])).tolist()
    [0.0, 0.5, 0.3]
    >>> jm.to_controller(jm.to_model(np.array([0.1, 0.2, 0.3]))).round(12).tolist()
    [0.1, 0.2, 0.3]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class JointMap:
    """q_model = matrix @ q_controller + offsets; matrix (n, n) invertible, offsets (n,) rad or m."""

    matrix: np.ndarray
    offsets: np.ndarray

    def __post_init__(self) -> None:
        M = np.array(self.matrix, dtype=float)
        b = np.array(self.offsets, dtype=float)
        n = M.shape[0] if M.ndim == 2 else -1
        if M.ndim != 2 or M.shape != (n, n) or b.shape != (n,):
            raise ValueError(f"joint map needs an (n, n) matrix and (n,) offsets, got {M.shape} and {b.shape}")
        if not (np.all(np.isfinite(M)) and np.all(np.isfinite(b))):
            raise ValueError("joint map matrix and offsets must be finite")
        if abs(np.linalg.det(M)) < 1e-9:
            raise ValueError("joint map matrix is singular: every model joint must follow from the controller joints")
        inverse = np.linalg.inv(M)
        for name, arr in (("matrix", M), ("offsets", b), ("_inverse", inverse)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @classmethod
    def identity(cls, n: int) -> JointMap:
        return cls(np.eye(n), np.zeros(n))

    @property
    def n(self) -> int:
        return self.matrix.shape[0]

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.matrix, np.eye(self.n)) and not np.any(self.offsets))

    def to_model(self, q_controller: np.ndarray) -> np.ndarray:
        """(…, n) controller joints → model joints."""
        return np.asarray(q_controller, dtype=float) @ self.matrix.T + self.offsets

    def to_controller(self, q_model: np.ndarray) -> np.ndarray:
        """(…, n) model joints → controller joints."""
        return (np.asarray(q_model, dtype=float) - self.offsets) @ self._inverse.T

    def as_dict(self) -> dict:
        return {"matrix": self.matrix.tolist(), "offsets": self.offsets.tolist()}
