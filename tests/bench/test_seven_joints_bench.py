"""benchmarks/seven_joints.py: a method that refuses is a row of the table (not a crash), and the exports column
counts what a local-POE fit of a simulated Panda writes without --force."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from labcal.robots import load

SCRIPT = Path(__file__).parents[2] / "benchmarks" / "seven_joints.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("seven_joints_bench", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_refused_method_is_a_row_and_exports_are_counted(bench, monkeypatch):
    real_fit = bench.fit

    def fit(obs, nominal, method, seed=0):
        if method == "hybrid":  # whatever the calibration code does today: the benchmark must report a refusal
            raise ValueError("method 'hybrid' learns the six joint motion errors of the equivalent robot")
        return real_fit(obs, nominal, method, seed=seed)

    monkeypatch.setattr(bench, "fit", fit)
    said: list[str] = []
    res = bench.run_family("three-targets", load("franka-panda"), 45, 1, ("local-poe", "hybrid"), said.append)
    assert res["hybrid"]["refused"] == {0: "ValueError: method 'hybrid' learns the six joint motion errors of the "
                                         "equivalent robot"}  # fmt: skip
    assert "hybrid refused" in said[-1]
    exported = res["local-poe"]["exports"][0]
    assert exported["json"] == exported["npz"] == exported["urdf"] == "ok"
    done, total = exported["filter-rows"]
    assert total > 0 and done >= 1
    lines = bench.report({"three-targets": res}, ("local-poe", "hybrid"), 1)
    hybrid_row = next(line for line in lines if line.startswith("three-targets") and " hybrid " in line)
    assert "refused: method 'hybrid' learns the six joint motion errors" in hybrid_row
    local_row = next(line for line in lines if line.startswith("three-targets") and "local-poe" in line)
    json, npz, urdf, filtered, rows = local_row.split()[-6:-1]
    assert [json, npz, urdf] == ["1/1"] * 3
    assert filtered == ("1/1" if done == total else "0/1") and rows == f"{done}/{total}"
