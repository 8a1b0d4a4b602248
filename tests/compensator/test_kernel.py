"""The compiled single-configuration kernel (labcal.compensator.kernel) against the batched numpy definition.

The definition of a correction is the batched residual and solver; ``robot.correct(q[None])`` runs it with a batch
of one (a (1, n) input never takes the kernel), so it takes the steps the kernel must take, and the two answers
agree to rounding, on configurations inside and outside the validity region, near singularities (the damped
fallback), beyond the 0.1 rad box, with a TCP, for local POE, a network and a linear series.

"To rounding" is 1e-12 rad for a Gauss-Newton answer: each step corrects the last one's rounding. A damped answer
is fixed by floating point only to the definition's own resolution there (:func:`rounding_spread`): the steps pass
through ill-conditioned systems, and once the cost is at its rounding floor the kept/refused test and λ's gain
ratio compare numbers that differ in their last bits, so one ulp of the residual changes the path. Measured over
1,357 damped answers (4 seeds, the 4 kinds, with and without a TCP and a short budget): the definition moved by up
to 5e-10 rad when its residual and Jacobian were perturbed by one ulp, and the kernel's answer was never farther
from the definition's than 1e-12 rad + 6.0 times that spread (median 0.46 times). The tests hold damped answers
to 1e-12 rad + :data:`SPREAD_FACTOR` times the spread at each configuration; a different step rule (a λ factor, a
stop) parts by orders of magnitude more.
"""

from __future__ import annotations

import itertools
import subprocess
import sys

import numpy as np
import pytest

from labcal.compensator import CalibratedRobot, Network, input_features, kernel
from labcal.compensator import solve as solver
from labcal.compensator.validity import ValidityRegion
from labcal.kinematics import se3
from labcal.robots import load

pytest.importorskip("numba")

AGREE = 1e-12  # rad
SPREAD_FACTOR = 16  # a damped answer's bound, in units of the definition's rounding spread (module docstring)
EPS = np.finfo(float).eps


def _network(model, features, hidden, seed, out=1e-3) -> Network:
    """A network of random weights: hidden = () is a linear series (the hybrid's learned term)."""
    rng = np.random.default_rng(seed)
    f = input_features(np.zeros((1, model.n)), features, model).shape[1]
    N = max(model.n, 6)
    sizes = [f, *hidden, N]
    weights = tuple(rng.normal(size=(b, a)) / np.sqrt(a) for a, b in itertools.pairwise(sizes))
    return Network(
        features=tuple(features),
        weights=weights,
        biases=tuple(rng.normal(size=b) * 0.1 for b in sizes[1:]),
        in_mean=rng.normal(size=f) * 0.1,
        in_scale=rng.uniform(0.5, 2.0, size=f),
        out_mean=rng.normal(size=N) * 1e-4,
        out_scale=np.full(N, out),
    )


def _data(seed=0, k=300) -> np.ndarray:
    """Configurations a calibration could have measured: a band of the workspace (the validity region's centres)."""
    rng = np.random.default_rng(seed)
    centre = np.array([0.2, -1.3, 1.2, -1.4, -0.3, 0.3])  # the wrist singularity q5 = 0 inside
    return centre + rng.uniform(-0.6, 0.6, size=(k, 6))


def make_robot(kind: str, seed: int = 0, region: bool = True) -> CalibratedRobot:
    nominal = load("ur10").model
    model = nominal.perturbed(np.random.default_rng(seed).normal(size=(7, 6)) * 0.5e-3)
    network = {
        "local-poe": None,
        "series": ("gravity", "harmonics:8"),  # the hybrid's learned term: harmonics and gravity, one layer
        "series-q": ("harmonics:3", "q"),
        "network": ("q", "sincos", "sincos2", "gravity"),  # the paper's ANN inputs, two tanh layers
    }[kind]
    if network is not None:
        hidden = () if kind.startswith("series") else (10, 8)
        network = _network(model, network, hidden, seed)
    validity = ValidityRegion.from_configurations(_data(seed)) if region else None
    return CalibratedRobot(nominal, model, network, method="hybrid", validity=validity)


def configurations(robot: CalibratedRobot, seed: int) -> np.ndarray:
    """Inside the region, outside it (within the joint ranges), and near the wrist singularity q5 = 0 and the
    elbow's (q3 = 0), where Gauss-Newton fails or leaves the 0.1 rad box and the damped steps run."""
    rng = np.random.default_rng(seed)
    inside = robot.validity.sample(60, rng) if robot.validity is not None else _data(seed, 60)
    anywhere = rng.uniform(-np.pi, np.pi, size=(60, 6))
    wrist = _data(seed + 1, 40)
    wrist[:, 4] = rng.choice([-1, 1], 40) * 10 ** rng.uniform(-6, -1.5, 40)
    elbow = _data(seed + 2, 20)
    elbow[:, 2] = rng.normal(size=20) * 1e-3
    return np.concatenate([inside, anywhere, wrist, elbow])


