"""Measurement sessions: configuration planning, plans as data, and the runner that records them.

Sessions talk to the driver *ports* (:mod:`labcal.drivers.base`) only; the CLI picks concrete drivers.
"""

from labcal.sessions.planning import (
    CRITERIA,
    DEFAULT_MAX_CONDITION,
    PlanningError,
    exchange_i_optimal,
    greedy_d_optimal,
    identifiable_basis,
    identification_jacobian,
    joint_ranges,
    length_scaled_condition,
    optimal_configurations,
    random_configurations,
)
from labcal.sessions.plans import Measure, Move, Plan, PlanError, PoseStep, Settle, make_plan
from labcal.sessions.runner import (
    Progress,
    RetryPolicy,
    RunOptions,
    RunSummary,
    SessionError,
    Validation,
    check_measurement,
    resume,
    run,
)

__all__ = [
    "CRITERIA",
    "DEFAULT_MAX_CONDITION",
    "Measure",
    "Move",
    "Plan",
    "PlanError",
    "PlanningError",
    "PoseStep",
    "Progress",
    "RetryPolicy",
    "RunOptions",
    "RunSummary",
    "SessionError",
    "Settle",
    "Validation",
    "check_measurement",
    "exchange_i_optimal",
    "greedy_d_optimal",
    "identifiable_basis",
    "identification_jacobian",
    "joint_ranges",
    "length_scaled_condition",
    "make_plan",
    "optimal_configurations",
    "random_configurations",
    "resume",
    "run",
]
