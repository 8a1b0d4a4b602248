"""What the URScript export sends to a robot cannot hurt it: ``labcal_correct`` returns only what ``correct()``
returns (within 1e-4 rad, in float64 and float32) and otherwise stops the program with a popup naming the
configuration; no string the exporter writes (robot name, provenance) can add a statement."""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from export_fixtures import hybrid

import urscript_subset
from labcal.compensator import CalibratedRobot, golden_configurations
from labcal.export.urscript import urscript_program_text, urscript_text
from labcal.robots import load

AGREE = 1e-4  # rad: the promise, written here rather than imported from the exporter
LOCAL, HYBRID = None, ("q", "sincos", "sincos2", "gravity")


def _robot(features, seed=3):
    return hybrid("ur10", features=features, seed=seed)


def _call(ns, q):
    """labcal_correct(q) → (n,) array, or None when the script halted."""
    try:
        return np.asarray(ns["labcal_correct"](list(map(float, q))), dtype=float)
    except urscript_subset.Halted:
        return None


@pytest.mark.parametrize("features", [LOCAL, HYBRID], ids=["local-poe", "hybrid"])
@pytest.mark.parametrize("float32", [False, True], ids=["float64", "float32"])
def test_script_stops_where_gauss_newton_diverges(features, float32):
    """Two millirad from the wrist singularity correct()'s Gauss-Newton fails (it answers from its damped
    fallback); the script's plain steps go astray there (hundreds of radians on the code before), so it must stop
    with a popup that names the configuration."""
    robot = _robot(features)
    q = golden_configurations(robot)[:2].copy()
    q[:, 4] = 0.002
    damped = np.max(np.abs(robot.correct(q, damped_iterations=0) - robot.correct(q)), axis=1) > 1e-12
    assert damped.all()  # the premise: correct() itself cannot solve these with Gauss-Newton
    ns = urscript_subset.load(urscript_text(robot), float32=float32)
    for row in q:
        ns["stats"].messages.clear()
        assert _call(ns, row) is None
        kind, text = ns["stats"].messages[-1]
        assert kind == "popup" and "no command for q = [" in text
        shown = [float(x) for x in re.findall(r"-?\d+\.\d+(?:e-?\d+)?", text.split("q = ", 1)[1])]
        np.testing.assert_allclose(shown, row, atol=1e-4)


def _near_singular(robot, k, seed):
    """k configurations in range with the wrist q5, and k with the elbow q3, uniform in ±0.05 rad."""
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(robot.joint_ranges[:, 0], -np.pi), np.minimum(robot.joint_ranges[:, 1], np.pi)
    q = rng.uniform(lo, hi, size=(2 * k, robot.n))
    q[:k, 4] = rng.uniform(-0.05, 0.05, size=k)
    q[k:, 2] = rng.uniform(-0.05, 0.05, size=k)
    return q


@pytest.mark.parametrize("features", [LOCAL, HYBRID], ids=["local-poe", "hybrid"])
def test_script_agrees_with_correct_near_singularities_wherever_it_returns(features):
    robot = _robot(features, seed=5)
    q = _near_singular(robot, 60, seed=11)
    expected = robot.correct(q)
    script = urscript_text(robot)
    for float32 in (False, True):
        ns = urscript_subset.load(script, float32=float32)
        got = [_call(ns, row) for row in q]
        returned = np.array([g is not None for g in got])
        err = np.array([np.max(np.abs(g - e)) for g, e in zip(got, expected, strict=True) if g is not None])
        assert np.all(err <= AGREE), f"float32={float32}: {np.sum(err > AGREE)} returned commands differ"
        # both outcomes occur here: the check is exercised, and the script is not a refusal machine (in float32 it
        # also refuses where ‖J⁻¹‖ could amplify the rounding beyond the agreement: fewer return there)
        assert (0.2 if float32 else 0.3) < returned.mean() < 0.95
        assert np.max(np.abs(expected[returned] - q[returned])) > 1e-3  # it corrected something real


