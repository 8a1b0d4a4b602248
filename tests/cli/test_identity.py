"""Unit identity on the command line (issue 17.1): `session import --unit`, `session list --unit`, and `fit` refusing
to pool sessions of different units (exit 2, one line naming the units and --pool-units) unless --pool-units."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from cli_testutil import invoke, last_line

import scenarios as sc
from labcal.datasets import SessionStore


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Three imports of one good scenario: unit UR-A, unit UR-B, and no unit."""
    root = tmp_path_factory.mktemp("ident")
    scn = sc.good("ur10", 30, seed=7)
    df = pd.DataFrame(scn.q, columns=[f"q{j + 1}" for j in range(6)])
    for i in range(3):
        for a, axis in enumerate("xyz"):
            df[f"t{i + 1}_{axis}"] = scn.points[:, i, a]
    df.to_csv(root / "data.csv", index=False, float_format="%.17g")
    pts = ", ".join(f"[{x:.17g}, {y:.17g}, {z:.17g}]" for x, y, z in scn.targets)
    (root / "targets.toml").write_text(f'unit = "m"\npoints = [{pts}]\n')
    store = root / "store"
    refs = {}
    for unit in ("UR-A", "UR-B", None):
        extra = ["--unit", unit] if unit else []
        r = invoke("session", "import", root / "data.csv", "--robot", "ur10", "--targets", root / "targets.toml",
                   *extra, store=store)  # fmt: skip
        assert r.exit_code == 0, r.stderr
        refs[unit] = last_line(r)
    return {"root": root, "store": store, "refs": refs}


def test_import_records_the_unit_in_the_session_metadata(world):
    st = SessionStore(world["store"])
    units = {u: st.manifest(ref)["session"]["metadata"].get("unit") for u, ref in world["refs"].items()}
    assert units == {"UR-A": "UR-A", "UR-B": "UR-B", None: None}
    r = invoke("session", "list", "--unit", "UR-A", store=world["store"])
    assert r.exit_code == 0, r.stderr
    assert world["refs"]["UR-A"].split("@")[0] in r.stdout
    assert world["refs"]["UR-B"].split("@")[0] not in r.stdout


def test_fit_refuses_to_pool_two_units_in_one_line(world):
    a, b = world["refs"]["UR-A"], world["refs"]["UR-B"]
    r = invoke("fit", a, b, "--method", "nominal", store=world["store"])
    assert r.exit_code == 2
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith("error: ") and "UR-A" in line and "UR-B" in line and "--pool-units" in line
    assert a in line and b in line
    assert not SessionStore(world["store"]).list_fits(a)  # nothing was fitted or stored


def test_a_session_without_unit_pools_with_a_unit(world):
    r = invoke("fit", world["refs"]["UR-A"], world["refs"][None], "--method", "nominal", store=world["store"])
    assert r.exit_code == 0, r.stderr


def test_pool_units_accepts_different_units(world):
    a, b = world["refs"]["UR-A"], world["refs"]["UR-B"]
    r = invoke("fit", a, b, "--method", "nominal", "--pool-units", store=world["store"])
    assert r.exit_code == 0, r.stderr
    rec = SessionStore(world["store"]).load_fit(a, last_line(r))
    assert [i["ref"] for i in rec.inputs] == [a, b]
    assert rec.metadata["pool_units"] is True  # the fit says it pooled units on purpose


def test_a_bad_unit_is_refused_before_anything_is_written(world, tmp_path):
    store = tmp_path / "s"
    r = invoke("session", "import", world["root"] / "data.csv", "--robot", "ur10", "--targets",
               world["root"] / "targets.toml", "--unit", " UR-A", store=store)  # fmt: skip
    assert r.exit_code == 2
    assert "--unit ' UR-A' is not a unit id" in r.stderr
    assert not store.exists() or not any(store.iterdir())


def test_rows_of_another_unit_are_not_appended_to_a_session(world, tmp_path):
    from labcal.datasets import ImportOptions, import_targets_csv, load_targets
    from labcal.datasets.errors import DatasetError
    from labcal.robots import load

    spec = load("ur10")
    st = SessionStore(tmp_path / "s")
    targets = load_targets(world["root"] / "targets.toml")
    ident = (spec.name, spec.hash, spec.model.n)
    ref = import_targets_csv(st, world["root"] / "data.csv", *ident, targets, ImportOptions(robot=spec, unit="UR-A"))
    sid = ref.split("@")[0]
    again = ImportOptions(robot=spec, unit="UR-B", session_id=sid, allow=("duplicates",))
    with pytest.raises(DatasetError, match="recorded with unit 'UR-A', the rows to add are of unit 'UR-B'"):
        import_targets_csv(st, world["root"] / "data.csv", *ident, targets, again)
    same = import_targets_csv(st, world["root"] / "data.csv", *ident, targets, again.with_changes(unit="UR-A"))
    assert st.manifest(same)["session"]["metadata"]["unit"] == "UR-A"
    assert np.isfinite(st.load(same).q).all() and len(st.load(same)) == 60