def definition(robot: CalibratedRobot, q: np.ndarray, **kw) -> np.ndarray:
    """The batched numpy definition with a batch of one."""
    return robot.correct(q[None], **kw)[0]


def condition(robot: CalibratedRobot, q: np.ndarray) -> float:
    D = np.array([1 / robot.length_scale] * 3 + [1.0] * 3)
    return float(np.linalg.cond(D[:, None] * robot.model.joint_twists(q[None])[0]))


def rounding_spread(robot: CalibratedRobot, q: np.ndarray, draws: int = 4, **kw) -> float:
    """How far the definition's answer moves when its residual and Jacobian are perturbed by one ulp (random signs,
    a fixed seed; the largest of ``draws`` runs): the resolution to which floating point fixes a damped answer."""
    rng = np.random.default_rng(0)
    exact = CalibratedRobot.residual

    def rounded(self, qc, T_target, jacobian=True):
        r, J = exact(self, qc, T_target, jacobian)
        r = r * (1 + EPS * rng.choice([-1.0, 1.0], r.shape))
        return r, None if J is None else J * (1 + EPS * rng.choice([-1.0, 1.0], J.shape))

    want = definition(robot, q, **kw)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(CalibratedRobot, "residual", rounded)
        return max(float(np.abs(definition(robot, q, **kw) - want).max()) for _ in range(draws))


def assert_damped_agree(robot: CalibratedRobot, q: np.ndarray, got: np.ndarray, want: np.ndarray, **kw) -> None:
    """A damped answer: within 1e-12 rad + SPREAD_FACTOR × the definition's rounding spread."""
    gap = float(np.abs(got - want).max())
    if gap > AGREE:
        spread = rounding_spread(robot, q, **kw)
        assert gap <= AGREE + SPREAD_FACTOR * spread, f"at {q.tolist()} {kw}: {gap:.3g} rad, spread {spread:.3g}"


def assert_agree(robot: CalibratedRobot, q: np.ndarray, **kw) -> None:
    """The kernel's answer is the definition's: 1e-12 rad, or for a damped answer the definition's rounding
    resolution there (:func:`assert_damped_agree`). An unconverged Gauss-Newton answer (``iterations`` cut short)
    near a singularity carries one step's rounding times the condition number: 1e-15 · cond there."""
    got, want = robot.correct(q, **kw), definition(robot, q, **kw)
    limit = AGREE if "iterations" not in kw else max(AGREE, 1e-15 * condition(robot, q))
    if np.abs(got - want).max() <= limit:
        return
    damped = solver._damped
    calls = []
    solver._damped = lambda *a, **k: calls.append(1) or damped(*a, **k)
    try:
        definition(robot, q, **kw)
    finally:
        solver._damped = damped
    assert calls, f"a Gauss-Newton answer differs at {q.tolist()} {kw}: {got - want}"
    assert_damped_agree(robot, q, got, want, **kw)


def pose_error(robot: CalibratedRobot, q: np.ndarray, q_cmd: np.ndarray) -> float:
    """Length-scaled size of log(T_nominal(q) T_real(q_cmd)⁻¹)."""
    scale = np.array([1 / robot.length_scale] * 3 + [1.0] * 3)
    e = se3.log_se3(robot.nominal.fk(q) @ se3.inv(robot.predict_pose(q_cmd)))
    return float(np.linalg.norm(e * scale))


@pytest.mark.parametrize("kind", ["local-poe", "series", "series-q", "network"])
def test_the_kernel_takes_the_definitions_steps(kind, monkeypatch):
    """Gauss-Newton answers agree to 1e-12 rad; damped answers to the definition's rounding resolution at each
    configuration (module docstring) and reach the same pose to 1e-12."""
    robot = make_robot(kind)
    assert robot._kernel is not None
    damped = solver._damped
    calls = []
    monkeypatch.setattr(solver, "_damped", lambda *a, **k: calls.append(len(a[1])) or damped(*a, **k))
    gauss_newton = inside_box = boxed = fell_back = 0
    for q in configurations(robot, seed=1):
        got = robot.correct(q, extrapolate=True)
        calls.clear()
        want = definition(robot, q, extrapolate=True)
        if calls:
            fell_back += 1
            assert_damped_agree(robot, q, got, want, extrapolate=True)
            assert abs(pose_error(robot, q, got) - pose_error(robot, q, want)) <= 1e-12
        else:
            gauss_newton += 1
            np.testing.assert_allclose(got, want, rtol=0, atol=AGREE, err_msg=str(q.tolist()))
        inside = robot.validity.inside(q[None])[0]
        inside_box += inside
        if inside:  # the bound holds inside the region, also where the unbounded answer lies beyond it
            assert np.abs(got - q).max() <= solver.MAX_CORRECTION + 1e-15
            unbounded = robot._newton(q[None], 10, 1e-11, None)[0]
            boxed += np.abs(unbounded - q).max() > solver.MAX_CORRECTION
    assert fell_back >= 10 and gauss_newton >= 100  # both modes ran on many configurations
    assert inside_box >= 60 and boxed >= 3  # some were held at the 0.1 rad box inside the region


