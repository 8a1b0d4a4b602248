"""`labcal evaluate` as a function: score held-out data (a CSV file or a stored version) with a stored fit.

What is fitted on the evaluation data, and what is not:

- **Nothing of the calibration.** The fitted robot (identified frames, network / series) is used exactly as stored.
- **Only the 6-DOF registration T_tracker_base, for tracker-frame data.** The tracker is set up anew for every
  session, so the base pose in the tracker frame differs from the fit's; it is estimated on the evaluation data
  by a closed-form least-squares rigid fit (Kabsch) of the robot's predicted target points to the measured ones,
  for the calibrated robot and, separately, for the nominal ("before"). Six parameters against 9 numbers per
  pose; the evaluation says so (``registration``). Base-frame data are scored as they are: nothing is fitted.

What the evaluation data let it claim about orientation (one target point: positions only; targets on a line: not
the rotation about it) is stored beside the errors as ``observability`` (:func:`labcal.calibration.metrics.
observability`), and ``primary`` says which errors to quote: the per-target point errors whenever some row sees
fewer than three non-collinear targets, else the pose errors.

A FILE is imported as a new session first (same options and sanity checks as ``labcal session import``), so the
evaluated data are stored and traceable by their version; a SESSION[@vN] is read from the store. The evaluation
(per-target point errors and pose errors, before/after, rows outside the fit's calibrated joint ranges) is written
as JSON under the fit (:meth:`SessionStore.save_evaluation`).
"""

from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labcal.atomicio import write_text
from labcal.cli.common import UserError, plain
from labcal.cli.ops.common import load_observations, split_ref
from labcal.cli.ops.fitting import load_stored_fit, metric_warnings
from labcal.datasets import SessionStore
from labcal.datasets._util import iso, utc_now


@dataclass
class EvaluationOutcome:
    """What ``labcal evaluate`` produced: the evaluation document and where it was stored."""

    evaluation: dict
    path: Path
    data_ref: str
    imported: bool


def register_base(robot, obs) -> tuple[np.ndarray, float]:
    """Least-squares T_tracker_base of robot on obs (tracker frame): the rigid transform that best maps the robot's
    predicted base-frame target points onto the measured ones, all points pooled (Kabsch). Returns (T, rms m)."""
    from labcal.calibration.observations import rigid_fit

    pred = robot.predict_points(obs.q, obs.targets).reshape(-1, 3)
    meas = np.asarray(obs.points, dtype=float).reshape(-1, 3)
    ok = np.isfinite(meas).all(axis=1)
    a, b = pred[ok], meas[ok]
    T = rigid_fit(a, b[None])[0]
    rms = float(np.sqrt(np.mean(np.sum((b - (a @ T[:3, :3].T + T[:3, 3])) ** 2, axis=1))))
    return T, rms


def _robot_argument(store: SessionStore, stored, robot: str | None, tmpdir: Path) -> str:
    """The --robot to import the file with: the user's, else the fit's model (a built-in name or its stored text)."""
    from labcal.robots import BUILTINS, load

    if robot is not None:
        return robot
    rec = store.load(stored.inputs[0]).robot
    if rec.get("name") in BUILTINS and load(str(rec["name"])).hash == rec.get("hash"):
        return str(rec["name"])  # the built-in is the very model of the fit: import under its name
    if rec.get("text"):
        path = tmpdir / f"robot.{'urdf' if rec.get('format') == 'urdf' else 'toml'}"
        write_text(path, rec["text"])
        return str(path)
    if rec.get("name") in BUILTINS:
        return str(rec["name"])
    raise UserError(f"the fit's robot model {rec.get('name')!r} is not built in: pass its file with --robot PATH")


def import_for_evaluation(store: SessionStore, stored, path: Path, robot: str | None, options: dict) -> str:
    """Import path as a new session through ``session import``'s own function (its checks and overrides)."""
    from labcal.cli.ops.imports import import_session

    options = {k: v for k, v in options.items() if v is not None}
    # A held-out file only has to be scored, not to identify a model: a handful of poses is enough, and the
    # override is recorded with the import like any other.
    options["allow"] = sorted({*(options.get("allow") or ()), "few-poses"})
    with tempfile.TemporaryDirectory(prefix="labcal-eval-") as tmp:
        robot_arg = _robot_argument(store, stored, robot, Path(tmp))
        return import_session(store, path, robot=robot_arg, **options)


SAME_CONFIGURATION = 1e-6  # rad (or m): closer than a controller reports joints apart, so the same configuration


def rows_the_fit_saw(store: SessionStore, stored, robot: str | None, q: np.ndarray) -> int:
    """How many of the configurations q (k, n model joints) the fit was fitted or validated on: within
    SAME_CONFIGURATION of a row of its inputs outside their test split. A later version of the fit's session (a
    superset of its rows) or a re-import of its data is not held out, though its ref is not one of the fit's."""
    from scipy.spatial import cKDTree

    fit_obs = load_observations(store, list(stored.inputs), robot, pool_units=True)[0]  # only their joints are read
    used = fit_obs.q[np.asarray(fit_obs.split) != "test"]
    if not len(used) or not len(q):
        return 0
    distance, _ = cKDTree(used).query(q, k=1, p=np.inf, distance_upper_bound=SAME_CONFIGURATION)
    return int(np.isfinite(distance).sum())


def _is_file_argument(data: str) -> bool:
    p = Path(data)
    return p.is_file() or p.suffix.lower() in (".csv", ".txt", ".tsv")


