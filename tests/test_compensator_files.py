"""Hostile compensator files (issue 24, item 5): checked before anything large is read; every refusal is one line
naming the file and the field, even when the file's checksums were recomputed after the edit."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent / "export"))

from export_fixtures import hybrid

from labcal.compensator import CalibratedRobot, Compensator, CompensatorFileError, field_checksums
from labcal.compensator import save as save_compensator
from labcal.robots import load


@pytest.fixture
def saved(tmp_path):
    nominal = load("ur10").model
    model = nominal.perturbed(np.random.default_rng(0).normal(size=(7, 6)) * 0.5e-3)
    robot = CalibratedRobot(nominal, model, method="local-poe")
    return Compensator(robot, {"session": "S@v001"}).save(tmp_path / "c.json")


def _resealed(path, edit):
    """Edit the JSON export and recompute its checksums, as someone crafting a file would."""
    data = json.loads(path.read_text())
    edit(data)
    data["checksums"] = field_checksums(data)
    path.write_text(json.dumps(data))
    return path


def _refusal(path, *fragments) -> str:
    with pytest.raises(CompensatorFileError) as err:
        Compensator.load(path)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    for fragment in fragments:
        assert fragment in message, message
    return message


def _set_ranges(value):
    def edit(d):
        d["joint_ranges"][0] = value

    return edit


def test_nan_joint_ranges_with_recomputed_checksums_are_refused_naming_the_field(saved):
    path = saved
    _refusal(_resealed(path, _set_ranges([float("nan"), 1.0])), "joint_ranges must be finite numbers")


def test_huge_joint_ranges_that_would_switch_off_the_range_guard_are_refused(saved):
    path = saved
    _refusal(_resealed(path, _set_ranges([-1e300, 1e300])), "joint_ranges[1] = [-1e+300, 1e+300]", "range guard")
    _refusal(_resealed(path, _set_ranges([-360.0, 360.0])), "joint_ranges[1]")  # degrees
    _refusal(_resealed(path, _set_ranges([1.0, -1.0])), "joint_ranges[1]")  # lo > hi


def test_repeated_joint_names_are_refused(saved):
    path = saved

    def edit(d):
        d["robot"]["joint_names"][3] = d["robot"]["joint_names"][1]

    _refusal(_resealed(path, edit), "robot.joint_names repeats 'shoulder_lift_joint' (joints 2 and 4)")


@pytest.mark.parametrize(
    "where,value,field",
    [
        ("robot.name", "ur10\nmovej([0,-1.57,0,-1.57,0,0], a=3, v=3)\n#", "robot.name must be 1 to 64"),
        ("model.joint_names", ["a\x1b[31m", "b", "c", "d", "e", "f"], "model.joint_names[1] must be"),
        ("provenance", {"arm_serial": "SN\x1b[2J1"}, "provenance.arm_serial must be printable text"),
        ("provenance", {"x": [[[[["deep"]]]]]}, "provenance.x[1][1][1]"),
        ("method", "hybrid\n#", "method must be"),
    ],
)
def test_strings_an_export_would_write_are_checked(saved, where, value, field):
    path = saved

    def edit(d):
        keys = where.split(".")
        target = d
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value

    _refusal(_resealed(path, edit), field)


def test_deeply_nested_json_names_the_file(saved):
    path = saved
    path.write_text('{"format": "labcal-compensator", "provenance": ' + "[" * 100_000 + "]" * 100_000 + "}")
    _refusal(path, "nested too deeply")


def _npz_with(path, name: str, shape: tuple, data: bytes = b"") -> None:
    """Rewrite a valid NPZ export with member ``name`` declaring ``shape`` (float64) but holding only ``data``."""
    with zipfile.ZipFile(path) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": shape})
    members[f"{name}.npy"] = header.getvalue() + data  # the header function writes the magic string too
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for member, blob in members.items():
            zf.writestr(member, blob)


def test_an_npz_member_declaring_gigabytes_is_refused_from_its_header(tmp_path, saved):
    """Before: the loader read every array first, so a 4.7 MB file asked for 4.47 GiB and died with a traceback.
    Run in a child process with 1 GiB of address space, the way a small controller-side PC would meet it."""
    json_path = saved
    path = Compensator.load(json_path).save(tmp_path / "c.npz")
    _npz_with(path, "joint_ranges", (20000, 30000), b"\0" * 4096)
    code = (
        "import resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))\n"
        "from labcal.compensator import Compensator, CompensatorFileError\n"
        "try:\n"
        f"    Compensator.load({str(path)!r})\n"
        "except CompensatorFileError as e:\n"
        "    print('refused:', e)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "Traceback" not in r.stderr, r.stderr
    assert r.stdout.strip() == (
        f"refused: {path}: joint_ranges has shape (20000, 30000), more numbers than its 4224 bytes hold: refusing "
        "to read it"
    )


def test_npz_members_of_the_wrong_shape_or_size_are_refused_naming_the_field(tmp_path, saved):
    """A member's shape is the payload check's, as for a JSON file; a file unpacking to more than any export holds
    is refused before its members are read."""
    comp = Compensator.load(saved)
    for name, shape, data, fragment in [
        ("joint_ranges", (3, 2), bytes(48), "joint_ranges must be numbers of shape (6, 2), got shape (3, 2)"),
        ("golden.q", (), bytes(8), "golden.q holds 0 configurations"),  # one number where the configurations belong
        ("joint_ranges", (7 * 1024**2, 1), bytes(8 * 7 * 1024**2), "its arrays unpack to"),  # 56 MiB, deflated 56 kB
    ]:
        path = comp.save(tmp_path / "c.npz")
        _npz_with(path, name, shape, data)
        _refusal(path, fragment)


def test_npz_metadata_may_reference_arrays_only_where_an_export_has_them(tmp_path, saved):
    """Before, an array where the payload holds text or a version number raised numpy's "truth value of an array
    is ambiguous" out of the loader."""
    path = Compensator.load(saved).save(tmp_path / "c.npz")
    with zipfile.ZipFile(path) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    meta = json.loads(str(np.load(io.BytesIO(members["__meta__.npy"]))))
    for field in ("schema_version", "method", "length_scale"):
        changed = {**meta, field: {"$array": "joint_ranges"}}
        buf = io.BytesIO()
        np.save(buf, np.array(json.dumps(changed)))
        with zipfile.ZipFile(path, "w") as zf:
            for member, blob in {**members, "__meta__.npy": buf.getvalue()}.items():
                zf.writestr(member, blob)
        _refusal(path, f"{field} must not be an array reference")


