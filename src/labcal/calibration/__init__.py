"""Calibration: observations, metrics, local-POE identification, the paper's equivalent robot + ANN, the hybrid.

The public API::

    fit(obs, nominal, method="auto", seed=0) -> FitResult      # every method on every row, CV choice, warnings
    fit_local_poe(obs, nominal) -> (CalibratedRobot, info)     # model-based (eq. 11)
    register(obs, nominal) -> (CalibratedRobot, info)          # the registered nominal ("before")
    fit_ann(obs, base, seed=0) -> (CalibratedRobot, info)      # the paper's method (imports torch lazily)
    fit_hybrid(obs, nominal, seed=0) -> (CalibratedRobot, info)

Importing this package does not import torch: the network's fitting imports it when it runs.
"""

from labcal.calibration.ann import fit_ann
from labcal.calibration.fit import METHODS, FitResult, fit, fit_hybrid
from labcal.calibration.local_poe import IdentificationError, expected_rank, fit_local_poe, register
from labcal.calibration.metrics import prediction_errors, reduction, split_table, summarize, validation_error
from labcal.calibration.observations import ObservationError, Observations, rigid_fit

__all__ = [
    "METHODS",
    "FitResult",
    "IdentificationError",
    "ObservationError",
    "Observations",
    "expected_rank",
    "fit",
    "fit_ann",
    "fit_hybrid",
    "fit_local_poe",
    "prediction_errors",
    "reduction",
    "register",
    "rigid_fit",
    "split_table",
    "summarize",
    "validation_error",
]
