"""The real-UR10 benchmark: protocol pieces, and a quick smoke run on the shared data (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import real_ur10 as bench

REPO = Path(__file__).resolve().parents[2]
DATA_DIRS = [REPO.parent / "shared" / "data" / bench.DATA_NAME, Path("/work/shared/data") / bench.DATA_NAME]


def _data_dir() -> Path:
    for d in DATA_DIRS:
        if (d / bench.CSV_NAME).is_file():
            return d
    pytest.skip("the shared UR10 data folder is absent")


def test_split_takes_a_third_of_the_drawn_poses_for_validation_and_tests_on_the_rest():
    s = bench.split_for(1000, 150, seed=3)
    assert (np.sum(s == "train"), np.sum(s == "val"), np.sum(s == "test")) == (100, 50, 850)
    np.testing.assert_array_equal(s, bench.split_for(1000, 150, seed=3))
    other = bench.split_for(1000, 150, seed=4)
    assert not np.array_equal(s, other)
    # A larger draw with the same seed contains the smaller one: the learning curve adds poses.
    big = bench.split_for(1000, 500, seed=3)
    assert np.all(big[s != "test"] != "test")
    with pytest.raises(ValueError, match="training-set size must be in 2 … 999, got 1000"):
        bench.split_for(1000, 1000, seed=0)


def test_missing_data_is_a_clear_error_and_exit_status_2(tmp_path, capsys):
    with pytest.raises(bench.DataNotFound, match=r"measurements_random_poses\.csv not found"):
        bench.locate_data(tmp_path)
    assert bench.main(["--data", str(tmp_path), "--quick"]) == 2
    assert "pass --data DIR" in capsys.readouterr().err


def test_table_reports_mean_and_spread_over_seeds():
    e = {"local-poe": np.array([1e-3, 3e-3]), "series": np.array([1e-4, 1e-4])}
    runs = [bench.Run(150, s, {m: v * (1 + s) for m, v in e.items()}, e, {}, "", "", 8, {}) for s in range(2)]
    text = bench.table(runs, 150, ("local-poe", "series"))
    lines = text.splitlines()
    assert lines[0].split()[:3] == ["method", "pos", "mean"]
    lp = lines[2].split()
    # seeds give means 2 mm and 4 mm: 3.000 ± 1.000
    assert lp[0] == "local-poe" and lp[1:4] == ["3.000", "±", "1.000"]
    assert len({len(line) for line in lines}) == 1  # aligned columns


@pytest.mark.slow
def test_quick_run_on_the_real_data_beats_local_poe_with_the_series(tmp_path, capsys):
    data = _data_dir()
    out, plot = tmp_path / "out.txt", tmp_path / "curve.png"
    assert bench.main(["--quick", "--data", str(data), "--out", str(out), "--plot", str(plot)]) == 0
    text = out.read_text()
    assert text == capsys.readouterr().out
    table_rows = [line.split() for line in text.splitlines() if len(line.split()) == 9]
    rows = {r[0]: r for r in table_rows if r[0] in bench.METHODS}
    assert set(rows) == set(bench.METHODS)
    mean = {m: float(r[1]) for m, r in rows.items()}
    # The data README's reference figures (registered nominal 0.91 mm, local POE about 0.45 mm) hold here too,
    # and the structured learned term is what the hybrid keeps.
    assert 0.8 < mean["nominal"] < 1.0 and 0.38 < mean["local-poe"] < 0.52
    assert mean["series"] < 0.7 * mean["local-poe"]
    assert mean["hybrid"] <= mean["local-poe"] and mean["auto"] <= mean["local-poe"]
    assert "2623 test poses" in text
    assert plot.stat().st_size > 1000
