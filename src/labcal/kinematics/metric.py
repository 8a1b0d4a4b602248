"""The length-scaled metric: how labcal compares metres with radians.

A twist (v, ω) mixes metres and radians, and so do the columns of a Jacobian whose joints are revolute and
prismatic. labcal makes them comparable with one length L (metres per radian, by default the robot's reach,
:meth:`LocalPOEModel.reach`): a linear quantity is divided by L, so 1 rad of rotation counts as much as L metres
of translation. Three places need the same L:

- the rows of a twist, δy = (δv, δω): weights ``(1/L, 1/L, 1/L, 1, 1, 1)`` (:func:`twist_weights`);
- the columns of a joint Jacobian J_ρ (actuated joints, then virtual joints): ``L`` for a prismatic joint (its
  value is in metres), ``1`` for a revolute or virtual one (:func:`joint_weights`);
- frame parameters δζ_j = (v, ω) of a local-POE identification, expressed as lengths: weights
  ``(1, 1, 1, 1/L, 1/L, 1/L)`` per frame (:func:`parameter_weights`).

:func:`scaled_condition` is the condition number of ``diag(twist rows) · J · diag(joint columns)``: the number the
planner, the simulation and the compensator's golden configurations rank configurations by.

Example (a 2R arm scaled by its reach of 2 m)::

    >>> twist_weights(2.0)
    array([0.5, 0.5, 0.5, 1. , 1. , 1. ])
    >>> joint_weights(("revolute", "prismatic"), 2.0, size=3)
    array([1., 2., 1.])
    >>> J = np.diag([2.0, 2.0, 2.0, 1.0, 1.0, 1.0])[None]       # (k, 6, 6): one configuration
    >>> scaled_condition(J, 2.0)                                 # the scaled J is the identity
    array([1.])

This module imports numpy only.
"""

from __future__ import annotations

import numpy as np


def twist_weights(length_scale: float) -> np.ndarray:
    """(6,) row weights of a twist (v, ω) in the length-scaled metric: (1/L, 1/L, 1/L, 1, 1, 1)."""
    inv = 1.0 / float(length_scale)
    return np.array([inv, inv, inv, 1.0, 1.0, 1.0])


def joint_weights(joint_types, length_scale: float, size: int | None = None) -> np.ndarray:
    """(size,) column weights of a joint Jacobian: L for prismatic joints, 1 for revolute and virtual joints.

    joint_types: the n actuated joints' types; size: the number of columns (default n; 6 for an equivalent
    robot's J_ρ, whose columns past n are virtual joints).
    """
    types = tuple(joint_types)
    out = np.ones(len(types) if size is None else int(size))
    out[[j for j, t in enumerate(types) if t == "prismatic"]] = float(length_scale)
    return out


def parameter_weights(n_frames: int, length_scale: float) -> np.ndarray:
    """(6·n_frames,) weights turning frame parameters (v, ω) per frame into lengths: (1, 1, 1, 1/L, 1/L, 1/L)."""
    inv = 1.0 / float(length_scale)
    return np.tile([1.0, 1.0, 1.0, inv, inv, inv], int(n_frames))


def scaled_condition(J: np.ndarray, length_scale: float, joint_types=None) -> np.ndarray:
    """Condition numbers of ``diag(twist_weights) · J · diag(joint_weights)``: (k, 6, N) → (k,), or (6, N) → ().

    The 2-norm condition number σ_max / σ_min, infinite where J is rank deficient. joint_types: the actuated
    joints' types (None: every column revolute or virtual, weight 1).
    """
    J = np.asarray(J, dtype=float)
    scaled = twist_weights(length_scale)[:, None] * J
    if joint_types is not None:
        scaled = scaled * joint_weights(joint_types, length_scale, J.shape[-1])
    s = np.linalg.svd(scaled, compute_uv=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = s[..., 0] / s[..., -1]
    return np.where(s[..., -1] > 0, ratio, np.inf)
