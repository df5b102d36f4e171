"""Authenticated is not authorized: the attacks of a key holder, each refused by the receiving agent.

Each test holds one robot's identity (a real endpoint with its certificate, talking over loopback
sockets to real agents) and sends what the policy (transport/policy.py) forbids: a task disguised
as a status, a team-level cancel, another robot's Pose, a watch of the whole team. Also the
eviction that keeps a command-line client able to connect while idle strangers hold the cap.
"""

from __future__ import annotations

import itertools
import logging

import pytest

from erni.blackboard import Pose, Task, TaskState
from erni.blackboard.schemas import Cancel, Peer, StatusRemoved, TaskQuery, WatchRequest
from erni.blackboard.testing import wait_until
from erni.transport.endpoint import Endpoint
from erni.transport.identity import load_identity
from tests.transport.helpers import free_port, identity, make_agent, make_client, settled


@pytest.fixture
def team():
    agents = []
    port = free_port()

    def spawn(name: str, **kw):
        agent = make_agent(name, port, **kw)
        agents.append(agent)
        return agent

    yield spawn
    for a in agents:
        a.stop()


@pytest.fixture
def holder():
    """An endpoint holding a team member's identity: it sends whatever it likes, in its own name."""
    endpoints = []

    def make(name: str, role: str = "robot"):
        ep = Endpoint(name, identity=load_identity(identity(name, role)), ttl=3.0, ack_timeout=0.3,
                      connect_timeout=0.3)
        ep.inbox = []  # type: ignore[attr-defined]
        ep.on_message = ep.inbox.append  # type: ignore[attr-defined]
        ep.start()
        endpoints.append(ep)
        return ep

    yield make
    for ep in endpoints:
        ep.stop()


def addr_of(agent) -> tuple[str, int]:
    return agent.plugin("transport").address


def counters(agent) -> dict[str, int]:
    return agent.plugin("transport").endpoint.counters


def goto(dest: str, source: str = "control", **where: float) -> Task:
    return Task(verb="BotMotion", preposition="goto", params=where or {"x": -2.5, "y": -2.5}, source=source,
                destination=dest)


def up(agent, name: str) -> bool:
    return any(p.name == name and p.up for p in agent.query(Peer))


def test_a_task_disguised_as_a_status_is_refused_and_never_relayed(team, holder, caplog):
    """(a) robot2's identity sends the control node a Task as a status update; today's control node
    took it as its own task and relayed it to robot1, whose journal named control as its sender."""
    control, robot1 = team("control", echo=False), team("robot1", echo=False)
    wait_until(lambda: up(control, "robot1"))
    mallory = holder("robot2")
    forged = goto("robot1")
    with caplog.at_level(logging.WARNING, logger="erni.control.transport"):
        for _ in range(5):
            mallory.send(addr_of(control), "status", forged, reliable=False, to="control")
        wait_until(lambda: counters(control).get("refused.status", 0) >= 3 or robot1.blackboard.contains(forged.uid))
        # robot2's own Pose after them, on the same path: once it is on control's board, the five were handled
        mallory.send(addr_of(control), "status", Pose(robot="robot2"), reliable=False, to="control")
        wait_until(lambda: control.blackboard.get("pose:robot2") is not None, timeout=30)
        settled(control)
    assert not robot1.blackboard.contains(forged.uid), "robot1 was given robot2's task in control's name"
    assert not control.blackboard.contains(forged.uid)
    assert not robot1.blackboard.contains(forged.uid)
    lines = [r.getMessage() for r in caplog.records if "refused status from robot2" in r.getMessage()]
    assert len(lines) == 1, "a refusal is logged once in a while, not once a message"
    assert "role robot" in lines[0] and "rule status" in lines[0] and "Task" in lines[0]


def test_a_robot_may_not_ask_the_control_node_to_relay_a_task(team, holder):
    control, robot1 = team("control", echo=False), team("robot1", echo=False)
    wait_until(lambda: up(control, "robot1"))
    mallory = holder("robot2")
    forged = goto("robot1", source="robot2")
    mallory.send(addr_of(control), "task.add", forged, reliable=True, to="control")
    wait_until(lambda: any(m.kind == "task.result" and m.body.uid == forged.uid for m in mallory.inbox))
    refusal = next(m.body.result for m in mallory.inbox if m.kind == "task.result")
    assert refusal.state is TaskState.FAILED and "not authorized" in refusal.message
    settled(control)
    assert not control.blackboard.contains(forged.uid) and not robot1.blackboard.contains(forged.uid)


