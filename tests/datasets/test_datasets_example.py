"""The committed example session must stay intact and loadable."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labcal.datasets import SessionStore
from labcal.datasets._util import sha256_file

SESSIONS = Path(__file__).resolve().parents[2] / "sessions"


@pytest.mark.skipif(not (SESSIONS / "example").is_dir(), reason="no committed example session")
def test_committed_example_verifies_and_loads():
    store = SessionStore(SESSIONS)
    assert store.verify("example").ok, store.verify("example").problems
    ds = store.load("example@v1")
    assert len(ds) == 20 and ds.frame == "tracker" and ds.q.shape == (20, 6)
    assert np.isfinite(ds.points).all()
    assert ds.manifest["source"] == f"import:{sha256_file(SESSIONS / 'example' / 'source-excerpt.csv')}"
    assert (SESSIONS / "example" / "LICENSE.md").is_file()