@pytest.mark.parametrize("kind", ["local-poe", "series"])
def test_the_kernel_honours_the_solver_options_and_a_tcp(kind):
    robot = make_robot(kind)
    tcp = se3.exp_se3(np.array([0.02, -0.01, 0.15, 0.3, -0.2, 0.1]))
    options = [
        {"tcp": tcp},
        {"iterations": 2},
        {"iterations": 0},
        {"tol": 1e-6},
        {"damped_iterations": 2},
        {"damped_iterations": 0},
        {"tcp": tcp, "damped_iterations": 5},
    ]
    for q in configurations(robot, seed=2)[::3]:
        for kw in options:
            assert_agree(robot, q, extrapolate=True, **kw)


def test_without_a_validity_region_nothing_is_bounded():
    robot = make_robot("series", region=False)
    assert robot._kernel is not None
    for q in configurations(robot, seed=3):
        assert_agree(robot, q)


def test_the_kernel_answers_single_calls_itself(monkeypatch):
    robot = make_robot("series")
    q = robot.validity.sample(1, np.random.default_rng(0))[0]
    want = robot.correct(q)

    def refused(*a, **k):
        raise AssertionError("the numpy solver ran for a single call")

    monkeypatch.setattr(CalibratedRobot, "_newton", refused)
    np.testing.assert_array_equal(robot.correct(q), want)
    with pytest.raises(AssertionError, match="numpy solver ran"):
        robot.correct(q[None])


def test_strided_and_read_only_configurations_take_the_kernel_too():
    robot = make_robot("series")
    q = robot.validity.sample(1, np.random.default_rng(1))[0]
    want = robot.correct(q)
    strided = np.empty((6, 2))
    strided[:, 0] = q
    frozen = q.copy()
    frozen.setflags(write=False)
    compiled = len(kernel.compiled().correct_one.signatures)
    for other in (strided[:, 0], frozen):
        np.testing.assert_array_equal(robot.correct(other), want)
    assert len(kernel.compiled().correct_one.signatures) == compiled  # no second compilation for them


def test_the_kernel_is_deterministic():
    robot = make_robot("series")
    qs = configurations(robot, seed=4)
    first = np.array([robot.correct(q, extrapolate=True) for q in qs])
    again = np.array([robot.correct(q, extrapolate=True) for q in qs[::-1]])[::-1]
    np.testing.assert_array_equal(first, again)


@pytest.mark.parametrize("kind", ["local-poe", "series"])
def test_failures_raise_the_definitions_errors(kind):
    robot = make_robot(kind)
    inside = robot.validity.sample(1, np.random.default_rng(0))[0]
    outside_region = inside.copy()
    outside_region[0] += 2.0  # within the joint ranges, far from the data
    assert not robot.validity.inside(outside_region[None])[0]
    outside_range = inside.copy()
    outside_range[3] = 7.0
    for q in [outside_region, outside_range, np.r_[inside[:5], np.nan], np.r_[inside[:5], np.inf]]:
        with pytest.raises(ValueError) as single:
            robot.correct(q)
        with pytest.raises(ValueError) as batch:
            robot.correct(q[None])
        assert str(single.value) == str(batch.value)
    with pytest.raises(ValueError, match=r"shape \(6,\) or \(k, 6\) .* got \(5,\)"):
        robot.correct(inside[:5])
    # outside the region with extrapolate=True: corrected without the bound, as the definition does
    assert_agree(robot, outside_region, extrapolate=True)


def test_without_numba_single_calls_take_the_batched_path(monkeypatch):
    monkeypatch.setattr(kernel, "compiled", lambda: None)  # as if numba were not importable
    for kind in ("local-poe", "series", "network"):
        robot = make_robot(kind)
        assert robot._kernel is None
        for q in configurations(robot, seed=5)[::4]:
            np.testing.assert_array_equal(robot.correct(q, extrapolate=True), definition(robot, q, extrapolate=True))