def test_a_relayed_task_keeps_its_originator_and_a_relay_must_be_allowed_to_relay(team, holder):
    control, robot1 = team("control", echo=False), team("robot1", echo=False)
    wait_until(lambda: up(control, "robot1"))
    client = make_client(addr_of(control))
    try:
        task = goto("robot1", source="cli")
        client.send(addr_of(control), "task.add", task)
        wait_until(lambda: robot1.blackboard.contains(task.uid))
        assert robot1.blackboard.get(task.uid).source == "cli"
        assert robot1.blackboard.get(f"received:{task.uid}").sender == "control"
        assert robot1.blackboard.get(f"received:{task.uid}").role == "cli"
    finally:
        client.endpoint.stop()
    # a robot that claims to relay the operator's task is no relay
    from erni.transport.tasking import Relayed

    mallory = holder("robot2")
    forged = goto("robot1", source="cli")
    mallory.send(addr_of(robot1), "task.relay", Relayed(task=forged, role="cli"), reliable=True, to="robot1")
    wait_until(lambda: counters(robot1).get("refused.relay", 0) >= 1 or robot1.blackboard.contains(forged.uid))
    assert not robot1.blackboard.contains(forged.uid)
    # nor may a robot pass its own task off as the control node's by naming another source
    forged = goto("robot1", source="control")
    mallory.send(addr_of(robot1), "task.add", forged, reliable=True, to="robot1")
    wait_until(lambda: counters(robot1).get("refused.task", 0) >= 1 or robot1.blackboard.contains(forged.uid))
    assert not robot1.blackboard.contains(forged.uid)


def test_a_robot_cannot_cancel_the_operators_remote_goto(team, holder):
    """(b) a newly issued robot identity sent `RemoteBotMotion cancel`, and the operator's remote
    goto ended 'cancelled by task ...'."""
    control, robot1 = team("control", echo=False), team("robot1", echo=False)
    wait_until(lambda: up(control, "robot1"))
    operators = Task(verb="RemoteBotMotion", preposition="goto", params={"x": 3.0, "y": 1.0}, source="control",
                     destination="robot1")
    with control.transaction() as tx:
        tx.add(operators)
    wait_until(lambda: robot1.blackboard.contains(operators.uid))
    mallory = holder("robot9")
    cancel = Task(verb="RemoteBotMotion", preposition="cancel", source="robot9", destination="robot1")
    mallory.send(addr_of(robot1), "task.add", cancel, reliable=True, to="robot1")
    mallory.send(addr_of(robot1), "task.cancel", Cancel(uid=operators.uid), reliable=True, to="robot1")
    wait_until(lambda: counters(robot1).get("refused.requester", 0) >= 1 or robot1.blackboard.contains(cancel.uid))
    assert not robot1.blackboard.contains(cancel.uid), "MissionControl never sees the cancel"
    wait_until(lambda: any(m.kind == "task.result" and m.body.uid == cancel.uid for m in mallory.inbox))
    assert robot1.blackboard.contains(operators.uid) and not robot1.blackboard.get(operators.uid).done
    # the operator's own cancel still works
    cancel = Task(verb="RemoteBotMotion", preposition="cancel", source="control", destination="robot1")
    with control.transaction() as tx:
        tx.add(cancel)
    wait_until(lambda: robot1.blackboard.contains(cancel.uid))


