"""Mission fixtures: in-process robot agents (fast simulated robot + motion + mission), helpers to task them."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from erni.blackboard import Agent, Pose, Task
from erni.blackboard.testing import wait_until
from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.world import RobotStart, World

FAST = {"sip_period": 0.02, "accel": 3.0, "decel": 3.0, "max_v": 2.0, "rot_accel": 720.0, "max_rv": 360.0}
FAST_MODEL = {"base": "pioneer3", "decel": 2.5, "rot_decel": 500.0, "max_rv": 300.0, "max_v": 2.0}
MOTION = {"model": FAST_MODEL, "rate_hz": 50, "pose_rate_hz": 25, "avoid_distance": 0.0, "sync_timeout": 0.3,
              "link_timeout": 0.5, "link_grace": 0.5, "blocked_timeout": 1.0, "stall_timeout": 0.5}


@pytest.fixture
def hosts() -> Iterator[list[RobotHost]]:
    made: list[RobotHost] = []
    yield made
    for h in made:
        h.stop()


@pytest.fixture
def robots(hosts) -> Iterator:
    """Factory: robot(name, x, y, mission=..., extra=[(class, settings, name)]) -> started Agent."""
    agents: list[Agent] = []

    def robot(name: str = "robot1", x: float = 0.0, y: float = 0.0, heading: float = 0.0,
              mission: dict[str, Any] | None = None, extra: list[tuple[Any, dict, str]] = (),
              world: World | None = None, with_motion: bool = True) -> Agent:
        agent = Agent(name, workers=2)
        for cls, settings, pname in extra:
            agent.add_plugin(cls, settings=settings, name=pname)
        if with_motion:
            base = world or World()
            starts = [RobotStart(name=name, x=x, y=y, heading=heading)]
            host = RobotHost(base.model_copy(update={"robot": starts}), physics_hz=200)
            host.add_robot(SimRobotConfig(name=name, **FAST), port=0)
            hosts.append(host.start())
            agent.add_plugin("motion", settings={**MOTION, "url": host.url()}, name="motion")
        agent.add_plugin("mission", settings={"audio": False, "network_aware": False, **(mission or {})},
                         name="mission")
        agents.append(agent)
        agent.start()
        if with_motion:
            wait_until(lambda: agent.query(Pose, where=lambda p: p.robot == name), timeout=5,
                       message=f"{name}: no Pose published")
        return agent

    yield robot
    for a in agents:  # agents stop before their simulated robots
        a.stop()


def send(agent: Agent, preposition: str, verb: str = "RemoteBotMotion", sender: str = "control",
         **params: object) -> Task:
    """Publish a task from `sender` addressed to the agent (as the transport would deliver it)."""
    task = Task(verb=verb, preposition=preposition, params=params, source=sender, destination=agent.name)
    with agent.transaction() as tx:
        tx.add(task)
    return task


def current(agent: Agent, uid: str) -> Task | None:
    found = agent.query(Task, where=lambda t: t.uid == uid)
    return found[0] if found else None


def pose_of(agent: Agent, robot: str | None = None) -> Pose:
    name = robot or agent.name
    return agent.query(Pose, where=lambda p: p.robot == name)[0]


def subs_of(agent: Agent, parent: str) -> list[Task]:
    return agent.query(Task, where=lambda t: t.parent == parent and t.verb == "BotMotion")


def plugin(agent: Agent, name: str = "mission") -> Any:
    """The agent's plugin called `name`."""
    return next(p for p in agent.plugins if p.name == name)
