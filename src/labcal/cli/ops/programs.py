"""Read a robot program for `labcal filter` the way `session import` reads measurements.

The number parsing, the row / line / column errors and the header checks are the importers' (``datasets``); this
module adds what a program file needs on top, so that ``export.program`` (which may not import ``datasets``)
receives plain arrays in SI units:

- the dialect, from the first non-blank line: a tab there makes the file tab-separated, else a ``;`` makes it
  ``;``-separated, else it is comma-separated. With ``;`` or tab, a comma in a program number cell is a decimal
  comma (``0,5``); a file mixing ``0,5`` and ``0.5`` is refused naming the cell;
- the header, matched case-insensitively (``X, Y, Z, RX, RY, RZ`` or ``Q1 … Qn``); other columns are ignored;
- a headerless file: when every cell of the first line is a number the file has no header, and its columns are
  taken by count: exactly 6 for a pose program (x, y, z, rx, ry, rz) and exactly n for a joint program (q1 … qn);
  any other count is refused (name the columns in a header line);
- units: x, y, z (and prismatic joints) in ``length_unit``, rx, ry, rz and revolute joints in ``angle_unit``.

Example::

    table = read_program(Path("prog.csv"), "poses", n=6, joint_types=("revolute",) * 6, length_unit="mm",
                         angle_unit="deg")
    table.values        # (k, 6) m and rad
    table.describe()    # "';'-separated, decimal comma, header"
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labcal.cli.common import UserError

POSE_COLUMNS = ("x", "y", "z", "rx", "ry", "rz")
SEPARATORS = {"\t": "tab", ";": "';'", ",": "','"}


@dataclass(frozen=True)
class ProgramTable:
    """A program read from a file: ``values`` (k, 6) m / rad poses or (k, n) SI joints; ``lines`` (k,) the file
    line of each row (1-based); how the file was read (``separator``, ``decimal``, ``header``)."""

    values: np.ndarray
    lines: np.ndarray
    separator: str
    decimal: str
    header: bool

    def describe(self) -> str:
        """How the file was read, for the summary line: "';'-separated, decimal comma, header"."""
        decimal = "decimal comma" if self.decimal == "," else "decimal point"
        return f"{SEPARATORS[self.separator]}-separated, {decimal}, {'header' if self.header else 'no header'}"

    def line_of(self, row: int | None) -> int | None:
        """The file line of 1-based program row ``row`` (None when unknown)."""
        if row is None or not 1 <= row <= len(self.lines):
            return None
        return int(self.lines[row - 1])


def _first_line(path: Path) -> tuple[list[str], str, int]:
    """The first non-blank line's cells, the separator it shows (the dialect rule of the module docstring) and its
    1-based line number."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as f:
            number, raw = next(((i, line) for i, line in enumerate(f, start=1) if line.strip()), (0, ""))
    except UnicodeDecodeError as e:
        raise UserError(f"program {path} is not UTF-8 text ({e.reason} at byte {e.start})") from None
    if not number:
        raise UserError(f"program {path} is empty")
    separator = "\t" if "\t" in raw else ";" if ";" in raw else ","
    return next(csv.reader([raw], delimiter=separator)), separator, number


def _is_number(cell: str, separator: str) -> bool:
    text = cell.strip()
    if separator != ",":
        text = text.replace(",", ".")
    try:
        float(text)
    except ValueError:
        return False
    return True


