"""The compiled single correction accepts, refuses and answers exactly as the batched definition, at the edges.

What a single ``correct(q)`` returns goes to a robot, so a disagreement in what is accepted is a safety bug: the
kernel must never answer where the definition (``correct(q[None])[0]``) raises, never exceed the 0.1 rad bound
inside the validity region, and raise the definition's error. tests/compensator/test_kernel.py compares answers
over the workspace; these cases sit where two implementations part: the validity region's boundary (its distances
summed in other orders), extrapolated configurations beyond a learned fit's joint ranges but inside its region,
the joint ranges' last ulp, option values of odd types, the order of the errors, files, and other processes.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_kernel import _data, assert_agree, definition, make_robot

from labcal.compensator import CalibratedRobot, Compensator
from labcal.compensator import save as save_compensator
from labcal.compensator import solve as solver
from labcal.kinematics import se3

pytest.importorskip("numba")

BOUND = solver.MAX_CORRECTION + 1e-15  # the damped box's last rounding, as test_kernel's


def outcome(call):
    """What a call gives: its answer, or (error class, message)."""
    try:
        return call()
    except Exception as err:  # any error: the single call must raise the definition's
        return type(err), str(err)


def assert_same_outcome(robot: CalibratedRobot, q, **kw) -> None:
    """The single call refuses with the definition's error, or answers as it does (test_kernel.assert_agree)."""
    single = outcome(lambda: robot.correct(q, **kw))
    batch = outcome(lambda: definition(robot, np.asarray(q), **kw))
    if isinstance(batch, tuple) or isinstance(single, tuple):
        assert single == batch, f"at {np.asarray(q).tolist()} {kw}"
    else:
        assert_agree(robot, q, **kw)


def learned_fit(kind: str = "series", region: bool = True) -> CalibratedRobot:
    """As a learned fit exports it: the joint ranges are its data's (calibration.hybrid._ranges), so the validity
    region's balls around the edge configurations reach beyond them."""
    robot = make_robot(kind, region=region)
    data = _data(0)
    return dataclasses.replace(robot, joint_ranges=np.stack([data.min(axis=0), data.max(axis=0)], axis=1))


def boundary(robot: CalibratedRobot, seed: int, count: int, judge) -> np.ndarray:
    """(2 count, n) pairs of configurations a ray apart by its last bisection step, on either side of the region's
    boundary as ``judge(q) → inside`` sees it (rays from random centres in random directions)."""
    region = robot.validity
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        c = region.centres[rng.integers(len(region.centres))]
        u = rng.normal(size=robot.n)
        u /= np.linalg.norm(u)
        a, b = 0.0, 3 * region.radius
        for _ in range(60):
            m = 0.5 * (a + b)
            a, b = (m, b) if judge((c + m * u) / region.weights) else (a, m)
        out += [(c + a * u) / region.weights, (c + b * u) / region.weights]
    return np.array(out)


def test_the_region_boundary_is_refused_as_the_definition_refuses_it():
    """ValidityRegion.distance (the refusal) sums |x|² − 2 x·c + |c|², the kernel |c − x|²: a ulp apart at the
    boundary the kernel answered where the definition refused (94 of 600 boundary configurations)."""
    robot = make_robot("local-poe")
    region = robot.validity

    def judge(q):
        return region.distance(q[None])[0] <= region.radius

    qs = boundary(robot, seed=1, count=150, judge=judge)
    refused = 0
    for q in qs:
        single, batch = outcome(lambda: robot.correct(q)), outcome(lambda: definition(robot, q))  # noqa: B023
        if isinstance(batch, tuple):
            refused += 1
            assert single == batch, f"the kernel answered at {q.tolist()}, where the definition says {batch}"
        else:
            assert not isinstance(single, tuple), single
            assert_agree(robot, q)  # the same answer: 1e-12 rad, a damped one to rounding
    assert refused >= 150  # every pair has a refused side (the bisection's outer end)


