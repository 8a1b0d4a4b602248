"""Shared CLI pieces: the --store option and the store it opens (``open_store``), ``UserError`` and its handling
(stderr, exit 2, no traceback; Ctrl-C exit 130), the option choices (typing.Literal: typer checks them and completes
them in the shell), JSON output (``plain``, ``print_json``), tables, and the fit warnings every command shows the
same way. ``labcal.cli.ops`` uses the same ``UserError``, ``open_store`` and ``plain``: one definition each.

Light on purpose: every command module imports this one, and `labcal --help` imports every command module. rich is
imported when the first line is printed through ``out`` / ``err`` or a table is built, so printing JSON needs none
of it.
"""

from __future__ import annotations

import functools
import json
import math
import os
import sys
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import typer

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

STORE_HELP = "Session store folder (default: $LABCAL_STORE, else ./sessions)."
StoreOption = typer.Option(None, "--store", help=STORE_HELP, show_default=False)
INTERRUPTED = 130  # exit code after Ctrl-C


TERMINATED_BY: list[int] = []  # the SIGTERM / SIGHUP labcal.cli.app.main turned into a KeyboardInterrupt, if any


def interruption(e: KeyboardInterrupt) -> tuple[str, int]:
    """(what to print, exit code) for an interrupt: Ctrl-C, or a SIGTERM / SIGHUP that :func:`labcal.cli.app.main`
    turned into a KeyboardInterrupt carrying the signal (the shell convention: 128 + the signal's number)."""
    if e.args and isinstance(e.args[0], int) and e.args[0] > 0:
        import signal

        return f"terminated ({signal.Signals(e.args[0]).name})", 128 + e.args[0]
    return "interrupted (Ctrl-C)", INTERRUPTED


VERIFY_FAILED = 1  # verification found damage, a recording failed or paused
USAGE_ERROR = 2  # bad option, bad input file, missing store …

# Option choices. typer turns a Literal annotation into a checked choice (a bad value: one line naming the allowed
# ones, exit 2) and into shell-completion candidates. They repeat tuples of the library (calibration.fit.METHODS,
# export.FORMATS, cli.ops.sessions.ROBOT_DRIVERS …) so that `labcal --help` need not import it;
# tests/cli/test_scripting.py fails when the two drift apart.
Method = Literal["nominal", "local-poe", "ann", "hybrid", "auto"]
ExportFormat = Literal["json", "npz", "urscript", "urscript-program", "urdf", "ur-kinematics"]
UnknownDynamics = Literal["zero", "refuse"]
RobotDriver = Literal["sim", "ur"]
TrackerDriver = Literal["sim", "serial"]
Planner = Literal["random", "optimal"]
SimErrors = Literal["paper", "default", "none"]
ProgramKind = Literal["poses", "joints"]
LengthUnit = Literal["m", "mm"]
AngleUnit = Literal["rad", "deg"]


class _FirstUseConsole:
    """A rich Console made when it first prints (or is asked anything): the commands that print JSON only, and the
    help, never import rich.console through it."""

    def __init__(self, stderr: bool) -> None:
        self._stderr = stderr
        self._console: Console | None = None

    def __getattr__(self, name: str):
        if self._console is None:
            from rich.console import Console

            # Piped output (files, CI logs, tests) gets room for the full metrics table instead of 80 columns, unless
            # COLUMNS says how wide the reader is (rich reads it when width is None). stderr keeps rich's width.
            wide = self._stderr or sys.stdout.isatty() or os.environ.get("COLUMNS", "").strip().isdigit()
            # No markup: labcal prints text as it is (a "[/x]" in a path or a message is not a closing tag).
            self._console = Console(
                stderr=self._stderr, soft_wrap=True, markup=False, highlight=False, width=None if wide else 200
            )
        return getattr(self._console, name)


out = _FirstUseConsole(stderr=False)
err = _FirstUseConsole(stderr=True)