@pytest.mark.parametrize("features", [LOCAL, ("gravity", "harmonics:3")], ids=["local-poe", "joint-series"])
def test_script_never_returns_where_correct_needs_its_damped_fallback(features):
    """The script judges its steps by correct()'s Gauss-Newton rule, so it returns only where that rule succeeds;
    where correct() falls back to damping (a different answer, often not a solution) the script stops."""
    robot = _robot(features, seed=3)
    q = _near_singular(robot, 150, seed=12)
    damped = np.max(np.abs(robot.correct(q, damped_iterations=0) - robot.correct(q)), axis=1) > 1e-12
    assert damped.sum() >= 10  # the premise: these sets hold configurations correct() has to damp
    ns = urscript_subset.load(urscript_text(robot))
    returned = np.array([_call(ns, row) is not None for row in q])
    assert not np.any(returned & damped), f"returned at {np.sum(returned & damped)} damped configurations"
    assert np.any(returned & ~damped)


# Two configurations 6-9 mrad from the elbow singularity (q3 = 0) of a UR10 whose only error is a -20 mrad elbow
# offset (correct() adds 20 mrad to q3, by plain Gauss-Newton). ‖J⁻¹‖ (length-scaled) is ~10³ there: the script
# before it checked its own conditioning returned, in float32, q_cmd 1.5e-4 and 1.1e-4 rad from correct()'s with a
# last step and residual below 1e-5.
ELBOW_ROUNDING = [
    [0.08282822950806867, 0.2877409951402239, 0.008450571328716641, 2.287144918950964, -0.35544173423510994,
     -0.6394368840379685],
    [2.5377066188842026, -2.668730744434381, 0.006612551895640754, -1.536367225076003, -0.5983617726739068,
     0.822233169503646],
]  # fmt: skip