def evaluate_fit(
    store: SessionStore,
    fit_id: str,
    data: str,
    *,
    robot: str | None = None,
    import_options: dict | None = None,
) -> EvaluationOutcome:
    """Score data (a CSV path, imported first, or SESSION[@vN]) with stored fit fit_id; store and return the result.

    import_options: keyword options of :func:`labcal.cli.ops.imports.import_session` (targets_file, mapping,
    length_unit, angle_unit, frame, form, allow) for a file. Raises UserError for a fit or data that do not exist,
    a different robot model, or a targets file that differs from the fit's.
    """
    from labcal.calibration.metrics import observability, split_table

    record = store.find_fit(fit_id)
    stored = load_stored_fit(store, record.ref, fit_id)
    imported = _is_file_argument(data)
    if imported:  # import_session names a missing file, a folder, a device or a FIFO
        ref = import_for_evaluation(store, stored, Path(data), robot, dict(import_options or {}))
    else:
        ref = str(store.resolve(split_ref(data)))
    obs, datasets = load_observations(store, [ref], robot, with_spec=True)[:2]
    _check_same_robot_and_targets(store, stored, fit_id, ref, obs, datasets[0])
    obs = dataclasses.replace(obs, split=np.full(obs.k, "test", dtype=object))
    before, after, registration = _registered(stored, obs)
    table = split_table(before, after, obs)
    claims = observability(obs)
    # Not a gate here (nothing is exported), but the same reading of the numbers: points far off while the pose
    # fits mean the evaluation file's targets or units do not match the data.
    warnings = metric_warnings({"test": table["all"], "all": table["all"]}) if "all" in table else []
    lo, hi = np.asarray(after.joint_ranges, dtype=float).T
    outside = ~np.all((obs.q >= lo - 1e-12) & (obs.q <= hi + 1e-12), axis=1)
    manifest = store.manifest(ref)
    seen = 0 if ref in stored.inputs else rows_the_fit_saw(store, stored, robot, obs.q)
    options = {k: str(Path(v).resolve()) if isinstance(v, Path) else v for k, v in (import_options or {}).items() if v}
    evaluation = {
        "kind": "labcal.evaluation",
        "evaluation_id": None,
        "created": iso(utc_now()),  # the store's timestamp format
        "fit_id": fit_id,
        "fit_ref": stored.ref,
        "fit_inputs": stored.inputs,
        "method": stored.robot.method,
        "data": {
            "ref": ref,
            "imported_from": str(Path(data).resolve()) if imported else None,
            "import_options": options if imported else None,
            "manifest_sha256": manifest.get("manifest_sha256"),
            "rows": int(obs.k),
            "frame": obs.frame,
        },
        "overlap_with_fit": ref in stored.inputs or seen > 0,
        "overlap_rows": int(obs.k if ref in stored.inputs else seen),
        "registration": registration,
        "metrics": {"all": table["all"]} if "all" in table else {},
        "primary": (table.get("all") or {}).get("primary", "pose"),
        "observability": claims,
        "outside_calibrated_ranges": int(outside.sum()),
        "warnings": warnings,
    }
    evaluation["evaluation_id"], path = store.save_evaluation(stored.ref, fit_id, plain(evaluation))
    return EvaluationOutcome(plain(evaluation), path, ref, imported)


def _check_same_robot_and_targets(store: SessionStore, stored, fit_id: str, ref: str, obs, ds) -> None:
    """Refuse data of another robot model than the fit's, or with other targets (the fitted tool frame is theirs)."""
    fit_hash = (stored.meta.get("robot") or {}).get("hash")
    if fit_hash and ds.robot.get("hash") != fit_hash:
        raise UserError(
            f"{ref} was recorded with robot model {ds.robot.get('name')!r} (hash {str(ds.robot.get('hash'))[:12]}…), "
            f"fit {fit_id} with {(stored.meta.get('robot') or {}).get('name')!r} (hash {fit_hash[:12]}…): "
            "a fit can only score data of the robot model it was fitted for"
        )
    fit_obs_targets = store.load(stored.inputs[0]).targets
    if not np.allclose(obs.targets, fit_obs_targets, atol=1e-9):
        raise UserError(
            f"{ref} has different targets from the data of fit {fit_id}: the fitted tool frame belongs to the fit's "
            "targets; evaluate with the same targets file"
        )


def _registered(stored, obs):
    """(before, after, registration): the nominal and the calibrated robot placed in the data's frame, and how.

    Tracker-frame data: T_tracker_base fitted to them, for each robot separately (nothing else is refitted)."""
    registration: dict = {"frame": obs.frame}
    T_after, T_before = np.eye(4), np.eye(4)  # base-frame data are in the robot's frame: scored as they are
    if obs.frame == "tracker":
        T_after, rms_after = register_base(stored.robot, obs)
        T_before, rms_before = register_base(stored.before, obs)
        registration.update(
            fitted="T_tracker_base only (6 parameters: rigid least-squares fit of the predicted to the measured "
            "points, separately for before and after); nothing of the calibration is refitted",
            parameters=6,
            numbers=int(np.isfinite(obs.points).all(axis=2).sum() * 3),
            T_tracker_base_after=T_after,
            T_tracker_base_before=T_before,
            rms_after=rms_after,
            rms_before=rms_before,
        )
    else:
        registration.update(fitted="nothing (base-frame data are scored as they are)", parameters=0)
    after = dataclasses.replace(stored.robot, T_tracker_base=T_after)
    before = dataclasses.replace(stored.before, T_tracker_base=T_before)
    return before, after, registration
