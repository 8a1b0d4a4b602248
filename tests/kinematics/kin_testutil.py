"""Independent reference maths for the kinematics tests (written apart from labcal's code on purpose)."""

from __future__ import annotations

import numpy as np
import scipy.linalg

from labcal.kinematics import se3
from labcal.kinematics.poe import PRISMATIC, REVOLUTE, LocalPOEModel


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def shift(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def dh_product(rows, q, modified: bool = False) -> np.ndarray:
    """The DH (or Craig's modified DH) product written out from the textbook definitions."""
    T = np.eye(4)
    for row, qj in zip(rows, q, strict=True):
        theta, d = row["theta"], row["d"]
        if row.get("type", "revolute") == "revolute":
            theta = theta + qj
        else:
            d = d + qj
        if modified:
            T = T @ rot_x(row["alpha"]) @ shift(x=row["a"]) @ rot_z(theta) @ shift(z=d)
        else:
            T = T @ rot_z(theta) @ shift(z=d) @ shift(x=row["a"]) @ rot_x(row["alpha"])
    return T


def poe_product(frames, twists, q) -> np.ndarray:
    """Local POE product eq. (1) with the matrix exponential from scipy: an oracle for LocalPOEModel.fk."""
    T = frames[0].copy()
    for j, qj in enumerate(q):
        T = T @ scipy.linalg.expm(se3.hat(twists[j]) * qj) @ frames[j + 1]
    return T


def assert_poses_close(A: np.ndarray, B: np.ndarray, atol: float = 1e-12) -> None:
    """Compare poses on the manifold: log(A⁻¹ B) ≈ 0 (position part in m, rotation part in rad)."""
    err = se3.log_se3(se3.inv(A) @ B)
    worst = float(np.max(np.abs(err)))
    assert worst <= atol, f"poses differ on the manifold by {worst:.3e} (> {atol:.1e})"


def random_model_rows(rng: np.random.Generator, n: int, prismatic=()) -> list[dict]:
    """Random DH/MDH rows with lengths ~0.5 m and any angles; joints listed in `prismatic` slide."""
    return [
        {
            "type": "prismatic" if j in prismatic else "revolute",
            "a": float(rng.uniform(-0.8, 0.8)),
            "alpha": float(rng.uniform(-np.pi, np.pi)),
            "d": float(rng.uniform(-0.8, 0.8)),
            "theta": float(rng.uniform(-np.pi, np.pi)),
        }
        for j in range(n)
    ]


def random_q(model: LocalPOEModel, k: int, seed: int) -> np.ndarray:
    lo, hi = model.limits[:, 0], model.limits[:, 1]
    lo, hi = np.maximum(lo, -np.pi), np.minimum(hi, np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, size=(k, model.n))


def general_model(seed: int = 0, n: int = 5) -> LocalPOEModel:
    """Random frames and random (non-z) unit twists, one prismatic joint: exercises the general exp path."""
    rng = np.random.default_rng(seed)
    frames = se3.exp_se3(rng.normal(size=(n + 1, 6)) * 0.7)
    types = tuple(PRISMATIC if j == 2 else REVOLUTE for j in range(n))
    twists = []
    for t in types:
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        if t == REVOLUTE:
            twists.append(np.concatenate([np.cross(rng.normal(size=3), u), u]))  # a line not through the origin
        else:
            twists.append(np.concatenate([u, np.zeros(3)]))
    return LocalPOEModel.from_frames(frames, types, np.array(twists))
