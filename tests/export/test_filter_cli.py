"""`labcal filter` through its typer command: pose and joint programs in their units, the outputs, and the errors
(row named, seed required, existing output)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))

from export_fixtures import hybrid, sample

import urscript_subset
from labcal.cli.filter import filter_program
from labcal.compensator import save
from labcal.export.program import filter_joints, filter_poses
from labcal.kinematics import se3

app = typer.Typer()
app.command("filter")(filter_program)
app.command("unused")(lambda: None)  # two commands: typer keeps "filter" as a subcommand name
runner = CliRunner()


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("filter")
    robot = hybrid("ur10", features=None, seed=7)
    save(robot, root / "ur10.json")
    q = sample(robot, 1, seed=2)[0] + np.linspace(0, 0.2, 4)[:, None] * np.array([1, -1, 1, 1, -1, 1])
    T = robot.nominal.fk(q)
    poses = np.concatenate([T[:, :3, 3] * 1000, se3.log_so3(T[:, :3, :3])], axis=1)
    (root / "poses.csv").write_text(
        "x,y,z,rx,ry,rz\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in poses) + "\n"
    )
    (root / "joints.csv").write_text(
        "q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(repr(float(v)) for v in np.degrees(row)) for row in q) + "\n"
    )
    return {"root": root, "robot": robot, "q": q, "poses": poses}


def run(*args):
    return runner.invoke(app, ["filter", *map(str, args)])


def read_q(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()[1:]
    return np.array([[float(v) for v in line.split(",")[1:7]] for line in lines])


def test_pose_program_in_mm_is_corrected_with_a_movej_script(setup):
    root, robot, q = setup["root"], setup["robot"], setup["q"]
    seed = ",".join(repr(float(v)) for v in q[0] + 0.02)
    out, script = root / "poses-out.csv", root / "poses-out.script"
    r = run(root / "poses.csv", "--calibration", root / "ur10.json", "--length-unit", "mm", "--seed-joints", seed,
            "--out", out, "--script", script)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    assert r.stdout.strip().splitlines()[-1] == str(out)
    assert "joint correction" in r.stderr
    poses_m = setup["poses"] * np.array([1e-3] * 3 + [1.0] * 3)
    expected = filter_poses(robot, poses_m, q[0] + 0.02)
    np.testing.assert_array_equal(read_q(out), expected.q_command)
    urscript_subset.check(script.read_text())


def test_joint_program_in_degrees(setup):
    root, robot, q = setup["root"], setup["robot"], setup["q"]
    out = root / "joints-out.csv"
    r = run(root / "joints.csv", "--kind", "joints", "--angle-unit", "deg", "--calibration", root / "ur10.json",
            "--out", out)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    assert "wrote q1..q6 in deg" in r.stderr  # written in the units it was read in
    np.testing.assert_allclose(np.radians(read_q(out)), filter_joints(robot, q).q_command, atol=1e-12)


def test_errors_name_the_row_and_the_fix(setup):
    root, q = setup["root"], setup["q"]
    r = run(root / "poses.csv", "--calibration", root / "ur10.json", "--out", root / "x.csv")
    assert r.exit_code != 0 and "--seed-joints" in r.stderr
    # metres read as millimetres: the program is 1000x too far away
    seed = ",".join(repr(float(v)) for v in q[0])
    r = run(root / "poses.csv", "--calibration", root / "ur10.json", "--seed-joints", seed, "--out", root / "y.csv")
    assert r.exit_code != 0 and "row 1: " in r.stderr
    (root / "z.csv").write_text("old")
    r = run(root / "joints.csv", "--kind", "joints", "--calibration", root / "ur10.json", "--out", root / "z.csv")
    assert r.exit_code != 0 and "already exists" in r.stderr
    assert (root / "z.csv").read_text() == "old"


# ------------------------------------------------------------------------------------------------------------
# issue 24 item 4: writes, dialects, units, checks


def joints_text(q_deg: np.ndarray, sep: str = ",", decimal: str = ".", header: str | None = "q1,q2,q3,q4,q5,q6") -> str:
    lines = [] if header is None else [header.replace(",", sep)]
    lines += [sep.join(repr(float(v)).replace(".", decimal) for v in row) for row in q_deg]
    return "\n".join(lines) + "\n"


def test_a_failed_write_leaves_the_previous_program_whole(setup, tmp_path):
    """A full disk met mid-write (here: the file-size limit, the same EFBIG/ENOSPC path): the program that was
    there stays whole, no temporary file is left, exit 2 with one line."""
    import resource
    import signal

    root, q = setup["root"], setup["q"]
    big = np.repeat(np.degrees(q), 100, axis=0)  # 400 rows: far more than the limit below lets through
    (tmp_path / "long.csv").write_text(joints_text(big))
    out = tmp_path / "out.csv"
    out.write_text("previous program\n" * 10)
    before = out.read_bytes()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))
    try:
        r = run(tmp_path / "long.csv", "--kind", "joints", "--angle-unit", "deg", "--calibration", root / "ur10.json",
                "--out", out, "--force")  # fmt: skip
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old_handler)
    assert r.exit_code == 2, r.stdout + r.stderr
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.csv", "out.csv"]  # no temporary file left
    assert r.stderr.strip().startswith("error: ") and str(out) in r.stderr and "Traceback" not in r.stderr


def _symlink(tmp_path: Path) -> Path:
    target = tmp_path / "target.csv"
    target.write_text("keep me\n")
    (tmp_path / "link.csv").symlink_to(target)
    return tmp_path / "link.csv"


def _device(tmp_path: Path) -> Path:
    import os
    import stat

    try:
        os.mknod(tmp_path / "null", 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # a /dev/null of our own
    except PermissionError:
        pytest.skip("creating a device node needs root")
    return tmp_path / "null"


def _folder(tmp_path: Path) -> Path:
    (tmp_path / "dir.csv").mkdir()
    return tmp_path / "dir.csv"


@pytest.mark.parametrize(
    ("make", "what"), [(_symlink, "a symbolic link"), (_device, "a device"), (_folder, "a folder")]
)
@pytest.mark.parametrize("flag", ["--out", "--script"])
def test_only_regular_files_are_replaced_even_with_force(setup, tmp_path, make, what, flag):
    import stat

    root = setup["root"]
    target = make(tmp_path)
    mode = target.lstat().st_mode
    paths = {"--out": tmp_path / "out.csv", "--script": tmp_path / "out.script", flag: target}
    r = run(root / "joints.csv", "--kind", "joints", "--angle-unit", "deg", "--calibration", root / "ur10.json",
            "--out", paths["--out"], "--script", paths["--script"], "--force")  # fmt: skip
    assert r.exit_code == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {flag} {target}") and what in lines[0], r.stderr
    assert target.lstat().st_mode == mode and stat.S_IFMT(mode) != stat.S_IFREG
    if what == "a symbolic link":
        assert (tmp_path / "target.csv").read_text() == "keep me\n"
    assert not paths["--out"].exists() or flag == "--out"  # refused before any work


def test_rotation_vectors_in_degrees_are_refused_with_the_hint(setup, tmp_path):
    root, q = setup["root"], setup["q"]
    poses = setup["poses"].copy()
    poses[:, 3:] = np.degrees(poses[:, 3:])  # a program whose rotation vectors are in degrees (norms about 100)
    (tmp_path / "p.csv").write_text(
        "x,y,z,rx,ry,rz\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in poses) + "\n"
    )
    seed = ",".join(repr(float(v)) for v in q[0] + 0.02)
    r = run(tmp_path / "p.csv", "--calibration", root / "ur10.json", "--length-unit", "mm", "--seed-joints", seed,
            "--out", tmp_path / "o.csv")  # fmt: skip
    assert r.exit_code == 2, r.stdout + r.stderr
    assert "line 2: row 1: rx, ry, rz" in r.stderr and "pass --angle-unit deg" in r.stderr
    assert not (tmp_path / "o.csv").exists()
    # told, the same file goes through, and agrees with the program in radians
    r = run(tmp_path / "p.csv", "--calibration", root / "ur10.json", "--length-unit", "mm", "--angle-unit", "deg",
            "--seed-joints", ",".join(repr(float(v)) for v in np.degrees(q[0] + 0.02)), "--out", tmp_path / "o.csv",
            "--out-angle-unit", "rad")  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    expected = filter_poses(setup["robot"], setup["poses"] * np.array([1e-3] * 3 + [1.0] * 3), q[0] + 0.02)
    np.testing.assert_allclose(read_q(tmp_path / "o.csv"), expected.q_command, atol=1e-9)


DIALECTS = {
    "upper-case header": lambda q: joints_text(q, header="Q1,Q2,Q3,Q4,Q5,Q6"),
    "no header": lambda q: joints_text(q, header=None),
    "semicolon, decimal comma": lambda q: joints_text(q, sep=";", decimal=","),
    "semicolon, decimal comma, no header": lambda q: joints_text(q, sep=";", decimal=",", header=None),
    "tab, decimal comma, mixed-case header": lambda q: joints_text(
        q, sep="\t", decimal=",", header="q1,Q2,q3,Q4,q5,Q6"
    ),
    "semicolon, decimal point, blank lines": lambda q: joints_text(q, sep=";").replace("\n", "\n\n", 2),
}


@pytest.mark.parametrize("dialect", DIALECTS)
def test_programs_are_read_like_session_import(setup, tmp_path, dialect):
    root, robot, q = setup["root"], setup["robot"], setup["q"]
    (tmp_path / "p.csv").write_text(DIALECTS[dialect](np.degrees(q)))
    r = run(tmp_path / "p.csv", "--kind", "joints", "--angle-unit", "deg", "--calibration", root / "ur10.json",
            "--out", tmp_path / "o.csv")  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    np.testing.assert_allclose(np.radians(read_q(tmp_path / "o.csv")), filter_joints(robot, q).q_command, atol=1e-12)
    assert "rows read (" in r.stderr


def test_what_the_reader_refuses_names_file_line_and_column(setup, tmp_path):
    root, q = setup["root"], setup["q"]
    args = ("--kind", "joints", "--angle-unit", "deg", "--calibration", root / "ur10.json", "--out", tmp_path / "o.csv")
    cases = {
        # headerless: the columns are taken by count, and only the exact count is accepted
        "a.csv": (
            joints_text(np.degrees(q)[:, :5], header=None),
            "has no header line and 5 columns: a headerless joint program has exactly 6",
        ),
        # a decimal point among decimal commas
        "b.csv": (
            joints_text(np.degrees(q), sep=";", decimal=",").replace(",", ".", 1),
            "line 2 of the file), column 'q1': value",
        ),
        "c.csv": ("x,q1,q2\n1,2,3\n", "missing column(s) q3, q4, q5, q6"),
        "d.csv": ("Q1,q1,q2,q3,q4,q5,q6\n" + "1," * 6 + "1\n", "'Q1' and 'q1' are the same name"),
        "e.csv": (joints_text(np.degrees(q), header=None) + "1,2,3\n", "line 5: 3 fields, the first line has 6"),
        "f.csv": ("\n \n" + joints_text(np.degrees(q)), "the header is on line 3, after blank lines: remove them"),
    }
    for name, (text, message) in cases.items():
        (tmp_path / name).write_text(text)
        r = run(tmp_path / name, *args)
        assert r.exit_code == 2 and message in r.stderr and str(tmp_path / name) in r.stderr, (name, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_robodk_style_program_in_mm_and_degrees(setup, tmp_path):
    """x, y, z in mm and the rotation vector in degrees; the output in degrees (as read) unless asked; the URScript
    always in rad (movej takes rad)."""
    root, robot, q = setup["root"], setup["robot"], setup["q"]
    poses = setup["poses"].copy()  # mm, rad
    poses[:, 3:] = np.degrees(poses[:, 3:])
    (tmp_path / "p.csv").write_text(
        "X;Y;Z;RX;RY;RZ\n" + "\n".join(";".join(repr(float(v)).replace(".", ",") for v in row) for row in poses)
    )
    seed = ",".join(repr(float(v)) for v in np.degrees(q[0] + 0.02))
    out, script = tmp_path / "o.csv", tmp_path / "o.script"
    r = run(tmp_path / "p.csv", "--calibration", root / "ur10.json", "--length-unit", "mm", "--angle-unit", "deg",
            "--seed-joints", seed, "--out", out, "--script", script)  # fmt: skip
    assert r.exit_code == 0, r.stdout + r.stderr
    expected = filter_poses(robot, setup["poses"] * np.array([1e-3] * 3 + [1.0] * 3), q[0] + 0.02)
    np.testing.assert_allclose(np.radians(read_q(out)), expected.q_command, atol=1e-9)
    ns = urscript_subset.load(script.read_text())
    ns["labcal_filtered"]()
    moves = [m[1] for m in ns["stats"].messages if m[0] == "movej"]
    np.testing.assert_allclose(moves, expected.q_command, atol=1e-9)


def test_joints_in_degrees_read_as_radians_get_the_hint(setup, tmp_path):
    root, q = setup["root"], setup["q"]
    r = run(root / "joints.csv", "--kind", "joints", "--calibration", root / "ur10.json", "--out", tmp_path / "o.csv")
    assert r.exit_code == 2
    assert "line 2: row 1: joint" in r.stderr and "pass --angle-unit deg" in r.stderr, r.stderr
    seed = ",".join(repr(float(v)) for v in np.degrees(q[0]))  # a seed in degrees, the flag forgotten
    r = run(root / "poses.csv", "--calibration", root / "ur10.json", "--length-unit", "mm", "--seed-joints", seed,
            "--out", tmp_path / "o.csv")  # fmt: skip
    assert r.exit_code == 2 and "--seed-joints: joint" in r.stderr and "pass --angle-unit deg" in r.stderr, r.stderr


def test_a_near_singular_row_is_named_singular_with_its_line(setup, tmp_path):
    root = setup["root"]
    q = np.array([[0.3, -1.2, 1.4, -1.6, -1.5, 0.4], [0.3, -1.2, 1e-5, -1.6, -1.5, 0.4]])
    (tmp_path / "p.csv").write_text(joints_text(q).replace("\n", "\n \n", 1))  # a blank line: row 2 is line 4
    r = run(tmp_path / "p.csv", "--kind", "joints", "--calibration", root / "ur10.json", "--out", tmp_path / "o.csv")
    assert r.exit_code == 2
    assert f"{tmp_path / 'p.csv'} line 4: row 2: singular: " in r.stderr and "q3 = 1e-05" in r.stderr, r.stderr
    assert "changes configuration branch" not in r.stderr
