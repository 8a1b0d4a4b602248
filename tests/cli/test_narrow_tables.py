"""The fit and evaluate tables at an 80-column terminal: every number printed whole (rich cut them to `2.…`)."""

from __future__ import annotations

import json
import re

import pytest
from cli_testutil import TARGETS, invoke, last_line

from labcal.cli import common
from labcal.cli.common import deg, mm
from labcal.datasets import SessionStore


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    root = tmp_path_factory.mktemp("narrow")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"
    r = invoke(
        "session", "new", "--robot", "ur10", "--robot-driver", "sim", "--tracker-driver", "sim",
        "--targets", root / "targets.toml", "--poses", 30, "--seed", 5, store=store,
    )  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    held_out = invoke(
        "session", "new", "--robot", "ur10", "--targets", root / "targets.toml", "--poses", 12, "--seed", 6,
        store=store,
    )  # fmt: skip
    assert held_out.exit_code == 0, held_out.stdout + held_out.stderr
    return {"store": store, "ref": last_line(r), "held_out": last_line(held_out)}


@pytest.fixture
def columns_80(monkeypatch):
    """COLUMNS=80, and a stdout console made afresh so that it reads it."""
    monkeypatch.setenv("COLUMNS", "80")
    monkeypatch.setattr(common.out, "_console", None)
    yield
    common.out._console = None  # the next test makes its own again


def numbers_of(metrics: dict) -> set[str]:
    """Every figure the tables print, formatted as they print it."""
    shown = set()
    for split in ("train", "val", "test", "all"):
        if split not in metrics:
            continue
        for when in ("before", "after"):
            s = metrics[split][when]
            shown |= {mm(s.get(f"pos_{k}")) for k in ("mean", "rms", "p95", "max")}
            shown |= {deg(s.get(f"ori_{k}")) for k in ("mean", "rms", "p95", "max")}
            points = metrics[split]["points"][when]
            shown |= {mm(points.get(k)) for k in ("mean", "p95", "max")}
            shown |= {mm(p.get(k)) for p in points.get("per_target") or [] for k in ("mean", "p95", "max")}
    return shown - {"—"}


def assert_whole(stdout: str, metrics: dict) -> None:
    assert "…" not in stdout, stdout
    table_lines = [line for line in stdout.splitlines() if set(line) & set("│┃━")]
    assert table_lines and max(len(line) for line in table_lines) <= 80, stdout
    printed = set(re.findall(r"(?<![\d.])\d+\.\d{4}(?![\d.])", stdout))
    missing = numbers_of(metrics) - printed
    assert not missing, f"not printed whole at 80 columns: {sorted(missing)}\n{stdout}"


def test_fit_tables_print_every_number_whole_at_80_columns(fitted, columns_80):
    r = invoke("fit", fitted["ref"], "--method", "local-poe", "--val-fraction", "0.3", store=fitted["store"])
    assert r.exit_code == 0, r.stderr
    record = SessionStore(fitted["store"]).load_fit(fitted["ref"], last_line(r))
    assert_whole(r.stdout, record.metadata["metrics"])


def test_evaluate_tables_print_every_number_whole_at_80_columns(fitted, columns_80):
    fit = invoke("fit", fitted["ref"], "--method", "local-poe", store=fitted["store"])
    assert fit.exit_code == 0, fit.stderr
    r = invoke("evaluate", last_line(fit), "--data", fitted["held_out"], "--json", store=fitted["store"])
    assert r.exit_code == 0, r.stderr
    metrics = json.loads(r.stdout)["metrics"]
    r = invoke("evaluate", last_line(fit), "--data", fitted["held_out"], store=fitted["store"])
    assert r.exit_code == 0, r.stderr
    assert_whole(r.stdout, metrics)
