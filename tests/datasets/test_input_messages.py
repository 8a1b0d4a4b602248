"""Bad input files get one line naming the file, the line and the fix (issue 26). Each test fails on main 5770eeb."""

from __future__ import annotations

import os

import numpy as np
import pytest
from typer.testing import CliRunner

from labcal.cli.app import app
from labcal.datasets import ImportFormatError, SessionStore, TargetsError, import_targets_csv, load_targets
from labcal.tomlschema import SchemaError, read_toml

runner = CliRunner()
TARGETS_MM = 'unit = "mm"\npoints = [[0, 0, 0], [100, 0, 0], [0, 80, 20]]\n'


def _csv_text(k: int = 3) -> str:
    rng = np.random.default_rng(0)
    head = [f"q{j}" for j in range(1, 7)] + [f"t{i}_{a}" for i in (1, 2, 3) for a in "xyz"]
    rows = [",".join(f"{v:.6f}" for v in rng.uniform(-1, 1, 15)) for _ in range(k)]
    return "\n".join([",".join(head), *rows]) + "\n"


def _import(tmp_path, csv_path):
    targets = load_targets(_targets(tmp_path))
    return import_targets_csv(SessionStore(tmp_path / "store"), csv_path, "ur10", "5" * 64, 6, targets)


def _targets(tmp_path):
    p = tmp_path / "t.toml"
    p.write_text(TARGETS_MM)
    return p


def _one_line(message: str, *fragments: str) -> None:
    assert "\n" not in message, message
    for f in fragments:
        assert f in message, message


def test_a_comment_line_above_the_header_is_named_with_its_line_and_the_fix(tmp_path):
    p = tmp_path / "data.csv"
    p.write_text("# exported by the tracker, 2026-11-26\n" + _csv_text())
    with pytest.raises(ImportFormatError) as e:
        _import(tmp_path, p)
    _one_line(str(e.value), "data.csv", "line 1", "comment line", "delete the comment lines")


def test_a_semicolon_file_with_decimal_commas_is_told_to_use_a_mapping(tmp_path):
    p = tmp_path / "data.csv"
    p.write_text(_csv_text().replace(",", ";").replace(".", ","))
    with pytest.raises(ImportFormatError) as e:
        _import(tmp_path, p)
    _one_line(str(e.value), "data.csv", "line 2", "';'-separated", 'separator = ";"', 'decimal = ","', "--mapping")


def test_a_latin1_byte_is_named_with_its_line_and_how_to_convert(tmp_path):
    p = tmp_path / "data.csv"
    text = _csv_text().encode()
    second = text.index(b"\n") + 1
    p.write_bytes(text[:second] + b"\xe9" + text[second + 1 :])  # a Latin-1 'é' at the start of line 2
    with pytest.raises(ImportFormatError) as e:
        _import(tmp_path, p)
    _one_line(str(e.value), "data.csv", "line 2, column 1", "0xe9 is not UTF-8", "iconv -f latin1 -t utf-8")


def test_a_byte_order_mark_in_a_toml_file_is_accepted(tmp_path):
    p = tmp_path / "t.toml"
    p.write_bytes(b"\xef\xbb\xbf" + TARGETS_MM.encode())  # as Notepad saves "UTF-8 with BOM"
    assert load_targets(p).shape == (3, 3)
    assert read_toml(p)["unit"] == "mm"


def test_a_non_utf8_toml_file_names_the_line(tmp_path):
    p = tmp_path / "robot.toml"
    p.write_bytes(b'name = "arm"\ndescription = "bras articul\xe9"\n')
    with pytest.raises(SchemaError) as e:
        read_toml(p)
    _one_line(str(e.value), "robot.toml", "line 2", "not UTF-8", "save it as UTF-8")


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
def test_a_device_is_called_a_device_not_a_missing_file(tmp_path):
    with pytest.raises(TargetsError, match="/dev/zero is a device, not a file"):
        load_targets("/dev/zero")
    r = runner.invoke(app, ["session", "import", "/dev/zero", "--robot", "ur10", "--targets", str(_targets(tmp_path)),
                            "--store", str(tmp_path / "s")])  # fmt: skip
    assert r.exit_code == 2 and "/dev/zero is a device, not a file" in r.stderr, r.stderr


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_is_called_a_fifo_and_never_opened(tmp_path):
    fifo = tmp_path / "data.csv"
    os.mkfifo(fifo)  # opening it for reading would block until a writer comes: the check must not open it
    with pytest.raises(TargetsError, match="is a FIFO"):
        load_targets(fifo)
    with pytest.raises(ImportFormatError, match="is a FIFO"):
        _import(tmp_path, fifo)
    r = runner.invoke(app, ["session", "import", str(fifo), "--robot", "ur10", "--targets", str(_targets(tmp_path)),
                            "--store", str(tmp_path / "s")])  # fmt: skip
    assert r.exit_code == 2 and "is a FIFO (named pipe)" in r.stderr, r.stderr


def test_targets_in_metres_declared_as_mm_are_told_to_write_unit_m(tmp_path):
    p = tmp_path / "t.toml"
    p.write_text('unit = "mm"\npoints = [[0, 0, 0], [0.1, 0, 0], [0, 0.08, 0.02]]\n')  # metres, labelled mm
    with pytest.raises(TargetsError) as e:
        load_targets(p)
    _one_line(str(e.value), "t.toml", "coincide", 'write unit = "m"')
    # targets that really coincide (far apart otherwise) get no unit hint
    p.write_text('unit = "mm"\npoints = [[0, 0, 0], [0.1, 0, 0], [0, 80, 20]]\n')
    with pytest.raises(TargetsError) as e:
        load_targets(p)
    assert "unit" not in str(e.value)
