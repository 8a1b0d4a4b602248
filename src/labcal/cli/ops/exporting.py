"""`labcal export` as a function: write a stored fit in one of the export formats, with provenance."""

from __future__ import annotations

from pathlib import Path

from labcal.cli.ops.common import UserError
from labcal.cli.ops.fitting import load_stored_fit
from labcal.datasets import SessionStore


def export_fit(store: SessionStore, ref: str, fmt: str, out: str | Path, fit_id: str | None = None) -> Path:
    """Write a stored fit as json | npz | urscript | urdf, with provenance (session, fit id, data hashes)."""
    from labcal.export import FORMATS, export

    if fmt not in FORMATS:
        raise UserError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    stored = load_stored_fit(store, ref, fit_id)
    record = store.load_fit(stored.ref, stored.fit_id, check_files=False)
    provenance = {
        "session": stored.ref,
        "fit_id": stored.fit_id,
        "inputs": ", ".join(i["ref"] for i in record.inputs),
        "data_sha256": ", ".join(i["manifest_sha256"] for i in record.inputs),
        "method": stored.robot.method,
    }
    out = Path(out)
    if out.parent and not out.parent.exists():
        raise UserError(f"output folder {out.parent} does not exist")
    return export(stored.robot, fmt, out, provenance)