def test_a_python_without_numba_gets_no_kernel_and_the_batched_answer():
    code = (
        "import sys; sys.modules['numba'] = None\n"  # import numba now raises ImportError
        "import numpy as np\n"
        "from labcal.compensator import CalibratedRobot, kernel\n"
        "from labcal.robots import load\n"
        "m = load('ur10').model\n"
        "robot = CalibratedRobot(m, m.perturbed(np.full((7, 6), 1e-4)), method='local-poe')\n"
        "q = np.array([0.1, -1.2, 1.0, -1.4, -1.5, 0.2])\n"
        "assert kernel.compiled() is None and robot._kernel is None\n"
        "assert np.array_equal(robot.correct(q), robot.correct(q[None])[0])\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("name", ["kuka-iiwa14-r820", "franka-panda"])
@pytest.mark.parametrize("learned", [False, True])
def test_a_redundant_arm_takes_the_definitions_least_change_steps(name, learned):
    nominal = load(name).model
    rng = np.random.default_rng(7)
    model = nominal.perturbed(rng.normal(size=(nominal.n + 1, 6)) * 0.5e-3)
    network = _network(model, ("q", "sincos", "gravity"), (8,), 1) if learned else None
    lo, hi = nominal.limits[:, 0], nominal.limits[:, 1]
    centre = 0.5 * (lo + hi) + 0.2
    data = centre + rng.uniform(-0.5, 0.5, size=(300, nominal.n))
    robot = CalibratedRobot(nominal, model, network, method="hybrid", validity=ValidityRegion.from_configurations(data))
    assert robot._kernel is not None
    anywhere = lo + (hi - lo) * rng.uniform(0.1, 0.9, size=(40, nominal.n))
    for q in np.concatenate([robot.validity.sample(40, rng), anywhere]):
        assert_agree(robot, q, extrapolate=True)


def test_robots_the_kernel_does_not_cover_take_the_batched_path():
    nominal = load("ur10").model
    tilted = nominal.replace(twists=np.tile([0, 0, 0, 0, np.sin(1e-3), np.cos(1e-3)], (6, 1)))
    scara = load("scara4").model  # 4 joints, virtual joints: the numpy path
    robots = [
        CalibratedRobot(nominal, tilted, method="local-poe"),
        CalibratedRobot(scara, scara.perturbed(np.full((5, 6), 1e-4)), method="local-poe"),
    ]
    for robot in robots:
        assert robot._kernel is None
        q = np.zeros(robot.n) + 0.3
        np.testing.assert_array_equal(robot.correct(q, extrapolate=True), definition(robot, q, extrapolate=True))


def test_the_compiled_features_are_the_registrys():
    from labcal.features import compute_all

    jit = kernel.compiled()
    model = load("ur10").model
    names = ("q", "sincos", "sincos2", "gravity", "harmonics:32")
    network = _network(model, names, (), 0)
    cols = kernel._feature_table(CalibratedRobot(model, model, network))
    H = 32
    rng = np.random.default_rng(3)
    for q in rng.uniform(-np.pi, np.pi, (20, 6)):
        T = model.link_frames(q[None])
        x = np.empty(len(cols))
        jit._features(q, T[0], cols, np.empty((6, H + 1, 2)), x)
        want = compute_all(q[None], names, model.joint_types, model.limits, T)[0]
        np.testing.assert_allclose(x, want, rtol=0, atol=H * np.pi * 2.3e-16 + 1e-15)


@pytest.mark.parametrize("angle", [1e-7, 3e-3, 5.01e-3, 0.02, 0.2, 0.52, 2.5, 0.8 * np.pi, np.pi - 1e-4])
def test_the_compiled_pose_error_is_the_logarithm_of_the_pose_difference(angle):
    jit = kernel.compiled()
    rng = np.random.default_rng(int(angle * 1e7) % 1000)
    e = np.empty(6)
    for _ in range(20):
        T = se3.exp_se3(rng.normal(size=6))
        xi = rng.normal(size=6)
        xi[3:] *= angle / np.linalg.norm(xi[3:])
        T_target = se3.exp_se3(xi * np.r_[1e-3, 1e-3, 1e-3, 1, 1, 1]) @ T
        jit._log_pose(T_target, T, e)
        np.testing.assert_allclose(e, se3.log_se3(T_target @ se3.inv(T)), rtol=0, atol=1e-12)


def test_importing_labcal_does_not_import_numba():
    code = "import sys, labcal.compensator, labcal.cli.app; assert 'numba' not in sys.modules, 'numba imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
