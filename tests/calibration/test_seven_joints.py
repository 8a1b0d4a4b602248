"""The equivalent robot and its learned terms on a redundant (7-joint) arm: eq. (21) as a minimum-norm δρ ∈ R⁷,
the joint series and the network with seven outputs, hybrid and auto considering them, and their exports.

The arm is the Franka Emika Panda from its published modified-DH parameters (Franka Control Interface
documentation, "Robot and interface specifications": a, d, alpha per joint, flange d = 0.107 m, joint limits),
written as a robot file here so the tests need no built-in Panda file. The link masses are rough values of a few kg
(they only shape the simulated gravity deflection, which the simulator scales to its configured size).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from labcal.calibration import Observations, fit
from labcal.calibration.equivalent import equivalent_joints, joint_error_observations
from labcal.compensator import CalibratedRobot, Compensator, CompensatorFileError, field_checksums
from labcal.compensator import save as save_compensator
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate

PANDA_A = (0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088)
PANDA_D = (0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0)
PANDA_ALPHA = (0.0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2)
PANDA_LIMITS = (
    (-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698), (-2.8973, 2.8973),
    (-0.0175, 3.7525), (-2.8973, 2.8973),
)  # fmt: skip
PANDA_MASSES = (4.0, 4.0, 3.0, 3.0, 2.0, 1.5, 0.5)
TARGETS = np.array([[0.12, 0.0, 0.05], [-0.06, 0.15, 0.05], [-0.07, -0.11, 0.04]])
REFLECTOR = np.array([[0.03, 0.02, 0.06]])


def panda_file(folder) -> object:
    text = 'name = "panda-test"\nkinematics = "mdh"\n'
    for j in range(7):
        lo, hi = PANDA_LIMITS[j]
        text += (
            f"[[joints]]\nname = 'panda_joint{j + 1}'\ntype = 'revolute'\na = {PANDA_A[j]}\n"
            f"alpha = {PANDA_ALPHA[j]!r}\nd = {PANDA_D[j]}\ntheta = 0.0\nlimits = [{lo}, {hi}]\n"
            f"mass = {PANDA_MASSES[j]}\n"
        )
    path = folder / "panda-test.toml"
    path.write_text(text + "[tool]\nxyz = [0.0, 0.0, 0.107]\n")
    return path


@pytest.fixture(scope="module")
def panda(tmp_path_factory):
    return load(panda_file(tmp_path_factory.mktemp("panda")))


def sample(model, k, rng, shrink=1.0):
    """Configurations inside the limits (a fraction ``shrink`` of each range, about its middle)."""
    mid, half = model.limits.mean(axis=1), 0.5 * np.diff(model.limits, axis=1)[:, 0] * shrink
    return rng.uniform(mid - half, mid + half, size=(k, model.n))


def simulated(spec, errors, targets, *, k=300, held_out=100, seed=3, shrink=1.0):
    """Observations of a simulated arm: the last ``held_out`` rows labelled "test" (never fitted)."""
    actual = simulate(spec, errors, seed=seed)
    rng = np.random.default_rng(seed)
    q = sample(spec.model, k, rng, shrink)
    split = np.array([""] * (k - held_out) + ["test"] * held_out, dtype=object)
    return Observations(q, actual.measure(q, targets, rng), targets, split=split)


def held_out(result) -> float:
    return result.metrics["test"]["after"]["pos_mean"]


@pytest.fixture(scope="module")
def default_errors(panda):
    """Geometric, compliance and gear errors, three targets; local POE and hybrid fitted once for the module."""
    obs = simulated(panda, ErrorSpec.default(), TARGETS)
    return obs, fit(obs, panda.model, "local-poe"), fit(obs, panda.model, "hybrid")


def test_the_equivalent_robot_of_a_redundant_arm_has_one_error_per_joint():
    assert [equivalent_joints(n) for n in (4, 5, 6, 7, 8)] == [6, 6, 6, 7, 8]


@pytest.mark.parametrize("targets", [TARGETS, REFLECTOR], ids=["three-targets", "one-reflector"])
def test_eq21_on_a_redundant_arm_is_the_minimum_norm_joint_error(panda, targets):
    """A known small joint error δ of all seven joints: the observation is the part of δ the points see, with
    nothing along the self-motion (three targets: δ minus its null-space part; one point: minimum norm)."""
    model = panda.model
    base = CalibratedRobot(nominal=model, model=model)
    rng = np.random.default_rng(5)
    q = sample(model, 40, rng, shrink=0.8)
    delta = rng.normal(0.0, 1e-6, size=(40, 7))
    T = model.fk(q + delta)
    obs = Observations(q, np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3], targets)
    jeo = joint_error_observations(obs, base, max_condition=1e5, soft_condition=None)
    assert jeo.delta_rho.shape == (40, 7) and jeo.PJ.shape == (40, 3 * len(targets), 7)
    assert jeo.kept.sum() >= 35  # the self-motion does not make every row "singular"
    kept = jeo.kept
    J = model.joint_twists(q[kept])
    null = np.linalg.svd(J)[2][:, -1]  # (r, 7) the self-motion at each configuration (unit, revolute joints)
    # Nothing along the self-motion, whatever the true δ had there.
    assert np.max(np.abs(np.einsum("ki,ki->k", null, jeo.delta_rho[kept]))) < 1e-13
    if len(targets) == 3:
        seen = delta[kept] - np.einsum("ki,ki->k", null, delta[kept])[:, None] * null
        np.testing.assert_allclose(jeo.delta_rho[kept], seen, atol=1e-9)
    else:  # one point fixes three directions: δρ reproduces the point's move and lies in the row space of P J_ρ
        PJ = jeo.PJ[kept]
        np.testing.assert_allclose(np.einsum("kab,kb->ka", PJ, jeo.delta_rho[kept]), jeo.delta_p[kept], atol=1e-12)
        row_space = np.linalg.svd(PJ, full_matrices=False)[2]  # (r, 3, 7)
        inside = np.einsum("kij,ki->kj", row_space, np.einsum("kij,kj->ki", row_space, jeo.delta_rho[kept]))
        np.testing.assert_allclose(inside, jeo.delta_rho[kept], atol=1e-15)
        assert jeo.rank is not None and set(jeo.rank.tolist()) == {3}


def test_the_condition_filter_sees_a_redundant_arms_singularity_not_its_self_motion(panda):
    """The self-motion alone is no singularity (random configurations are kept); joints 1, 3 and 5 in one line
    (q2 = 0, the elbow stretched out, q4 = 0: just outside the Panda's range, whose end at -0.07 rad already drops
    about a third of such rows) leave even seven joints short of six directions: dropped, with that cause."""
    model = panda.model
    base = CalibratedRobot(nominal=model, model=model)
    q = sample(model, 100, np.random.default_rng(0), shrink=0.8)
    free = joint_error_observations(Observations(q, model.target_points(q, TARGETS), TARGETS), base)
    assert free.kept.mean() > 0.95
    q = q.copy()
    q[:, 1], q[:, 3] = 0.0, 0.0
    stuck = joint_error_observations(Observations(q, model.target_points(q, TARGETS), TARGETS), base)
    assert stuck.kept.mean() < 0.1
    cause = stuck.causes(base)[0]
    assert cause["joint"] == 2 and {1, 3} <= set(cause["lost"]) and cause["rows"] > 0.3 * len(q)


def test_hybrid_keeps_a_seven_output_learned_term_that_beats_local_poe_on_held_out_poses(panda, default_errors):
    obs, lp, hy = default_errors
    assert hy.chosen == "hybrid" and hy.info["kept"] in ("local-poe+series", "local-poe+ann")
    network = hy.robot.network
    assert network is not None and network.outputs == 7
    assert not [w for w in hy.warnings if w["code"] in ("worse-than-nominal", "overfit")]
    # cross-validation preferred it, and the held-out rows (never fitted, never used to choose) agree
    assert hy.info["val_error_hybrid"] < hy.info["val_error_local_poe"]
    assert held_out(hy) < 0.95 * held_out(lp)
    # the learned errors act on the seven joints: every joint's error varies over the data
    rho = hy.robot.joint_motion_errors(obs.q)
    assert rho.shape == (obs.k, 7) and np.all(np.std(rho, axis=0) > 0)


def test_hybrid_keeps_local_poe_when_the_errors_are_geometric(panda):
    obs = simulated(panda, ErrorSpec.paper(), TARGETS, k=150, held_out=50)
    hy = fit(obs, panda.model, "hybrid", stage2=("series",))
    assert hy.info["kept"] == "local-poe" and hy.robot.network is None
    assert hy.info["val_errors"]["series"] >= 0.98 * hy.info["val_error_local_poe"]


def test_the_papers_network_learns_seven_joint_errors_on_the_nominal(panda):
    """method "ann": eq. (21) observations of all seven joints train a 7-output network on the registered nominal."""
    obs = simulated(panda, ErrorSpec.default(), TARGETS, shrink=0.25)
    result = fit(obs, panda.model, "ann")
    assert result.chosen == "ann" and "no_network" not in result.info
    assert result.robot.network.outputs == 7 and result.info["hidden"] == [7]  # round(√(7 outputs · 7 inputs))
    assert result.info["observations"]["dropped"] < 0.1 * result.info["observations"]["count"]
    assert result.info["stopped_at"] > 0
    before = result.metrics["test"]["before"]["pos_mean"]
    assert held_out(result) < 0.6 * before


def test_auto_considers_the_learned_terms_of_a_redundant_arm(panda, default_errors):
    obs, lp, _ = default_errors
    lines: list[str] = []
    auto = fit(obs, panda.model, "auto", progress=lines.append)
    assert set(auto.info["cv_errors"]) == {"local-poe", "hybrid+series", "hybrid+ann", "ann"}
    assert all(np.isfinite(v) for v in auto.info["cv_errors"].values())
    assert not any("at most 6 joints" in line for line in lines + auto.notes)
    assert auto.chosen == "hybrid" and auto.robot.network is not None and auto.robot.network.outputs == 7
    assert held_out(auto) < 0.95 * held_out(lp)


def test_a_seven_joint_learned_term_survives_its_export_and_corrects_to_the_nominal_pose(
    panda, default_errors, tmp_path
):
    obs, _, hy = default_errors
    robot = hy.robot
    q = obs.q[obs.split == "test"]
    # away from singular configurations, where the redundant solver's damped steps need not reach the pose
    # (local POE alone misses them too: the solver's matter, not the learned term's)
    q = q[np.linalg.cond(robot.model.joint_twists(q)) < 100][:20]
    assert len(q) == 20
    for suffix in ("json", "npz"):
        comp = Compensator.load(save_compensator(robot, tmp_path / f"panda.{suffix}"))
        np.testing.assert_array_equal(comp.predict_pose(q, extrapolate=True), robot.predict_pose(q))
        q_cmd = comp.correct(q, extrapolate=True)
        miss = se3.log_se3(se3.inv(robot.predict_pose(q_cmd)) @ robot.nominal.fk(q))
        assert np.max(np.abs(miss)) < 1e-9
    # the correction includes the learned term: without it the commands would reach another pose
    geometric = CalibratedRobot(robot.nominal, robot.model, T_tracker_base=robot.T_tracker_base)
    moved, _ = se3.pose_distance(geometric.predict_pose(q_cmd), robot.nominal.fk(q))
    assert np.max(moved) > 1e-6


def test_a_seven_joint_file_whose_network_has_six_outputs_is_refused_by_name(panda, default_errors, tmp_path):
    path = save_compensator(default_errors[2].robot, tmp_path / "panda.json")
    data = json.loads(path.read_text())
    net = data["network"]
    net["weights"][-1], net["biases"][-1] = net["weights"][-1][:6], net["biases"][-1][:6]
    net["out_mean"], net["out_scale"] = net["out_mean"][:6], net["out_scale"][:6]
    data["checksums"] = field_checksums(data)  # consistently edited: the shape check, not the checksum, refuses it
    path.write_text(json.dumps(data))
    with pytest.raises(CompensatorFileError, match=r"network\.out_mean.*\(7,\)"):
        Compensator.load(path)