def _headerless_table(path: Path, separator: str, names: list[str]):
    """The importers' CSV table of a file without a header line: ``names`` name its columns, every non-blank line
    is a row (and must have len(names) fields)."""
    import pandas as pd

    from labcal.datasets import ImportFormatError
    from labcal.datasets.importers import _Csv

    rows, lines = [], []
    with open(path, encoding="utf-8-sig", newline="") as f:
        reader = csv.reader(f, delimiter=separator)
        for row in reader:
            if not any(c.strip() for c in row):
                continue
            if len(row) != len(names):
                raise ImportFormatError(
                    f"{len(row)} fields, the first line has {len(names)} (a file without a header keeps one count)",
                    path=str(path), line=reader.line_num,
                )  # fmt: skip
            rows.append(row)
            lines.append(reader.line_num)
    table = _Csv.__new__(_Csv)  # the importers' number parsing and errors over rows read here (no header line)
    table.path, table.columns = path, list(names)
    table.frame = pd.DataFrame(rows, columns=names, dtype=str)
    table.lines = np.asarray(lines)
    return table


def read_program(
    path: Path,
    kind: str,
    *,
    n: int,
    joint_types,
    length_unit: str = "m",
    angle_unit: str = "rad",
) -> ProgramTable:
    """Read a pose (``kind="poses"``) or joint (``"joints"``, n columns) program; values in SI (module docstring).

    Errors (a missing column, a bad number, a ragged row …) name the file, the row and line, and the column.
    """
    from labcal.datasets.importers import _Csv
    from labcal.export.program import joint_factors

    if kind not in ("poses", "joints"):
        raise UserError(f"--kind must be poses or joints, got {kind!r}")
    if not path.is_file():
        raise UserError(f"program {path} is a folder, not a CSV file" if path.is_dir() else f"no such file: {path}")
    wanted = list(POSE_COLUMNS) if kind == "poses" else [f"q{j + 1}" for j in range(n)]
    what = "x, y, z, rx, ry, rz" if kind == "poses" else f"q1 … q{n} (the robot has {n} joints)"
    first, separator, number = _first_line(path)
    header = not all(_is_number(c, separator) for c in first if c.strip())
    if header and number > 1:  # the importers' reader takes line 1 as the header
        raise UserError(f"program {path}: the header is on line {number}, after blank lines: remove them")
    if header:
        table = _Csv(path, separator)
        by_name: dict[str, str] = {}
        for name in table.columns:
            key = name.strip().lower()
            if key in by_name and key in wanted:
                raise UserError(
                    f"program {path}: the columns {by_name[key]!r} and {name!r} are the same name (headers are "
                    "case-insensitive): keep one"
                )
            by_name.setdefault(key, name)
        missing = [c for c in wanted if c not in by_name]
        if missing:
            raise UserError(
                f"program {path}: missing column(s) {', '.join(missing)}; a {kind[:-1]} program needs {what} "
                f"(case-insensitive; other columns are ignored); the header has {', '.join(table.columns)}"
            )
        if kind == "joints" and f"q{n + 1}" in by_name:
            raise UserError(f"program {path}: a column q{n + 1} but the robot has {n} joints (q1 … q{n})")
        columns = [by_name[c] for c in wanted]
    else:
        if len(first) != len(wanted):
            raise UserError(
                f"program {path} has no header line and {len(first)} columns: a headerless {kind[:-1]} program has "
                f"exactly {len(wanted)} ({what}); add a header line naming the columns"
            )
        table = _headerless_table(path, separator, wanted)
        columns = wanted
    cells = table.frame[columns]
    decimal = (
        "," if separator != "," and cells.apply(lambda s: s.str.contains(",", regex=False)).to_numpy().any() else "."
    )
    raw = np.stack([table.numbers(c, decimal) for c in columns], axis=1)
    if kind == "poses":
        factors = pose_factors(length_unit, angle_unit)
    else:
        factors = joint_factors(joint_types, length_unit, angle_unit)
    return ProgramTable(raw * factors, np.asarray(table.lines), separator, decimal, header)


def pose_factors(length_unit: str, angle_unit: str) -> np.ndarray:
    """(6,) SI factors of x, y, z (``length_unit``) and rx, ry, rz (``angle_unit``)."""
    from labcal.export.program import ANGLE_UNITS, LENGTH_UNITS

    return np.array([LENGTH_UNITS[length_unit]] * 3 + [ANGLE_UNITS[angle_unit]] * 3)


