"""ROS 2 tests: a Zenoh router in the test process, ROBOTIS' zenoh-ros2-sdk (an independent rmw_zenoh
client) connected to it, and its message definitions given offline from rosbags' Jazzy store."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

zenoh = pytest.importorskip("zenoh")
sdk = pytest.importorskip("zenoh_ros2_sdk")

from zenoh_ros2_sdk import message_registry  # noqa: E402
from zenoh_ros2_sdk.session import ZenohSession  # noqa: E402

from erni.blackboard import Agent, Pose  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.plugins.motion import RobotMotionControl  # noqa: E402
from erni.plugins.ros2 import ROS2Plugin  # noqa: E402
from erni.ros2_messages import TYPESTORE  # noqa: E402
from erni.sim.team import free_port  # noqa: E402
from erni.testing import fake_robot  # noqa: E402

SEPARATOR = "=" * 80 + "\nMSG: "
TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/Twist", "geometry_msgs/msg/PoseStamped",
         "diagnostic_msgs/msg/DiagnosticArray",
         "tf2_msgs/msg/TFMessage", "std_msgs/msg/String", "visualization_msgs/msg/MarkerArray",
         "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/BatteryState")


def write_definitions(root: Path, typenames: tuple[str, ...] = TYPES) -> Path:
    """The `.msg` files of `typenames` and all they use, laid out as the SDK's registry reads them
    (`<root>/<package>/msg/<Name>.msg`), from rosbags' definitions: the SDK fetches nothing."""
    for typename in typenames:
        text, _ = TYPESTORE.generate_msgdef(typename, ros_version=2)
        sections = text.split(SEPARATOR)
        named = [(typename, sections[0])]
        for section in sections[1:]:
            head, _, body = section.partition("\n")
            package, name = head.strip().split("/")
            named.append((f"{package}/msg/{name}", body))
        for full, body in named:
            package, _, name = full.split("/")
            path = root / package / "msg" / f"{name}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(body.rstrip("\n") + "\n")
    return root


def erni_publisher_matched(agent: Agent, topic: str, timeout: float = 20.0) -> None:
    """Until the publisher of `topic` of `agent`'s ros2 plugin knows a subscriber of it (its Zenoh
    publisher matches one, as the router told its session): what it publishes from then on reaches it."""
    def matching() -> bool:
        node = agent.plugin("ros2").node
        pub = node.publishers.get(topic) if node is not None else None
        return pub is not None and bool(pub._pub.matching_status.matching)

    wait_until(matching, timeout=timeout, message=f"ERNI's publisher of {topic} knows no subscriber")


def sdk_publisher_matched(pub: Any, timeout: float = 20.0) -> None:
    """Until the SDK's publisher `pub` knows a subscription of its topic (ERNI's, once declared)."""
    wait_until(lambda: pub.pub.matching_status.matching, timeout=timeout,
               message=f"the SDK's publisher of {pub.topic} knows no subscription")


def commands_heard(agent: Agent, n: int, robot: str = "robot1", timeout: float = 30.0) -> None:
    """Until `agent`'s ros2 plugin has heard `n` more cmd_vel commands for `robot` (each one's arrival on
    its clock) and a run of it that began after the last of them is over: what it made of them is on the
    blackboard."""
    from tests.core.helpers import scheduler_idle

    plugin = agent.plugin("ros2")
    drive = plugin._drives[robot]
    arrivals = {drive.heard}
    wait_until(lambda: arrivals.add(drive.heard) or len(arrivals) > n, timeout=timeout,
               message=f"{len(arrivals) - 1} of {n} cmd_vel commands for {robot} heard")
    runs = plugin._run
    wait_until(lambda: plugin._run > runs and scheduler_idle(plugin), timeout=timeout, message="the ros2 plugin did not run")


@pytest.fixture(scope="session")
def definitions(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_definitions(tmp_path_factory.mktemp("msg"))


@pytest.fixture(scope="module")
def router() -> Iterator[tuple[str, int]]:
    """A Zenoh router in this process (as zenohd would run for rmw_zenoh); yields (endpoint, port)."""
    from erni.transport.zenoh_wire import open_router
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    session = open_router([endpoint])
    yield endpoint, port
    session.close()


@pytest.fixture
def ros(router: tuple[str, int], definitions: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, Any]]:
    """The SDK's shared session on the router, its registry reading `definitions` (no git, no network)."""
    monkeypatch.setenv("ZENOH_ROS2_SDK_CACHE", str(definitions / "no-cache"))
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    message_registry._registry = None
    message_registry.get_registry(str(definitions))
    ZenohSession._instance = None
    session = ZenohSession.get_instance("127.0.0.1", router[1])
    yield {"router_ip": "127.0.0.1", "router_port": router[1], "session": session}
    session.close()
    message_registry._registry = None


@pytest.fixture
def robot(router: tuple[str, int]) -> Iterator[Callable[..., Agent]]:
    """robot1: the motion plugin on ERNI's simulated robot and the ros2 plugin on its own Zenoh session."""
    agents: list[Agent] = []

    def start(name: str = "robot1", **settings: Any) -> Agent:
        agent = Agent(name, workers=2)
        agent.add_plugin(RobotMotionControl, settings=fake_robot(name), name="motion")
        agent.add_plugin(ROS2Plugin, settings={"session": "own", "mode": "client", "connect": [router[0]],
                                               **settings}, name="ros2")
        agents.append(agent)
        agent.start()
        wait_until(lambda: agent.query(Pose), timeout=5, message="no Pose published")
        return agent

    yield start
    for agent in agents:
        agent.stop()
