"""`labcal filter`: correct a robot program (TCP poses or nominal joint targets) with a calibration, offline."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import AngleUnit, LengthUnit, ProgramKind, StoreOption, UserError, err, open_store, user_errors


def _numbers(text: str | None, count: int, option: str) -> list[float] | None:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.replace(";", ",").split(",") if v.strip()]
    except ValueError:
        raise UserError(f"{option} must be {count} comma-separated numbers, got {text!r}") from None
    if len(values) != count:
        raise UserError(f"{option} must be {count} comma-separated numbers, got {len(values)}")
    return values


@user_errors
def filter_program(
    program: Path = typer.Argument(
        ...,
        help="Program CSV (',' ';' or tab separated, decimal commas with ';' or tab; a header row, case-insensitive, "
        "or none: see --kind; other columns are ignored).",
    ),
    calibration: str = typer.Option(
        ...,
        "--calibration",
        help="A compensator export (.json / .npz from `labcal export`), or SESSION or SESSION@vN to use a stored fit.",
    ),
    kind: ProgramKind = typer.Option(
        "poses",
        "--kind",
        case_sensitive=False,
        help="poses: columns x,y,z,rx,ry,rz (TCP in the robot base frame; x,y,z in --length-unit, rx,ry,rz a "
        "rotation vector in --angle-unit, as URScript poses; a file without a header: exactly these 6 columns) | "
        "joints: columns q1..qn (nominal joint targets in --angle-unit; without a header: exactly n columns).",
    ),
    out: Path = typer.Option(
        ..., "--out", help="Corrected joint targets (CSV: row, q1..qn, nominal_q1..qn in --out-angle-unit, sizes)."
    ),
    script: Path | None = typer.Option(None, "--script", help="Also write a URScript movej program here (rad)."),
    length_unit: LengthUnit = typer.Option(
        "m", "--length-unit", help="x,y,z (and --tcp) unit: m | mm.", case_sensitive=False
    ),
    angle_unit: AngleUnit = typer.Option(
        "rad",
        "--angle-unit",
        help="q1..qn, rx,ry,rz (and --seed-joints, the --tcp rotation) unit: rad | deg.",
        case_sensitive=False,
    ),
    out_angle_unit: AngleUnit | None = typer.Option(
        None,
        "--out-angle-unit",
        help="Unit of the joints in --out: rad | deg (default: --angle-unit).",
        case_sensitive=False,
    ),
    out_length_unit: LengthUnit | None = typer.Option(
        None,
        "--out-length-unit",
        help="Unit of prismatic joints in --out: m | mm (default: --length-unit).",
        case_sensitive=False,
    ),
    seed_joints: str | None = typer.Option(
        None,
        "--seed-joints",
        help="Pose programs: joints near the first row's solution ('q1,...,qn', --angle-unit); they choose the "
        "configuration branch (shoulder, elbow, wrist) the whole program keeps.",
    ),
    tcp: str | None = typer.Option(
        None,
        "--tcp",
        help="The working TCP in the robot's tool frame, 'x,y,z,rx,ry,rz' (--length-unit, --angle-unit): pose "
        "programs give its poses; corrections and reported errors are taken there; default: the tool frame of the "
        "robot file (the flange for the built-in robots), not the calibration's measurement tool.",
    ),
    fit_id: str | None = typer.Option(None, "--fit", help="With SESSION: the fit id (default: the newest)."),
    speed: float = typer.Option(1.05, "--speed", help="movej speed in the script (rad/s)."),
    acceleration: float = typer.Option(1.4, "--acceleration", help="movej acceleration in the script (rad/s²)."),
    force: bool = typer.Option(False, "--force", help="Replace existing --out / --script files (regular files only)."),
    store: Path | None = StoreOption,
) -> None:
    """Correct a program: the joint targets at which the calibrated robot reaches the program's poses.

    The program is read like `session import` reads data: ',' ';' or tab separated (from the first line), decimal
    commas with ';' or tab, case-insensitive headers, or no header (columns by count). Pose programs are solved on
    the nominal model first (inverse kinematics from --seed-joints, then each row from the previous row, staying
    on that configuration branch), then corrected with the calibration; joint programs are corrected directly.
    Refused, naming the row: rotation vectors whose norm exceeds a full turn (degrees read as radians), joints
    outside the robot's limits or the calibrated ranges, unreachable rows, rows at or near a singular
    configuration, and corrections that would change branch. --out is written in the program's units (or
    --out-angle-unit), the script in rad; both are replaced atomically and only if they are regular files.
    Prints the correction size; the path of --out is the last line.

    Examples:

      labcal filter prog.csv --calibration ur10.json --length-unit mm --seed-joints 0,-1.6,1.6,-1.6,-1.6,0 --out c.csv

      labcal filter rdk.csv --calibration u.json --length-unit mm --angle-unit deg --seed-joints 0,-90,90,0,90,0 --out o

      labcal filter joints.csv --kind joints --angle-unit deg --calibration S@v1 --out corrected.csv --script c.script
    """
    import numpy as np

    from labcal import atomicio
    from labcal.cli.ops.exporting import check_output
    from labcal.cli.ops.programs import read_program
    from labcal.export import program as prog

    if kind not in ("poses", "joints"):
        raise UserError(f"--kind must be poses or joints, got {kind!r}")
    outputs = [("--out", out)] + ([("--script", script)] if script is not None else [])
    for flag, path in outputs:  # a device, symlink or folder is refused before any work, --force or not
        try:
            atomicio.check_target(path)
        except atomicio.UnsafeTargetError as e:
            raise UserError(f"{flag} {e}") from None
        check_output(path, force=force)
    if script is not None and out.resolve() == script.resolve():
        raise UserError(f"--out and --script name the same file {out}: give two paths")
    robot = _calibration(calibration, fit_id, store)
    if robot.joint_map is not None:
        raise UserError("this calibration's robot has a joint map: filter works in model joints only (UR arms)")
    if script is not None and robot.n != 6:
        raise UserError(
            f"--script writes a URScript movej program for a UR controller (6 joints); this robot has {robot.n} "
            "joints: leave out --script and send the corrected joints (--out) with the robot's own controller"
        )
    types = robot.nominal.joint_types
    table = read_program(program, kind, n=robot.n, joint_types=types, length_unit=length_unit, angle_unit=angle_unit)
    offset = _numbers(tcp, 6, "--tcp")
    if offset is not None:
        offset = np.asarray(offset) * np.array(
            [prog.LENGTH_UNITS[length_unit]] * 3 + [prog.ANGLE_UNITS[angle_unit]] * 3
        )
    try:
        if kind == "joints":
            tcp4 = None if offset is None else prog.pose_matrix(offset)[0]
            result = prog.filter_joints(robot, table.values, angle_unit=angle_unit, tcp=tcp4)
        else:
            seed = _numbers(seed_joints, robot.n, "--seed-joints")
            if seed is None:
                raise UserError("a pose program needs --seed-joints (joints near its first row: they pick the branch)")
            seed = np.asarray(seed) * prog.joint_factors(types, length_unit, angle_unit)
            result = prog.filter_poses(robot, table.values, seed, tcp=offset, angle_unit=angle_unit)
    except prog.ProgramError as e:  # the message names the row; the file line helps find it
        line = table.line_of(e.row)
        raise UserError(f"{program}{f' line {line}' if line is not None else ''}: {e}") from None
    out_angle, out_length = out_angle_unit or angle_unit, out_length_unit or length_unit
    atomicio.write_text(out, prog.joints_csv(result, angle_unit=out_angle, length_unit=out_length, joint_types=types))
    if script is not None:
        atomicio.write_text(script, prog.movej_program(result.q_command, a=acceleration, v=speed))
    err.print(f"{program}: {len(result.q_command)} rows read ({table.describe()})", markup=False)
    err.print(result.summary(), markup=False)
    err.print(
        f"wrote q1..q{robot.n} in {out_angle}" + (" (the script in rad)" if script is not None else ""), markup=False
    )
    if script is not None:
        print(script)
    print(out)


def _calibration(calibration: str, fit_id: str | None, store: Path | None):
    path = Path(calibration)
    if path.suffix.lower() in (".json", ".npz"):
        from labcal.compensator import CompensatorFileError, load

        try:
            return load(path).robot
        except (OSError, CompensatorFileError) as e:
            raise UserError(f"--calibration {path}: {e}") from None
    from labcal.cli.ops import split_ref
    from labcal.cli.ops.fitting import load_stored_fit

    return load_stored_fit(open_store(store, create=False), split_ref(calibration), fit_id).robot
