"""Mutation benchmark (issue 26): ``python benchmarks/mutation.py [--jobs N] [--only TEXT] [--check] [--out FILE]``.

Each entry of :data:`MUTATIONS` is one small, realistic bug: a file under ``src/labcal``, an exact snippet of it,
its replacement, what the bug means, and the test files that should catch it. The bugs are applied one at a time
to a temporary copy of ``src/`` (never the working tree), the named tests run against that copy
(``PYTHONPATH=<copy>/src``, ``pytest -x``, a timeout), and a failing run kills the mutation. The table gives per
module the mutations, killed, survived and the kill rate; every survivor is listed with the reason it is
equivalent or accepted (``accepted=``), or as a gap when it has none.

A snippet that is no longer in its file is reported as **stale** (the code moved: update the entry), one found more
than once as **ambiguous**; neither is run nor silently skipped. ``--check`` only validates the snippets (seconds).

Why not mutmut or cosmic-ray: mutmut 3.8.1 (installed privately) generated 519 mutants for ``journal.py`` alone,
and its coverage pass found no test reaching them through this src layout and the editable install; thousands of
operator swaps over these modules cannot run on two shared cores in minutes. A short list of bugs a person makes
(dropped fsync, ``<=`` → ``<``, a dropped check, a looser constant) runs in minutes and each survivor says something.

Two batches: batch 1 was written first and tests were added for its survivors; batch 2 was written after batch 1
was all killed and run before any test for it (``--batch 2``), which measures the suite on bugs nobody targeted.
Results: benchmarks/results/mutation.txt (``--out``); mutation_before.txt (batch 1 before the tests it asked for)
and mutation_batch2_before.txt (batch 2 before its tests). Each mutation runs only its named tests, so a new test
that would catch a mutation counts only once it is named in the entry.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / "src"


@dataclass(frozen=True)
class Mutation:
    module: str  # the row of the table
    path: str  # relative to src/labcal
    original: str  # exact snippet, must occur once in the file
    replacement: str
    what: str  # the bug, in words
    tests: tuple[str, ...]  # test files (or node ids) that should catch it
    accepted: str = ""  # why a survivor is equivalent or accepted (empty: a survivor is a gap)
    batch: int = 1  # 1: the first list (tests written for its survivors); 2: added later, run before any new test


def M(module, path, original, replacement, what, *tests, accepted="", batch=1):
    return Mutation(module, path, original, replacement, what, tuple(tests), accepted, batch)


T_JOURNAL = "tests/datasets/test_datasets_journal.py"
T_STORE = "tests/datasets/test_datasets_store.py"
T_DAMAGE = "tests/datasets/test_store_damage.py"
T_COMPF = "tests/test_compensator_files.py"
T_DUR = "tests/datasets/test_durability_mutants.py"
T_DOCS = "tests/datasets/test_documents.py"
T_IMPORT = "tests/datasets/test_datasets_import.py"
T_SANITY = "tests/datasets/test_sanity.py"
T_SANITY_M = "tests/datasets/test_sanity_mutants.py"
T_RUNNER = "tests/sessions/test_sessions_runner.py"
T_FAULTS = "tests/sessions/test_session_faults.py"
T_PLANS = "tests/sessions/test_sessions_plans.py"
T_PLANNING = "tests/sessions/test_sessions_planning.py"
T_COMP = "tests/test_compensator.py"
T_GATES = "tests/calibration/test_gate_mutants.py"
T_GATES_CLI = "tests/cli/test_gates.py"
T_FIT = "tests/calibration/test_fit.py"
T_CV = "tests/calibration/test_cv.py"
T_DUR2 = "tests/datasets/test_durability_files.py"
T_STOREM = "tests/datasets/test_store_mutants.py"
T_RUNM = "tests/sessions/test_runner_mutants.py"
T_COMPM = "tests/test_compensator_mutants.py"
T_TK = "tests/datasets/test_targets_k.py"
T_REF = "tests/datasets/test_refusals.py"

J = "datasets/journal.py"
S = "datasets/store.py"
U = "datasets/_util.py"
R = "sessions/runner.py"
P = "sessions/plans.py"
IO = "compensator/io.py"
F = "calibration/fit.py"

# the line after read_line's choice of timeout (read_exact makes the same choice, followed by other lines)
_READ_LINE_LOOP = "        deadline = self.clock() + wait\n        buf = bytearray()\n        term"

# fmt: off
MUTATIONS: list[Mutation] = [
    # ---------------------------------------------------------------------------------------- datasets: journal
    M("datasets/journal", J, 'if d["seq"] <= last_seq:', 'if d["seq"] < last_seq:',
      "a line repeating the previous seq is accepted", T_DUR, T_JOURNAL),
    M("datasets/journal", J, "            write_all(self._fd, line)\n            os.fsync(self._fd)\n",
      "            write_all(self._fd, line)\n", "append returns before the document is fsynced", T_DUR, T_JOURNAL),
    M("datasets/journal", J, "if contents.needs_newline or contents.torn_lines:", "if contents.torn_lines:",
      "a complete last line without its newline is not repaired on open", T_DUR, T_JOURNAL),
    M("datasets/journal", J, '(b"\\n" if contents.needs_newline else b"")', 'b""',
      "the repair after a torn line does not start a fresh line", T_JOURNAL, T_DUR),
    M("datasets/journal", J, "        elif ln in repaired:", "        elif True:",
      "an unexplained corrupt middle line is taken for a repaired torn write", T_JOURNAL, T_DUR),
    M("datasets/journal", J, 'if d["type"] == "start" and docs:', 'if d["type"] == "start" and docs and False:',
      "a second start document in the middle is accepted", T_DUR2, T_JOURNAL),
    M("datasets/journal", J, "            os.fsync(fd)\n            fsync_dir(path.parent)\n",
      "            os.fsync(fd)\n", "the new journal's folder entry is not fsynced", T_DUR2, T_JOURNAL),
    M("datasets/journal", J, "os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND",
      "os.O_WRONLY | os.O_CREAT | os.O_APPEND",
      "creating a journal appends to an existing one", T_DUR2, T_JOURNAL),
    M("datasets/journal", J, "            _lock(fd, path)\n            contents = read_journal(path)\n",
      "            contents = read_journal(path)\n", "a second writer may open the journal", T_JOURNAL),
    M("datasets/journal", J, 'if self.state != "running":\n            raise JournalError(f"cannot record',
      'if self.state == "paused":\n            raise JournalError(f"cannot record',
      "a stopped run still accepts measurements", T_JOURNAL),
    M("datasets/journal", J, "pose_index >= self.plan_length", "pose_index > self.plan_length",
      "pose index one past the plan accepted", T_JOURNAL),
    M("datasets/journal", J, "            self._broken = True\n", "",
      "appends continue after a failed write", T_DUR2, T_JOURNAL),
    M("datasets/journal", J, "        self.next_seq += 1\n", "", "every measurement gets the same seq", T_JOURNAL),
    # ------------------------------------------------------------------------------------------ datasets: store
    M("datasets/store", S, "(p.name == FITS and p.is_dir())", "p.is_dir()",
      "verify does not report an extra folder inside a version", T_DUR, T_STORE),
    M("datasets/store", S, '        checked.append(f"{where}{name}")\n        if actual != info.get("sha256"):',
      '        checked.append(f"{where}{name}")\n        if False:', "verify ignores a changed data file",
      T_STORE),
    M("datasets/store", S, 'elif sha256_file(jpath, limit=n) != info.get("sha256"):', "elif False:",
      "verify ignores an edited journal prefix", T_STORE, T_DAMAGE),
    M("datasets/store", S, 'elif sha256_file(jpath, limit=n) != info.get("sha256"):',
      'elif sha256_file(jpath) != info.get("sha256"):',
      "verify hashes the whole journal, not the sealed prefix", T_STORE, T_DUR, T_DAMAGE),
    M("datasets/store", S, 'elif canonical_json(obj, indent=2).encode("utf-8") != data:', "elif False:",
      "a reformatted manifest passes verify", T_STOREM, T_STORE),
    M("datasets/store", S, "    if actual != obj[key]:\n", "    if actual != actual:\n",
      "a manifest whose content no longer matches its sha256 passes", T_STORE),
    M("datasets/store", S, "if m.seq > through and m.valid]", "if m.seq >= through and m.valid]",
      "sealing again repeats the last sealed row", T_STORE, T_DUR),
    M("datasets/store", S, "if m.seq > through and m.valid]", "if m.seq > through]",
      "rejected measurements are sealed as rows", T_STORE),
    M("datasets/store", S, "        if first_bad is not None and ln > first_bad:\n",
      "        if False:\n", "valid-prefix seals the documents after a corrupt line", T_STORE, T_DAMAGE),
    M("datasets/store", S, "np.allclose(ta, tb, rtol=0, atol=1e-9)", "np.allclose(ta, tb, rtol=0, atol=1e-2)",
      "new rows with targets 1 cm off are merged into a session", T_STOREM, T_IMPORT),
    M("datasets/store", S, 'if a["frame"] != b["frame"]:', "if False:",
      "new rows in another frame are merged into a session", T_STOREM, T_IMPORT),
    M("datasets/store", S, "            self.verify(r).raise_if_bad()\n            m = self.manifest(r)",
      "            m = self.manifest(r)", "a fit is stored on a corrupted version", T_STORE),
    M("datasets/store", S, "if current != inp.get(\"manifest_sha256\"):", "if False:",
      "verify_fits misses an input version that changed", T_STOREM, T_STORE),
    M("datasets/store", S,
      'expected = manifest["files"][MEASUREMENTS]["sha256"]\n        if sha256_bytes(data) != expected:',
      'expected = manifest["files"][MEASUREMENTS]["sha256"]\n        if False:',
      "load does not re-hash the bytes it parses (a change after its verify)", T_STOREM),
    # -------------------------------------------------------------------------------- datasets: files and ids
    M("datasets/util", U, "        write_all(fd, data)\n        os.fsync(fd)\n", "        write_all(fd, data)\n",
      "version files are not fsynced before the rename", T_DUR2),
    M("datasets/util", U, "    os.chmod(path, READ_ONLY)\n", "",
      "version files stay writable", T_STORE),
    M("datasets/util", U, "    os.rename(tmp, final)\n    fsync_dir(final.parent)\n", "    os.rename(tmp, final)\n",
      "the renamed version's folder entry is not fsynced", T_DUR2),
    M("datasets/util", U, "    if final.exists():\n        raise FileExistsError",
      "    if False:\n        raise FileExistsError",
      "publishing over an existing empty folder succeeds", T_DUR2, T_STORE),
    M("datasets/util", U, "f.read(min(1 << 20, remaining))", "f.read(1 << 20)",
      "sha256_file ignores its limit", T_STORE, T_DUR),
    M("datasets/util", U, 'json.dumps(obj, sort_keys=True, separators=(",", ":")',
      'json.dumps(obj, sort_keys=False, separators=(",", ":")',
      "canonical JSON depends on key order (equal content, different hashes)", T_DUR2, T_STORE),
    M("datasets/util", U, 'separators=(",", ":"), allow_nan=False', 'separators=(",", ":"), allow_nan=True',
      "NaN is written into the journal", T_DUR2, T_JOURNAL),
    M("datasets/ids", "datasets/ids.py", ' or ".." in value:', ":",
      "an id containing '..' is accepted", T_STOREM, T_STORE),
    M("datasets/ids", "datasets/ids.py", "if not isinstance(number, int) or number < 1:",
      "if not isinstance(number, int) or number < 0:", "version v000 is accepted", T_STOREM, T_STORE),
    M("datasets/ids", "datasets/ids.py", '[A-Za-z0-9._-]{0,99}$', '[A-Za-z0-9._-]{0,199}$',
      "ids of up to 200 characters accepted", T_STOREM, T_STORE),
    # ------------------------------------------------------------------------------- datasets: data checking
    M("datasets/documents", "datasets/documents.py",
      "    if not seen.any():\n        raise JournalError(f\"points have no seen",
      "    if False:\n        raise JournalError(f\"points have no seen",
      "a valid measurement with no target seen is accepted", T_JOURNAL, T_DOCS),
    M("datasets/documents", "datasets/documents.py", "    bad = ~seen & ~lost\n    if bad.any():",
      "    bad = ~seen & ~lost\n    if False:", "a partly NaN target is stored as not seen", T_STOREM, T_JOURNAL),
    M("datasets/documents", "datasets/documents.py", "if np.isinf(a).any() or any(", "if any(",
      "an infinite spread of a target not seen is stored", T_STOREM, T_JOURNAL),
    M("datasets/schema", "datasets/schema.py", "    if partly.any():\n        i, t = ",
      "    if False:\n        i, t = ",
      "a partly empty target cell is imported",
      f"{T_TK}::test_normalize_table_names_the_row_and_column_of_a_partly_empty_target", T_IMPORT),
    M("datasets/schema", "datasets/schema.py", "pose.min() < 0", "pose.min() < -1", "pose index -1 accepted",
      T_STOREM, T_IMPORT),
    M("datasets/schema", "datasets/schema.py", 's = "" if value is None else str(value).strip()',
      "s = str(value).strip()",
      "a missing split (None) is refused", T_STOREM, T_IMPORT),
    M("datasets/targets", "datasets/targets.py", "if not isinstance(points, list | tuple) or not points:",
      "if not isinstance(points, list | tuple):",
      "an empty targets file is accepted", T_STOREM),
    M("datasets/sanity", "datasets/sanity.py", "UNIT_RATIO_TOL = 1.05", "UNIT_RATIO_TOL = 1.5",
      "the unit-slip tolerance is 10× looser", T_SANITY_M, T_SANITY),
    M("datasets/sanity", "datasets/sanity.py", "TARGET_ABS_TOL = 1.5e-3", "TARGET_ABS_TOL = 15e-3",
      "targets file checked 10× looser", T_SANITY_M, T_SANITY),
    M("datasets/sanity", "datasets/sanity.py", "NOMINAL_MEAN_LIMIT = 25e-3", "NOMINAL_MEAN_LIMIT = 250e-3",
      "data 10× further off the nominal robot accepted", T_SANITY_M, T_SANITY),
    M("datasets/sanity", "datasets/sanity.py", "ROW_ABS_TOL = 2e-3", "ROW_ABS_TOL = 20e-3",
      "outlier rows 10× larger accepted", T_SANITY_M, T_SANITY),
    # -------------------------------------------------------------------------------------- sessions: runner
    M("sessions/runner", R, "if int(seen.sum()) < validation.min_targets:",
      "if int(seen.sum()) < validation.min_targets - 1:",
      "a pose missing one target more than allowed is valid", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, "tol = validation.absolute_tolerance + validation.spread_factor * worst",
      "tol = validation.absolute_tolerance + validation.spread_factor",
      "triangle tolerance adds the spread factor instead of factor × spread", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, "deviation = float(np.max(np.abs(q_actual - q_cmd)))",
      "deviation = float(np.min(np.abs(q_actual - q_cmd)))",
      "one joint far from its command goes unnoticed", T_RUNM, T_RUNNER),
    M("sessions/runner", R, "            if robot.state().protective_stop:\n                raise ProtectiveStop",
      "            if False:\n                raise ProtectiveStop",
      "a frame measured during a protective stop is kept", T_RUNM, T_RUNNER),
    M("sessions/runner", R, "range(1, self.retry.max_attempts + 1)", "range(1, self.retry.max_attempts)",
      "one attempt fewer than the retry policy allows", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, "silent = timeouts == self.retry.max_attempts", "silent = timeouts > 0",
      "a pose with one tracker timeout counts as silent", T_RUNM, T_RUNNER),
    M("sessions/runner", R, "silent >= self.retry.max_silent_poses", "silent > self.retry.max_silent_poses",
      "one more silent pose before the run stops", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, "        if self.measured and not valid_now:\n", "        if False:\n",
      "a run that rejected every pose ends as success", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, 'reasons.append(f"motion rejected: {e}")\n                    return _Outcome(',
      'reasons.append(f"motion rejected: {e}")\n                    continue\n                    return _Outcome(',
      "a motion the robot refused (limits, caps) is retried", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, 'if seal and exit_status != "paused":', "if seal:",
      "a paused run is sealed", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, "if robot.n_joints != spec.model.n or plan.n_joints != spec.model.n:",
      "if robot.n_joints != spec.model.n:", "a plan for another joint count starts", T_RUNM, T_RUNNER),
    M("sessions/runner", R, "        except KeyboardInterrupt as e:\n            _safe_stop(robot)\n",
      "        except KeyboardInterrupt as e:\n", "Ctrl-C does not stop the robot", T_RUNNER, T_FAULTS),
    M("sessions/runner", R, "needed = SANITY_MIN_ROWS if at_end else self.sanity_at", "needed = self.sanity_at",
      "a short session is never sanity-checked", T_RUNM, T_RUNNER),
    # --------------------------------------------------------------------------------------- sessions: plans
    M("sessions/plans", P, '"Move.speed (rad/s)", above=True)', '"Move.speed (rad/s)")',
      "speed 0 accepted", T_PLANS),
    M("sessions/plans", P, 'checked_number(self.seconds, "Settle.seconds")',
      'checked_number(self.seconds, "Settle.seconds", least=-math.inf)',
      "a negative settle time accepted", T_PLANS),
    M("sessions/plans", P, '"Measure.samples", least=1, integer=True)', '"Measure.samples", least=0, integer=True)',
      "a measurement of 0 samples accepted", T_PLANS),
    M("sessions/plans", P, "if i > 0 and measures != 1:", "if i > 0 and measures > 1:",
      "a pose without a Measure accepted", T_PLANS),
    M("sessions/planning", "sessions/planning.py", "if not (0 < range_fraction <= 1):",
      "if not (0 < range_fraction <= 2):",
      "planning beyond the joint limits with range_fraction 2", T_RUNM, T_PLANNING),
    # -------------------------------------------------------------------------------------------- compensator
    M("compensator/io", IO, '    "joint_ranges",\n    "T_tracker_base",', '    "T_tracker_base",',
      "a widened joint range is not caught by the checksums", T_COMP),
    M("compensator/io", IO, "        if not legacy:\n            _check_checksums(data, source)",
      "        if legacy:\n            _check_checksums(data, source)",
      "checksums are not checked", T_COMP),
    M("compensator/io", IO, "legacy = stored and version == 1", "legacy = version == 1",
      "a schema-1 export file outside a store is loaded", T_COMP),
    M("compensator/io", IO, "if not (dq <= GOLDEN_TOL_Q and dT <= GOLDEN_TOL_POSE):",
      "if not (dq <= GOLDEN_TOL_Q or dT <= GOLDEN_TOL_POSE):", "golden vectors pass when either agrees", T_COMP),
    M("compensator/io", IO, "GOLDEN_TOL_Q = 1e-10", "GOLDEN_TOL_Q = 1e-3", "golden commands checked to a mrad", T_COMP),
    M("compensator/io", IO, 'if model_hash(nominal, joint_map) != data["robot"].get("hash"):',
      'if model_hash(nominal) != data["robot"].get("hash"):', "the robot hash ignores the joint map", T_COMP),
    M("compensator/io", IO, 'for key, shape in (("matrix", (n, n)), ("offsets", (n,))):', "for key, shape in ():",
      "a joint map for another joint count passes the payload check", T_COMP, T_COMPF),
    M("compensator/io", IO, "            elif dtype != np.float64:\n", "            elif False:\n",
      "an NPZ export may carry pickled objects (or any other dtype)", T_COMPM, T_COMP, T_COMPF),
    M("compensator/io", IO, "    if not 1 <= k <= MAX_GOLDEN:", "    if not 0 <= k <= MAX_GOLDEN:",
      "an export without golden vectors is loaded", T_COMP, T_COMPF),
    M("compensator/io", IO, "        if not extrapolate:\n            self._check_model_range(q_model)\n        q_cmd",
      "        q_cmd", "a mapped compensator corrects outside its calibrated ranges", T_COMP),
    M("compensator/io", IO, "        if extrapolate:\n            return\n        if self._map is None:",
      "        if self._map is None:", "check_range(extrapolate=True) still refuses", T_COMPM, T_COMP),
    # ----------------------------------------------------------------------------------------- fit: the gates
    M("calibration/fit gates", F, 'warnings.append(_warn("rows-dropped", text + "; the kept network never saw them"))',
      'notes.append("rows-dropped: " + text + "; the kept network never saw them")',
      "rows-dropped demoted from a warning to a note", T_GATES),
    M("calibration/fit gates", F, "if distinct < MIN_POSES_PER_JOINT * n:", "if distinct < n:",
      "few-poses only below one pose per joint", T_GATES,
      f"{T_CV}::test_fewer_than_two_poses_per_joint_block_the_export_even_when_the_fit_looks_good"),
    M("calibration/fit gates", F, 'if lp["rank"] < lp["expected_rank"]:', 'if lp["rank"] < lp["expected_rank"] - 1:',
      "one unidentified direction is not rank-deficient", T_GATES, T_GATES_CLI,
      f"{T_CV}::test_identical_poses_end_with_a_rank_deficient_warning_listing_the_directions"),
    M("calibration/fit gates", F, "POOR_FIT = 5e-3", "POOR_FIT = 5e-2", "poor-fit 10× looser", T_GATES),
    M("calibration/fit gates", F, "OVERFIT_RATIO = 10.0", "OVERFIT_RATIO = 100.0", "overfit 10× looser", T_GATES,
      f"{T_CV}::test_five_poses_are_flagged_as_overfitted_and_ten_get_a_note"),
    M("calibration/fit gates", F, "        if e_c >= e_n:\n", "        if e_c > e_n + 1e-3:\n",
      "worse-than-nominal only when a mm worse", T_GATES),
    M("calibration/fit gates", F, "if span[j] < least and claimed[j, 1] - claimed[j, 0] > span[j] + least:",
      "if span[j] < least:", "narrow-joint flags a joint whose claimed range is its data's", T_GATES),
    M("calibration/fit gates", F, '"revolute": np.deg2rad(5.0)', '"revolute": np.deg2rad(0.5)',
      "narrow-joint 10× looser", T_GATES,
      f"{T_CV}::test_a_joint_the_data_hardly_moved_is_a_narrow_joint_warning_for_a_geometric_model"),
    M("calibration/fit gates", F, "if size > FRAME_JUMP and size > 4 * spread", "if size > FRAME_JUMP",
      "frame-jump fires on noise as large as the step", T_GATES),
    M("calibration/fit gates", F, "FRAME_JUMP = 1e-3", "FRAME_JUMP = 1e-2", "frame-jump 10× looser", T_GATES),
    M("calibration/fit gates", F, "large = np.any(over > 1.0, axis=1) & tool", "large = np.any(over > 1.0, axis=1)",
      "large-correction by the joint bound alone (singular wrists flagged)", T_GATES,
      f"{T_CV}::test_a_good_fit_of_singular_wrist_sweeps_is_not_a_large_correction"),
    M("calibration/fit gates", F, '"revolute": 0.05, "prismatic": 0.01}  # rad, m: largest joint',
      '"revolute": 0.5, "prismatic": 0.01}  # rad, m: largest joint', "large-correction 10× looser", T_GATES,
      f"{T_CV}::test_a_large_joint_offset_gives_a_large_correction_warning"),
    M("calibration/fit gates", F, '    for part in ("val", "test"):\n', '    for part in ():\n',
      "held-out rows worse than the nominal are not a warning", T_GATES, T_FIT),
    # ------------------------------------------------------------------- the other survivors of issue 26
    M("other (issue 26)", "drivers/serial/link.py",
      "wait = self.timeout if timeout is None else timeout\n" + _READ_LINE_LOOP,
      "wait = self.timeout\n" + _READ_LINE_LOOP,
      "read_line ignores its per-call timeout",
      "tests/drivers/test_read_timeout.py", "tests/drivers/test_serial_link.py"),
    M("other (issue 26)", "cli/fit.py", '"std": "std_m"}', '"std": "std"}', "the --json key cv.std_m renamed",
      "tests/cli/test_json_keys.py"),
    M("other (issue 26)", "calibration/metrics.py", 'np.einsum("ab,kmb->kma", R, pred)',
      'np.einsum("ba,kmb->kma", R, pred)', "point_residuals applies the tracker rotation transposed", T_GATES),
    # ------------------------------------------------------------------------------------------------------------
    # Batch 2: written after batch 1 was all killed, and run before any test was added for them, to see how well
    # the suite catches bugs nobody wrote a test for (benchmarks/results/mutation.txt gives both batches).
    M("datasets/journal", J, 'if doc.get("status") not in STATUSES:', "if False:",
      "a measurement with an unknown status is read as a document", T_REF, T_JOURNAL, batch=2),
    M("datasets/journal", J, "        if ln > last_good:\n", "        if ln > last_good + 1:\n",
      "a torn last line is called corrupt (and blocks sealing)", T_JOURNAL, T_DUR, batch=2),
    M("datasets/journal", J,
      '        if self.state == "stopped":\n            raise JournalError("the run is already stopped")\n',
      "", "a stopped run can be stopped again", T_REF, T_JOURNAL, batch=2),
    M("datasets/journal", J, "or samples < 0:", "or samples < -1:", "a negative sample count is journaled",
      T_REF, T_JOURNAL, batch=2),
    M("datasets/journal", J, "        validate_id(session_id)\n        doc = header", "        doc = header",
      "Journal.create writes a start document with an unsafe session id", T_REF, T_JOURNAL, batch=2),
    M("datasets/store", S, "            return Ref(r.session_id, versions[-1])",
      "            return Ref(r.session_id, versions[0])", "SESSION without @vN resolves to the first version",
      T_STORE, T_DUR, batch=2),
    M("datasets/store", S, '            raise DatasetError(f"fit {fit_id!r} already exists under {under}")',
      "            pass", "a fit id that exists is not refused", T_REF, T_STORE, batch=2),
    M("datasets/store", S, "            if name == FIT_JSON:\n", "            if False:\n",
      "a caller's file may replace fit.json", T_REF, T_STORE, batch=2),
    M("datasets/store", S, "if fp.name != FIT_JSON and fp.name not in files:", "if False:",
      "verify_fits ignores an extra file in a fit", T_STORE, T_FAULTS, batch=2),
    M("datasets/sanity", "datasets/sanity.py", "SPAN_WIDE_LIMITS = math.radians(60.0)",
      "SPAN_WIDE_LIMITS = math.radians(600.0)", "radians read as degrees no longer suspected", T_SANITY_M, T_SANITY,
      batch=2),
    M("datasets/sanity", "datasets/sanity.py", "FAR_ROWS_NAMED = 0.45", "FAR_ROWS_NAMED = 0.05",
      "far rows named only up to 5 % of the rows", T_SANITY_M, T_SANITY, batch=2),
    M("sessions/runner", R, "                if step.index in self.done:\n                    continue\n",
      "                if step.index in self.done:\n                    pass\n",
      "a resumed run measures the done poses again", T_RUNM, T_RUNNER, T_FAULTS, batch=2),
    M("sessions/runner", R, "    if serial is not None and serial != unit:\n", "    if False:\n",
      "a unit that disagrees with the controller's serial leaves no note", T_RUNM, T_RUNNER,
      "tests/sessions/test_unit_identity.py", batch=2),
    M("sessions/runner", R, "and now not in (None, \"\") and str(recorded) != str(now):",
      "and now not in (None, \"\") and False:", "a session is resumed on another arm", T_RUNM, T_RUNNER,
      "tests/sessions/test_unit_identity.py", batch=2),
    M("sessions/plans", P, "                if len(c.q) != n:\n", "                if False:\n",
      "a plan mixing joint counts is accepted", T_PLANS, batch=2),
    M("compensator/io", IO, 'data.get("format") != SCHEMA:', 'data.get("format") is None:',
      "a file of another format is read as a compensator", T_COMPM, T_COMP, batch=2),
    M("compensator/io", IO, "    if isinstance(value, int | float | np.number):\n        return float(value)\n", "",
      "checksums depend on how a JSON writer spelled a number (1 or 1.0)", T_COMPM, T_COMP, batch=2),
    M("compensator/io", IO, "GOLDEN_TOL_POSE = 1e-10", "GOLDEN_TOL_POSE = 1e-3", "golden poses checked to a mm",
      T_COMPM, T_COMP, batch=2),
    M("compensator/io", IO, "        self._check_model_range(self.to_model(q))\n", "        pass\n",
      "a mapped compensator predicts outside its ranges", T_COMPM, T_COMP, batch=2),
    M("calibration/fit gates", F, "OVERFIT_NOTE_RATIO = 2.0", "OVERFIT_NOTE_RATIO = 20.0",
      "the overfit-risk note 10× looser", T_GATES,
      f"{T_CV}::test_five_poses_are_flagged_as_overfitted_and_ten_get_a_note",
      batch=2),
    M("calibration/fit gates", F, "_CORRECTION_SHARE = 0.10", "_CORRECTION_SHARE = 0.5",
      "large-correction only when half the configurations exceed", T_GATES,
      f"{T_CV}::test_a_large_joint_offset_gives_a_large_correction_warning", batch=2),
    M("calibration/fit gates", F, "MIN_POSES_PER_JOINT = 2", "MIN_POSES_PER_JOINT = 1",
      "few-poses at one pose per joint", T_GATES,
      f"{T_CV}::test_fewer_than_two_poses_per_joint_block_the_export_even_when_the_fit_looks_good", batch=2),
    M("calibration/fit gates", F,
      '        ("point-residuals", point_residual_warning(metrics.get("all"))),\n', "",
      "the point-residuals warning is dropped", T_GATES, T_GATES_CLI, batch=2),
]
# fmt: on


# --------------------------------------------------------------------------------------------------------------
# running


@dataclass
class Outcome:
    mutation: Mutation
    status: str  # killed | survived | stale | ambiguous | timeout | error
    seconds: float = 0.0
    detail: str = ""


def snippet_state(m: Mutation, src: Path = SRC) -> str:
    """ "ok", "stale" (not found), "ambiguous" (found more than once) or "missing-file"."""
    f = src / "labcal" / m.path
    if not f.is_file():
        return "missing-file"
    n = f.read_text(encoding="utf-8").count(m.original)
    return "ok" if n == 1 else ("stale" if n == 0 else "ambiguous")


def _env(copy_src: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        PYTHONPATH=str(copy_src),
        # No .pyc anywhere: a mutated file of the same size written within the same second as the original would
        # otherwise be served from a stale cache (and pytest would write its rewritten tests into the worktree).
        PYTHONDONTWRITEBYTECODE="1",
        OPENBLAS_NUM_THREADS="1",
        OMP_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
    )
    return env


def _pytest(tests: tuple[str, ...], copy_src: Path, timeout: float) -> tuple[int | None, str]:
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "--no-header", *tests]
    proc = subprocess.Popen(cmd, cwd=REPO, env=_env(copy_src), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)  # fmt: skip
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the whole pytest process group, subprocess fakes included
        proc.communicate()
        return None, ""
    return proc.returncode, out


def _last_line(out: str) -> str:
    lines = [ln for ln in out.strip().splitlines() if ln.strip()]
    return lines[-1][:160] if lines else ""


def run_one(m: Mutation, copy_src: Path, timeout: float) -> Outcome:
    state = snippet_state(m, copy_src)
    if state != "ok":
        return Outcome(m, "stale" if state in ("stale", "missing-file") else "ambiguous")
    f = copy_src / "labcal" / m.path
    original = f.read_text(encoding="utf-8")
    mutated = original.replace(m.original, m.replacement, 1)
    try:
        compile(mutated, str(f), "exec")
    except SyntaxError as e:
        return Outcome(m, "error", detail=f"the mutation is not valid Python: {e}")
    t0 = time.perf_counter()
    f.write_text(mutated, encoding="utf-8")
    try:
        code, out = _pytest(m.tests, copy_src, timeout)
    finally:
        f.write_text(original, encoding="utf-8")
    dt = time.perf_counter() - t0
    if code is None:
        return Outcome(m, "timeout", dt, f"no result within {timeout:g} s (a hang counts as caught)")
    if code == 0:
        return Outcome(m, "survived", dt, _last_line(out))
    if code in (1, 2):  # 1: a test failed; 2: collection failed (the mutated module no longer imports)
        return Outcome(m, "killed", dt, _last_line(out))
    return Outcome(m, "error", dt, f"pytest exit {code}: {_last_line(out)}")


def make_copy(root: Path) -> Path:
    dst = root / "src"
    shutil.copytree(SRC / "labcal", dst / "labcal", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return dst


def baseline(mutations: list[Mutation], copy_src: Path, timeout: float) -> str:
    """Run every named test file once on the unmutated copy: a kill only means something if they pass."""
    tests = tuple(sorted({t for m in mutations for t in m.tests}))
    missing = [t for t in tests if not (REPO / t.split("::")[0]).exists()]
    if missing:
        return f"test file(s) not found: {missing}"
    code, out = _pytest(tests, copy_src, timeout * 4)
    if code != 0:
        return f"the named tests fail without any mutation (exit {code}): {_last_line(out)}"
    probe = subprocess.run([sys.executable, "-c", "import labcal; print(labcal.__file__)"], env=_env(copy_src),
                           capture_output=True, text=True, check=False)  # fmt: skip
    if not probe.stdout.strip().startswith(str(copy_src)):
        return f"labcal is not imported from the copy ({probe.stdout.strip() or probe.stderr.strip()})"
    return ""


def table(outcomes: list[Outcome]) -> str:
    rows = []
    modules = list(dict.fromkeys(o.mutation.module for o in outcomes))
    head = f"{'module':<28} {'mutations':>9} {'killed':>6} {'survived':>8} {'stale':>5} {'kill rate':>9}"
    rows += [head, "-" * len(head)]

    def line(name: str, group: list[Outcome]) -> str:
        killed = sum(o.status in ("killed", "timeout") for o in group)
        survived = sum(o.status == "survived" for o in group)
        stale = sum(o.status in ("stale", "ambiguous", "error") for o in group)
        run = killed + survived
        rate = f"{killed / run:.0%}" if run else "-"
        return f"{name:<28} {len(group):>9} {killed:>6} {survived:>8} {stale:>5} {rate:>9}"

    for mod in modules:
        rows.append(line(mod, [o for o in outcomes if o.mutation.module == mod]))
    rows.append("-" * len(head))
    for scope in ("datasets/", "sessions/", "compensator/io", "calibration/fit gates"):
        rows.append(line(f"{scope.rstrip('/')} (all)", [o for o in outcomes if o.mutation.module.startswith(scope)]))
    target = [o for o in outcomes if not o.mutation.module.startswith("other")]
    rows.append(line("issue 26 scope", target))
    for batch in sorted({o.mutation.batch for o in outcomes}):
        rows.append(line(f"  batch {batch}", [o for o in target if o.mutation.batch == batch]))
    rows.append(line("all", outcomes))
    return "\n".join(rows)


def report(outcomes: list[Outcome], wall: float, jobs: int) -> str:
    parts = [table(outcomes), ""]
    survivors = [o for o in outcomes if o.status == "survived"]
    parts.append(f"survivors ({len(survivors)}):")
    for o in survivors:
        m = o.mutation
        why = f"accepted: {m.accepted}" if m.accepted else "GAP: no test catches it"
        parts.append(f"  {m.path}: {m.what} [{m.original.strip().splitlines()[0][:60]!r}] — {why}")
    bad = [o for o in outcomes if o.status in ("stale", "ambiguous", "error")]
    if bad:
        parts.append(f"not run ({len(bad)}): update these entries of MUTATIONS")
        for o in bad:
            parts.append(f"  {o.status}: {o.mutation.path}: {o.mutation.what} {o.detail}")
    parts.append("")
    parts.append("every mutation:")
    for o in outcomes:
        parts.append(f"  {o.status:<9} {o.seconds:6.1f} s  {o.mutation.path}: {o.mutation.what}")
    parts.append("")
    parts.append(f"{len(outcomes)} mutations in {wall:.0f} s wall with {jobs} job(s), load average "
                 f"{os.getloadavg()[0]:.1f}")  # fmt: skip
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=1, help="mutations run in parallel, each in its own copy (default 1)")
    ap.add_argument("--batch", type=int, choices=(1, 2), help="run only this batch of MUTATIONS")
    ap.add_argument("--only", default="", help="run the mutations whose module, file or description contains this")
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds per mutation before it counts as a hang")
    ap.add_argument("--check", action="store_true", help="only check that every snippet is found exactly once")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run of the named tests")
    ap.add_argument("--out", type=Path, help="also write the report here (e.g. benchmarks/results/mutation.txt)")
    args = ap.parse_args(argv)
    chosen = [m for m in MUTATIONS if not args.only or any(args.only in s for s in (m.module, m.path, m.what))]
    chosen = [m for m in chosen if args.batch is None or m.batch == args.batch]
    if args.check:
        bad = [(snippet_state(m), m) for m in chosen if snippet_state(m) != "ok"]
        for state, m in bad:
            print(f"{state}: {m.path}: {m.what}: {m.original!r}")
        print(f"{len(chosen) - len(bad)} of {len(chosen)} snippets found exactly once")
        return 1 if bad else 0
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="labcal-mutation-") as tmp:
        copies = [make_copy(Path(tmp) / f"w{i}") for i in range(max(1, args.jobs))]
        if not args.no_baseline:
            why = baseline(chosen, copies[0], args.timeout)
            if why:
                print(f"mutation benchmark: {why}", file=sys.stderr)
                return 2
        free = list(copies)
        outcomes: list[Outcome | None] = [None] * len(chosen)

        def work(i: int) -> None:
            copy = free.pop()
            try:
                outcomes[i] = run_one(chosen[i], copy, args.timeout)
            finally:
                free.append(copy)
            o = outcomes[i]
            print(f"{o.status:<9} {o.seconds:6.1f} s  {o.mutation.path}: {o.mutation.what}", flush=True)

        with concurrent.futures.ThreadPoolExecutor(max_workers=len(copies)) as pool:
            list(pool.map(work, range(len(chosen))))
    text = report([o for o in outcomes if o is not None], time.perf_counter() - t0, len(copies))
    print()
    print(text)
    if args.out:
        sys.path.insert(0, str(SRC))
        from labcal.atomicio import write_text

        cmd = "python benchmarks/mutation.py " + " ".join(argv if argv is not None else sys.argv[1:])
        write_text(args.out, f"$ {cmd}\n\n{text}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
