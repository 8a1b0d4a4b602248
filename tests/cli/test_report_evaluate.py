"""`labcal report` (warnings first, per-target residuals, identifiable parameters only with ± σ) and
`labcal evaluate` (held-out file or session, stored under the fit, JSON, tracker-frame registration only)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_testutil import SWAPPED, TARGETS, invoke, last_line

from labcal.cli.ops.sessions import sim_actual
from labcal.datasets import SessionStore, load_targets
from labcal.kinematics import se3
from labcal.robots import load

SEED = 11


def one_line_error(result, *fragments: str) -> None:
    assert result.exit_code == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stdout + result.stderr and result.stderr.startswith("error: ")
    for f in fragments:
        assert f in result.stderr, result.stderr


def held_out_csv(root: Path, path: Path, k: int = 20, T: np.ndarray | None = None) -> None:
    """k new poses of the same simulated robot as the sim sessions of seed SEED (optionally in a tracker frame T)."""
    spec = load("ur10")
    actual = sim_actual(spec, "default", SEED)
    targets = np.asarray(getattr(t := load_targets(root / "targets.toml"), "points", t), dtype=float)
    rng = np.random.default_rng(123)
    q = rng.uniform(0.8 * spec.model.limits[:, 0], 0.8 * spec.model.limits[:, 1], size=(k, 6))
    pts = actual.measure(q, targets, rng)
    if T is not None:
        pts = np.einsum("ab,kmb->kma", T[:3, :3], pts) + T[:3, 3]
    cols = {f"q{j + 1}": q[:, j] for j in range(6)}
    for i in range(3):
        for a, axis in enumerate("xyz"):
            cols[f"t{i + 1}_{axis}"] = pts[:, i, a]
    lines = [",".join(cols)] + [",".join(repr(float(cols[c][r])) for c in cols) for r in range(k)]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("repeval")
    (root / "targets.toml").write_text(TARGETS)
    store = root / "store"
    refs, fits = {}, {}
    for name, poses in (("good", 30), ("few", 4)):
        r = invoke("session", "new", "--robot", "ur10", "--targets", root / "targets.toml", "--poses", poses,
                   "--seed", SEED, store=store)  # fmt: skip
        assert r.exit_code == 0, r.stdout + r.stderr
        refs[name] = last_line(r)
        f = invoke("fit", refs[name], "--method", "local-poe", "--val-fraction", 0, store=store)
        assert f.exit_code == 0, f.stderr
        fits[name] = last_line(f)
    return {"root": root, "store": store, "refs": refs, "fits": fits}


# -- report --------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def reports(world, tmp_path_factory):
    out = tmp_path_factory.mktemp("reports")
    texts = {}
    for name in ("good", "few"):
        r = invoke("report", world["refs"][name], "--out", out / name, store=world["store"])
        assert r.exit_code == 0, r.stderr
        texts[name] = (Path(last_line(r)).read_text(), r, out / name)
    return texts


def test_report_starts_with_the_warnings(world, reports):
    text, result, _ = reports["few"]
    first_fit = text.index("## Fit ")
    assert text.index("## Warnings") < first_fit
    assert text.index("**WARNING [rank-deficient]**") < first_fit
    assert "WARNING [rank-deficient]" in result.stderr  # and on the terminal


def _parameter_rows(text: str) -> list[list[str]]:
    start = text.index("| frame | vx (mm)")
    rows = []
    for line in text[start:].splitlines()[2:]:
        if not line.startswith("| A"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")][1:])
    return rows


def test_parameter_table_marks_unidentifiable_parameters(reports):
    good = [c for row in _parameter_rows(reports["good"][0]) for c in row]
    few = [c for row in _parameter_rows(reports["few"][0]) for c in row]
    assert len(good) == len(few) == 42
    # Full rank (30 of 42): 12 null directions leave some parameters undetermined on their own; the rest get ± σ.
    assert 0 < good.count("—") < 42 and sum("±" in c for c in good) == 42 - good.count("—")
    # Rank 24 of 30 from 4 poses: more parameters lose their σ than at full rank.
    assert few.count("—") > good.count("—")
    assert (
        "Identifiable combinations" in reports["good"][0]
        and "Directions the data do not determine" in (reports["good"][0])
    )


def test_combination_sigma_matches_the_fits_own_standard_deviations(world):
    """The report recomputes the covariance to give combinations a σ; on single parameters it must agree with the
    standard deviations local POE computed itself."""
    from labcal.reports import _covariance, _fit_data

    st = SessionStore(world["store"])
    data = _fit_data(st, world["refs"]["good"], world["fits"]["good"])
    lp = data["meta"]["info"]
    cov = _covariance(lp, data)
    std = np.asarray(lp["std"], dtype=float).reshape(-1)  # base-frame data: every frame A1 … A7 estimated
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), std, rtol=1e-6)


def test_report_has_per_target_residuals(reports):
    text, _, folder = reports["good"]
    assert "| split | | t1 mean (mm)" in text and "point mean (mm)" in text
    pngs = list(folder.glob("targets-*.png"))
    assert len(pngs) == 1 and pngs[0].stat().st_size > 1000


# -- evaluate ------------------------------------------------------------------------------------------------------


def test_evaluate_a_held_out_file(world, tmp_path):
    held_out_csv(world["root"], tmp_path / "held.csv")
    s, fit = world["store"], world["fits"]["good"]
    r = invoke("evaluate", fit, "--data", tmp_path / "held.csv", "--targets", world["root"] / "targets.toml", store=s)
    assert r.exit_code == 0, r.stderr
    eval_id = last_line(r)
    assert "imported" in r.stdout and "point mean mm" in r.stdout and "t2 max" in r.stdout
    docs = SessionStore(s).list_evaluations(world["refs"]["good"], fit)
    doc = next(d for d in docs if d["evaluation_id"] == eval_id)
    assert not doc.get("corrupt")
    m = doc["metrics"]["all"]
    assert m["after"]["pos_mean"] < 0.2 * m["before"]["pos_mean"]  # the calibration carries over to new poses
    assert m["points"]["after"]["mean"] < 0.2 * m["points"]["before"]["mean"]
    assert doc["registration"]["parameters"] == 0 and doc["data"]["rows"] == 20
    # The file became a stored, traceable session.
    ds = SessionStore(s).load(doc["data"]["ref"])
    assert (
        len(ds) == 20
        and doc["data"]["manifest_sha256"] == SessionStore(s).manifest(doc["data"]["ref"])["manifest_sha256"]
    )
    # A session can be evaluated by reference, and --json gives the same numbers.
    j = invoke("evaluate", fit, "--data", doc["data"]["ref"], "--json", store=s)
    assert j.exit_code == 0, j.stderr
    out = json.loads(j.stdout)
    assert out["schema"] == "labcal.evaluate/1"
    assert out["metrics"]["all"]["after"]["pos_mean"] == pytest.approx(m["after"]["pos_mean"], rel=1e-12)
    assert Path(out["stored_at"]).is_file()


def test_evaluate_tracker_frame_fits_only_the_base_pose(world, tmp_path):
    T = se3.pose(np.array([1.2, -0.4, 0.3])) @ se3.exp_se3(np.array([0, 0, 0, 0.1, -0.2, 0.4]))
    held_out_csv(world["root"], tmp_path / "base.csv")
    held_out_csv(world["root"], tmp_path / "tracker.csv", T=T)
    s, fit, t = world["store"], world["fits"]["good"], world["root"] / "targets.toml"
    base = json.loads(invoke("evaluate", fit, "--data", tmp_path / "base.csv", "--targets", t, "--json",
                             store=s).stdout)  # fmt: skip
    r = invoke("evaluate", fit, "--data", tmp_path / "tracker.csv", "--targets", t, "--frame", "tracker", "--json",
               store=s)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    trk = json.loads(r.stdout)
    reg = trk["registration"]
    assert reg["parameters"] == 6 and "nothing of the calibration" in reg["fitted"]
    T_est = np.asarray(reg["T_tracker_base_after"])
    assert np.linalg.norm(T_est[:3, 3] - T[:3, 3]) < 1e-3 and np.abs(T_est[:3, :3] - T[:3, :3]).max() < 1e-3
    # Six parameters on 180 numbers: the errors stay those of the base-frame evaluation of the same poses.
    a, b = trk["metrics"]["all"]["points"]["after"]["mean"], base["metrics"]["all"]["points"]["after"]["mean"]
    assert 0.7 * b < a <= b * 1.01


def test_evaluate_uses_the_import_checks_and_refuses_other_robots_or_targets(world, tmp_path):
    s, fit = world["store"], world["fits"]["good"]
    held_out_csv(world["root"], tmp_path / "held.csv")
    (tmp_path / "swapped.toml").write_text(SWAPPED)
    # The import's sanity checks apply (swapped targets are caught and the override named) …
    r = invoke("evaluate", fit, "--data", tmp_path / "held.csv", "--targets", tmp_path / "swapped.toml", store=s)
    one_line_error(r, "--allow")
    # … and the targets must be the fit's: the fitted tool frame belongs to them.
    r = invoke("evaluate", fit, "--data", tmp_path / "held.csv", "--targets", tmp_path / "swapped.toml",
               "--allow", "target-distances", "--allow", "target-outliers", "--allow", "nominal", store=s)  # fmt: skip
    one_line_error(r, "different targets")
    r = invoke("session", "new", "--robot", "ur5e", "--targets", world["root"] / "targets.toml", "--poses", 6,
               store=s)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    one_line_error(invoke("evaluate", fit, "--data", last_line(r), store=s), "robot model")
    one_line_error(invoke("evaluate", "no-such-fit", "--data", last_line(r), store=s), "no-such-fit")
    one_line_error(invoke("evaluate", fit, "--data", tmp_path / "none.csv", store=s), "no such file")


def test_evaluate_on_the_fits_own_data_says_it_is_not_held_out(world):
    r = invoke("evaluate", world["fits"]["good"], "--data", world["refs"]["good"], store=world["store"])
    assert r.exit_code == 0, r.stderr
    assert "not a held-out score" in r.stdout


def test_evaluate_on_a_reimport_of_the_fits_data_says_it_is_not_held_out(world, tmp_path):
    # a re-import (or a later version) of the fit's rows has another ref: the rows themselves give it away
    from labcal.cli.ops.common import load_observations

    s, fit = world["store"], world["fits"]["good"]
    obs = load_observations(SessionStore(s), [world["refs"]["good"]])[0]
    held_out_csv(world["root"], tmp_path / "held.csv", k=10)
    lines = (tmp_path / "held.csv").read_text().splitlines()
    for q, pts in zip(obs.q[:7], obs.points[:7], strict=True):  # 7 of the fit's own poses among 10 new ones
        lines.append(",".join(repr(float(v)) for v in (*q, *pts.ravel())))
    (tmp_path / "mixed.csv").write_text("\n".join(lines) + "\n")
    t = world["root"] / "targets.toml"
    doc = json.loads(invoke("evaluate", fit, "--data", tmp_path / "held.csv", "--targets", t, "--json", store=s).stdout)
    assert (doc["overlap_with_fit"], doc["overlap_rows"]) == (False, 0)
    r = invoke("evaluate", fit, "--data", tmp_path / "mixed.csv", "--targets", t, store=s)
    assert r.exit_code == 0, r.stderr
    assert "7 of 17 rows are configurations the fit was fitted on" in r.stdout and "not a held-out score" in r.stdout


def test_fit_refuses_a_session_named_twice(world):
    # pooled twice, its poses weighed double and the cross-validation scored poses it was fitted on, without a word
    s, ref = world["store"], world["refs"]["good"]
    session = ref.split("@")[0]
    for refs in ((ref, ref), (session, ref)):
        r = invoke("fit", *refs, "--method", "local-poe", store=s)
        one_line_error(r, "are the same version", "name each session once")


def test_report_lists_the_stored_evaluations(world, tmp_path):
    invoke("evaluate", world["fits"]["good"], "--data", world["refs"]["good"], store=world["store"])
    r = invoke("report", world["refs"]["good"], "--out", tmp_path / "rep", store=world["store"])
    assert r.exit_code == 0, r.stderr
    assert "Evaluations on other data" in Path(last_line(r)).read_text()


@pytest.mark.parametrize("cmd", [["evaluate"], ["export"], ["report"], ["fit"]])
def test_help_has_examples(cmd):
    r = invoke(*cmd, "--help")
    assert r.exit_code == 0 and "Example" in r.stdout


def test_session_verify_checks_stored_evaluations(world, tmp_path):
    s, fit, ref = world["store"], world["fits"]["good"], world["refs"]["good"]
    r = invoke("evaluate", fit, "--data", ref, store=s)
    assert r.exit_code == 0, r.stderr
    store = SessionStore(s)
    (path,) = [p for p in (store.version_dir(ref) / "fits" / ".evaluations" / fit).glob("*.json")
               if p.stem == last_line(r)]  # fmt: skip
    assert invoke("session", "verify", ref.split("@")[0], store=s).exit_code == 0
    path.chmod(0o644)
    path.write_text(path.read_text().replace('"rows": ', '"rows": 1'))  # an edited evaluation
    bad = invoke("session", "verify", ref.split("@")[0], store=s)
    assert bad.exit_code == 1 and path.name in bad.stdout, bad.stdout
    assert next(d for d in store.list_evaluations(ref, fit) if d["evaluation_id"] == path.stem)["corrupt"]


# -- fewer than three targets (issue 15.3) ---------------------------------------------------------------------------

ONE_TARGET = 'unit = "mm"\npoints = [[120.0, 0.0, 60.0]]\n'


@pytest.fixture(scope="module")
def one_target(tmp_path_factory):
    """A simulated one-reflector session, fitted with local POE, its report, and an evaluation of it."""
    root = tmp_path_factory.mktemp("onetarget")
    (root / "one.toml").write_text(ONE_TARGET)
    store = root / "store"
    r = invoke("session", "new", "--robot", "ur10", "--targets", root / "one.toml", "--poses", 30, "--seed", SEED,
               store=store)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    ref = last_line(r)
    f = invoke("fit", ref, "--method", "local-poe", store=store)
    assert f.exit_code == 0, f.stderr
    rep = invoke("report", ref, "--out", root / "report", store=store)
    assert rep.exit_code == 0, rep.stderr
    ev = invoke("evaluate", last_line(f), "--data", ref, store=store)
    assert ev.exit_code == 0, ev.stderr
    return {"store": store, "ref": ref, "fit": last_line(f), "report": Path(last_line(rep)).read_text(), "eval": ev}


def test_fit_stores_what_orientation_accuracy_it_can_claim(one_target, world):
    one = SessionStore(one_target["store"]).load_fit(one_target["ref"], one_target["fit"]).metadata["observability"]
    assert one["targets"] == 1 and one["orientation"] == "none" and one["rows_with_pose"] == 0
    three = SessionStore(world["store"]).load_fit(world["refs"]["good"], world["fits"]["good"]).metadata
    assert three["observability"]["orientation"] == "measured"
    assert three["pool_units"] is False  # one session: nothing pooled across units


def test_one_target_report_leads_with_point_errors_and_claims_no_orientation(one_target, reports):
    text = one_target["report"]
    fit = text.index("## Fit ")
    claim = text.index("**Orientation accuracy: not measured.**", fit)
    points, pose = text.index("| split | | t1 mean (mm)", fit), text.index("| split | n | | pos mean (mm)", fit)
    assert claim < points < pose  # the claim first, then the point errors, then the (empty) pose table
    assert "Primary figures: the per-target point errors" in text
    assert "Not determined by these data" in text and "orientation of the tool" in text
    pose_rows = [line for line in text[pose:].splitlines()[2:6]]
    assert all("| — | — |" in line for line in pose_rows)  # no pose is measured: no pose error is claimed
    good = reports["good"][0]
    assert "**Orientation accuracy: measured.**" in good and "Primary figures" not in good
    assert good.index("| split | n | | pos mean (mm)") < good.index("| split | | t1 mean (mm)")


def test_one_target_evaluation_says_points_are_primary_and_what_is_not_determined(one_target):
    out = one_target["eval"].stdout
    assert out.index("primary figures: the per-target point errors") < out.index("pos mean mm")
    assert "orientation: Only target point t1 was measured" in out and "not determined by these data" in out
    doc = SessionStore(one_target["store"]).list_evaluations(one_target["ref"], one_target["fit"])[-1]
    assert doc["primary"] == "points" and doc["observability"]["orientation"] == "none"