def user_errors(fn):
    """Turn the errors a user can fix into `error: …` on stderr and exit code 2, without a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from labcal.datasets import DatasetError

        try:
            return fn(*args, **kwargs)
        except typer.Exit:
            raise
        except KeyboardInterrupt as e:
            # The shell convention for SIGINT (128 + 2): scripts must not mistake an interrupted run for a
            # successful one. Whatever was recorded is already on disk (the journal is fsynced per measurement).
            message, code = interruption(e)
            err.print(message)
            raise typer.Exit(code) from None
        except (ValueError, DatasetError, OSError, KeyError, RuntimeError) as e:
            # OSError covers more than missing / forbidden files: a full disk or a read-only file system met
            # mid-write is a one-line error too, not a traceback.
            msg = f"missing field {e}" if isinstance(e, KeyError) else str(e)
            if isinstance(e, OSError) and e.strerror and msg.startswith("[Errno"):  # not a message of labcal's own
                msg = f"{e.strerror}: {e.filename}" if e.filename else e.strerror
            err.print(f"error: {msg}")
            raise typer.Exit(USAGE_ERROR) from None

    return wrapper


def session_unit(session: dict) -> str | None:
    """The robot unit a session records (its ``metadata["unit"]``), None for a session recorded without one."""
    unit = (session.get("metadata") or {}).get("unit")
    return None if unit in (None, "") else str(unit)


def complete_robot(incomplete: str) -> list[str]:
    """Shell completion of --robot: the built-in models starting with what was typed (none: the shell completes a
    file name, for a robot TOML/URDF)."""
    from labcal.robots import BUILTINS

    return [name for name in BUILTINS if name.startswith(incomplete)]


class UserError(ValueError):
    """A problem with the command's input that the user can fix (the message says what): :func:`user_errors` prints
    it as one `error: …` line, exit 2. The one definition: ``labcal.cli.ops`` raises this class too."""


STORE_HINT = "set --store or LABCAL_STORE; `labcal session new` or `labcal session import` creates a store"
RETRY_HINT = "set --store or LABCAL_STORE"  # a store that cannot be made or written: only another one helps


def open_store(path: Path | str | None, *, create: bool | None = None, write: bool = False):
    """The session store (a :class:`labcal.datasets.SessionStore`) at ``path``, else
    :func:`labcal.datasets.store.default_root` ($LABCAL_STORE, else ./sessions), checked before any work is done.

    - ``create=False`` (read commands): the folder must exist, else UserError "no session store at PATH (…)". Only
      `session new` and `session import` create a store: every other command refuses a missing one with one line
      naming the path (exit 2), instead of reporting "no session X" in a store that is not there, or writing a fit
      into a folder a typo created;
    - ``create=None`` (callers that do not say; kept for old callers): no existence check here; a command that
      names a session still gets that one-line error from the store itself (``SessionStore.require_root``);
    - ``write=True`` (commands that add a fit, an export record, a version …): it must exist and accept a new
      file, so a read-only store fails here rather than after minutes of fitting;
    - ``create=True`` (commands that create sessions): it may be missing and is then created; it must accept a new
      file.
    """
    from labcal.datasets.store import SessionStore, default_root  # no pandas: tables are read when a version loads

    root = Path(path) if path is not None else default_root()
    if root.exists() and not root.is_dir():
        raise UserError(f"the session store {root} is not a folder ({STORE_HINT})")
    if not root.exists():
        if create is None:
            return SessionStore(root)
        if not create:
            raise UserError(f"no session store at {root} ({STORE_HINT})")
        try:
            root.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise UserError(f"cannot create the session store {root}: {e.strerror or e} ({RETRY_HINT})") from None
    if create or write:
        _check_writable(root)
    return SessionStore(root)


def _check_writable(root: Path) -> None:
    """Create and remove a hidden probe file: the only test that also catches read-only mounts and root squash."""
    probe = root / f".labcal-write-probe-{uuid.uuid4().hex[:12]}"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        probe.unlink()
    except OSError as e:
        raise UserError(f"the session store {root} is not writable: {e.strerror or e} ({RETRY_HINT})") from None


def plain(obj, depth: int = 0):
    """JSON types only: mappings → dicts (str keys), sequences and arrays → lists, numpy scalars → Python numbers,
    NaN / ±inf → None (JSON has no NaN), anything else → its str. numpy is never imported here."""
    if depth > 32:
        return None
    if obj is None or isinstance(obj, bool | int | str):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): plain(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v, depth + 1) for v in obj]
    if hasattr(obj, "tolist"):  # numpy arrays and scalars
        return plain(obj.tolist(), depth + 1)
    return str(obj)  # paths too


def print_json(schema: str, doc: dict) -> None:
    """Write ONE JSON document to stdout: ``{"schema": "labcal.<command>/1", …}``, keys sorted (a stable order to
    diff), numbers in SI units (the key names say which), NaN as null. Everything else a command says goes to
    stderr when --json is given, so `labcal … --json | jq` always parses. See docs/cli-json.md."""
    body = plain({**doc, "schema": schema})
    sys.stdout.write(json.dumps(body, indent=1, sort_keys=True, allow_nan=False, ensure_ascii=False) + "\n")
    sys.stdout.flush()


def metrics_doc(metrics: dict | None) -> dict | None:
    """A split table (``labcal.calibration.metrics.split_table``) for JSON, with the unit in every key: pose stats
    ``pos_mean`` → ``pos_mean_m``, ``ori_mean`` → ``ori_mean_rad``; point stats ``mean`` → ``mean_m`` (per target
    too); ``count`` and ``primary`` unchanged. The stored fit.json keeps the old keys; this is the CLI's view."""
    if metrics is None:
        return None

    def stats(d: dict) -> dict:
        out: dict = {}
        for k, v in (d or {}).items():
            if k == "per_target":
                out[k] = [stats(p) for p in v or []]
            elif k == "count":
                out[k] = None if v is None else int(v)
            else:  # orientation stats (ori_*) in rad, every other one (pos_*, point stats) in m
                out[f"{k}_{'rad' if k.startswith('ori_') else 'm'}"] = v
        return out

    def entry(key: str, value):
        if key in ("before", "after"):
            return stats(value)
        return {w: stats(v) for w, v in (value or {}).items()} if key == "points" else value

    return {
        split: {key: entry(key, value) for key, value in block.items()} if isinstance(block, dict) else block
        for split, block in metrics.items()
    }


