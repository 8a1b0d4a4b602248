"""Acceptance (issue 12): every bad input of bad_input_cases.py, fed through the real CLI, ends as the case expects.

One test per case. ``must-stop``: no compensator comes out; ``stop``: the mistake is refused or gated; ``pass``:
good data go through untouched; ``clean-error``: a one-line error, no traceback, a non-zero exit (and, where the
case checks it, no file changed and no robot motion). ``info`` cases (honest but hard data) may go either way but
must not end in a traceback or a broken setup. ``python benchmarks/bad_inputs.py`` prints the same cases as a table.
"""

from __future__ import annotations

import tomllib

import bad_input_cases as B
import numpy as np
import pytest

import scenarios as S


@pytest.mark.slow
@pytest.mark.parametrize("case", B.CASES, ids=[c.name for c in B.CASES])
def test_bad_input_ends_as_expected(case):
    o = B.run_case(case)
    seen = f"{case.name} ({case.what}): stopped at {o.stage!r}, exit {o.code}, traceback {o.traceback}: {o.message}"
    if case.expect == "info":
        assert not o.traceback and not o.stage.startswith("setup"), seen
    else:
        assert B.verdict(case, o) == "ok", seen


def test_bad_input_verdicts():
    stopped, through = B.Outcome("import", "error: x", 2), B.Outcome("NOT stopped", "written", 0)
    case = {e: B.Case("c", e, "", lambda *_: through) for e in ("must-stop", "stop", "pass", "clean-error")}
    assert B.verdict(case["must-stop"], stopped) == "ok" and B.verdict(case["must-stop"], through) == "FAIL"
    assert B.verdict(case["pass"], through) == "ok" and B.verdict(case["pass"], stopped) == "FAIL"
    assert B.verdict(case["stop"], through) == "open"
    assert B.verdict(case["clean-error"], B.Outcome("fit", "Traceback", 1, traceback=True)) == "FAIL"
    assert B.verdict(case["clean-error"], stopped) == "ok"


def test_bad_input_message_is_the_error_line_with_its_first_named_check():
    run = B.Run(2, "", "error: 2 sanity checks failed\n  [reach] rows out of reach\n  [nominal] far\n")
    assert run.first_line() == "error: 2 sanity checks failed | [reach] rows out of reach"
    assert not run.traceback
    assert B.Run(1, "", "Traceback (most recent call last):\n  File x\nKeyError: 'a'\n").first_line() == "KeyError: 'a'"


def test_bad_input_files(tmp_path):
    scn = S.good("ur10", 4, seed=0)
    csv = B.write_csv(tmp_path / "d.csv", scn.q, scn.points, length=1000.0, angle=180 / np.pi)
    rows = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert rows.shape == (4, 15)
    assert np.allclose(rows[:, :6], np.degrees(scn.q)) and np.allclose(rows[:, 6:], scn.points.reshape(4, 9) * 1000)
    # Robot-file sanity refuses these files (that is the point), so read them as TOML.
    nominal = tomllib.loads((B.builtin_path("ur10")).read_text())["joints"]
    mm = tomllib.loads(B.robot_file_scaled(tmp_path / "ur10-mm.toml", lengths=1000.0).read_text())["joints"]
    assert np.isclose(mm[0]["d"], 1000 * nominal[0]["d"]) and mm[0]["alpha"] == nominal[0]["alpha"]
    deg = tomllib.loads(B.robot_file_scaled(tmp_path / "ur10-deg.toml", degrees=True).read_text())["joints"]
    assert np.isclose(deg[0]["alpha"], np.degrees(nominal[0]["alpha"])) and deg[0]["limits"][1] > 300
    assert [c.name for c in B.CASES].count("good") == 1 and len({c.name for c in B.CASES}) == len(B.CASES)
    # Every must-stop data mistake is also run with the import checks overridden, so the fit/export gates are measured.
    names = {c.name: c for c in B.CASES}
    for name in ("mm-as-m", "m-as-mm", "deg-as-rad", "identical-60", "pure-noise", "pure-noise-rigid"):
        assert names[name].expect == "must-stop" and names[name + "+allow"].expect == "must-stop"
