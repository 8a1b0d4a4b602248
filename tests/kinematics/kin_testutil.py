"""Independent reference maths for the kinematics tests (written apart from labcal's code on purpose)."""

from __future__ import annotations

import xml.etree.ElementTree as ET

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


def to_urdf(model: LocalPOEModel, robot_name: str | None = None, comment: str = "") -> str:
    """Write any local-POE model as a URDF chain (base_link → link_1 … → tool0), exact to printed precision (17
    digits): the inputs of from_urdf's round-trip tests (labcal's own URDF export, labcal.export.urdf, writes a
    calibrated robot in the z-axis form with its dynamics). Built with xml.etree, so names and the comment are
    escaped as XML requires."""

    def fmt(v) -> str:
        return " ".join(repr(float(x)) for x in v)

    robot = ET.Element("robot", name=robot_name or model.name or "robot")
    if comment:
        robot.append(ET.Comment(f" {comment.replace('--', '- -')} "))
    links = ["base_link", *[f"link_{j + 1}" for j in range(model.n)], "tool0"]
    for link in links:
        ET.SubElement(robot, "link", name=link)
    for j in range(model.n + 1):
        T = model.frames[j]
        if j < model.n:
            kind = "prismatic" if model.joint_types[j] == PRISMATIC else "revolute"
            joint = ET.SubElement(robot, "joint", name=model.joint_names[j], type=kind)
        else:
            joint = ET.SubElement(robot, "joint", name="tool_fixed", type="fixed")
        ET.SubElement(joint, "parent", link=links[j])
        ET.SubElement(joint, "child", link=links[j + 1])
        ET.SubElement(joint, "origin", xyz=fmt(T[:3, 3]), rpy=fmt(se3.matrix_to_rpy(T[:3, :3])))
        if j < model.n:
            axis = model.twists[j, :3] if kind == "prismatic" else model.twists[j, 3:]
            ET.SubElement(joint, "axis", xyz=fmt(axis))
            lo, hi = model.limits[j]
            ET.SubElement(joint, "limit", lower=repr(float(lo)), upper=repr(float(hi)), effort="0", velocity="0")
    ET.indent(robot, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"
