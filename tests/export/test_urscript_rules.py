"""URScript a controller accepts: every emitted script passes the static rule checker (list capacity, integer
indexing, fixed types, local scope, built-ins), the statement budget between sync() calls holds, the float32
evaluation stays within the documented bound, and the deployable program's self test runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from export_fixtures import hybrid, make_network, sample

import urscript_subset
from labcal.compensator import CalibratedRobot
from labcal.export.urscript import FLOAT32_BOUND, urscript_program_text, urscript_text
from labcal.robots import load

ROOT = Path(__file__).parents[2]


def _scripts():
    """(label, script) of every script form and kind the exporter writes."""
    out = []
    for features in [("q", "sincos", "sincos2", "gravity"), ("sincos", "gravity"), ("harmonics:2",), ("gravity",)]:
        robot = hybrid("ur10", features=features, odd_twists="sincos" in features, seed=3)
        out.append((f"newton {features}", urscript_text(robot)))
    robot = hybrid("ur10", seed=1, hidden=(6, 5))
    out.append(("two hidden layers", urscript_text(robot, statements_per_sync=200)))
    out.append(("program", urscript_program_text(robot)))
    nominal = load("ur10").model
    ann = CalibratedRobot(nominal, nominal, make_network(nominal, ("q", "sincos")), method="ann")
    out.append(("paper", urscript_text(ann, method="paper")))
    out.append(("paper program", urscript_program_text(ann, method="paper")))
    out.append(("scara local-poe", urscript_text(hybrid("scara4", features=None, seed=2))))
    return out


SCRIPTS = _scripts()


@pytest.mark.parametrize("label,script", SCRIPTS, ids=[s[0] for s in SCRIPTS])
def test_every_emitted_script_keeps_the_controller_rules(label, script):
    urscript_subset.check(script)


# One broken rule each; the checker must name it.
BROKEN = {
    "capacity": ("def f(a):\n  local F = [0.0]\n  F = [1.0, 2.0]\n  return F\nend\n", "list capacity"),
    "capacity via call": (
        "def g():\n  return [1.0, 2.0, 3.0]\nend\ndef f():\n  local F = [0.0]\n  F = g()\n  return F\nend\n",
        "list capacity",
    ),
    "float index": ("def f(a):\n  local x = 1.0\n  return a[x]\nend\n", "index must be an int"),
    "division index": ("def f(a):\n  local i = 4\n  return a[i / 2]\nend\n", "'/' of two ints"),
    "int becomes float": ("def f(a):\n  local i = 0\n  i = 0.5\n  return i\nend\n", "created as int"),
    "no local": ("def f(a):\n  x = 1.0\n  return x\nend\n", "without 'local'"),
    "builtin": ("def f(a):\n  local x = tanh(a)\n  return x\nend\n", "neither a URScript built-in"),
    "arity": ("def f(a):\n  local x = atan2(a)\n  return x\nend\n", "takes 2 argument"),
    "list arithmetic": ("x = [1.0] + [2.0]\n", "arithmetic on a list"),
    "mixed list": ("x = [1.0, True]\n", "one type"),
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_checker_refuses_each_broken_rule(name):
    script, message = BROKEN[name]
    with pytest.raises(urscript_subset.URScriptRuleError, match=message):
        urscript_subset.check(script)


def test_checker_refuses_the_one_element_placeholders_of_the_old_exporter():
    """The exporter of 65c384c declared ``local F = [0.0]`` and assigned 84-element lists to it."""
    try:
        old = subprocess.run(
            ["git", "show", "65c384c:src/labcal/export/urscript.py"], cwd=ROOT, capture_output=True, text=True
        )
    except OSError:
        old = None
    if old is None or old.returncode != 0:
        pytest.skip("git history of 65c384c not available")
    namespace: dict = {"__name__": "old_urscript"}
    exec(compile(old.stdout, "old_urscript.py", "exec"), namespace)
    text = namespace["urscript_text"](hybrid("ur10", seed=3))
    assert "local F = [0.0]" in text
    with pytest.raises(urscript_subset.URScriptRuleError, match="list capacity"):
        urscript_subset.check(text)


def _run(script: str, q: np.ndarray, float32: bool = False, name: str = "labcal_correct"):
    ns = urscript_subset.load(script, float32=float32)
    ns["stats"].reset()
    out = np.array([ns[name](list(map(float, row))) for row in q], dtype=float)
    return out, ns["stats"]


@pytest.mark.parametrize("budget", [200, 1000])
@pytest.mark.parametrize(
    "features,hidden", [(("q", "sincos", "sincos2", "gravity"), (8,)), (("gravity", "harmonics:24"), (32,))]
)
def test_statements_between_syncs_stay_within_the_budget(budget, features, hidden):
    robot = hybrid("ur10", features=features, hidden=hidden, seed=4)
    q = sample(robot, 3, seed=5)
    script = urscript_text(robot, statements_per_sync=budget)
    _, stats = _run(script, q)
    per_call = stats.total / len(q)
    assert stats.max_window <= budget
    # sync() is what keeps the window short: a call runs many budgets' worth of statements
    assert per_call > 2 * budget and stats.syncs >= len(q) * per_call / budget


def test_float32_evaluation_is_within_the_documented_bound():
    robot = hybrid("ur10", seed=3)
    q = sample(robot, 12, seed=8)
    q = q[np.max(np.abs(robot.correct(q) - q), axis=1) < 0.05]
    assert len(q) >= 8
    script = urscript_text(robot)
    expected = robot.correct(q)
    got32, _ = _run(script, q, float32=True)
    got64, _ = _run(script, q)
    np.testing.assert_allclose(got64, expected, atol=1e-9, rtol=0)
    err32 = np.max(np.abs(got32 - expected))
    assert err32 <= FLOAT32_BOUND
    assert err32 > 1e-9  # the float32 mode really rounds (a no-op mode would agree to 1e-11)


def test_float32_mode_rounds_every_literal_and_builtin():
    ns = urscript_subset.load("def f(a):\n  return 0.1 + sin(0.3)\nend\n", float32=True)
    value = ns["f"](0.0)
    assert isinstance(value, np.float32)
    assert value == np.float32(np.float32(0.1) + np.float32(np.sin(0.3)))


def test_program_self_test_passes_in_float32_and_halts_on_a_wrong_file():
    robot = hybrid("ur10", seed=6)
    move = "movej(labcal_correct([0.1, -1.2, 1.0, -1.4, -1.5, 0.2]), a=1.2, v=0.25)"
    text = urscript_program_text(robot, body=[move])
    assert text.startswith("#") and "\ndef labcal_program():\n" in text and text.rstrip().endswith("end")
    ns = urscript_subset.load(text, float32=True)
    ns["labcal_program"]()
    messages = ns["stats"].messages
    assert ("textmsg", "labcal: compensator self test passed") in messages
    assert messages[-1][0] == "movej"  # the body runs after the self test
    # a file whose expected answers are wrong (another calibration's) stops the program
    other = urscript_program_text(hybrid("ur10", seed=7))
    expected_line = next(line for line in other.splitlines() if "lc_tx = " in line)
    mine = next(line for line in text.splitlines() if "lc_tx = " in line)
    broken = urscript_subset.load(text.replace(mine, expected_line), float32=True)
    with pytest.raises(urscript_subset.Halted):
        broken["labcal_program"]()


def test_program_body_is_checked_like_the_rest():
    robot = hybrid("ur10", seed=6)
    text = urscript_program_text(robot, body=["x = tanh(1.0)"])
    with pytest.raises(urscript_subset.URScriptRuleError, match="built-in"):
        urscript_subset.check(text)


def test_exports_are_deterministic():
    a = urscript_program_text(hybrid("ur10", seed=2), provenance={"fit_id": "x"})
    b = urscript_program_text(hybrid("ur10", seed=2), provenance={"fit_id": "x"})
    assert a == b
