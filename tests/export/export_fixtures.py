"""Calibrated robots and configurations for the export tests (built here, so these tests do not depend on the
layout of other test folders)."""

from __future__ import annotations

import itertools

import numpy as np

from labcal.compensator import CalibratedRobot, Network, input_features
from labcal.kinematics.metric import scaled_condition
from labcal.robots import load


def make_network(model, features, hidden=(8,), seed=0, out=0.5e-3) -> Network:
    """A random network with the given hidden layer sizes: outputs of about ``out`` rad."""
    rng = np.random.default_rng(seed)
    f = input_features(np.zeros((1, model.n)), tuple(features), model).shape[1]
    sizes = [f, *hidden, 6]
    weights = tuple(rng.normal(size=(b, a)) / np.sqrt(a) for a, b in itertools.pairwise(sizes))
    biases = tuple(rng.normal(size=b) * 0.1 for b in sizes[1:])
    return Network(
        features=tuple(features),
        weights=weights,
        biases=biases,
        in_mean=rng.normal(size=f) * 0.1,
        in_scale=rng.uniform(0.5, 2.0, size=f),
        out_mean=rng.normal(size=6) * 1e-4,
        out_scale=np.full(6, out),
    )


def hybrid(
    robot="ur10", features=("q", "sincos", "sincos2", "gravity"), seed=0, odd_twists=False, hidden=(8,), pitch=False
):
    """A hybrid calibration of a built-in robot: frames perturbed by ~0.5 mm / mrad plus a random network
    (features None: local POE only); odd_twists: joint axes slightly off z and off the frame origin (the
    exporters' general joint path); pitch: those twists also get a screw pitch."""
    nominal = load(robot).model
    rng = np.random.default_rng(seed)
    model = nominal.perturbed(rng.normal(size=(nominal.n + 1, 6)) * 0.5e-3)
    if odd_twists:
        tw = model.twists.copy()
        for j, t in enumerate(model.joint_types):
            if t == "revolute":
                w = tw[j, 3:] + rng.normal(size=3) * 2e-3
                w /= np.linalg.norm(w)
                v = rng.normal(size=3) * 2e-3
                tw[j] = np.concatenate([v if pitch else v - (v @ w) * w, w])
            else:
                d = tw[j, :3] + rng.normal(size=3) * 2e-3
                tw[j, :3] = d / np.linalg.norm(d)
        model = model.replace(twists=tw)
    if features is None:
        return CalibratedRobot(nominal, model, method="local-poe")
    net = make_network(model, features, hidden=hidden, seed=seed)
    return CalibratedRobot(nominal, model, net, method="hybrid")


def sample(robot: CalibratedRobot, k: int, seed: int, max_cond: float = 100.0) -> np.ndarray:
    """k configurations inside the robot's ranges (and ±π) whose scaled Jacobian condition is below max_cond."""
    rng = np.random.default_rng(seed)
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    lo, hi = np.maximum(lo, -np.pi), np.minimum(hi, np.pi)
    q = lo + (hi - lo) * rng.uniform(size=(20 * k, robot.n))
    J = robot.model.equivalent_jacobian(q, length_scale=robot.length_scale)
    cond = scaled_condition(J, robot.length_scale, robot.model.joint_types)
    return q[cond < max_cond][:k]