def test_float32_rounding_near_the_elbow_never_yields_a_silently_different_command():
    nominal = load("ur10").model
    offset = np.zeros((nominal.n + 1, 6))
    offset[2, 5] = -0.02  # frame 2's rotation about its z axis: an offset of joint 3
    robot = CalibratedRobot(nominal, nominal.perturbed(offset), method="local-poe")
    q = np.array(ELBOW_ROUNDING)
    expected = robot.correct(q)
    # the premise: correct() solves these with plain Gauss-Newton, 20 mrad on the elbow
    np.testing.assert_allclose(robot.correct(q, damped_iterations=0), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(expected - q, np.tile([0, 0, 0.02, 0, 0, 0], (2, 1)), atol=1e-6)
    script = urscript_text(robot)
    exact = urscript_subset.load(script)
    for row, e in zip(q, expected, strict=True):
        got = _call(exact, row)  # in float64 the rounding is far too small to matter: it answers
        assert got is not None and np.max(np.abs(got - e)) <= 1e-8
    ns = urscript_subset.load(script, float32=True)
    for row, e in zip(q, expected, strict=True):
        ns["stats"].messages.clear()
        got = _call(ns, row)
        if got is not None:
            assert np.max(np.abs(got - e)) <= AGREE, f"float32 q_cmd {np.max(np.abs(got - e)):.2e} rad off at {row}"
        else:
            kind, text = ns["stats"].messages[-1]
            assert kind == "popup" and "float precision" in text


def test_program_self_test_covers_the_wrist_and_elbow_singularities():
    robot = _robot(HYBRID, seed=6)
    text = urscript_program_text(robot)
    line = next(x for x in text.splitlines() if x.strip().startswith("lc_tq = "))
    tq = np.array(eval(line.split("=", 1)[1], {})).reshape(-1, 6)  # a list of numbers
    assert np.any(np.abs(tq[:, 4]) <= 0.2) and np.any(np.abs(tq[:, 2]) <= 0.2)
    ns = urscript_subset.load(text, float32=True)
    ns["labcal_program"]()
    assert ("textmsg", "labcal: compensator self test passed") in ns["stats"].messages
    # a controller that gets the near-singular configurations wrong by 2e-4 rad fails the self test
    expected_line = next(x for x in text.splitlines() if x.strip().startswith("lc_tx = "))
    values = np.array(eval(expected_line.split("=", 1)[1], {})).reshape(-1, 6)
    near = (np.abs(tq[:, 4]) <= 0.2) | (np.abs(tq[:, 2]) <= 0.2)
    values[near, 0] += 2e-4
    shifted = "lc_tx = [" + ", ".join(repr(float(v)) for v in values.ravel()) + "]"
    broken = urscript_subset.load(text.replace(expected_line.strip(), shifted), float32=True)
    with pytest.raises(urscript_subset.Halted):
        broken["labcal_program"]()


HOSTILE = [
    "ur10\nmovej([0,-1.57,0,-1.57,0,0], a=3, v=3)\n#",
    "ur10\rmovej([0,-1.57,0,-1.57,0,0], a=3, v=3)\r#",
    "ur10\u2028movej([0,-1.57,0,-1.57,0,0], a=3, v=3)\u2028#",
    'ur10")\nmovej([0,0,0,0,0,0])\n#',
    "ur10\\",
    "ur10\x1b[31m\x00",
]


def _statements(text: str) -> list[str]:
    """The lines a controller executes: every line, split at any line break, without comments and blanks."""
    out = []
    for line in re.split(r"\r\n|[\n\r\v\f\x1c-\x1e\x85\u2028\u2029]", text):
        body = line.strip()
        if body and not body.startswith("#"):
            out.append(body)
    return out


@pytest.mark.parametrize("name", HOSTILE, ids=[f"name{i}" for i in range(len(HOSTILE))])
@pytest.mark.parametrize("program", [False, True], ids=["function-file", "program"])
def test_no_injected_string_becomes_a_statement(name, program):
    robot = _robot(LOCAL)
    writer = urscript_program_text if program else urscript_text
    benign = writer(robot, provenance={"fit_id": "x"})
    robot = type(robot)(robot.nominal.replace(name=name), robot.model, method=robot.method)
    text = writer(robot, provenance={"fit_id": name, name: "x", "note": 'a "quoted" \\ value\n#'})
    assert _statements(text) == _statements(benign)  # the same program, whatever the strings
    assert all(ch == "\n" or ch.isprintable() for ch in text)  # no other line break, escape or NUL anywhere
    urscript_subset.check(text)
    assert "movej" not in " ".join(_statements(text))


def test_script_corrects_only_inside_the_validity_region():
    """Where correct() refuses without extrapolate (inside the joint ranges, but far from every measured
    configuration) the script stops with a popup naming the region; at the measured configurations it answers as
    correct() does."""
    import scenarios
    from labcal.calibration import Observations, fit

    scn = scenarios.good("ur10", 40, seed=0)
    robot = fit(Observations(scn.q, scn.points, scn.targets), load("ur10").model, "local-poe").robot
    ns = urscript_subset.load(urscript_text(robot))
    for row in scn.q[:5]:
        np.testing.assert_allclose(_call(ns, row), robot.correct(row), atol=AGREE, rtol=0)
    lo, hi = robot.joint_ranges.T
    box = np.random.default_rng(5).uniform(lo, hi, size=(200, 6))
    outside = box[~robot.validity.inside(box)][:5]
    assert len(outside) == 5
    for row in outside:
        with pytest.raises(ValueError, match="validity radius"):
            robot.correct(row)
        ns["stats"].messages.clear()
        assert _call(ns, row) is None
        kind, text = ns["stats"].messages[-1]
        assert kind == "popup" and "outside the validity region of the calibration" in text


def test_program_self_test_runs_inside_the_validity_region_of_a_fit_with_wide_joint_ranges():
    """A local-POE fit keeps the robot's ±2π ranges while its data fill a fraction of them: the self test must
    pick configurations where the script answers (the golden ones span the ranges and left the region: the export
    failed with correct()'s 'validity radius' refusal)."""
    import scenarios
    from labcal.calibration import Observations, fit

    scn = scenarios.good("ur10", 40, seed=0)
    robot = fit(Observations(scn.q, scn.points, scn.targets), load("ur10").model, "local-poe").robot
    assert not robot.validity.inside(golden_configurations(robot)).all()  # the premise
    ns = urscript_subset.load(urscript_program_text(robot), float32=True)
    ns["labcal_program"]()
    assert ("textmsg", "labcal: compensator self test passed") in ns["stats"].messages


def _stopped_by(ns, q) -> str | None:
    """The popup text when labcal_correct(q) halted, None when it returned a command."""
    ns["stats"].messages.clear()
    if _call(ns, q) is not None:
        return None
    return [text for kind, text in ns["stats"].messages if kind == "popup"][-1]


def _narrow_region_robot():
    """A local-POE robot whose validity region comes from data in which joint 5 never moved (issue 27's narrow
    series): joint 5 scaled by 1 / MIN_SPREAD, so near q5 = 4.7 rad its scaled value is ~4,700 and the float32
    spacing there (5e-4 scaled units) is a visible share of the radius."""
    from labcal.compensator.validity import MIN_RADIUS, MIN_SPREAD, ValidityRegion

    robot = _robot(LOCAL)
    w = np.array([1.0, 1.0, 1.0, 1.0, 1.0 / MIN_SPREAD, 1.0])
    centres = golden_configurations(robot)[:2] * w
    return dataclasses.replace(robot, validity=ValidityRegion(centres=centres, radius=MIN_RADIUS, weights=w))


def test_float32_script_refuses_every_configuration_just_outside_the_validity_region():
    """correct() refuses beyond the radius; the controller's float32 distance is off by ~1e-4 of the radius here:
    compared with the radius itself, the float32 script passed 16, 6 and 2 of these 40 configurations (1e-6,
    3e-5 and 1e-4 of the radius outside). Just inside (1 % of the radius) it answers as correct() does."""
    robot = _narrow_region_robot()
    region = robot.validity
    rng = np.random.default_rng(1)
    u = rng.normal(size=(40, 6))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    ns = urscript_subset.load(urscript_text(robot), float32=True)
    for delta in (1e-6, 3e-5, 1e-4):
        q = (region.centres[0] + region.radius * (1 + delta) * u) / region.weights
        assert not region.inside(q).any()  # the premise: correct() refuses every one
        passed = [row for row in q if "outside the validity region" not in (_stopped_by(ns, row) or "")]
        assert not passed, f"{len(passed)} configurations {delta:g} of the radius outside passed the region check"
    q = (region.centres[0] + region.radius * (1 - 1e-2) * u[:8]) / region.weights
    for row in q:
        got = _call(ns, row)
        assert got is not None and np.max(np.abs(got - robot.correct(row))) <= AGREE


@pytest.mark.parametrize("float32", [False, True], ids=["float64", "float32"])
def test_script_refuses_every_joint_just_past_its_calibrated_range(float32):
    """q_j = b (1 + 1e-8) past a bound b = ±2π: below half a float32 spacing of b, so the float32 script compared
    with the bound itself passed every one. Past the range (or not a number) the script stops with the range
    popup; 1e-5 of the bound inside it passes the range check."""
    robot = _robot(LOCAL)
    base = golden_configurations(robot)[0]
    ns = urscript_subset.load(urscript_text(robot), float32=float32)
    for j in range(robot.n):
        for b in robot.joint_ranges[j]:
            q = base.copy()
            q[j] = b * (1 + 1e-8)
            with pytest.raises(ValueError, match="outside the calibrated range"):
                robot.correct(q)  # the premise
            assert "outside the calibrated range" in (_stopped_by(ns, q) or ""), f"joint {j + 1} at {q[j]!r}"
            q[j] = b * (1 - 1e-5)
            robot.correct(q)  # accepted (q5 = ±2π is the wrist singularity: there the script stops for that)
            assert "outside the calibrated range" not in (_stopped_by(ns, q) or ""), f"joint {j + 1} at {q[j]!r}"
    q = base.copy()
    q[2] = np.nan
    assert "outside the calibrated range" in (_stopped_by(ns, q) or "")
