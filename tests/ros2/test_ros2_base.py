"""The motion plugin driving a ROS 2 base (`url = "ros2://tb3?..."`): a simulated differential-drive base
written here with zenoh-ros2-sdk (its own node: Twist on /tb3/cmd_vel in; Odometry on /tb3/odom and a
LaserScan on /tb3/scan out) takes the behaviour stack's commands; goto, forward and turn end within
their tolerances, a stop halts it, a wall in the scan stops it short, a silent base fails the task."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import pytest

pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

from pydantic import ValidationError  # noqa: E402

from erni.blackboard import Agent, Pose, TaskState  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.plugins.motion import RobotMotionControl  # noqa: E402
from erni.plugins.motion.plugin import MotionSettings  # noqa: E402
from erni.plugins.motion.ros2_base import parse_url, scan_sectors  # noqa: E402
from erni.testing import post_task, run_task, wait_for_task  # noqa: E402
from tests.ros2.diffdrive import DiffDriveBase  # noqa: E402


@pytest.fixture
def base_and_agent(ros: dict[str, Any]) -> Iterator[Callable[..., tuple[DiffDriveBase, Agent]]]:
    made: list[tuple[DiffDriveBase, Agent]] = []

    def start(wall: float | None = None, **settings: Any) -> tuple[DiffDriveBase, Agent]:
        base = DiffDriveBase(ros["router_port"], wall=wall)
        agent = Agent("tb3", workers=2)
        url = f"ros2://tb3?connect=tcp/127.0.0.1:{ros['router_port']}&mode=client"
        agent.add_plugin(RobotMotionControl, settings={"url": url, "rate_hz": 20, "link_timeout": 1.0,
                                                       "link_grace": 1.0, "blocked_timeout": 2.0, **settings},
                         name="motion")
        made.append((base, agent))
        agent.start()
        wait_until(lambda: agent.query(Pose), timeout=10, message="no Pose from the ROS 2 base's odometry")
        return base, agent

    yield start
    for base, agent in made:
        agent.stop()
        base.close()


def test_urls_are_checked_in_one_line() -> None:
    assert parse_url("ros2://tb3?connect=tcp/10.0.0.2:7447&mode=client&domain=7") == {
        "namespace": "/tb3", "connect": ["tcp/10.0.0.2:7447"], "mode": "client", "domain": 7, "scan": "scan",
        "battery": "battery_state"}
    assert parse_url("ros2://")["namespace"] == "" and parse_url("ros2://a/b?scan=")["scan"] == ""
    for bad, words in (("ros2://tb-3", "not a ROS 2 name"), ("ros2://tb3?domain=300", "0-232"),
                       ("ros2://tb3?speed=1", "unknown parameter"), ("ros2://tb3?connect=10.0.0.2", "PROTOCOL/HOST")):
        with pytest.raises(ValidationError) as err:
            MotionSettings(url=bad)
        assert words in str(err.value), (bad, str(err.value))


def test_scan_sectors() -> None:
    ranges = [1.0, 0.5, float("inf"), 9.0]  # ahead, 90 deg left, behind (nothing), 90 deg right (beyond range_max)
    got = scan_sectors(0.0, math.pi / 2, ranges, 0.1, 3.5)
    assert got == {0: 1.0, 4: 0.5, 8: 5.0, 12: 5.0}


def test_goto_forward_and_turn_on_a_ros2_base(base_and_agent: Callable[..., tuple[DiffDriveBase, Agent]]) -> None:
    base, agent = base_and_agent()
    assert agent.query(Pose)[0].battery == 12.3  # the BatteryState's voltage, in the first Pose already
    done = run_task(agent, "BotMotion", "goto", x=1.0, y=0.5, timeout=30)
    assert done.state is TaskState.SUCCEEDED, done.result
    assert math.hypot(base.x - 1.0, base.y - 0.5) <= 0.1 + 0.05  # the goto's tolerance, and the stop's coast
    assert base.commands > 10
    done = run_task(agent, "BotMotion", "turn", angle=90, timeout=20)
    assert done.state is TaskState.SUCCEEDED, done.result
    heading = math.degrees(agent.query(Pose)[0].theta)
    th0 = heading
    done = run_task(agent, "BotMotion", "forward", distance=0.5, timeout=20)
    assert done.state is TaskState.SUCCEEDED, done.result
    pose = agent.query(Pose)[0]
    assert abs(math.degrees(pose.theta) - th0) < 5
    assert math.hypot(base.v, base.w) < 0.05  # it stands at the end


def test_a_stop_halts_the_base_and_a_silent_base_fails_the_task(
        base_and_agent: Callable[..., tuple[DiffDriveBase, Agent]]) -> None:
    base, agent = base_and_agent()
    moving = post_task(agent, "BotMotion", "velocity", v=0.3)
    wait_until(lambda: base.v > 0.25, timeout=5, message="the base did not take the velocity")
    # a standing command is repeated for the base's cmd_vel watchdog (0.5 s here): it never slows down,
    # watched (the speed sampled at each look) until the base has heard commands for twice its watchdog
    before, first, speeds = base.commands, base.cmd_at, []
    wait_until(lambda: speeds.append(base.v) or (base.commands - before >= 4 and base.cmd_at - first >= 1.0),
               timeout=20, message="the standing command was not repeated")
    assert min(speeds) > 0.25, (base.commands - before, min(speeds))
    stop = run_task(agent, "BotMotion", "stop", timeout=5)
    assert stop.state is TaskState.SUCCEEDED, stop.result
    assert wait_for_task(agent, moving, timeout=5).state is TaskState.CANCELLED
    assert abs(base.v) < 0.01 and abs(agent.query(Pose)[0].v) < 0.01
    # the base's odometry stops coming: the link is lost and the task fails
    long = post_task(agent, "BotMotion", "velocity", v=0.2)
    wait_until(lambda: base.v > 0.15, timeout=5)
    base.silent.set()
    failed = wait_for_task(agent, long, timeout=10)
    assert failed.state is TaskState.FAILED and failed.result is not None
    assert failed.result.message.startswith("link lost: no Odometry on /tb3/odom within 1 s"), failed.result
    # no command for 0.5 s: the base stopped itself (it would go on at 0.2 m/s on a repeated command)
    wait_until(lambda: abs(base.v) < 0.01, timeout=20, message="the base still drives")


def test_a_wall_in_the_scan_stops_the_base_short(base_and_agent: Callable[..., tuple[DiffDriveBase, Agent]]) -> None:
    base, agent = base_and_agent(wall=1.5, avoid_distance=0.4)
    task = post_task(agent, "BotMotion", "velocity", v=0.3)
    wait_until(lambda: base.v > 0.25, timeout=5)
    wait_until(lambda: base.x > 0.5 and abs(base.v) < 0.01, timeout=15, message="the base did not stop at the wall")
    odometry = agent.plugin("motion").resource.driver.stats
    seen = odometry.sips
    wait_until(lambda: odometry.sips >= seen + 10, timeout=20)  # ten Odometry samples (0.5 s) on, it still stands
    assert 0.5 < base.x < 1.5 - 0.3, base.x  # stopped short of the wall
    pose = agent.query(Pose)[0]
    assert pose.sonar and min(pose.sonar) < 1.0  # the scan reached the avoidance as sonar echoes
    blocked = wait_for_task(agent, task, timeout=10)  # held by the avoidance for blocked_timeout: it gives up
    assert blocked.state is TaskState.FAILED and "blocked by an obstacle" in (blocked.result.message
                                                                             if blocked.result else ""), blocked


def test_a_base_whose_router_comes_later_is_driven_once_it_does(definitions: Any) -> None:
    """The agent starts while nothing listens on the router's port (the driver says why it has no link);
    once the router and the base come up, the driver opens its session by itself and the base is driven."""
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    from erni.sim.team import free_port
    from erni.transport.zenoh_wire import open_router

    port = free_port()
    agent = Agent("tb3", workers=2)
    url = f"ros2://tb3?connect=tcp/127.0.0.1:{port}&mode=client"
    plugin = agent.add_plugin(RobotMotionControl, settings={"url": url, "rate_hz": 20}, name="motion")
    router = base = None
    agent.start()
    try:
        wait_until(lambda: plugin.resource.driver.last_error, timeout=20, message="the driver says nothing")
        assert not agent.query(Pose)
        assert plugin.resource.driver.last_error.startswith("cannot open a Zenoh session: Unable to connect")
        router = open_router([f"tcp/127.0.0.1:{port}"])
        message_registry._registry = None
        message_registry.get_registry(str(definitions))
        ZenohSession._instance = None
        base = DiffDriveBase(port)
        wait_until(lambda: agent.query(Pose), timeout=10, message="no Pose once the router came")
        done = run_task(agent, "BotMotion", "forward", distance=0.3, timeout=20)
        assert done.state is TaskState.SUCCEEDED, done.result
        assert base.x == pytest.approx(0.3, abs=0.05)
    finally:
        agent.stop()
        if base is not None:
            base.close()
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
        message_registry._registry = None
        if router is not None:
            router.close()


def test_odometry_with_nan_or_an_infinity_is_refused_and_the_base_is_read_on() -> None:
    """An Odometry sample of a base whose driver sends NaN or an infinity (as CDR doubles carry them)
    makes no robot state: it is counted as a bad sample and named, and the next good one is read."""
    from erni import ros2_messages as messages
    from erni.plugins.motion.ros2_base import Ros2BaseDriver

    driver = Ros2BaseDriver("ros2://tb3?battery=", name="tb3")  # not opened: fed samples by hand

    def odometry(x: float, y: float, v: float = 0.0) -> bytes:
        pose = Pose.model_construct(robot="tb3", x=x, y=y, theta=0.0, v=v, w=0.0)  # what a faulty driver sends
        return messages.serialize(messages.odometry(pose, 0))

    for x, y, v in ((math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (1.0, 2.0, -math.inf)):
        driver._on_odom(odometry(x, y, v))
        assert driver.state is None
    assert driver.stats.bad_sips == 3 and "expected finite numbers" in driver.last_error
    driver._on_odom(odometry(1.0, 2.0))
    assert driver.state is not None and (driver.state.x, driver.state.y) == (1.0, 2.0)
