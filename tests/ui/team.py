"""A running team for the GUI tests: a control agent (transport + UI) and robot agents driving
simulated robots, each agent with its own transport on loopback."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from erni.blackboard import Agent, Pose
from erni.blackboard.testing import wait_until
from erni.plugins.ui import UIPlugin
from erni.sim.robot import SimRobotConfig
from erni.sim.robot_host import RobotHost
from erni.sim.team import free_port
from erni.sim.world import World

KEY = "ui-test-team-key"
FAST = dict(sip_period=0.05, accel=3.0, decel=3.0, max_v=2.0, rot_accel=720.0, max_rv=360.0)
MOTION = dict(model={"base": "pioneer3", "decel": 2.5, "rot_decel": 500.0, "max_rv": 300.0, "max_v": 2.0},
              rate_hz=20, pose_rate_hz=10, avoid_distance=0.3, sync_timeout=0.5, link_timeout=2.0,
              link_grace=3.0, blocked_timeout=5.0, stall_timeout=1.0)  # loose: shared machines stall
ARENA = Path(__file__).with_name("arena.toml")


def transport_settings(discovery: int, role: str) -> dict[str, Any]:
    return {"key": KEY, "discovery_port": discovery, "beacon_period": 0.2, "peer_timeout": 2.5,
            "ack_timeout": 0.3, "connect_timeout": 0.3, "task_ttl": 5.0, "role": role}


@dataclass
class Team:
    """The agents of a running test team and the simulated robots they drive."""

    control: Agent
    ui: UIPlugin
    transport: Any
    robots: list[Agent]
    host: RobotHost
    stopped: set[str] = field(default_factory=set)

    def pose(self, name: str) -> Pose | None:
        """The robot's own Pose (from its agent, not the control node's copy)."""
        agent = next(a for a in self.robots if a.name == name)
        found = agent.query(Pose)
        return found[0] if found else None

    @property
    def via(self) -> str:
        """The control node's transport address, HOST:PORT."""
        host, port = self.transport.address
        return f"{host}:{port}"

    def kill(self, name: str) -> None:
        """Stop one robot agent (its link goes silent)."""
        agent = next(a for a in self.robots if a.name == name)
        agent.stop()
        self.stopped.add(name)

    def stop(self) -> None:
        for agent in self.robots:
            if agent.name not in self.stopped:
                agent.stop()
        self.control.stop()
        self.host.stop()


def start_team(robots: int = 3, *, ui: dict[str, Any] | None = None, mission: dict[str, Any] | None = None) -> Team:
    """Start simulated robots, their agents and a control agent with the UI; wait until all are seen.

    With `mission` (MissionControl settings) the robots run MissionControl and the UI sends
    RemoteBotMotion tasks (the two-tier design); without it the UI sends BotMotion.
    """
    world = World.load(ARENA)
    assert robots <= len(world.robot), f"{ARENA} has starts for {len(world.robot)} robots"
    host = RobotHost(world, physics_hz=100)
    for i in range(robots):
        host.add_robot(SimRobotConfig(name=f"sim{i + 1}", **FAST), port=0)  # type: ignore[arg-type]
    host.start()
    discovery = free_port()
    agents: list[Agent] = []
    control: Agent | None = None
    try:
        for i in range(robots):
            agent = Agent(f"robot{i + 1}", workers=2)
            agent.add_plugin("transport", settings=transport_settings(discovery, "robot"), name="transport")
            agent.add_plugin("erni.plugins.motion:RobotMotionControl", settings={**MOTION, "url": host.url(i)},
                             name="motion")
            if mission is not None:
                agent.add_plugin("erni.plugins.mission:MissionControl", settings=mission, name="mission")
            agents.append(agent.start())
        control = Agent("control", workers=2)
        bridge = control.add_plugin("transport", settings=transport_settings(discovery, "control"),
                                    name="transport")
        verb = "BotMotion" if mission is None else "RemoteBotMotion"
        plugin = control.add_plugin(UIPlugin, settings={"listen": "127.0.0.1:0", "verb": verb,
                                                        "speak": False, "rate_hz": 20, "floorplan": str(ARENA),
                                                        **(ui or {})}, name="ui")
        control.start()
        team = Team(control, plugin, bridge, agents, host)  # type: ignore[arg-type]
        wait_until(lambda: len(control.query(Pose)) == robots, timeout=10,
                   message="the control node did not receive every robot's Pose")
        return team
    except BaseException:
        for a in agents:
            a.stop()
        if control is not None:
            control.stop()
        host.stop()
        raise
