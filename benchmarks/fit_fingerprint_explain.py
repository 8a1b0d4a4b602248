"""Why the fingerprints of issue 27 (datadirs) changed: per fit, the parameters without the new ``validity`` field
against a saved run, and which corrections the 0.1 rad bound changed.

    python benchmarks/fit_fingerprint_explain.py benchmarks/results/fit_fingerprint_datadirs_base.txt

The base file is ``fit_fingerprint.py --save`` at the commit before this branch (42e6ae7). Prints, per case: the
digest of the payload without ``validity`` (same as the base: the fit did not change), the weak directions local
POE held, how many of the 200 fingerprint configurations need more than 0.1 rad unbounded (those are bounded now),
and the largest change of ``correct()`` at the other configurations that had converged.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from fit_fingerprint import _cases, _configurations, converged
from labcal.calibration.fit import fit
from labcal.compensator import to_payload
from labcal.compensator.solve import MAX_CORRECTION


def _digest_without_validity(robot) -> str:
    payload = to_payload(robot)
    for volatile in ("golden", "checksums", "validity"):
        payload.pop(volatile, None)
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def main(argv: list[str]) -> int:
    base = Path(argv[0])
    saved = {tuple(ln.split()[:2]): ln.split()[3] for ln in base.read_text().splitlines() if ln.strip()}
    before = np.load(base.with_suffix(".npz"))
    print(f"{'data set':24s} {'method':10s} {'fit':10s} {'weak':>4s} {'bounded rows':>12s} {'max |Δ| other rows':>18s}")
    for name, build, methods in _cases():
        obs, nominal = build()
        for method in methods:
            res = fit(obs, nominal, method, seed=0)
            q = _configurations(res.robot)
            same = _digest_without_validity(res.robot) == saved.get((name, method))
            lp = res.info if "weak" in res.info else res.info.get("local-poe", {})
            unbounded = dataclasses.replace(res.robot, validity=None).correct(q, extrapolate=True)
            far = np.abs(unbounded - q).max(axis=1) > MAX_CORRECTION
            now = res.robot.correct(q, extrapolate=True)
            old = before[f"{name}/{method}"]
            ok = converged(res.robot, q, old) & ~far
            rest = float(np.abs(now - old).max(axis=1)[ok].max(initial=0.0))
            print(f"{name:24s} {method:10s} {'identical' if same else 'CHANGED':10s} {lp.get('weak', '-')!s:>4s} "
                  f"{int(far.sum()):12d} {rest:18.3g}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
