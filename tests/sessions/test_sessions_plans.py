"""Plans are data: built, listed, grouped into poses, stored as pose documents, validated with errors naming the
command."""

from __future__ import annotations

import json

import pytest

from labcal.sessions.plans import Measure, Move, Plan, PlanError, Settle, command_from_dict, make_plan


def test_make_plan_lists_its_commands():
    plan = make_plan([[0.0, 0.1], [0.2, 0.3]], samples=4, settle=0.25, speed=0.3, acceleration=0.6)
    assert list(plan) == [
        Move((0.0, 0.1), 0.3, 0.6),
        Settle(0.25),
        Measure(4),
        Move((0.2, 0.3), 0.3, 0.6),
        Settle(0.25),
        Measure(4),
    ]
    assert plan.n_poses == 2 and plan.n_joints == 2
    assert plan.configurations.tolist() == [[0.0, 0.1], [0.2, 0.3]]


def test_zero_settle_is_left_out():
    plan = make_plan([[0.0], [1.0]], samples=1, settle=0.0)
    assert [type(c) for c in plan] == [Move, Measure, Move, Measure]


def test_poses_group_commands_and_add_up_settles():
    plan = Plan((Move((0.0,), 1, 1), Settle(0.1), Settle(0.2), Measure(3), Move((1.0,), 1, 1), Measure(1)))
    poses = plan.poses()
    assert [(p.index, p.q.tolist(), p.samples) for p in poses] == [(0, [0.0], 3), (1, [1.0], 1)]
    assert poses[0].settle == pytest.approx(0.3) and poses[1].settle == 0.0


def test_pose_documents_round_trip():
    plan = make_plan([[0.1, -0.2, 0.3]] * 3, samples=2, settle=0.5)
    docs = plan.pose_documents()
    assert [d["pose"] for d in docs] == [0, 1, 2]
    assert docs[0]["commands"][0] == {"command": "move", "q": [0.1, -0.2, 0.3], "speed": 0.5, "acceleration": 0.5}
    assert Plan.from_pose_documents(json.loads(json.dumps(docs))) == plan


@pytest.mark.parametrize(
    ("commands", "message"),
    [
        ((Measure(1),), "command 0: a plan must start with a Move"),
        ((Move((0.0,), 1, 1), Measure(1), Measure(1)), "last pose has 2 Measure"),
        ((Move((0.0,), 1, 1), Move((1.0,), 1, 1), Measure(1)), "command 1: the pose before this Move has 0"),
        ((Move((0.0,), 1, 1), Measure(1), Move((0.0, 1.0), 1, 1), Measure(1)), "command 2: Move has 2 joint"),
        ((), "at least one Move"),
    ],
)
def test_malformed_plans_are_refused(commands, message):
    with pytest.raises(PlanError, match=message):
        Plan(commands)


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: Move((0.0, float("nan")), 1, 1), "Move.q"),
        (lambda: Move((0.0,), 0.0, 1), "Move.speed"),
        (lambda: Move((0.0,), 1, -2), "Move.acceleration"),
        (lambda: Settle(-1), "Settle.seconds"),
        (lambda: Measure(0), "Measure.samples"),
        (lambda: Measure(True), "Measure.samples"),
    ],
)
def test_bad_command_fields_are_named(build, message):
    with pytest.raises(PlanError, match=message):
        build()


def test_bad_serialised_commands_are_named():
    with pytest.raises(PlanError, match="command 3: unknown command 'jump'"):
        command_from_dict({"command": "jump"}, "command 3")
    with pytest.raises(PlanError, match="measure needs fields"):
        command_from_dict({"command": "measure", "samples": 1, "extra": 2})
    with pytest.raises(PlanError, match="configuration 1"):
        make_plan([[0.0], [float("inf")]])


# --------------------------------------------------------------------------------------------------------------
# Motion time: what the plan's order costs


def test_move_time_is_trapezoidal_and_triangular_for_short_moves():
    from labcal.sessions.plans import move_time

    # 2 rad at 0.5 rad/s, 1 rad/s²: 0.5 s to speed up, 0.5 s to slow down (0.125 rad each), 1.75 rad cruise (3.5 s).
    assert move_time(2.0, 0.5, 1.0) == pytest.approx(4.5)
    # 0.1 rad never reaches 0.5 rad/s: two halves of 0.05 rad at 1 rad/s², √0.1 s each.
    assert move_time(0.1, 0.5, 1.0) == pytest.approx(2 * 0.1**0.5)
    assert move_time(-2.0, 0.5, 1.0) == move_time(2.0, 0.5, 1.0)


def test_motion_time_adds_the_slowest_joint_of_each_move():
    from labcal.sessions.plans import motion_time, move_time

    plan = make_plan([[0.0, 1.0], [2.0, 1.1], [2.0, 0.0]], speed=0.5, acceleration=1.0)
    slowest = [move_time(2.0, 0.5, 1.0), move_time(1.1, 0.5, 1.0)]
    assert motion_time(plan) == pytest.approx(sum(slowest))