def test_extrapolated_boundary_configurations_are_bounded_as_the_definition_bounds_them():
    """With extrapolate=True the definition bounds a configuration inside the region (ValidityRegion.inside); near
    the wrist singularity, where the unbounded answer exceeds 0.1 rad, the kernel's verdict must be the same at the
    boundary's last ulp."""
    robot = make_robot("local-poe")
    region = robot.validity
    rng = np.random.default_rng(5)
    base = region.sample(40, rng)
    base[:, 4] = 3e-4  # near q5 = 0: Gauss-Newton's answer lies far beyond the box
    qs = []
    for q in base:
        u = np.r_[rng.normal(size=4), 0.0, rng.normal()]  # q5 kept
        a, b = 0.0, 4.0
        for _ in range(60):
            m = 0.5 * (a + b)
            a, b = (m, b) if region.inside((q + m * u / np.linalg.norm(u))[None])[0] else (a, m)
        qs += [q + a * u / np.linalg.norm(u), q + b * u / np.linalg.norm(u)]
    for q in qs:
        got = robot.correct(q, extrapolate=True)
        if region.inside(q[None])[0]:
            assert np.abs(got - q).max() <= BOUND, f"{np.abs(got - q).max()} rad inside the region at {q.tolist()}"
        assert_agree(robot, q, extrapolate=True)


def test_a_configuration_accepted_without_extrapolate_stays_bounded_with_it():
    """The definition refused by ValidityRegion.distance but bounded extrapolated rows by a |c − x|² test, which at the
    boundary's last ulp disagree: a configuration correct(q) accepts as inside (bounded to 0.0998 rad) got 0.169
    rad from correct(q, extrapolate=True), what Compensator.correct does for a robot with a joint map after its
    own range check. Near the wrist singularity, bisected on the refusal's distance."""
    robot = make_robot("local-poe")
    region = robot.validity
    rng = np.random.default_rng(5)
    base = region.sample(300, rng)
    base[:, 4] = 3e-4
    parted = needed = 0
    for q in base:
        u = np.r_[rng.normal(size=4), 0.0, rng.normal()]  # q5 kept
        u /= np.linalg.norm(u)
        a, b = 0.0, 4.0
        for _ in range(60):
            m = 0.5 * (a + b)
            a, b = (m, b) if region.distance((q + m * u)[None])[0] <= region.radius else (a, m)
        inner = q + a * u  # accepted by correct(inner)
        d = region.centres - inner * region.weights  # |c − x|², summed otherwise than .distance's expansion
        if np.einsum("ca,ca->c", d, d).min() <= region.radius**2:
            continue
        parted += 1
        needed += np.abs(robot._newton(inner[None], 10, 1e-11, None)[0] - inner).max() > solver.MAX_CORRECTION
        for got in (robot.correct(inner[None], extrapolate=True)[0], robot.correct(inner, extrapolate=True)):
            assert np.abs(got - inner).max() <= BOUND, f"{np.abs(got - inner).max()} rad at {inner.tolist()}"
    assert parted >= 5 and needed >= 1  # the two tests parted, and the bound mattered at some


def test_extrapolated_configurations_beyond_the_joint_ranges_inside_the_region_keep_the_bound():
    """A learned fit's joint ranges are its data's; the region reaches beyond them. extrapolate=True there: the
    definition bounds the correction (the region holds q); the kernel used to skip the region test outside the
    ranges and returned up to 0.19 rad."""
    robot = learned_fit()
    lo, hi = robot._ranges
    rng = np.random.default_rng(0)
    qs = robot.validity.sample(3000, rng)
    beyond = qs[((qs < lo) | (qs > hi)).any(axis=1)]
    beyond = beyond[robot.validity.inside(beyond)]
    beyond = beyond[np.argsort(np.abs(beyond[:, 4]))[:60]]  # nearest the wrist singularity: the largest answers
    assert len(beyond) == 60
    held = 0
    for q in beyond:
        got = robot.correct(q, extrapolate=True)
        assert np.abs(got - q).max() <= BOUND, f"{np.abs(got - q).max()} rad inside the region at {q.tolist()}"
        held += np.abs(robot._newton(q[None], 10, 1e-11, None)[0] - q).max() > solver.MAX_CORRECTION
        assert_agree(robot, q, extrapolate=True)
    assert held >= 5  # the bound was needed at some of them
    # without extrapolate they are refused with the definition's range error
    assert_same_outcome(robot, beyond[0])


@pytest.mark.parametrize("region", [True, False])
def test_the_joint_ranges_last_ulp(region):
    """At the calibrated range's ends (and its 1e-12 margin) and one ulp beyond: refused or answered alike."""
    robot = learned_fit(region=region)
    ranges = robot.joint_ranges
    lo, hi = robot._ranges
    q0 = _data(3, 1)[0]
    for j in range(robot.n):
        for edge in (ranges[j, 0], ranges[j, 1], lo[j], hi[j]):
            for value in (edge, np.nextafter(edge, -np.inf), np.nextafter(edge, np.inf)):
                q = q0.copy()
                q[j] = value
                assert_same_outcome(robot, q)
    for j in (0, 4):  # −0.0 (q5 = −0.0: exactly the wrist singularity)
        q = q0.copy()
        q[j] = -0.0
        assert_same_outcome(robot, q, extrapolate=True)


