"""Exact conversions of DH, modified DH and URDF descriptions into a :class:`LocalPOEModel` (labcal.export.urdf writes
a calibrated robot back as a URDF).

Standard DH (Denavit-Hartenberg): ``T = Π_j Rz(θ_j + q_j) Tz(d_j) Tx(a_j) Rx(α_j) · T_tool``. Joint j moves about
z of DH frame j−1, so K_j is DH frame j−1: A_1(0) = I, A_{j+1}(0) = Rz(θ_j) Tz(d_j) Tx(a_j) Rx(α_j), and the
last row's transform times the tool becomes A_{n+1}(0). A prismatic joint adds q_j to d_j; Tz commutes with Rz,
so the same frames hold with the twist (0, 0, 1, 0, 0, 0).

Modified DH (Craig): ``T = Π_j Rx(α_{j−1}) Tx(a_{j−1}) Rz(θ_j + q_j) Tz(d_j) · T_tool``, each row holding
(a_{j−1}, α_{j−1}, d_j, θ_j). Tz(d_j) commutes with Rz(q_j), so A_j(0) = Rx(α_{j−1}) Tx(a_{j−1}) Rz(θ_j) Tz(d_j)
and A_{n+1}(0) = T_tool.

URDF: a joint's ``origin`` (xyz, rpy) is the pose of the joint frame in the parent link frame at q = 0 and its
``axis`` is expressed in the joint frame, which is exactly A_j(0) and ξ_j. Fixed joints fold into the next frame.
We parse with the standard library's ElementTree: a URDF chain needs only joints, origins, axes and limits, and
a dependency for that would add weight without adding correctness.

Example (a one-joint DH arm of length 1 m)::

    >>> m = from_dh([{"type": "revolute", "a": 1.0, "alpha": 0.0, "d": 0.0, "theta": 0.0}])
    >>> np.round(m.fk(np.array([np.pi / 2]))[:3, 3], 12) + 0.0
    array([0., 1., 0.])
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence

import numpy as np

from labcal.kinematics import se3
from labcal.kinematics.poe import PRISMATIC, REVOLUTE, LocalPOEModel


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def trans(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _limits(rows: Sequence[Mapping]) -> np.ndarray:
    out = []
    for j, row in enumerate(rows):
        lim = row.get("limits")
        if lim is None:
            lim = [-np.pi, np.pi] if row.get("type", REVOLUTE) == REVOLUTE else [-1.0, 1.0]
        if len(lim) != 2:
            raise ValueError(f"joint {j + 1}: limits must be [lo, hi], got {lim}")
        out.append([float(lim[0]), float(lim[1])])
    return np.array(out).reshape(len(rows), 2)


def dh_transform(a: float, alpha: float, d: float, theta: float) -> np.ndarray:
    """Standard DH link transform Rz(θ) Tz(d) Tx(a) Rx(α)."""
    return rot_z(theta) @ trans(z=d) @ trans(x=a) @ rot_x(alpha)


def mdh_transform(a: float, alpha: float, d: float, theta: float) -> np.ndarray:
    """Modified DH link transform Rx(α_{j−1}) Tx(a_{j−1}) Rz(θ_j) Tz(d_j)."""
    return rot_x(alpha) @ trans(x=a) @ rot_z(theta) @ trans(z=d)


def from_dh(rows: Sequence[Mapping], T_flange_tool=None, name: str = "", joint_names=()) -> LocalPOEModel:
    """Convert standard DH rows (dicts with type, a, alpha, d, theta [, limits]) into a local POE model."""
    n = len(rows)
    frames = [np.eye(4)]
    for row in rows:
        frames.append(dh_transform(float(row["a"]), float(row["alpha"]), float(row["d"]), float(row["theta"])))
    if T_flange_tool is not None:
        frames[n] = frames[n] @ np.asarray(T_flange_tool, float)
    types = tuple(row.get("type", REVOLUTE) for row in rows)
    return LocalPOEModel.from_frames(np.array(frames), types, limits=_limits(rows), name=name, joint_names=joint_names)


def from_mdh(rows: Sequence[Mapping], T_flange_tool=None, name: str = "", joint_names=()) -> LocalPOEModel:
    """Convert modified DH rows (a_{j−1}, alpha_{j−1}, d_j, theta_j per joint) into a local POE model."""
    frames = [mdh_transform(float(r["a"]), float(r["alpha"]), float(r["d"]), float(r["theta"])) for r in rows]
    frames.append(np.eye(4) if T_flange_tool is None else np.asarray(T_flange_tool, float))
    types = tuple(row.get("type", REVOLUTE) for row in rows)
    return LocalPOEModel.from_frames(np.array(frames), types, limits=_limits(rows), name=name, joint_names=joint_names)


# --------------------------------------------------------------------------------------------------------------
# URDF


def _floats(text: str | None, default: Sequence[float], what: str) -> np.ndarray:
    if text is None:
        return np.array(default, dtype=float)
    try:
        values = np.array([float(x) for x in text.split()])
    except ValueError as err:
        raise ValueError(f"{what}: not a list of numbers: {text!r}") from err
    if values.shape != (3,):
        raise ValueError(f"{what}: expected 3 numbers, got {text!r}")
    return values


def from_urdf(text: str, tip_link: str | None = None, name: str | None = None) -> LocalPOEModel:
    """Parse a URDF string into a local POE model of the chain from the root link to ``tip_link``.

    Without ``tip_link`` the chain must not branch. Fixed joints fold into the neighbouring frames; continuous
    joints are revolute with limits ±π unless given.
    """
    try:
        root = ET.fromstring(text)
    except ET.ParseError as err:
        raise ValueError(f"URDF is not valid XML: {err}") from err
    if root.tag != "robot":
        raise ValueError(f"URDF root element must be <robot>, got <{root.tag}>")
    joints = []  # (A_j(0), type, twist, [lo, hi], name) of every movable joint
    pending = np.eye(4)
    for el in _urdf_chain(root, tip_link):
        jname, jtype = el.get("name"), el.get("type")
        origin = el.find("origin")
        xyz = _floats(origin.get("xyz") if origin is not None else None, [0, 0, 0], f"joint {jname} origin xyz")
        rpy = _floats(origin.get("rpy") if origin is not None else None, [0, 0, 0], f"joint {jname} origin rpy")
        T = pending @ se3.pose(xyz, rpy)
        if jtype == "fixed":
            pending = T
            continue
        joints.append((T, *_urdf_joint(el, jname, jtype), jname))
        pending = np.eye(4)
    if not joints:
        raise ValueError("URDF chain has no movable joints")
    frames, types, twists, limits, names = zip(*joints, strict=True)
    name = name or root.get("name") or ""
    return LocalPOEModel(np.array([*frames, pending]), types, np.array(twists), np.array(limits), name, names)


def _urdf_chain(root, tip_link: str | None) -> list:
    """The <joint> elements from the root link down to ``tip_link`` (or the end of an unbranched chain)."""
    joints = {}
    for el in root.findall("joint"):
        if el.get("name") is None or el.find("parent") is None or el.find("child") is None:
            raise ValueError("every URDF <joint> needs a name, a <parent link> and a <child link>")
        joints[el.get("name")] = el
    children: dict[str | None, list] = {}  # parent link -> its <joint> elements
    for el in joints.values():
        children.setdefault(el.find("parent").get("link"), []).append(el)
    carrier = {el.find("child").get("link"): el for el in joints.values()}  # child link -> the joint that moves it
    roots = [lk for lk in children if lk not in carrier]
    if len(roots) != 1:
        raise ValueError(f"URDF must have exactly one root link, found {roots}")
    chain: list = []
    if tip_link is not None:  # up from the tip: a tree has one path to its root
        link: str | None = tip_link
        while link in carrier and len(chain) < len(joints):  # the bound: a cycle of links must not hang
            chain.append(carrier[link])
            link = carrier[link].find("parent").get("link")
        if not chain or link != roots[0]:
            raise ValueError(f"tip link {tip_link!r} not found in the URDF chain")
        return chain[::-1]
    link = roots[0]
    while link in children:
        if len(children[link]) > 1:
            raise ValueError(f"URDF branches at link {link!r}: pass tip_link to choose the chain")
        chain.append(children[link][0])
        link = children[link][0].find("child").get("link")
    return chain


def _urdf_joint(el, jname: str, jtype: str) -> tuple[str, np.ndarray, list[float]]:
    """A movable URDF joint's (type, unit twist (6,), [lo, hi])."""
    if jtype not in ("revolute", "continuous", "prismatic"):
        raise ValueError(f"joint {jname}: unsupported URDF joint type {jtype!r}")
    axis_el = el.find("axis")
    axis = _floats(axis_el.get("xyz") if axis_el is not None else None, [1, 0, 0], f"joint {jname} axis")
    norm = np.linalg.norm(axis)
    if norm < 1e-12:
        raise ValueError(f"joint {jname}: zero axis")
    axis = axis / norm
    kind = PRISMATIC if jtype == "prismatic" else REVOLUTE
    limit = el.find("limit")
    if jtype == "continuous" or limit is None or limit.get("lower") is None:
        lo, hi = (-np.pi, np.pi) if kind == REVOLUTE else (-1.0, 1.0)
    else:
        lo, hi = float(limit.get("lower")), float(limit.get("upper"))
    twist = np.concatenate([np.zeros(3), axis]) if kind == REVOLUTE else np.concatenate([axis, np.zeros(3)])
    return kind, twist, [lo, hi]
