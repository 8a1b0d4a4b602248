"""`labcal fit --json`: the cross-validation block carries exactly the keys docs/cli-json.md documents, with the unit
in every length key (issue 26: renaming `cv.std_m` survived the other tests, and a script reading it would break)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_testutil import TARGETS, invoke, last_line

# docs/cli-json.md, `cv` row of labcal.fit/1
CV_KEYS = {"folds", "scheme", "chosen", "metric", "fold_errors_m", "mean_m", "std_m", "failures", "pruned_after"}


@pytest.fixture(scope="module")
def fit_doc(tmp_path_factory):
    root = tmp_path_factory.mktemp("json-keys")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"
    r = invoke("session", "new", "--robot", "ur10", "--targets", root / "targets.toml", "--poses", 14, "--seed", 7,
               store=store)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    f = invoke("fit", last_line(r), "--method", "local-poe", "--json", store=store)
    assert f.exit_code == 0, f.stdout + f.stderr
    return json.loads(f.stdout)


def test_fit_json_cv_keys_are_the_documented_ones(fit_doc):
    cv = fit_doc["cv"]
    assert set(cv) == CV_KEYS


def test_fit_json_cv_mean_and_std_are_the_fold_errors_in_metres(fit_doc):
    cv = fit_doc["cv"]
    folds = [e for e in cv["fold_errors_m"]["local-poe"] if e is not None]
    assert len(folds) == cv["folds"] >= 2
    assert cv["std_m"]["local-poe"] == pytest.approx(float(np.std(folds)), rel=1e-12)
    assert 0 < cv["mean_m"]["local-poe"] < 5e-3  # metres: a sim UR10 fits to well under 5 mm
    assert 0 <= cv["std_m"]["local-poe"] < cv["mean_m"]["local-poe"]
