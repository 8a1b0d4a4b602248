"""`labcal filter`: correct a robot program (TCP poses or nominal joint targets) with a calibration, offline."""

from __future__ import annotations

from pathlib import Path

import typer

from labcal.cli.common import AngleUnit, LengthUnit, ProgramKind, StoreOption, err, store_of, user_errors


def _numbers(text: str | None, count: int, option: str) -> list[float] | None:
    if text is None:
        return None
    from labcal.cli.ops.common import UserError

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
        ..., help="Program CSV with a header row (columns: see --kind; other columns are ignored)."
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
        "rotation vector in rad, as URScript poses) | joints: columns q1..qn (nominal joint targets, --angle-unit).",
    ),
    out: Path = typer.Option(..., "--out", help="Corrected joint targets (CSV: row, q1..qn in rad, sizes)."),
    script: Path | None = typer.Option(None, "--script", help="Also write a URScript movej program here."),
    length_unit: LengthUnit = typer.Option(
        "m", "--length-unit", help="x,y,z (and --tcp) unit: m | mm.", case_sensitive=False
    ),
    angle_unit: AngleUnit = typer.Option(
        "rad", "--angle-unit", help="q1..qn (and --seed-joints) unit: rad | deg.", case_sensitive=False
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
        help="The program's TCP in the robot's tool frame, 'x,y,z,rx,ry,rz' (--length-unit, rad); default: the "
        "tool frame of the robot file (the flange for the built-in robots).",
    ),
    fit_id: str | None = typer.Option(None, "--fit", help="With SESSION: the fit id (default: the newest)."),
    speed: float = typer.Option(1.05, "--speed", help="movej speed in the script (rad/s)."),
    acceleration: float = typer.Option(1.4, "--acceleration", help="movej acceleration in the script (rad/s²)."),
    force: bool = typer.Option(False, "--force", help="Replace existing --out / --script files."),
    store: Path | None = StoreOption,
) -> None:
    """Correct a program: the joint targets at which the calibrated robot reaches the program's poses.

    Pose programs are solved on the nominal model first (inverse kinematics from --seed-joints, then each row
    from the previous row, staying on that configuration branch), then corrected with the calibration; joint
    programs are corrected directly. A row that is unreachable, outside the calibrated joint ranges, or whose
    solution would change branch is refused with its row number. Prints the correction size; the path of
    --out is the last line.

    Examples:

      labcal filter prog.csv --calibration ur10.json --length-unit mm --seed-joints 0,-1.6,1.6,-1.6,-1.6,0 --out c.csv

      labcal filter prog.csv --calibration ur10.json --seed-joints 0,-1.6,1.6,-1.6,-1.6,0 --out c.csv --script c.script

      labcal filter joints.csv --kind joints --angle-unit deg --calibration S@v1 --out corrected.csv
    """
    import numpy as np

    from labcal.cli.ops.common import UserError
    from labcal.cli.ops.exporting import check_output
    from labcal.export import program as prog

    if kind not in ("poses", "joints"):
        raise UserError(f"--kind must be poses or joints, got {kind!r}")
    check_output(out, force=force)
    if script is not None:
        check_output(script, force=force)
    robot = _calibration(calibration, fit_id, store)
    if robot.joint_map is not None:
        raise UserError("this calibration's robot has a joint map: filter works in model joints only (UR arms)")
    if not program.is_file():
        raise UserError(f"program {program} does not exist")
    try:
        rows = prog.read_program(program, kind, length_unit, angle_unit, n=robot.n if kind == "joints" else None)
        if kind == "joints":
            result = prog.filter_joints(robot, rows)
        else:
            seed = _numbers(seed_joints, robot.n, "--seed-joints")
            if seed is None:
                raise UserError("a pose program needs --seed-joints (joints near its first row: they pick the branch)")
            seed = np.radians(seed) if angle_unit == "deg" else np.asarray(seed)
            offset = _numbers(tcp, 6, "--tcp")
            if offset is not None and length_unit == "mm":
                offset = [v / 1000.0 for v in offset[:3]] + offset[3:]
            result = prog.filter_poses(robot, rows, seed, tcp=None if offset is None else np.asarray(offset))
    except ValueError as e:  # ProgramError and CSV errors name the row / column
        raise UserError(f"{program}: {e}") from None
    out.write_text(prog.joints_csv(result))
    if script is not None:
        script.write_text(prog.movej_program(result.q_command, a=acceleration, v=speed))
    err.print(result.summary(), markup=False)
    if script is not None:
        print(script)
    print(out)


def _calibration(calibration: str, fit_id: str | None, store: Path | None):
    from labcal.cli.ops.common import UserError

    path = Path(calibration)
    if path.suffix.lower() in (".json", ".npz"):
        from labcal.compensator import CompensatorFileError, load

        try:
            return load(path).robot
        except (OSError, CompensatorFileError) as e:
            raise UserError(f"--calibration {path}: {e}") from None
    from labcal.cli.ops import split_ref
    from labcal.cli.ops.fitting import load_stored_fit

    return load_stored_fit(store_of(store), split_ref(calibration), fit_id).robot
