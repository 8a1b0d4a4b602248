"""Helpers shared by the labcal.datasets tests (a plain module: tests/datasets has no __init__.py)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from labcal.datasets import SessionHeader, SessionStore

ROBOT_HASH = "5" * 64
TARGETS = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.08, 0.02]])


def shared_data_dir() -> Path | None:
    """The shared UR10 data folder: /work/shared/data/... or ../shared/data/... relative to the repo."""
    repo = Path(__file__).resolve().parents[2]
    for base in (Path("/work/shared/data"), repo.parent / "shared" / "data"):
        d = base / "ipa-robot-accuracy-ur10"
        if (d / "measurements_random_poses.csv").is_file():
            return d
    return None


def new_journal(store: SessionStore, n_joints: int = 6, plan_len: int = 10, **kw):
    header = SessionHeader.of(
        "ur10",
        ROBOT_HASH,
        n_joints,
        kw.pop("robot", None),
        targets=kw.pop("targets", TARGETS),
        frame=kw.pop("frame", "base"),
        tracker={"driver": "sim", "seed": 1},
        robot_driver={"driver": "sim"},
        plan=[{"q": [0.1 * i] * n_joints} for i in range(plan_len)],
        extra_units={"temperature": "degC"},
        metadata={"operator": "test"},
        **kw,
    )
    return store.create_session(header)


def fake_measurement(rng: np.random.Generator, n_joints: int = 6) -> dict:
    q = rng.uniform(-3, 3, n_joints)
    return {
        "q_commanded": q,
        "q_actual": q + rng.normal(0, 1e-4, n_joints),
        "points": rng.normal(0, 0.5, (3, 3)),
        "spread": rng.uniform(0, 1e-4, 3),
        "samples": 5,
    }


def flip_byte(path: Path, offset: int) -> None:
    """Flip one byte of a (read-only) file in place."""
    os.chmod(path, 0o644)
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))
