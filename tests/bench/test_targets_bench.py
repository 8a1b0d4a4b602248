"""The targets benchmark's pieces: variants cut from one draw, the shared held-out score, the pose sweep's
interpolation, the goal checks, and a tiny run end to end."""

from __future__ import annotations

import numpy as np
import pytest

import targets as T


@pytest.fixture(scope="module")
def draw():
    return T.FAMILY["paper-A"].make(1, 40, 20)


def test_variants_are_cut_from_the_same_measurements(draw):
    q1, p1, t1 = T.variant(draw, "1", 30, seed=0)
    q3, p3, t3 = T.variant(draw, "3", 30, seed=0)
    assert p1.shape == (30, 1, 3) and p3.shape == (30, 3, 3) and t1.shape == (1, 3)
    np.testing.assert_array_equal(t3, draw.targets)
    np.testing.assert_array_equal(q1, q3)
    np.testing.assert_array_equal(p1[:, 0], p3[:, 0])
    _, p2, _ = T.variant(draw, "2", 30, seed=0)
    np.testing.assert_array_equal(p2, p3[:, :2])
    _, pm, _ = T.variant(draw, "3-missing", 30, seed=0)
    lost = np.isnan(pm).all(axis=-1)
    assert lost.sum() == round(T.MISSING * 90) and not lost.all(axis=1).any()
    np.testing.assert_array_equal(pm[~lost], p3[~lost])
    _, again, _ = T.variant(draw, "3-missing", 30, seed=0)
    np.testing.assert_array_equal(np.isnan(again), np.isnan(pm))  # seeded


def test_scores_compare_with_the_held_out_points_at_t1_and_all(draw):
    def shifted(q, targets):
        out = draw.test_points.copy()
        out[:, 0] += [0.003, 0.0, 0.004]  # t1 off by 5 mm, the others exact
        return out

    s = T.scores(shifted, draw)
    assert s["t1"] == pytest.approx(0.005) and s["all"] == pytest.approx(0.005 / 3)


def _cell(values: dict) -> T.Cell:
    return T.Cell(scores={s: {"t1": v, "all": v} for s, v in values.items()}, seconds=[0.0])


def test_poses_to_match_interpolates_between_the_sweep_sizes():
    cells = {
        ("3", 100, "m"): _cell({0: 1.0, 1: 1.0}),
        ("1", 100, "m"): _cell({0: 1.6, 1: 1.6}),
        ("1", 200, "m"): _cell({0: 1.2, 1: 1.2}),
        ("1", 300, "m"): _cell({0: 0.8, 1: 0.8}),
    }
    need, top = T.poses_to_match(cells, "m", 100)
    assert need == pytest.approx(250.0) and top == 300
    cells[("1", 300, "m")] = _cell({0: 1.1, 1: 1.1})
    assert T.poses_to_match(cells, "m", 100) == (None, 300)
    cells[("1", 100, "m")] = _cell({0: 0.9, 1: 1.0})
    assert T.poses_to_match(cells, "m", 100)[0] == 100


def test_goals_follow_the_issue_thresholds():
    def fam(one, miss, sweep):
        return {
            ("3", 100, "m"): _cell({0: 1.0, 1: 1.0}),
            ("1", 100, "m"): _cell({0: one, 1: one}),
            ("2", 100, "m"): _cell({0: 1.0, 1: 1.0}),
            ("3-missing", 100, "m"): _cell({0: miss, 1: miss}),
            ("1", 200, "m"): _cell({0: sweep, 1: sweep}),
        }

    lines, goals = T.report({"good": fam(1.4, 1.05, 0.99), "bad": fam(1.6, 1.2, 1.1)}, ("m",), [0, 1],
                            {"good": 100, "bad": 100})  # fmt: skip
    g, b = goals["good"]["m"], goals["bad"]["m"]
    assert g["within-1.5x"] and g["equal-at-2x"] and g["missing<10%"]
    assert not (b["within-1.5x"] or b["equal-at-2x"] or b["missing<10%"])
    text = "\n".join(lines)
    assert "1.40 ± 0.00" in text and "> 200" in text and "5.0 ± 0.0" in text


def test_a_tiny_run_prints_every_table_and_the_plot(tmp_path, capsys):
    out, png = tmp_path / "t.txt", tmp_path / "t.png"
    code = T.main(["--quick", "--families", "paper-A", "--methods", "plain-lsq,local-poe", "--poses", "40",
                   "--held-out", "20", "--out", str(out), "--plot", str(png)])  # fmt: skip
    assert code == 0
    text = out.read_text()
    assert text == capsys.readouterr().out
    for part in ("1 target", "2 targets", "3, 30 % cells missing", "1 target @ 80", "poses 1 target needs",
                 "Goals (issue 15)"):  # fmt: skip
        assert part in text, part
    rows = [line.split() for line in text.splitlines() if line.startswith("paper-A") and "3 targets" in line]
    lsq, lp = float(rows[0][4]), float(rows[0][5])
    assert 0 < lp < 0.2 and abs(lp - lsq) < 0.1 * lsq  # calibrated to tens of µm, and the stick agrees
    assert png.stat().st_size > 1000
    with pytest.raises(SystemExit):
        T.main(["--families", "paper-C"])
