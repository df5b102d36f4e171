"""The policy table on its own: who may task, relay, publish and watch (no sockets)."""

from __future__ import annotations

import pytest

from erni.blackboard import BBObject, NetInfo, Pose, Task
from erni.transport.policy import Refusal, check_relay, check_status, check_task, check_watch, table


@pytest.mark.parametrize("role, receiver", [("control", "robot"), ("cli", "robot"), ("cli", "control"),
                                            ("control", "control")])
def test_the_operating_roles_task_robots_and_control_nodes_with_anything(role, receiver):
    for verb, prep in (("BotMotion", "goto"), ("RemoteBotMotion", "cancel"), ("Deploy", "relay")):
        check_task(role, receiver, verb, prep)


def test_a_robot_tasks_a_robot_only_for_a_mission_and_nobody_else_at_all():
    for prep in ("relay", "spread", "widep", "patrol"):
        check_task("robot", "robot", "Deploy", prep)
    for verb, prep in (("BotMotion", "goto"), ("RemoteBotMotion", "cancel"), ("BotMotion", "stop")):
        with pytest.raises(Refusal, match="only Deploy"):
            check_task("robot", "robot", verb, prep)
    for role, receiver in (("robot", "control"), ("consumer", "robot"), ("", "robot"), ("cli", "cli")):
        with pytest.raises(Refusal) as refused:
            check_task(role, receiver, "BotMotion", "goto")
        assert refused.value.rule == "task"


def test_only_the_control_node_relays_and_only_for_operators():
    check_relay("control", "cli")
    check_relay("control", "control")
    for relay, origin in (("control", "robot"), ("robot", "cli"), ("cli", "cli"), ("control", "")):
        with pytest.raises(Refusal, match="may not relay"):
            check_relay(relay, origin)


def test_status_is_the_senders_own_object_under_its_own_uid():
    check_status("robot1", "robot", Pose(robot="robot1", x=1.0))
    check_status("control", "control", Pose(robot="control"))
    check_status("robot1", "robot", NetInfo(node="robot1", kind="neighbor_list"))
    refused = [("robot2", "robot", Pose(robot="robot1")),  # another's
               ("robot2", "robot", Pose(uid="pose:robot1", robot="robot2")),  # under another's uid
               ("cli", "cli", Pose(robot="cli")),  # a client publishes nothing
               ("robot2", "robot", NetInfo(node="robot1", kind="path_cost")),
               ("robot2", "robot", Task(verb="BotMotion", preposition="stop", source="robot2"))]
    for sender, role, obj in refused:
        with pytest.raises(Refusal) as err:
            check_status(sender, role, obj)
        assert err.value.rule == "status"


def test_a_plugin_type_travels_only_as_its_senders_own():
    class Beat(BBObject):
        robot: str

    class Loose(BBObject):
        value: int = 0

    check_status("robotA", "robot", Beat(robot="robotA"))
    with pytest.raises(Refusal):
        check_status("robotB", "robot", Beat(robot="robotA"))
    with pytest.raises(Refusal, match="no shared state"):
        check_status("robotA", "robot", Loose())


def test_only_operators_watch_and_the_table_reads():
    check_watch("control")
    check_watch("cli")
    with pytest.raises(Refusal, match="may not watch"):
        check_watch("robot")
    assert "| robot | robot | Deploy patrol, Deploy relay, Deploy spread, Deploy widep |" in table()
