"""The paper's ANN method: training, export to the numpy runtime, determinism, learnability, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.calibration.ann import NetworkDataError, default_hidden, fit_ann, torch_predict
from labcal.calibration.observations import Observations
from labcal.compensator import CalibratedRobot
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

TARGETS = np.array([[0.1, 0.0, 0.0], [0.0, 0.15, 0.0], [0.0, 0.0, 0.2]])
# A region of the UR10 away from the wrist (q5) and elbow (q3) singularities.
LO = np.array([-1.5, -2.5, 0.5, -1.5, 0.5, -1.5])
HI = np.array([1.5, -0.5, 2.5, 1.5, 2.6, 1.5])


def smooth_rho(q):
    """A learnable joint-motion-error field δρ(q), (k, 6) rad."""
    return 1e-3 * np.stack(
        [np.sin(q[:, 0]), np.cos(q[:, 1]), 0.5 * q[:, 2], np.sin(q[:, 1] + q[:, 2]), 0.3 + 0 * q[:, 0], q[:, 3] ** 2],
        axis=1,
    )


def injected(k_train=100, k_val=50, k_test=150, seed=0):
    """UR10 observations whose pose errors are exactly the equivalent robot driven by smooth_rho."""
    model = load("ur10").model
    base = CalibratedRobot(nominal=model, model=model)
    rng = np.random.default_rng(seed)
    k = k_train + k_val + k_test
    q = rng.uniform(LO, HI, size=(k, 6))
    T = se3.exp_se3(np.einsum("kab,kb->ka", base.equivalent_jacobian(q), smooth_rho(q))) @ model.fk(q)
    pts = np.einsum("kab,mb->kma", T[:, :3, :3], TARGETS) + T[:, None, :3, 3]
    split = np.array(["train"] * k_train + ["val"] * k_val + ["test"] * k_test, dtype=object)
    return base, Observations(q, pts, TARGETS, split=split)


@pytest.fixture(scope="module")
def data():
    return injected()


@pytest.fixture(scope="module")
def fitted(data):
    base, obs = data
    return fit_ann(obs, base, seed=0, restarts=2)


def test_learns_a_smooth_joint_error_field_on_held_out_configurations(data, fitted):
    base, obs = data
    robot, info = fitted
    test = obs.where("test")
    pred, true = robot.joint_motion_errors(test.q), smooth_rho(test.q)
    rel = np.sqrt(np.mean((pred - true) ** 2)) / np.sqrt(np.mean(true**2))
    assert rel < 0.2, rel
    # The learned robot predicts held-out poses far better than the base robot.
    T_meas = test.measured_poses()
    before = se3.pose_distance(T_meas, base.predict_pose(test.q, tcp=base.measurement_tool))[0]
    after = se3.pose_distance(T_meas, robot.predict_pose(test.q, tcp=robot.measurement_tool))[0]
    assert np.mean(after) < 0.3 * np.mean(before)
    assert robot.method == "ann" and robot.model is base.model
    # the ranges of every row the network was given (train + early-stopping rows), not only the rows it trained on
    given = obs.subset(obs.split != "test").q
    np.testing.assert_array_equal(robot.joint_ranges, np.stack([given.min(axis=0), given.max(axis=0)], axis=1))
    assert info["hidden"] == [default_hidden(6)] == [6]
    assert info["chosen_restart"] == int(np.argmin(info["restart_val_losses"]))


def test_training_curve_and_stopping_point(fitted):
    _, info = fitted
    val = np.array(info["curve"]["val"])
    assert len(val) == len(info["curve"]["train"]) == info["iterations"] + 1
    assert info["stopped_at"] == int(np.argmin(val))
    assert info["val_loss"] == val[info["stopped_at"]] < val[0]


def test_exported_network_equals_the_torch_model(data, fitted):
    base, obs = data
    robot, info = fitted
    assert info["export_max_abs_diff"] <= 1e-12
    q = obs.q[:20]
    np.testing.assert_allclose(robot.network(q, base.model), torch_predict(robot.network, q, base.model), atol=1e-12)


def test_same_seed_is_bit_identical_and_another_seed_differs(data, fitted):
    base, obs = data
    robot, _ = fitted
    again, _ = fit_ann(obs, base, seed=0, restarts=2)
    for a, b in zip(
        robot.network.weights + robot.network.biases, again.network.weights + again.network.biases, strict=True
    ):
        assert np.array_equal(a, b)
    other, _ = fit_ann(obs, base, seed=1, restarts=1, max_iter=3)
    assert not np.array_equal(robot.network.weights[0], other.network.weights[0])


@pytest.mark.parametrize(
    "options",
    [
        dict(trainer="adam", max_iter=300, patience=50),
        dict(trainer="gd", max_iter=300, patience=50),
        dict(loss="task", max_iter=20),
        dict(features=("sincos", "gravity"), hidden=(5, 4), weight_decay=1e-4, max_iter=20),
        dict(features=("q", "harmonics:2"), max_iter=20),  # every name the feature registry (the runtime) knows
    ],
)
def test_every_trainer_and_option_lowers_the_validation_loss(data, options):
    base, obs = data
    robot, info = fit_ann(obs, base, seed=0, restarts=1, **options)
    assert info["val_loss"] < info["curve"]["val"][0]
    assert robot.network.hidden == tuple(info["hidden"])
    q = obs.q[:5]
    np.testing.assert_allclose(robot.network(q, base.model), torch_predict(robot.network, q, base.model), atol=1e-12)


def test_too_many_weights_are_warned_about(data):
    base, obs = data
    small = obs.subset(np.r_[0:10, 100:105])
    _, info = fit_ann(small, base, seed=0, restarts=1, hidden=20, max_iter=2)
    assert any("over-fitting" in w for w in info["warnings"])


def test_without_val_rows_early_stopping_uses_an_inner_split_of_the_training_rows(data):
    base, obs = data
    train = obs.subset(obs.split == "train")
    _, info = fit_ann(train, base, seed=0, restarts=1, max_iter=5)
    assert "inner split" in info["early_stopping"]
    assert info["train_rows"] + info["val_rows"] == train.k and info["val_rows"] == round(0.25 * train.k)
    _, with_val = fit_ann(obs, base, seed=0, restarts=1, max_iter=5)
    assert with_val["early_stopping"] == "the 'val' rows" and with_val["val_rows"] == int(np.sum(obs.split == "val"))
    # unassigned rows are training rows
    _, unsplit = fit_ann(Observations(train.q, train.points, train.targets), base, seed=0, restarts=1, max_iter=5)
    assert unsplit["train_rows"] == info["train_rows"]


def test_max_rows_caps_the_training_rows(data):
    base, obs = data
    _, info = fit_ann(obs, base, seed=0, restarts=1, max_iter=3, max_rows=40)
    assert info["train_rows"] == 40 and info["subsampled_from"] == int(np.sum(obs.split == "train"))


def test_analytic_jacobian_equals_forward_mode_autodiff():
    import torch

    from labcal.calibration import ann

    rng = np.random.default_rng(0)
    shapes = ann._layer_shapes(6, (5,))
    theta = torch.as_tensor(ann._init_params(shapes, 0, 0) * 30)
    x, y, w = rng.normal(size=(15, 6)), rng.normal(size=(15, 6)), rng.uniform(0.5, 1.0, 15)
    A, b = rng.normal(size=(15, 9, 6)), rng.normal(size=(15, 9))
    for prob in (ann._Problem(torch, x, y, w), ann._Problem(torch, x, None, w, A, b)):
        auto = torch.func.jacfwd(lambda t, prob=prob: prob.residual(t, shapes))(theta)
        np.testing.assert_allclose(prob.jacobian(theta, shapes).numpy(), auto.numpy(), atol=1e-14)


def test_too_few_rows_after_the_condition_filter_names_the_singular_joint():
    spec = load("ur10")
    base = CalibratedRobot(spec.model, spec.model)
    rng = np.random.default_rng(3)
    q = rng.uniform(spec.model.limits[:, 0], spec.model.limits[:, 1], size=(30, 6))
    q[:25, 4] = rng.normal(0.0, 1e-4, 25)  # a wrist at q5 ≈ 0: joints 4 and 6 align
    obs = Observations(q, simulate(spec, ErrorSpec.paper(), seed=3).measure(q, TARGETS, rng), TARGETS)
    with pytest.raises(NetworkDataError, match=r"joint 5 near a singular value \(q5 ≈ .*joints 4, 6") as err:
        fit_ann(obs, base, seed=0, restarts=1)
    assert err.value.causes[0]["joint"] == 5 and err.value.causes[0]["rows"] >= 25


def test_clear_errors(data):
    base, obs = data
    with pytest.raises(ValueError, match="joint values per row"):
        fit_ann(Observations(obs.q[:, :4], obs.points, obs.targets, split=obs.split), base)
    with pytest.raises(ValueError, match="trainer"):
        fit_ann(obs, base, trainer="newton")
    with pytest.raises(ValueError, match="features"):
        fit_ann(obs, base, features=("cos",))
    with pytest.raises(ValueError, match="hidden"):
        fit_ann(obs, base, hidden=0)
    robot, _ = fit_ann(obs, base, seed=0, restarts=1, max_iter=1)
    with pytest.raises(ValueError, match="already has a network"):
        fit_ann(obs, robot)