def test_configurations_of_other_kinds_get_the_definitions_answer():
    """Only a plain native float64 (n,) array reaches the compiled entry point (which refuses another dtype with
    numba's TypeError); every other kind of q is converted or refused by the batched path, or (strided, unaligned)
    read as the same numbers."""
    robot = make_robot("series")
    q = robot.validity.sample(1, np.random.default_rng(8))[0]
    want = robot.correct(q)
    assert_agree(robot, q)
    q32 = q.astype(np.float32)
    unaligned = np.frombuffer(bytearray(q.nbytes + 1), dtype=float, offset=1, count=6)
    unaligned[:] = q
    strided = np.repeat(q, 2)[::2]
    same = [list(q), tuple(q), q.astype(">f8"), unaligned, strided, np.ma.masked_array(q), q[::-1][::-1]]
    for other in same:
        np.testing.assert_allclose(robot.correct(other), want, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(robot.correct(q32), definition(robot, q32.astype(float)))
    np.testing.assert_array_equal(robot.correct(q[None]), definition(robot, q)[None])
    for wrong in (q[:5], np.r_[q, 0.0], q.astype(int) + 0j, q.astype(str), np.ma.masked_array(q, mask=q > 0)):
        with pytest.raises(ValueError, match="q "):
            robot.correct(wrong)
    assert_same_outcome(robot, np.round(q).astype(int), extrapolate=True)


SINGULAR = np.array([0.2, -0.75, 0.76, -0.8, 1e-7, 0.2])  # q5 ≈ 0: the damped mode runs


@pytest.mark.parametrize(
    "options",
    [
        {"damped_iterations": -1},  # the definition indexes an empty history (IndexError); compiled: out of bounds
        {"damped_iterations": -5},
        {"damped_iterations": 2**70},
        {"damped_iterations": 2.7},
        {"damped_iterations": "3"},
        {"iterations": 2.5},
        {"iterations": "3"},
        {"iterations": np.float64(3.0)},
        {"iterations": None},
        {"iterations": 2**70},
        {"iterations": np.int64(3)},
        {"iterations": True},
        {"iterations": -3},
        {"tol": "1e-6"},
        {"tol": None},
        {"tol": np.float32(1e-6)},  # float32 arithmetic in the definition's 1e-3 · tol
        {"tol": 0},
        {"tol": -1.0},
        {"tol": float("nan")},
        {"tol": np.inf},
        {"extrapolate": np.bool_(True)},
        {"extrapolate": 1},
        {"extrapolate": np.array([True, False])},
        {"method": "paper"},
        {"method": "Newton"},
    ],
    ids=repr,
)
def test_options_are_accepted_or_refused_as_the_definition_does(options):
    robot = make_robot("series")
    regular = robot.validity.sample(1, np.random.default_rng(2))[0]
    for q in (SINGULAR, regular):
        assert_same_outcome(robot, q, **({"extrapolate": True} | options))
    assert_same_outcome(robot, np.r_[regular[:5], np.nan], **options)  # the definition's first error wins


def test_a_bad_tcp_is_named_after_the_errors_the_definition_names_first():
    robot = make_robot("local-poe")
    inside = robot.validity.sample(1, np.random.default_rng(0))[0]
    far = inside.copy()
    far[0] += 2.0
    not_rigid = np.eye(4)
    not_rigid[0, 0] = 1.01
    nan_pose = np.eye(4)
    nan_pose[0, 3] = np.nan
    for tcp in (not_rigid, nan_pose, np.eye(3), "tool"):
        for q in (np.r_[inside[:5], np.nan], far, np.r_[inside[:5], 7.0], inside):
            assert_same_outcome(robot, q, tcp=tcp)
    far_tcp = se3.exp_se3(np.array([0.5, -0.3, 2.0, 0.3, -0.2, 0.1]))  # 2 m out: a long tool, still rigid
    for tcp in (np.eye(4), far_tcp, far_tcp.tolist()):
        for q in (inside, SINGULAR):
            assert_same_outcome(robot, q, tcp=tcp, extrapolate=True)


HYPOTHESIS = settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize("kind", ["local-poe", "series-q", "network"])
def test_random_configurations_over_and_beyond_the_ranges(kind):
    """Property: anywhere (inside the data, beyond a learned fit's ranges, beyond ±2π, near a singularity), with
    and without extrapolate, the single call and the definition agree on accept/refuse and the answer."""
    robot = learned_fit(kind)
    lo, hi = robot.joint_ranges[:, 0], robot.joint_ranges[:, 1]
    joint = st.floats(-1.0, 2.0, allow_nan=False)  # fraction of each joint's range: 0 … 1 inside
    wide = st.floats(-10.0, 10.0, allow_nan=False, allow_subnormal=True)

    @HYPOTHESIS
    @given(
        st.lists(joint, min_size=6, max_size=6),
        st.sampled_from([None, 0, 4]),
        wide,
        st.booleans(),
        st.sampled_from([None, 1e-3, 0.0]),
    )
    def check(fractions, which, value, extrapolate, wrist):
        q = lo + (hi - lo) * np.array(fractions)
        if which is not None:
            q[which] = value  # far beyond the ranges (or a tiny value: hypothesis shrinks towards 0)
        if wrist is not None:
            q[4] = wrist
        assert_same_outcome(robot, q, extrapolate=extrapolate)
        if extrapolate and robot.validity.inside(q[None])[0]:
            assert np.abs(robot.correct(q, extrapolate=True) - q).max() <= BOUND

    check()


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_a_loaded_compensator_answers_as_the_robot_it_was_saved_from(tmp_path, suffix):
    robot = learned_fit("series")
    path = save_compensator(robot, tmp_path / f"c{suffix}")
    loaded = Compensator.load(path)
    assert loaded.robot._kernel is not None
    rng = np.random.default_rng(4)
    for q in np.concatenate([robot.validity.sample(20, rng), SINGULAR[None]]):
        for extrapolate in (False, True):
            want = outcome(lambda: robot.correct(q, extrapolate=extrapolate))  # noqa: B023
            got = outcome(lambda: loaded.correct(q, extrapolate=extrapolate))  # noqa: B023
            if isinstance(want, tuple):
                assert got == want
            else:
                np.testing.assert_array_equal(got, want)  # the same numbers: the same bits
                assert_agree(loaded.robot, q, extrapolate=extrapolate)


def test_another_process_with_the_cached_kernel_gives_the_same_bits():
    """numba's on-disk cache (written by this process's compile, or an earlier one) is what a second process runs:
    its answers are bit-identical to this one's."""
    robot = make_robot("series")
    qs = np.concatenate([robot.validity.sample(10, np.random.default_rng(6)), SINGULAR[None]])
    here = np.array([robot.correct(q, extrapolate=True) for q in qs])
    assert np.array_equal(here, np.array([robot.correct(q, extrapolate=True) for q in qs]))  # the same call twice
    code = (
        "import sys, numpy as np\n"
        f"sys.path.insert(0, {str(__import__('pathlib').Path(__file__).parent)!r})\n"
        "from test_kernel import make_robot\n"
        "robot = make_robot('series')\n"
        "qs = np.frombuffer(bytes.fromhex(sys.argv[1])).reshape(-1, 6)\n"
        "print(np.array([robot.correct(q.copy(), extrapolate=True) for q in qs]).tobytes().hex())\n"
    )
    run = subprocess.run([sys.executable, "-c", code, qs.tobytes().hex()], check=True, capture_output=True, text=True)
    there = np.frombuffer(bytes.fromhex(run.stdout.strip())).reshape(here.shape)
    np.testing.assert_array_equal(there, here)


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"damped_iterations": -1}, "damped_iterations"),
        ({"damped_iterations": 2.7}, "damped_iterations"),
        ({"iterations": "3"}, "iterations"),
        ({"iterations": np.float64(3.0)}, "iterations"),
        ({"tol": "1e-6"}, "tol"),
        ({"tol": None}, "tol"),
    ],
    ids=repr,
)
def test_solver_options_of_the_wrong_kind_are_refused_by_name_single_and_batched(options, field):
    robot = make_robot("series")
    for q in (SINGULAR, SINGULAR[None]):
        with pytest.raises(ValueError, match=f"^{field} must be"):
            robot.correct(q, extrapolate=True, **options)
