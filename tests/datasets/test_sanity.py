"""Sanity checks at import (issue 12.1): every mistake a new user makes is refused with the check's name, the bad
rows and the fix, nothing is written, and only ``allow=[CHECK]`` (``--allow CHECK``) lets it through, on record.

The data are simulated (``benchmarks/scenarios.py``) and go through the real import path: a CSV on disk,
``import_targets_csv`` / ``import_probe_csv`` with the robot spec, as ``labcal session import`` calls them.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import scenarios as sc
from labcal.datasets import DatasetError, SessionStore, import_probe_csv, import_targets_csv, load_version
from labcal.datasets.sanity import CHECKS, SanityError, check_measurements, registered_residuals
from labcal.kinematics import se3
from labcal.robots import load

UR10 = load("ur10")


def _csv(path, q, points, *, length_scale=1.0, degrees=False):
    """Write q (k, n) and points (k, 3, 3) as the three-target CSV; numbers scaled as a user's file would be."""
    n = q.shape[1]
    df = pd.DataFrame(np.degrees(q) if degrees else q, columns=[f"q{j + 1}" for j in range(n)])
    for i in range(3):
        for a, axis in enumerate("xyz"):
            df[f"t{i + 1}_{axis}"] = points[:, i, a] * length_scale
    df.to_csv(path, index=False, float_format="%.17g")
    return path


def _import(tmp_path, q, points, targets, *, robot=UR10, name="data.csv", length_scale=1.0, degrees=False, **kw):
    store = SessionStore(tmp_path / "store")
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = _csv(tmp_path / name, q, points, length_scale=length_scale, degrees=degrees)
    ref = import_targets_csv(store, path, robot.name, robot.hash, robot.model.n, targets, robot=robot, **kw)
    return store, ref


def _refused(tmp_path, q, points, targets, check, *fragments, **kw) -> SanityError:
    """Import must fail on ``check`` with every fragment in the message, leave the store empty, and go through
    with ``allow=[every failed check]``, recording the overrides."""
    with pytest.raises(SanityError) as e:
        _import(tmp_path, q, points, targets, **kw)
    msg = str(e.value)
    failed = [f.check for f in e.value.report.failures]
    assert check in failed, msg
    assert f"--allow {check}" in msg, msg
    for frag in fragments:
        assert frag in msg, msg
    store = SessionStore(tmp_path / "store")
    assert not store.root.exists() or store.session_ids() == []
    store, ref = _import(tmp_path, q, points, targets, allow=failed, **kw)
    imp = load_version(store, ref).manifest["provenance"]["import"]
    assert imp["options"]["allow"] == sorted(set(failed))
    assert sorted({f["check"] for f in imp["checks"]["allowed"]}) == sorted(set(failed))
    return e.value


@pytest.fixture(scope="module")
def good():
    return sc.good("ur10", 40, seed=3)


# -- the good file ----------------------------------------------------------------------------------------------