def test_npz_members_are_checked_for_dtype_and_reference(tmp_path, saved):
    json_path = saved
    path = Compensator.load(json_path).save(tmp_path / "c.npz")
    with zipfile.ZipFile(path) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    buf = io.BytesIO()
    np.save(buf, np.zeros((6, 2), dtype=np.int64))

    def rewrite(**changed):
        with zipfile.ZipFile(path, "w") as zf:
            for member, blob in {**members, **changed}.items():
                zf.writestr(member, blob)

    rewrite(**{"joint_ranges.npy": buf.getvalue()})
    _refusal(path, "joint_ranges must be float64 numbers, got dtype int64")
    rewrite(**{"extra.npy": members["robot.limits.npy"]})
    _refusal(path, "array 'extra' is not referenced by the metadata")
    rewrite()
    Compensator.load(path)


def test_a_network_layer_larger_than_a_compensator_holds_is_refused(tmp_path):
    path = save_compensator(hybrid("ur10"), tmp_path / "h.npz")
    _npz_with(path, "network.weights.0", (5000, 40000))
    _refusal(path, "network.weights.0 has shape (5000, 40000)")
    path = save_compensator(hybrid("ur10"), tmp_path / "h.json")
    _resealed(path, lambda d: d["network"]["weights"].__setitem__(0, [[0.0]]))
    _refusal(path, "network.weights.0 must be numbers of shape")


def test_a_valid_file_still_loads_and_saving_refuses_what_loading_would(tmp_path, saved):
    path = saved
    comp = Compensator.load(path)
    assert Compensator.load(comp.save(tmp_path / "again.npz")).provenance == {"session": "S@v001"}
    with pytest.raises(ValueError, match=r"provenance\.serial must be printable"):
        Compensator(comp.robot, {"serial": "a\nb"}).save(tmp_path / "bad.json")
    assert not (tmp_path / "bad.json").exists()