def mm(x) -> str:
    return "—" if x is None else f"{x * 1e3:.4f}"


def deg(x) -> str:
    return "—" if x is None else f"{x * 180 / 3.141592653589793:.4f}"


def table(columns, rows, title: str | None = None, *, right: tuple[int, ...] = ()) -> Table:
    """A rich table with its title on the left: one column per name (left-aligned, the indices in ``right`` right-
    aligned) and the rows as given (text cells)."""
    from rich.table import Table

    t = Table(title=title, title_justify="left")
    for i, name in enumerate(columns):
        t.add_column(name, justify="right" if i in right else "left")
    for row in rows:
        t.add_row(*row)
    return t


def _number_table(title: str | None, head: list[str], numbers: list[str], rows: list[list[str]]) -> Table:
    """A table whose number columns never shrink below their widest cell: at 80 columns a narrow terminal wraps the
    headers, never the numbers (rich's default cut them to ``2.…``)."""
    from rich.table import Table

    t = Table(title=title, title_justify="left", show_edge=False)
    for name in head:
        t.add_column(name, no_wrap=True)
    for j, name in enumerate(numbers, start=len(head)):
        widest = max((len(row[j]) for row in rows), default=1)
        t.add_column(name, justify="right", no_wrap=False, overflow="fold", min_width=widest)
    for row in rows:
        t.add_row(*row)
    return t


def print_metrics(metrics: dict, title: str, *, points_lead: str | None = None) -> None:
    """Rich tables of a split table, split × (before, after): mean / RMS / p95 / max of the tool position error (mm)
    and of the orientation error (deg), mean / p95 / max of the point error (mm), then that point error per target if
    there is one. Narrow tables (three for the pose errors, one per target) so that each fits an 80-column terminal
    whole. ``points_lead``: when there are point errors per target, print this line and those first."""
    from rich.console import Group

    from labcal.reports import POINT_STATS, POSE_STATS, split_rows, target_rows

    pos, ori, points = [], [], []
    for lead, n, when, *cells in split_rows(metrics, mm, deg):
        pos.append([lead, n, when, *cells[0]])
        ori.append([lead, when, *cells[1]])
        points.append([lead, when, *cells[2]])
    tables = [
        Group(
            _number_table(title, ["split", "n", ""], [f"pos {k} mm" for k in POSE_STATS], pos),
            _number_table(None, ["split", ""], [f"ori {k} °" for k in POSE_STATS], ori),
            _number_table(None, ["split", ""], [f"point {k} mm" for k in POINT_STATS], points),
        )
    ]
    rows, none = target_rows(metrics, mm), [mm(None)] * len(POINT_STATS)
    if rows:
        tables.append(Group(*[
            _number_table("per-target point error (mm): mean / p95 / max" if i == 0 else None, ["split", ""],
                          [f"t{i + 1} {k}" for k in POINT_STATS],
                          [[lead, when, *(per[i] if i < len(per) else none)] for lead, when, per in rows])
            for i in range(len(rows[1][2]))  # the targets of the first split's "after" row
        ]))  # fmt: skip
        if points_lead is not None:
            out.print(points_lead)
            tables.reverse()
    for table in tables:
        out.print(table)


def print_gates(gates: dict | None, *, what: str = "this fit", footer: bool = True) -> None:
    """Every blocking warning on stderr as `WARNING [code] message`, then the notes; nothing when clean."""
    gates = gates or {}
    warnings = gates.get("warnings") or []
    for w in warnings:
        err.print(f"WARNING [{w.get('code')}] {w.get('message')}", style="bold yellow")
    for n in gates.get("notes") or []:
        err.print(f"note: {n}")
    if warnings and footer:
        err.print(
            f"{what} has {len(warnings)} warning(s): `labcal export` refuses it unless --force is given",
            style="bold yellow",
        )
