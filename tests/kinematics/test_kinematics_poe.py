"""LocalPOEModel: forward kinematics against independent DH/MDH/POE products, immutability, validation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from kin_testutil import (
    assert_poses_close,
    dh_product,
    general_model,
    poe_product,
    random_model_rows,
    random_q,
    rot_x,
    shift,
)

from labcal.kinematics import se3
from labcal.kinematics.conversions import from_dh, from_mdh
from labcal.kinematics.poe import (
    PRISMATIC,
    REVOLUTE,
    LocalPOEModel,
    poe_fk,
    poe_joint_twists,
    poe_link_frames,
)
from labcal.robots import BUILTINS, load

# UR5e DH (Universal Robots' table) and the same arm written by hand as a modified-DH (Craig) table: regrouping
# Π Rz Tz Tx Rx as Π Rx(α_{j−1}) Tx(a_{j−1}) Rz Tz leaves Tx(a_6) Rx(α_6) = I as the tool, so both products agree.
HALF_PI = np.pi / 2
UR5E_DH = [
    {"a": 0.0, "alpha": HALF_PI, "d": 0.1625, "theta": 0.0},
    {"a": -0.425, "alpha": 0.0, "d": 0.0, "theta": 0.0},
    {"a": -0.3922, "alpha": 0.0, "d": 0.0, "theta": 0.0},
    {"a": 0.0, "alpha": HALF_PI, "d": 0.1333, "theta": 0.0},
    {"a": 0.0, "alpha": -HALF_PI, "d": 0.0997, "theta": 0.0},
    {"a": 0.0, "alpha": 0.0, "d": 0.0996, "theta": 0.0},
]
UR5E_MDH = [
    {"a": 0.0, "alpha": 0.0, "d": 0.1625, "theta": 0.0},
    {"a": 0.0, "alpha": HALF_PI, "d": 0.0, "theta": 0.0},
    {"a": -0.425, "alpha": 0.0, "d": 0.0, "theta": 0.0},
    {"a": -0.3922, "alpha": 0.0, "d": 0.1333, "theta": 0.0},
    {"a": 0.0, "alpha": HALF_PI, "d": 0.0997, "theta": 0.0},
    {"a": 0.0, "alpha": -HALF_PI, "d": 0.0996, "theta": 0.0},
]


# --------------------------------------------------------------------------------------------------------------
# forward kinematics


def test_ur5e_home_pose_matches_its_known_geometry():
    # At q = 0 a UR arm is stretched along −x: x = a2 + a3, y = −(d4 + d6), z = d1 − d5, tool z along base −y.
    T = load("ur5e").model.fk(np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [-0.425 - 0.3922, -(0.1333 + 0.0996), 0.1625 - 0.0997], atol=1e-15)
    np.testing.assert_allclose(T[:3, 2], [0.0, -1.0, 0.0], atol=1e-15)


@pytest.mark.parametrize("robot", ["ur5e", "ur10", "ur10e", "fanuc-m1000ia", "scara4"])
def test_builtin_dh_model_equals_the_textbook_dh_product(robot):
    import tomllib

    from labcal.robots import builtin_path

    data = tomllib.loads(builtin_path(robot).read_text())
    rows = data["joints"]
    tool = se3.pose(data["tool"]["xyz"], data["tool"]["rpy"])  # from_dh appends the tool after the last row
    model = load(robot).model
    q = random_q(model, 20, seed=1)
    for qi, Ti in zip(q, model.fk(q), strict=True):
        ref = dh_product(rows, qi) @ tool
        assert_poses_close(Ti, ref, atol=1e-14)


def test_random_dh_and_mdh_tables_with_prismatic_joints():
    rng = np.random.default_rng(2)
    for trial in range(10):
        rows = random_model_rows(rng, 6, prismatic={trial % 6, (trial + 3) % 6})
        tool = se3.exp_se3(rng.normal(size=6) * 0.3)
        q = rng.uniform(-3, 3, size=(8, 6))
        dh, mdh = from_dh(rows, tool), from_mdh(rows, tool)
        assert dh.joint_types == tuple(r["type"] for r in rows)
        for qi, T_dh, T_mdh in zip(q, dh.fk(q), mdh.fk(q), strict=True):
            assert_poses_close(T_dh, dh_product(rows, qi) @ tool, atol=1e-13)
            assert_poses_close(T_mdh, dh_product(rows, qi, modified=True) @ tool, atol=1e-13)


def test_hand_written_ur5e_mdh_table_equals_the_dh_model():
    dh, mdh = from_dh(UR5E_DH), from_mdh(UR5E_MDH)
    q = random_q(dh, 50, seed=3)
    for A, B in zip(dh.fk(q), mdh.fk(q), strict=True):
        assert_poses_close(A, B, atol=1e-14)
    # and with a constant base and tool: FK_mdh = X · FK_dh · Y for the moved frames
    X, Y = se3.exp_se3(np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])), rot_x(0.3) @ shift(0.01, 0.02, 0.15)
    moved = from_mdh(UR5E_MDH, Y).with_base(X)
    for A, B in zip(dh.fk(q), moved.fk(q), strict=True):
        assert_poses_close(X @ A @ Y, B, atol=1e-14)


def test_scara_prismatic_joint_moves_the_tool_down():
    model = load("scara4").model
    assert model.joint_types[2] == PRISMATIC
    q = np.array([0.3, -0.4, 0.0, 0.2])
    dz = model.fk(q + np.array([0, 0, 0.1, 0]))[:3, 3] - model.fk(q)[:3, 3]
    np.testing.assert_allclose(dz, [0, 0, -0.1], atol=1e-15)  # alpha_2 = π flips the quill to point down


def test_general_twists_match_the_matrix_exponential_product():
    model = general_model()
    assert not any(model._z_joint)
    q = np.random.default_rng(4).uniform(-2, 2, size=(10, model.n))
    for qi, T in zip(q, model.fk(q), strict=True):
        assert_poses_close(T, poe_product(model.frames, model.twists, qi), atol=1e-13)


def test_z_joint_fast_path_equals_the_general_exponential():
    for robot in BUILTINS:
        model = load(robot).model
        assert all(model._z_joint)
        q = random_q(model, 200, seed=5)
        ref = np.empty((len(q), 4, 4))
        for i, qi in enumerate(q):
            T = model.frames[0]
            for j in range(model.n):
                T = T @ se3.exp_se3(model.twists[j] * qi[j]) @ model.frames[j + 1]
            ref[i] = T
        np.testing.assert_allclose(model.fk(q), ref, rtol=0, atol=2e-15)


def test_batch_equals_single_and_shapes():
    for model in (load("ur10").model, load("scara4").model, general_model()):
        q = random_q(model, 7, seed=6)
        batch = model.fk(q)
        assert batch.shape == (7, 4, 4)
        np.testing.assert_array_equal(batch, np.array([model.fk(qi) for qi in q]))
        assert model.fk(q[0]).shape == (4, 4)
        T, J = model.fk_and_twists(q)
        np.testing.assert_array_equal(T, batch)
        assert J.shape == (7, 6, model.n)
        np.testing.assert_array_equal(model.joint_twists(q), J)
        np.testing.assert_array_equal(J[3], model.joint_twists(q[3])[0])
        assert model.link_frames(q).shape == (7, model.n + 1, 4, 4)
        np.testing.assert_array_equal(model.link_frames(q)[:, -1], batch)
        assert model.frame_jacobian(q).shape == (7, 6, 6 * (model.n + 1))
        assert model.equivalent_jacobian(q).shape == (7, 6, 6)
        with pytest.raises(ValueError, match=r"q must have shape"):
            model.fk(np.zeros(model.n + 1))
        with pytest.raises(ValueError, match=r"q must have shape"):
            model.fk(np.zeros((2, 2, model.n)))


def test_target_points():
    model = load("ur10").model
    q = random_q(model, 5, seed=7)
    targets = np.array([[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.05]])
    pts = model.target_points(q, targets)
    assert pts.shape == (5, 3, 3)
    T = model.fk(q)
    for i in range(5):
        for m in range(3):
            np.testing.assert_allclose(pts[i, m], (T[i] @ np.append(targets[m], 1.0))[:3], atol=1e-15)


# --------------------------------------------------------------------------------------------------------------
# immutability and semantics


def test_model_is_immutable_and_perturbed_returns_a_new_model():
    model = load("ur10").model
    for name in ("frames", "twists", "limits"):
        arr = getattr(model, name)
        assert not arr.flags.writeable
        with pytest.raises(ValueError):
            arr[0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        model.name = "other"
    frames_before = model.frames.copy()
    dz = np.random.default_rng(8).normal(size=(model.n + 1, 6)) * 1e-3
    new = model.perturbed(dz)
    assert new is not model
    np.testing.assert_array_equal(model.frames, frames_before)
    for j in range(model.n + 1):
        np.testing.assert_allclose(new.frames[j], model.frames[j] @ se3.exp_se3(dz[j]), atol=1e-15)
    np.testing.assert_array_equal(model.perturbed(dz.ravel()).frames, new.frames)
    assert not new.frames.flags.writeable


def test_model_copies_its_inputs():
    frames = np.array([np.eye(4)] * 3)
    frames[1, 0, 3] = 1.0
    model = LocalPOEModel.from_frames(frames, (REVOLUTE, REVOLUTE))
    frames[1, 0, 3] = 5.0
    assert model.frames[1, 0, 3] == 1.0


def test_defaults_of_from_frames():
    model = LocalPOEModel.from_frames(np.array([np.eye(4)] * 3), (REVOLUTE, PRISMATIC))
    np.testing.assert_array_equal(model.twists, [[0, 0, 0, 0, 0, 1], [0, 0, 1, 0, 0, 0]])
    np.testing.assert_array_equal(model.limits, [[-np.pi, np.pi], [-1, 1]])
    assert model.joint_names == ("joint1", "joint2")
    assert model.n == 2


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"frames": np.array([np.eye(4)] * 2)}, r"frames must have shape \(3, 4, 4\)"),
        ({"twists": np.zeros((2, 5))}, r"twists must have shape \(2, 6\)"),
        ({"limits": np.zeros((2, 3))}, r"limits must be \(2, 2\)"),
        ({"limits": np.array([[1.0, -1.0], [0, 1]])}, r"lo <= hi"),
        ({"twists": np.array([[0, 0, 0, 0, 0, 1.1], [0, 0, 0, 0, 0, 1]])}, r"joint 1: the twist's axis is not unit"),
        ({"joint_types": (REVOLUTE, "helical")}, r"revolute' or 'prismatic'.*helical"),
        ({"joint_names": ("a",)}, r"joint_names has 1 entries for 2 joints"),
        ({"frames": np.array([np.eye(4)] * 3) * 2}, r"homogeneous"),
        ({"frames": np.array([np.eye(4)] * 2 + [np.full((4, 4), np.nan)])}, r"homogeneous"),
    ],
)
def test_validation_errors(kwargs, message):
    fields = {
        "frames": np.array([np.eye(4)] * 3),
        "joint_types": (REVOLUTE, REVOLUTE),
        "twists": np.array([[0, 0, 0, 0, 0, 1.0]] * 2),
        "limits": np.array([[-1.0, 1.0]] * 2),
    }
    fields.update(kwargs)
    with pytest.raises(ValueError, match=message):
        LocalPOEModel(**fields)


def test_prismatic_twist_validation():
    frames = np.array([np.eye(4)] * 2)
    with pytest.raises(ValueError, match=r"joint 1: the twist's direction is not unit"):
        LocalPOEModel.from_frames(frames, (PRISMATIC,), [[0, 0, 2.0, 0, 0, 0]])
    with pytest.raises(ValueError, match=r"joint 1: a prismatic twist has no angular part"):
        LocalPOEModel.from_frames(frames, (PRISMATIC,), [[0, 0, 1.0, 0, 0.1, 0]])


def test_within_limits():
    model = load("scara4").model  # limits differ per joint, one prismatic
    lo, hi = model.limits[:, 0], model.limits[:, 1]
    mid = 0.5 * (lo + hi)
    q = np.array([mid, lo, hi, mid + np.array([0, 0, 0.3, 0]), mid - np.array([2.7, 0, 0, 0])])
    np.testing.assert_array_equal(model.within_limits(q), [True, True, True, False, False])
    np.testing.assert_array_equal(model.within_limits(q, margin=1e-6), [True, False, False, False, False])
    assert model.within_limits(mid).shape == (1,)


def test_with_tool_and_with_base():
    model = load("ur10").model
    rng = np.random.default_rng(9)
    T_flange_tool, T_world_base = se3.exp_se3(rng.normal(size=(2, 6)))
    q = random_q(model, 10, seed=10)
    tooled, based = model.with_tool(T_flange_tool), model.with_base(T_world_base)
    np.testing.assert_allclose(tooled.fk(q), model.fk(q) @ T_flange_tool, atol=1e-14)
    np.testing.assert_allclose(based.fk(q), T_world_base @ model.fk(q), atol=1e-14)
    # the twists of a robot with a moved base are the old ones carried by the adjoint of the base transform
    np.testing.assert_allclose(based.joint_twists(q), se3.adjoint(T_world_base) @ model.joint_twists(q), atol=1e-14)
    np.testing.assert_allclose(tooled.joint_twists(q), model.joint_twists(q), atol=1e-15)
    np.testing.assert_array_equal(model.frames, load("ur10").model.frames)  # original untouched


def test_replace_keeps_other_fields_and_validates():
    model = load("ur10").model
    renamed = model.replace(name="x")
    assert renamed.name == "x" and model.name == "ur10"
    np.testing.assert_array_equal(renamed.frames, model.frames)
    with pytest.raises(ValueError):
        model.replace(limits=np.zeros((5, 2)))


def test_the_definition_is_the_textbook_product_of_matrix_exponentials():
    for model in [load("ur10").model, general_model(), general_model(seed=3, n=4)]:
        for q in random_q(model, 5, seed=13):
            assert_poses_close(poe_fk(model.frames, model.twists, q), poe_product(model.frames, model.twists, q))


@pytest.mark.parametrize("k", [5, 300], ids=["few configurations", "a batch"])
def test_every_kernel_result_equals_the_product_of_exponentials(k):
    # Few configurations walk the chain with 4×4 matmuls, large batches batch-last (poe._SMALL_BATCH): both are
    # compared with the definition, not with each other.
    targets = np.array([[0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.3], [0.1, 0.1, 0.1]])
    for model in [load(r).model for r in BUILTINS] + [general_model(), general_model(seed=3, n=4)]:
        q = random_q(model, k, seed=12)
        frames = poe_link_frames(model.frames, model.twists, q)
        twists = poe_joint_twists(model.frames, model.twists, q)
        T = frames[:, -1]
        points = np.einsum("kab,mb->kma", T[:, :3, :3], targets) + T[:, None, :3, 3]
        expected = {
            "fk": (model.fk(q), T),
            "link_frames": (model.link_frames(q), frames),
            "fk_and_twists": (model.fk_and_twists(q), (T, twists)),
            "frames_and_twists": (model.frames_and_twists(q), (frames, twists)),
            "joint_twists": (model.joint_twists(q), twists),
            "frame_jacobian": (
                model.frame_jacobian(q),
                se3.adjoint(frames).transpose(0, 2, 1, 3).reshape(k, 6, -1),
            ),
            "target_points": (model.target_points(q, targets), points),
        }
        for name, (got, want) in expected.items():
            for g, w in zip(*((got, want) if isinstance(got, tuple) else ((got,), (want,))), strict=True):
                np.testing.assert_allclose(g, w, rtol=0, atol=1e-12, err_msg=f"{model.name} {name}")
        np.testing.assert_allclose(model.fk(q[0]), T[0], rtol=0, atol=1e-12)
