"""Measurement sessions: configuration planning, plans as data, and the runner that records them.

Sessions talk to the driver *ports* (:mod:`labcal.drivers.base`) only; the CLI picks concrete drivers. The package
names what a caller records a session with; the rest (plan commands, the planner's criteria and Jacobians) is
imported from :mod:`labcal.sessions.planning`, :mod:`labcal.sessions.plans` and :mod:`labcal.sessions.runner`.
"""

from labcal.sessions.planning import optimal_configurations, random_configurations
from labcal.sessions.plans import Plan, make_plan
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
    "Plan",
    "Progress",
    "RetryPolicy",
    "RunOptions",
    "RunSummary",
    "SessionError",
    "Validation",
    "check_measurement",
    "make_plan",
    "optimal_configurations",
    "random_configurations",
    "resume",
    "run",
]
