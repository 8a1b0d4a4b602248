"""The workflows behind the commands, as plain functions (usable from Python; the command modules only parse).

Every function takes an opened :class:`~labcal.datasets.SessionStore` and returns data; nothing here prints.
Errors the user can fix are raised as :class:`UserError` (or the library's ValueError subclasses) with a message
that names the bad input.

Submodules: ``common`` (robot model, pooled observations), ``fitting``, ``exporting``, ``sessions``, ``imports``;
the store (``open_store``) and ``UserError`` are :mod:`labcal.cli.common`'s. New code imports from the submodule;
the names below are kept for existing callers.
"""

from labcal.cli.common import UserError, open_store
from labcal.cli.ops.common import load_observations, robot_for, split_ref
from labcal.cli.ops.exporting import export_fit
from labcal.cli.ops.fitting import BEFORE_FILE, ROBOT_FILE, FitOutcome, StoredFit, load_stored_fit, run_fit, slim_info
from labcal.cli.ops.imports import import_session
from labcal.cli.ops.sessions import (
    PLANNERS,
    ROBOT_DRIVERS,
    SIM_ERRORS,
    TRACKER_DRIVERS,
    new_session,
    plan_configurations,
    resume_session,
    sim_actual,
)

__all__ = [
    "BEFORE_FILE",
    "PLANNERS",
    "ROBOT_DRIVERS",
    "ROBOT_FILE",
    "SIM_ERRORS",
    "TRACKER_DRIVERS",
    "FitOutcome",
    "StoredFit",
    "UserError",
    "export_fit",
    "import_session",
    "load_observations",
    "load_stored_fit",
    "new_session",
    "open_store",
    "plan_configurations",
    "resume_session",
    "robot_for",
    "run_fit",
    "sim_actual",
    "slim_info",
    "split_ref",
]
