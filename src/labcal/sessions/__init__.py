"""Measurement sessions: configuration planning, plans as data, and the runner that records them.

Sessions talk to the driver *ports* (:mod:`labcal.drivers.base`) only; the CLI picks concrete drivers.
"""

from labcal.sessions.planning import (
    CRITERIA,
    DEFAULT_MAX_CONDITION,
    LineOfSight,
    Observability,
    PlanningError,
    exchange_i_optimal,
    greedy_d_optimal,
    identifiable_basis,
    identification_jacobian,
    joint_ranges,
    length_scaled_condition,
    observability,
    optimal_configurations,
    prediction_variance,
    random_configurations,
)
from labcal.sessions.plans import Measure, Move, Plan, PlanError, PoseStep, Settle, make_plan
from labcal.sessions.runner import (
    Progress,
    RetryPolicy,
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
    "LineOfSight",
    "Measure",
    "Move",
    "Observability",
    "Plan",
    "PlanError",
    "PlanningError",
    "PoseStep",
    "Progress",
    "RetryPolicy",
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
    "observability",
    "optimal_configurations",
    "prediction_variance",
    "random_configurations",
    "resume",
    "run",
]
