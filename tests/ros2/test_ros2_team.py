"""The ros2 plugin on agents whose transport runs `wire = "zenoh"`: it rides on the transport's Zenoh
session; on a control node it publishes the odometry of a robot it hears of through ERNI, and a
cmd_vel for that robot reaches it as a task through ERNI's transport; on a robot told to serve
another robot, the other robot's role policy refuses the motion task."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from typing import Any

import pytest

pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

from zenoh_ros2_sdk import ROS2Subscriber, get_topic_names_and_types  # noqa: E402

from erni import ros2_messages as messages  # noqa: E402
from erni.blackboard import Agent, Pose, Task  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.plugins.ros2 import ROS2Plugin  # noqa: E402
from erni.testing import fake_robot  # noqa: E402
from erni.transport import Peer  # noqa: E402
from tests.ros2.test_ros2_plugin import Teleop  # noqa: E402
from tests.transport.helpers import make_agent  # noqa: E402

TEAM = "rostest"


@pytest.fixture
def team(router: tuple[str, int]) -> Iterator[Callable[..., Agent]]:
    agents: list[Agent] = []

    def spawn(name: str, plugins: Callable[[Agent], None]) -> Agent:
        agent = make_agent(name, 0, echo=False, start=False, wire="zenoh",
                           zenoh={"team": TEAM, "mode": "client", "connect": [router[0]]})
        plugins(agent)
        agents.append(agent)
        return agent.start()

    yield spawn
    for agent in agents:
        agent.stop()


def test_a_control_node_shows_the_team_and_drives_a_robot_through_erni(team: Callable[..., Agent],
                                                                        ros: dict[str, Any]) -> None:
    control = team("control", lambda a: a.add_plugin(ROS2Plugin, name="ros2"))  # session "auto", no own settings
    robot = team("robot1", lambda a: a.add_plugin("motion", settings=fake_robot("robot1"), name="motion"))
    wait_until(lambda: any(p.name == "robot1" and p.up for p in control.query(Peer)), timeout=10)
    wait_until(lambda: control.blackboard.get("pose:robot1"), timeout=10, message="no Pose of robot1 at control")
    # the node's tokens are on the transport's session (its Zenoh id), not on a session of its own
    zid = str(control.plugin("transport").endpoint.session.info.zid())  # type: ignore[attr-defined]
    plugin = control.plugin("ros2")
    assert isinstance(plugin, ROS2Plugin)
    wait_until(lambda: plugin.node is not None, timeout=5)
    assert plugin.node is not None and plugin.node.zid == zid
    wait_until(lambda: dict(get_topic_names_and_types(router_port=ros["router_port"])).get("/robot1/cmd_vel"),
               timeout=5, message="robot1's topics not listed")
    got: list[Any] = []
    statuses: list[dict[str, Any]] = []
    sub = ROS2Subscriber("/robot1/odom", messages.ODOMETRY, got.append, router_port=ros["router_port"])
    status_sub = ROS2Subscriber("/erni/task_status", messages.STRING, lambda m: statuses.append(json.loads(m.data)),
                                router_port=ros["router_port"])
    teleop = Teleop(ros["router_port"])
    try:
        teleop.v = 0.25
        teleop.running.set()
        wait_until(lambda: robot.query(Pose)[0].x > 0.2, timeout=10, message="cmd_vel did not reach robot1")
        tasks = [t for t in robot.query(Task) if t.preposition == "velocity"]
        assert tasks and tasks[0].source == "control" and tasks[0].destination == "robot1"
        wait_until(lambda: got and got[-1].pose.pose.position.x > 0.2, timeout=5,
                   message="robot1's odometry not published by the control node")
        teleop.running.clear()
        wait_until(lambda: abs(robot.query(Pose)[0].v) < 0.01, timeout=5, message="robot1 kept going")
        # robot1's results came back to the control node; the task it removed ends on /erni/task_status
        uid = tasks[0].uid

        def last() -> dict[str, Any] | None:
            mine = [st for st in statuses if st["uid"] == uid]
            return mine[-1] if mine else None

        wait_until(lambda: (found := last()) is not None and found["state"] != "running", timeout=5,
                   message=f"robot1's velocity task stays running on /erni/task_status: {last()}")
        final = last()
        assert final is not None and final["state"] == "succeeded" and "stream stopped" in final["message"]
        assert any(st["uid"] == uid and st["state"] == "running" for st in statuses)  # robot1's own report
    finally:
        teleop.close()
        sub.close()
        status_sub.close()


def test_the_plugin_rides_on_the_transports_session_whatever_the_plugins_order(team: Callable[..., Agent]) -> None:
    """Plugin order is unspecified: set up before the transport, the plugin still takes the session
    the transport offers (once every plugin has been set up), not a session of its own."""
    def ros2_first(agent: Agent) -> None:
        agent.add_plugin(ROS2Plugin, name="ros2")
        agent.plugins.insert(0, agent.plugins.pop())  # listed, and so set up, before the transport

    control = team("control", ros2_first)
    plugin = control.plugins[0]
    assert isinstance(plugin, ROS2Plugin)
    wait_until(lambda: plugin.node is not None, timeout=10, message="no ROS 2 node")
    zid = str(control.plugin("transport").endpoint.session.info.zid())  # type: ignore[attr-defined]
    assert plugin.node is not None and plugin.node.zid == zid


def test_the_role_policy_decides_a_robot_agent_may_not_drive_another_robot(team: Callable[..., Agent],
                                                                            ros: dict[str, Any]) -> None:
    """robot2's plugin is told to serve robot1 too: its cmd_vel becomes a task from robot2 to robot1,
    which robot1's transport refuses (a robot tasks a robot only for a mission), so robot1 stays put."""
    robot1 = team("robot1", lambda a: a.add_plugin("motion", settings=fake_robot("robot1"), name="motion"))
    robot2 = team("robot2", lambda a: a.add_plugin(ROS2Plugin, settings={"robots": ["robot1"]}, name="ros2"))
    wait_until(lambda: any(p.name == "robot1" and p.up for p in robot2.query(Peer)), timeout=10)
    wait_until(lambda: robot1.query(Pose), timeout=5, message="robot1 has no Pose")
    wait_until(lambda: dict(get_topic_names_and_types(router_port=ros["router_port"])).get("/robot1/cmd_vel"),
               timeout=5, message="robot1's cmd_vel not listed")
    teleop = Teleop(ros["router_port"])
    try:
        teleop.v = 0.25
        teleop.running.set()
        sent = wait_until(lambda: [t for t in robot2.query(Task) if t.preposition == "velocity"], timeout=5,
                          message="robot2 posted no velocity task for robot1")
        assert sent[0].destination == "robot1"
        refused = wait_until(lambda: [t for t in robot2.query(Task) if t.preposition == "velocity" and t.done],
                             timeout=10, message="the task to robot1 was not answered")
        assert refused[0].result is not None and refused[0].result.message.startswith(
            "refused by robot1: not authorized: role robot may give a robot only Deploy"), refused[0].result
        assert not [t for t in robot1.query(Task) if t.preposition == "velocity"]
        assert abs(robot1.query(Pose)[0].x) < 0.01 and abs(robot1.query(Pose)[0].v) < 0.01
    finally:
        teleop.close()
