"""labcal's data store: session journals, immutable versioned data sets, fits, and import of external data.

Layout of a store (default ``$LABCAL_STORE``, else ``./sessions`` relative to the current directory)::

    <store>/<session-id>/journal.jsonl            append-only run documents (recorded sessions only)
    <store>/<session-id>/v001/measurements.parquet immutable measurements table (read-only)
    <store>/<session-id>/v001/manifest.json        metadata + units + sha256 of every file (read-only)
    <store>/<session-id>/v001/fits/<fit-id>/       fits that read v001 (added later; outside the hashes)

Units are SI: q in rad, points and targets in m, time in s. ``points[:, i]`` is target t(i+1).

Recording a session (what the session runner does)::

    from labcal.datasets import SessionStore

    store = SessionStore()                                   # or SessionStore("path/to/store")
    header = SessionHeader(robot=spec.record(),              # name, hash, n_joints + the robot file itself
                           targets=targets,                  # (m, 3) m, tool frame (1..k targets)
                           frame="tracker",                  # frame of the measured points
                           tracker={"driver": "ndi", "serial": "P9-01234"},
                           robot_driver={"driver": "ur", "host": "192.168.0.10"},
                           plan=[{"q": q.tolist()} for q in plan_q])
    with store.create_session(header) as journal:
        for i, q in enumerate(plan_q):
            if i in journal.valid_pose_indices():            # already measured in an earlier run
                continue
            ...move, measure...
            journal.append_measurement(pose_index=i, q_commanded=q, q_actual=q_read,
                                       points=m.points,      # (m, 3), a NaN row = target not seen
                                       spread=m.spread, samples=5)
        journal.stop("success")
    print(store.seal(journal.session_id).ref)              # e.g. 20261122-031500-ur10-3f9a@v001
    store.seal(session_id, valid_prefix=True)              # a journal with a corrupt line: seal the lines before
                                                           # it; the version's provenance lists what was left out

Resuming after Ctrl-C, a protective stop or a crash::

    with store.open_journal(session_id) as journal:        # repairs a torn last line
        journal.resume("operator restarted")
        todo = [i for i in range(len(plan)) if i not in journal.valid_pose_indices()]
        ...
        journal.pause("protective stop")                   # or journal.stop("paused", "Ctrl-C")

Reading, verifying, fitting::

    ds = load_version(store, "20261122-031500-ur10-3f9a@v1")   # verified; DatasetCorrupted if not intact
    ds.q, ds.points, ds.targets, ds.frame, ds.split          # (k, n), (k, m, 3), (m, 3), str, (k,)
    ds.seen                                                  # (k, m) bool: False where points[r, i] is NaN
    store.verify("20261122-031500-ur10-3f9a").ok            # latest version
    store.verify_fits("20261122-031500-ur10-3f9a@v1").ok    # every fit stored under that version
    store.list_sessions(); store.show(session_id)           # id, robot, status, versions with row counts
    fit = store.save_fit([ds.ref], {"model.npz": blob}, {"method": "local-poe", "seed": 0, "metrics": {...}})
    store.list_fits(ds.ref); store.load_fit(ds.ref, fit.fit_id).read("model.npz")

Importing external data (each returns the new ``SESSION@vNNN``)::

    targets = load_targets("targets.toml")                   # unit = "mm", points = [[...], [...], [...]]
    import_targets_csv(store, "data.csv", "ur10", h, 6, targets,   # t1_x … tm_z, an empty cell = not seen
                       ImportOptions(length_unit="mm", angle_unit="deg", frame="tracker"))
    import_probe_csv(store, "probe.csv", "ur10", h, 6, ImportOptions(rotation="euler", euler_sequence="XYZ",
                     length_unit="mm", rotation_unit="deg", frame="tracker"))
    import_mapped(store, "measurements_random_poses.csv", "ipa-ur10", "ur10", h, 6)

Self-contained versions: a version's manifest (``session.robot``) holds the robot model's name, hash, joint count
and, for data recorded or imported since the robot file's text was stored, the file text and format
(``RobotSpec.record()``); ``cli.ops.common.robot_for`` reads it back, so fitting, reporting, exporting and resuming
need nothing outside the store. Older versions without the text fall back to the built-in of that name.

Versions are never rewritten: sealing again, appending to a journal, or importing into an existing session
(``session_id=...``) makes ``vNNN+1`` with ``parent = vNNN`` holding the old rows plus the new ones.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # for type checkers: the names of the table below, imported where they are defined
    from .documents import EXIT_STATUSES, MeasurementDoc, SessionHeader, StartDoc, StopDoc  # noqa: F401
    from .errors import (  # noqa: F401
        DatasetCorrupted,
        DatasetError,
        ImportFormatError,
        InvalidId,
        JournalCorrupted,
        JournalError,
        MappingError,
        TargetsError,
        UnknownSession,
        UnknownVersion,
    )
    from .ids import Ref, new_fit_id, new_session_id, parse_ref, validate_id, version_name  # noqa: F401
    from .importers import (  # noqa: F401
        DEFAULT_PROBE_OFFSETS,
        ImportOptions,
        ImportSpec,
        import_mapped,
        import_probe_csv,
        import_targets_csv,
        list_mappings,
        load_mapping,
        probe_points,
    )
    from .journal import Journal, JournalContents, read_journal  # noqa: F401
    from .schema import SCHEMA_VERSION, SPLITS, core_columns, joint_columns, spread_columns, target_columns  # noqa: F401
    from .store import (  # noqa: F401
        Dataset,
        FitRecord,
        SealResult,
        SessionInfo,
        SessionStore,
        StoreWriteError,
        VerifyReport,
        VersionInfo,
        default_root,
        load_version,
    )
    from .targets import MIN_TARGET_HEIGHT, load_targets, target_layout, validate_targets  # noqa: F401

# Each name is imported from its module on first use (PEP 562): `labcal session list` and `labcal --help` read
# manifests and journals without the table machinery (pandas, pyarrow) the importers and loaders need. The table
# holds the names imported for type checkers above (tests/datasets/test_package_names.py checks they agree).
_MODULES: dict[str, str] = {
    "documents": "EXIT_STATUSES MeasurementDoc SessionHeader StartDoc StopDoc",
    "errors": "DatasetCorrupted DatasetError ImportFormatError InvalidId JournalCorrupted JournalError MappingError "
    "TargetsError UnknownSession UnknownVersion",
    "ids": "Ref new_fit_id new_session_id parse_ref validate_id version_name",
    "importers": "DEFAULT_PROBE_OFFSETS ImportOptions ImportSpec import_mapped import_probe_csv import_targets_csv "
    "list_mappings load_mapping probe_points",
    "journal": "Journal JournalContents read_journal",
    "schema": "SCHEMA_VERSION SPLITS core_columns joint_columns spread_columns target_columns",
    "store": "Dataset FitRecord SealResult SessionInfo SessionStore StoreWriteError VerifyReport VersionInfo "
    "default_root load_version",
    "targets": "MIN_TARGET_HEIGHT load_targets target_layout validate_targets",
}
_LAZY: dict[str, str] = {name: module for module, names in _MODULES.items() for name in names.split()}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # the next access skips this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
