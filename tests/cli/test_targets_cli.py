"""Any number of targets through the command line: import → fit → export → correct, checked on the true robot.

The data come from the simulator's true robot (geometric and non-geometric errors, tracker noise), written as a
user's CSV would be (degrees, millimetres, an empty cell where a target was not seen). The exported compensator
must bring the true robot's tool points close to where the nominal model puts them on poses the fit never saw.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_testutil import invoke, last_line

import scenarios
from labcal.compensator import Compensator
from labcal.robots import load

ONE = np.array([[0.0, 0.0, 0.1]])  # a single reflector 100 mm out along the flange axis
THREE = np.array([[0.12, 0.0, 0.06], [-0.06, 0.1, 0.06], [-0.06, -0.1, 0.09]])


def _write_csv(path: Path, q: np.ndarray, points: np.ndarray) -> None:
    header = [f"q{j + 1}" for j in range(q.shape[1])] + [f"t{i + 1}_{a}" for i in range(points.shape[1]) for a in "xyz"]
    lines = [",".join(header)]
    for qk, pk in zip(np.degrees(q), points * 1e3, strict=True):
        cells = [repr(float(v)) for v in qk] + ["" if np.isnan(v) else repr(float(v)) for v in pk.reshape(-1)]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def _write_targets(path: Path, targets: np.ndarray) -> None:
    rows = ", ".join("[" + ", ".join(repr(float(v)) for v in t) + "]" for t in targets * 1e3)
    path.write_text(f'unit = "mm"\npoints = [{rows}]\n')


@pytest.mark.parametrize(
    ("targets", "missing", "method"),
    [(ONE, 0.0, "local-poe"), (ONE, 0.0, "auto"), (THREE, 0.3, "local-poe")],
    ids=["one-reflector-local-poe", "one-reflector-auto", "three-targets-30pct-missing"],
)
def test_import_fit_export_correct_with_any_number_of_targets(tmp_path, targets, missing, method):
    scn = scenarios.good("ur10", 160, seed=11, targets=targets)
    points = scn.points.copy()
    if missing:
        rng = np.random.default_rng(3)
        hidden = rng.random(points.shape[:2]) < missing
        hidden[hidden.all(axis=1), 0] = False  # every row keeps at least one target
        points[hidden] = np.nan
    fit_rows, held_out = np.arange(120), np.arange(120, 160)
    _write_csv(tmp_path / "data.csv", scn.q[fit_rows], points[fit_rows])
    _write_targets(tmp_path / "targets.toml", targets)
    store = tmp_path / "store"

    r = invoke(
        "session", "import", tmp_path / "data.csv", "--robot", "ur10", "--targets", tmp_path / "targets.toml",
        "--length-unit", "mm", "--angle-unit", "deg", store=store,
    )  # fmt: skip
    assert r.exit_code == 0, r.stderr
    session = last_line(r)
    r = invoke("fit", session, "--method", method, "--seed", "0", store=store)
    assert r.exit_code == 0, r.stderr
    fit_id = last_line(r)
    r = invoke("export", session, "--fit", fit_id, "--format", "json", "--out", tmp_path / "comp.json", store=store)
    assert r.exit_code == 0, r.stderr + r.stdout

    comp = Compensator.load(tmp_path / "comp.json")
    nominal = load("ur10").model
    q = scn.q[held_out]
    lo, hi = scn.q[fit_rows].min(axis=0), scn.q[fit_rows].max(axis=0)
    q = q[((q >= lo) & (q <= hi)).all(axis=1)]  # the compensator refuses to extrapolate a learned term
    assert len(q) >= 10
    # held-out point error on the session's own targets, on the fixture as the calibration identified it (robot and
    # tool apart: the compensator brings the robot's flange to its nominal pose, and the fixture with it)
    X = np.eye(4) if comp.robot.measurement_tool is None else comp.robot.measurement_tool
    T = nominal.fk(q) @ X
    wanted = np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]
    before = np.linalg.norm(scn.actual.true_points(q, targets) - wanted, axis=-1).mean()
    after = np.linalg.norm(scn.actual.true_points(comp.correct(q), targets) - wanted, axis=-1).mean()
    print(f"held-out point error {before * 1e3:.3f} -> {after * 1e3:.3f} mm")
    assert after < 0.25 * before, (before, after)