def test_good_file_goes_through_untouched(tmp_path, good):
    """mm + degrees as a user writes them: no finding, no note, and exactly the rows an unchecked import gave."""
    store, ref = _import(tmp_path, good.q, good.points, good.targets, length_scale=1e3, degrees=True,
                         length_unit="mm", angle_unit="deg")  # fmt: skip
    ds = load_version(store, ref)
    np.testing.assert_allclose(ds.q, good.q, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(ds.points, good.points, rtol=1e-13, atol=1e-15)
    checks = ds.manifest["provenance"]["import"]["checks"]
    assert checks["allowed"] == [] and checks["notes"] == []
    assert 0 < checks["stats"]["nominal_mean_mm"] < 10
    # The same file without the robot (data-only checks) stores the very same table: the checks change nothing.
    plain = import_targets_csv(
        store, tmp_path / "data.csv", UR10.name, UR10.hash, 6, good.targets, length_unit="mm", angle_unit="deg"
    )
    pd.testing.assert_frame_equal(load_version(store, plain).table, ds.table)
    # The session carries the robot model itself.
    robot = ds.manifest["session"]["robot"]
    assert robot["text"] == UR10.text and robot["hash"] == UR10.hash and robot["format"] == "toml"


def test_good_tracker_frame_and_probe_data_pass(tmp_path, good):
    trk = sc.in_tracker_frame(good)
    _import(tmp_path, trk.q, trk.points, trk.targets, frame="tracker")
    # A 6-DOF probe on an unknown mount, seen by a tracker: the check registers both frames.
    T = trk.T_tracker_base @ good.actual.true_pose(good.q) @ se3.pose([0.02, -0.01, 0.15], [0.4, -0.3, 1.2])
    df = pd.DataFrame(good.q, columns=[f"q{j + 1}" for j in range(6)])
    df[["x", "y", "z"]] = T[:, :3, 3] * 1e3
    df[["rx", "ry", "rz"]] = Rotation.from_matrix(T[:, :3, :3]).as_rotvec()
    df.to_csv(tmp_path / "probe.csv", index=False, float_format="%.17g")
    store = SessionStore(tmp_path / "p")
    ref = import_probe_csv(store, tmp_path / "probe.csv", "ur10", UR10.hash, 6, length_unit="mm", frame="tracker",
                           robot=UR10)  # fmt: skip
    assert load_version(store, ref).manifest["provenance"]["import"]["checks"]["stats"]["nominal_mean_mm"] < 10
    # The same probe file with its mm read as m: refused, and the fix is named.
    with pytest.raises(SanityError, match="--length-unit mm"):
        import_probe_csv(store, tmp_path / "probe.csv", "ur10", UR10.hash, 6, frame="tracker", robot=UR10)


# -- length units -------------------------------------------------------------------------------------------------


def test_mm_imported_as_m(tmp_path, good):
    e = _refused(tmp_path, good.q, good.points, good.targets, "target-distances",
                 "mm imported as m — pass --length-unit mm", length_scale=1e3)  # fmt: skip
    assert "nominal" in [f.check for f in e.report.failures]


def test_m_imported_as_mm(tmp_path, good):
    _refused(tmp_path, good.q, good.points, good.targets, "target-distances", "m imported as mm — pass --length-unit m",
             length_unit="mm")  # fmt: skip


def test_inches_and_mm_confused(tmp_path, good):
    _refused(tmp_path, good.q, good.points, good.targets, "target-distances",
             "in imported as mm — pass --length-unit in", length_scale=1 / 0.0254, length_unit="mm")  # fmt: skip
    _refused(tmp_path / "b", good.q, good.points, good.targets, "target-distances",
             "mm imported as in — pass --length-unit mm", length_scale=1e3, length_unit="in")  # fmt: skip


def test_points_times_25_4(tmp_path, good):
    slip = sc.unit_slip(good, sc.INCH)
    _refused(tmp_path, slip.q, slip.points, slip.targets, "target-distances", "25.4×", "length unit slip")


# -- joint angles -------------------------------------------------------------------------------------------------


def test_degrees_imported_as_radians(tmp_path, good):
    e = _refused(tmp_path, good.q, good.points, good.targets, "joint-limits", "the values look like degrees",
                 "pass --angle-unit deg", "row 1 (line 2)", degrees=True)  # fmt: skip
    nominal = [f for f in e.report.failures if f.check == "nominal"]
    assert nominal and "with --angle-unit deg" in nominal[0].message


def test_a_joint_a_whole_turn_off_is_named_as_a_turn_not_as_degrees(tmp_path, good):
    # "look like degrees" sent the user round in circles: following it, the check advised --angle-unit rad again
    q = good.q.copy()
    q[:, 5] += 2 * np.pi
    _refused(tmp_path, q, good.points, good.targets, "joint-limits", "whole turns off: q6 by +1 turn(s) (+360°)")


def test_a_turn_off_behind_a_joint_map_is_named_as_a_turn(tmp_path):
    # the turn is in the file's (controller) column; the limits are the model's, after the map
    coupled = load("coupled-elbow-6r")
    scn = sc.good("coupled-elbow-6r", 40, seed=5)
    q_ctrl = coupled.joints.to_controller(scn.q)
    q_ctrl[:, 5] += 2 * np.pi
    with pytest.raises(SanityError) as e:
        _import(tmp_path, q_ctrl, scn.points, scn.targets, robot=coupled)
    message = next(f.message for f in e.value.report.failures if f.check == "joint-limits")
    assert "whole turns off: q6 by +1 turn(s)" in message and "degrees" not in message


def test_wrist_joints_in_degrees_are_named_with_the_joints_in_radians(tmp_path, good):
    q = good.q.copy()
    q[:, 3:] = np.degrees(q[:, 3:])  # a file whose wrist columns are degrees, the others radians
    _refused(tmp_path, q, good.points, good.targets, "joint-limits",
             "joint(s) 4, 5, 6 look like degrees while joint(s) 1, 2, 3 look like radians")  # fmt: skip


def test_two_joint_columns_swapped_are_named(tmp_path, good):
    q = good.q[:, [0, 2, 1, 3, 4, 5]]  # q2 and q3 swapped in the file: "no single fix found" before
    _refused(tmp_path, q, good.points, good.targets, "nominal", "with the columns of joints 2 and 3 swapped")


def test_radians_imported_with_angle_unit_deg(tmp_path, good):
    _refused(tmp_path, good.q, good.points, good.targets, "joint-span", "radians imported as degrees",
             "pass --angle-unit rad", angle_unit="deg")  # fmt: skip


def test_joint_limits_apply_to_model_joints_after_the_joint_map(tmp_path):
    """Controller joints of a coupled-elbow arm pass with its robot file and are refused as plain fanuc joints."""
    coupled = load("coupled-elbow-6r")
    scn = sc.good("coupled-elbow-6r", 40, seed=5)
    q_ctrl = coupled.joints.to_controller(scn.q)
    _import(tmp_path / "ok", q_ctrl, scn.points, scn.targets, robot=coupled)
    fanuc = load("fanuc-m1000ia")
    assert fanuc.model.limits.tobytes() == coupled.model.limits.tobytes()
    with pytest.raises(SanityError) as e:
        _import(tmp_path / "bad", q_ctrl, scn.points, scn.targets, robot=fanuc)
    assert "nominal" in [f.check for f in e.value.report.failures]
    assert "if model q2 = −J2; q3 = J2 + J3" in str(e.value)  # the example file's map, found from the data


def test_unconverted_coupled_elbow_names_the_coupling(tmp_path):
    scn = sc.coupled_elbow("ur10", 40, seed=2)
    _refused(tmp_path, scn.q_controller, scn.points, scn.targets, "nominal", "if model q3 = J2 + J3", "[joint_map]")


# -- targets file -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("i", "j"), [(0, 1), (1, 2)])
def test_swapped_targets_are_named(tmp_path, good, i, j):
    bad = sc.swapped_targets(good, i, j)
    _refused(tmp_path, bad.q, bad.points, bad.targets, "target-distances",
             f"targets look swapped: t{i + 1}↔t{j + 1}")  # fmt: skip


def test_wrong_targets_file(tmp_path, good):
    bad = sc.wrong_targets(good)
    _refused(tmp_path, bad.q, bad.points, bad.targets, "target-distances",
             "the targets file's triangle does not match the data", "t1–t2")  # fmt: skip


def test_single_rows_with_a_mismeasured_target_are_named(tmp_path, good):
    pts = good.points.copy()
    pts[[4, 17], 2] += [0.02, 0.0, 0.0]  # t3 of rows 5 and 18 off by 20 mm
    e = _refused(tmp_path, good.q, pts, good.targets, "target-outliers", "row 5 (line 6)", "row 18 (line 19)")
    assert [f.rows for f in e.report.failures if f.check == "target-outliers"] == [[4, 17]]


# -- frame and reach ----------------------------------------------------------------------------------------------


def test_tracker_frame_data_imported_as_base(tmp_path, good):
    trk = sc.in_tracker_frame(good)
    e = _refused(tmp_path, trk.q, trk.points, trk.targets, "reach", "fit the nominal model to", "with --frame tracker")
    nominal = [f for f in e.report.failures if f.check == "nominal"]
    assert nominal and "with --frame tracker" in nominal[0].message


# -- poses --------------------------------------------------------------------------------------------------------


def test_identical_poses(tmp_path):
    scn = sc.identical_poses("ur10", 30, seed=1)
    e = _refused(tmp_path, scn.q, scn.points, scn.targets, "duplicates", "29 of 30 rows repeat a pose")
    assert "few-poses" in [f.check for f in e.report.failures]
    # Allowed, the repeats are still reported with the version.
    store = SessionStore(tmp_path / "store")
    notes = load_version(store, store.session_ids()[0]).manifest["provenance"]["import"]["checks"]["notes"]
    assert any("repeat an earlier pose" in n and "row 1 (line 2) = row 2 (line 3)" in n for n in notes)


def test_a_few_repeats_are_a_note_not_an_error(tmp_path, good):
    q = good.q.copy()
    q[7] = q[3]
    pts = good.points.copy()
    pts[7] = pts[3]
    store, ref = _import(tmp_path, q, pts, good.targets)
    checks = load_version(store, ref).manifest["provenance"]["import"]["checks"]
    assert checks["stats"]["duplicate_rows"] == 1 and "row 4 (line 5) = row 8 (line 9)" in checks["notes"][0]


def test_too_few_poses(tmp_path, good):
    few = good.subset(np.arange(8))
    _refused(tmp_path, few.q, few.points, few.targets, "few-poses", "only 8 distinct pose(s)", "at least 12")


@pytest.mark.parametrize("share", [0.05, 0.2, 0.4])
def test_a_minority_of_rows_far_off_is_named(tmp_path, good, share):
    # a block measured with the tracker knocked 40 mm: above a tenth of the rows it passed unnamed (a plain mean)
    bad = good.points.copy()
    rows = np.arange(len(bad) - round(share * len(bad)), len(bad))
    bad[rows] += np.array([0.04, 0.0, 0.0])
    e = _refused(tmp_path, good.q, bad, good.targets, "nominal", f"{len(rows)} of {len(bad)} rows are far from")
    named = next(f for f in e.report.failures if f.check == "nominal").rows
    assert set(named) <= set(rows.tolist()) and len(named) == min(len(rows), 20)


# -- nonsense -----------------------------------------------------------------------------------------------------


def test_pure_noise(tmp_path, good):
    noise = sc.pure_noise(good)
    _refused(tmp_path, noise.q, noise.points, noise.targets, "target-distances", "does not match the data")


@pytest.mark.parametrize("corrupt", [lambda s: sc.pure_noise(s, rigid=True), sc.shuffled_rows])
def test_rigid_noise_and_shuffled_rows_fail_the_nominal_check(tmp_path, good, corrupt):
    bad = corrupt(good)
    e = _refused(tmp_path, bad.q, bad.points, bad.targets, "nominal", "no single fix found")
    assert "target-distances" not in [f.check for f in e.report.failures]  # the triangles themselves are right


# -- the check function itself ------------------------------------------------------------------------------------


def test_unknown_override_names_are_refused():
    with pytest.raises(DatasetError, match="unknown check"):
        check_measurements(np.zeros((1, 6)), np.zeros((1, 3, 3)), sc.TARGETS, allow=["units"])
    assert {"target-distances", "joint-limits", "nominal", "reach", "duplicates", "few-poses"} <= set(CHECKS)


def test_runner_can_check_a_session_still_recording(good):
    """final=False: a few poses recorded so far are not 'too few'; a wrong unit is caught from the first rows."""
    first = good.subset(np.arange(4))
    assert check_measurements(first.q, first.points, first.targets, robot=UR10, final=False).ok
    assert not check_measurements(first.q, first.points, first.targets, robot=UR10).ok
    slipped = check_measurements(first.q, first.points * 1e3, first.targets, robot=UR10, final=False)
    assert "target-distances" in [f.check for f in slipped.failures]


def test_registration_recovers_tracker_and_probe_mount(good):
    """The closed-form hand-eye registration gives the nominal residual of the true frames (noise-free robot)."""
    exact = sc.good("ur10", 30, seed=4, errors=sc.ErrorSpec.none())
    T_tb = se3.pose([2.0, -1.0, 0.3], [0.3, 2.0, -1.0])
    X = se3.pose([0.03, 0.01, 0.2], [1.0, 0.2, -2.5])
    poses = T_tb @ UR10.model.fk(exact.q) @ X
    v = sc.TARGETS
    pts = np.einsum("kab,mb->kma", poses[:, :3, :3], v) + poses[:, None, :3, 3]
    res = registered_residuals(UR10, exact.q, pts, v, frame="tracker", tool_known=False)
    assert res.max() < 1e-9
    res_base = registered_residuals(UR10, exact.q, np.einsum("ab,kmb->kma", se3.inv(T_tb)[:3, :3], pts)
                                    + se3.inv(T_tb)[:3, 3], v, frame="base", tool_known=False)  # fmt: skip
    assert res_base.max() < 1e-9


def test_a_single_mistyped_row_is_named_and_does_not_spoil_the_registration(tmp_path, good):
    trk = sc.in_tracker_frame(good)
    q = trk.q.copy()
    q[11, 0] += 1.0  # a typo in joint 1 of row 12: its targets are ~1 m off, the other rows are fine
    e = _refused(tmp_path, q, trk.points, trk.targets, "nominal", "1 of 40 rows are far from", "row 12 (line 13)",
                 frame="tracker")  # fmt: skip
    assert [f.check for f in e.report.failures] == ["nominal"]
    assert e.report.stats["nominal_mean_mm"] < 10  # the other rows, registered without row 12


def test_a_joint_zero_offset_is_named(tmp_path, good):
    q = good.q.copy()
    q[:, 1] -= np.pi / 2  # the controller's J2 zero is a quarter turn from the model's
    _refused(
        tmp_path, q, good.points, good.targets, "nominal", "joint 2's zero is +90° from the model's", "[joint_map]"
    )


def test_targets_in_another_tool_frame_are_named(tmp_path):
    """Targets measured on a tool 150 mm from the flange, with a targets file written relative to the flange."""
    offset = se3.pose([0.0, 0.05, 0.15], [0.0, 0.3, 0.0])
    on_tool = (offset[:3, :3] @ sc.TARGETS.T).T + offset[:3, 3]
    scn = sc.good("ur10", 40, seed=6, targets=on_tool)
    _refused(tmp_path, scn.q, scn.points, sc.TARGETS, "nominal", "another frame than the robot file's tool frame")


def test_the_report_stores_undefined_statistics_as_null_and_documents_refuse_nan():
    from labcal.datasets._util import canonical_json, jsonable
    from labcal.datasets.sanity import SanityReport

    report = SanityReport(stats={"ratio": float("nan"), "worst": np.float64(np.inf), "mm": np.array([1.5, np.nan])})
    assert report.as_dict()["stats"] == {"ratio": None, "worst": None, "mm": [1.5, None]}
    assert canonical_json(report.as_dict())  # what the import's provenance stores
    with pytest.raises(ValueError):  # a document keeps the NaN, so the store refuses it instead of writing a null
        canonical_json(jsonable({"x": np.float64(np.nan)}))