def parse_numbers(text: str | None, count: int, option: str) -> list[float] | None:
    """``count`` comma- (or ';'-) separated numbers of an option, None when the option is not given."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.replace(";", ",").split(",") if v.strip()]
    except ValueError:
        raise UserError(f"{option} must be {count} comma-separated numbers, got {text!r}") from None
    if len(values) != count:
        raise UserError(f"{option} must be {count} comma-separated numbers, got {len(values)}")
    return values


def load_calibration(calibration: str, fit_id: str | None, store: Path | None):
    """The calibrated robot of a compensator export (.json / .npz) or of a stored fit (SESSION[@vN], --fit)."""
    path = Path(calibration)
    if path.suffix.lower() in (".json", ".npz"):
        from labcal.compensator import CompensatorFileError, load

        try:
            return load(path).robot
        except (OSError, CompensatorFileError) as e:
            raise UserError(f"--calibration {path}: {e}") from None
    from labcal.cli.common import open_store
    from labcal.cli.ops.common import split_ref
    from labcal.cli.ops.fitting import load_stored_fit

    return load_stored_fit(open_store(store, create=False), split_ref(calibration), fit_id).robot


def check_filter_outputs(out: Path, script: Path | None, force: bool) -> None:
    """Refuse, before any work, outputs that are not (new or, with force, existing) regular files, or one file
    given twice."""
    from labcal import atomicio
    from labcal.cli.ops.exporting import check_output

    outputs = [("--out", out)] + ([("--script", script)] if script is not None else [])
    for flag, path in outputs:  # a device, symlink or folder is refused before any work, --force or not
        try:
            atomicio.check_target(path)
        except atomicio.UnsafeTargetError as e:
            raise UserError(f"{flag} {e}") from None
        check_output(path, force=force)
    if script is not None and out.resolve() == script.resolve():
        raise UserError(f"--out and --script name the same file {out}: give two paths")


def check_filterable(robot, script: Path | None) -> None:
    """Refuse a robot filter cannot correct (a joint map), and --script for a robot that is not a 6-joint UR."""
    if robot.joint_map is not None:
        raise UserError("this calibration's robot has a joint map: filter works in model joints only (UR arms)")
    if script is not None and robot.n != 6:
        raise UserError(
            f"--script writes a URScript movej program for a UR controller (6 joints); this robot has {robot.n} "
            "joints: leave out --script and send the corrected joints (--out) with the robot's own controller"
        )


def filter_program_file(
    program: Path,
    kind: str,
    robot,
    *,
    length_unit: str,
    angle_unit: str,
    tcp: str | None,
    seed_joints: str | None,
):
    """(FilteredProgram, ProgramTable): the program file read and corrected; a refused row names its file line."""
    from labcal.export import program as prog

    types = robot.nominal.joint_types
    table = read_program(program, kind, n=robot.n, joint_types=types, length_unit=length_unit, angle_unit=angle_unit)
    offset = parse_numbers(tcp, 6, "--tcp")
    if offset is not None:
        offset = np.asarray(offset) * pose_factors(length_unit, angle_unit)
    try:
        if kind == "joints":
            tcp4 = None if offset is None else prog.pose_matrix(offset)[0]
            result = prog.filter_joints(robot, table.values, angle_unit=angle_unit, tcp=tcp4)
        else:
            seed = parse_numbers(seed_joints, robot.n, "--seed-joints")
            if seed is None:
                raise UserError("a pose program needs --seed-joints (joints near its first row: they pick the branch)")
            seed = np.asarray(seed) * prog.joint_factors(types, length_unit, angle_unit)
            result = prog.filter_poses(robot, table.values, seed, tcp=offset, angle_unit=angle_unit)
    except prog.ProgramError as e:  # the message names the row; the file line helps find it
        line = table.line_of(e.row)
        raise UserError(f"{program}{f' line {line}' if line is not None else ''}: {e}") from None
    return result, table