def test_a_robot_cannot_overwrite_or_delete_another_robots_pose(team, holder):
    """(c) robot2 overwrote robot1's Pose on the control node with (99, -99) and it stayed (stamps
    were compared across senders), and could delete it."""
    control, robot1 = team("control", echo=False), team("robot1", echo=False)
    wait_until(lambda: up(robot1, "control"))
    with robot1.transaction() as tx:
        tx.add(Pose(robot="robot1", x=1.0, y=1.0))
    wait_until(lambda: (p := control.blackboard.get("pose:robot1")) is not None and p.x == 1.0)
    mallory = holder("robot2")
    mallory._seq = itertools.count(10**9)  # numbered far beyond robot1's own updates
    for forged in (Pose(robot="robot1", x=99.0, y=-99.0),  # in robot1's name
                   Pose(uid="pose:robot1", robot="robot2", x=99.0, y=-99.0)):  # its own, under robot1's uid
        mallory.send(addr_of(control), "status", forged, reliable=False, to="control")
    mallory.send(addr_of(control), "status.remove", StatusRemoved(uid="pose:robot1"), reliable=True, to="control")
    wait_until(lambda: counters(control).get("refused.status", 0) >= 3
               or (p := control.blackboard.get("pose:robot1")) is None or p.x != 1.0)
    settled(control)  # the run that refused the third has committed (an accepted forgery would be on the board)
    pose = control.blackboard.get("pose:robot1")
    assert pose is not None and (pose.x, pose.y) == (1.0, 1.0)
    with robot1.transaction() as tx:  # robot1's own updates still count
        tx.change(robot1.blackboard.get("pose:robot1").evolve(x=2.0))
    wait_until(lambda: control.blackboard.get("pose:robot1").x == 2.0)
    mallory.send(addr_of(control), "status", Pose(robot="robot2", x=5.0), reliable=False, to="control")
    wait_until(lambda: control.blackboard.get("pose:robot2") is not None)  # its own Pose is its to give


def test_a_robot_cannot_watch_the_team(team, holder):
    """(d) a watch request under robot2's identity returned every task and every position."""
    control, robot1 = team("control", echo=False), team("robot1", echo=False)
    wait_until(lambda: up(robot1, "control"))
    with robot1.transaction() as tx:
        tx.add(Pose(robot="robot1", x=1.0))
    with control.transaction() as tx:
        tx.add(goto("robot1"))
    wait_until(lambda: control.blackboard.get("pose:robot1") is not None)
    mallory = holder("robot2")
    mallory.send(addr_of(control), "watch.request", WatchRequest(lease=5.0), reliable=True, to="control")
    mallory.send(addr_of(control), "peers.request", None, reliable=True, to="control")
    wait_until(lambda: counters(control).get("refused.watch", 0) >= 2 or mallory.inbox)
    # both were refused, in runs now over: a refused request runs no handler, so nothing was sent for it
    settled(control)
    assert not [m for m in mallory.inbox if m.kind in ("watch.event", "peers.reply")]
    client = make_client(addr_of(control))  # the operator's client watches
    try:
        client.send(addr_of(control), "watch.request", WatchRequest(lease=5.0))
        wait_until(lambda: (m := client.receive(0.1)) is not None and m.kind == "watch.event")
    finally:
        client.endpoint.stop()


def test_an_operator_cancels_a_task_it_did_not_give_and_its_requester_is_told(team):
    control, robot1 = team("control", echo=False), team("robot1", echo=False)
    wait_until(lambda: up(control, "robot1"))
    task = goto("robot1")
    with control.transaction() as tx:
        tx.add(task)
    wait_until(lambda: robot1.blackboard.contains(task.uid))
    client = make_client(addr_of(robot1))  # the operator's client, straight at the robot
    try:
        client.send(addr_of(robot1), "task.cancel", Cancel(uid=task.uid))
        wait_until(lambda: not robot1.blackboard.contains(task.uid))
        wait_until(lambda: control.blackboard.get(task.uid).done)
        result = control.blackboard.get(task.uid).result
        assert result.state is TaskState.CANCELLED and result.message == "cancelled by cli (cli)"
    finally:
        client.endpoint.stop()


def test_a_message_naming_a_uid_is_acted_on_only_with_its_own_body_type(team, holder):
    """A kind and its body say the same thing: a `task.query` whose body is a `Cancel` (the type
    that six kinds once shared) is not answered; a `TaskQuery` is, by a `TaskUnknown` naming it."""
    robot1 = team("robot1", echo=False)
    asker = holder("control", "control")
    asker.send(addr_of(robot1), "task.query", Cancel(uid="wrong-type"), reliable=True, to="robot1")
    asker.send(addr_of(robot1), "task.query", TaskQuery(uid="no-such-task"), reliable=True, to="robot1")
    wait_until(lambda: any(m.kind == "task.unknown" for m in asker.inbox))  # in order: the first was handled
    answers = [m.body for m in asker.inbox if m.kind == "task.unknown"]
    assert [(type(body).__name__, body.uid) for body in answers] == [("TaskUnknown", "no-such-task")]
