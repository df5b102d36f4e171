"""ERNI's frames over Zenoh (`wire = "zenoh"`): agents that meet only through a Zenoh router in
this process, on loopback, with real Zenoh sessions; the same sessions, acknowledgements and
authorization as on ERNI's own wire."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

zenoh = pytest.importorskip("zenoh")

from erni.blackboard import Agent, Pose, Task, TaskState  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.sim.team import free_port  # noqa: E402
from erni.transport import Peer  # noqa: E402
from erni.transport.zenoh_wire import open_router  # noqa: E402
from tests.transport.helpers import make_agent  # noqa: E402

TEAM = "ztest"


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    """A Zenoh router in this process; yields the endpoint agents connect to."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_router([endpoint])
    yield endpoint
    session.close()


@pytest.fixture
def team(router: str) -> Iterator[Callable[..., Agent]]:
    agents: list[Agent] = []

    def spawn(name: str, **kw: Any) -> Agent:
        kw.setdefault("zenoh", {"team": TEAM, "mode": "client", "connect": [router]})
        agent = make_agent(name, 0, wire="zenoh", **kw)
        agents.append(agent)
        return agent

    yield spawn
    for a in agents:
        a.stop()


def up(agent: Agent, name: str) -> bool:
    return any(p.name == name and p.up for p in agent.query(Peer))


def test_a_task_goes_through_the_router_is_acknowledged_and_done_and_poses_come_back(team):
    control, robot = team("control", echo=False), team("robot1")
    wait_until(lambda: up(control, "robot1") and up(robot, "control"))
    peer = next(p for p in control.query(Peer) if p.name == "robot1")
    assert peer.address == "zenoh/robot1:0"
    task = Task(verb="BotMotion", preposition="forward", params={"distance": 1.0}, source="control",
                destination="robot1")
    with control.transaction() as tx:
        tx.add(task)
    final = wait_until(lambda: (t := control.blackboard.get(task.uid)) is not None and t.done and t)
    assert final.state is TaskState.SUCCEEDED
    with robot.transaction() as tx:
        tx.add(Pose(uid="pose:robot1", robot="robot1", x=1.5, y=-2.0, theta=0.25))
    pose = wait_until(lambda: control.blackboard.get("pose:robot1"))
    assert (pose.x, pose.y) == (1.5, -2.0)
    counters = control.plugin("transport").endpoint.counters
    assert counters.get("sent.reliable", 0) >= 1 and counters.get("dropped.auth", 0) == 0
