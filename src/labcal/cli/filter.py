"""`labcal filter`: correct a robot program (TCP poses or nominal joint targets) with a calibration, offline."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import AngleUnit, LengthUnit, ProgramKind, StoreOption, err, user_errors

_PROGRAM = typer.Argument(
    ...,
    help="Program CSV (',' ';' or tab separated, decimal commas with ';' or tab; a header row, case-insensitive, "
    "or none: see --kind; other columns are ignored).",
)
_CALIBRATION = typer.Option(
    ...,
    "--calibration",
    help="A compensator export (.json / .npz from `labcal export`), or SESSION or SESSION@vN to use a stored fit.",
)
_KIND = typer.Option(
    "poses",
    "--kind",
    case_sensitive=False,
    help="poses: columns x,y,z,rx,ry,rz (TCP in the robot base frame; x,y,z in --length-unit, rx,ry,rz a "
    "rotation vector in --angle-unit, as URScript poses; a file without a header: exactly these 6 columns) | "
    "joints: columns q1..qn (nominal joint targets in --angle-unit; without a header: exactly n columns).",
)
_OUT = typer.Option(
    ..., "--out", help="Corrected joint targets (CSV: row, q1..qn, nominal_q1..qn in --out-angle-unit, sizes)."
)
_SCRIPT = typer.Option(None, "--script", help="Also write a URScript movej program here (rad).")
_LENGTH_UNIT = typer.Option("m", "--length-unit", help="x,y,z (and --tcp) unit: m | mm.", case_sensitive=False)
_ANGLE_UNIT = typer.Option(
    "rad",
    "--angle-unit",
    help="q1..qn, rx,ry,rz (and --seed-joints, the --tcp rotation) unit: rad | deg.",
    case_sensitive=False,
)
_OUT_ANGLE_UNIT = typer.Option(
    None,
    "--out-angle-unit",
    help="Unit of the joints in --out: rad | deg (default: --angle-unit).",
    case_sensitive=False,
)
_OUT_LENGTH_UNIT = typer.Option(
    None,
    "--out-length-unit",
    help="Unit of prismatic joints in --out: m | mm (default: --length-unit).",
    case_sensitive=False,
)
_SEED_JOINTS = typer.Option(
    None,
    "--seed-joints",
    help="Pose programs: joints near the first row's solution ('q1,...,qn', --angle-unit); they choose the "
    "configuration branch (shoulder, elbow, wrist) the whole program keeps.",
)
_TCP = typer.Option(
    None,
    "--tcp",
    help="The working TCP in the robot's tool frame, 'x,y,z,rx,ry,rz' (--length-unit, --angle-unit): pose "
    "programs give its poses; corrections and reported errors are taken there; default: the tool frame of the "
    "robot file (the flange for the built-in robots), not the calibration's measurement tool.",
)


@user_errors
def filter_program(
    program: Path = _PROGRAM,
    calibration: str = _CALIBRATION,
    kind: ProgramKind = _KIND,
    out: Path = _OUT,
    script: Path | None = _SCRIPT,
    length_unit: LengthUnit = _LENGTH_UNIT,
    angle_unit: AngleUnit = _ANGLE_UNIT,
    out_angle_unit: AngleUnit | None = _OUT_ANGLE_UNIT,
    out_length_unit: LengthUnit | None = _OUT_LENGTH_UNIT,
    seed_joints: str | None = _SEED_JOINTS,
    tcp: str | None = _TCP,
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
    from labcal import atomicio
    from labcal.cli.ops import programs as ops
    from labcal.export import program as prog

    ops.check_filter_outputs(out, script, force)
    robot = ops.load_calibration(calibration, fit_id, store)
    ops.check_filterable(robot, script)
    result, table = ops.filter_program_file(
        program, kind, robot, length_unit=length_unit, angle_unit=angle_unit, tcp=tcp, seed_joints=seed_joints
    )
    types = robot.nominal.joint_types
    out_angle, out_length = out_angle_unit or angle_unit, out_length_unit or length_unit
    atomicio.write_text(out, prog.joints_csv(result, angle_unit=out_angle, length_unit=out_length, joint_types=types))
    if script is not None:
        atomicio.write_text(script, prog.movej_program(result.q_command, a=acceleration, v=speed))
    err.print(f"{program}: {len(result.q_command)} rows read ({table.describe()})")
    err.print(result.summary())
    err.print(f"wrote q1..q{robot.n} in {out_angle}" + (" (the script in rad)" if script is not None else ""))
    if script is not None:
        print(script)
    print(out)
