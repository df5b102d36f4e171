"""ROS 2 on a secured team: a TLS router whose access control comes from the team's certificates
(`erni router --acl`), the control node's ros2 plugin on its transport's session through it, and
ROBOTIS' zenoh-ros2-sdk (an independent rmw_zenoh client) connecting with certificates of several
roles. A watcher sees the team but moves nothing; an operator drives; a robot's certificate sees
nothing."""

from __future__ import annotations

import io
import json
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

from zenoh_ros2_sdk import ROS2ServiceClient, ROS2Subscriber, get_topic_names_and_types, message_registry  # noqa: E402
from zenoh_ros2_sdk.discovery import get_service_names_and_types  # noqa: E402
from zenoh_ros2_sdk.session import ZenohSession  # noqa: E402

from erni import ros2_messages as messages  # noqa: E402
from erni.blackboard import Agent, Pose, Task  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.plugins.ros2 import ROS2Plugin  # noqa: E402
from erni.sim.team import free_port  # noqa: E402
from erni.testing import fake_robot  # noqa: E402
from erni.transport import Peer  # noqa: E402
from erni.transport.identity import load_identity  # noqa: E402
from tests.ros2.test_ros2_plugin import Teleop  # noqa: E402
from tests.transport.helpers import authority, identity, make_agent  # noqa: E402

TEAM = "rosacl"
CERTS = {"control": "control", "robot1": "robot", "robot2": "robot", "rviz-viewer": "observer",
         "rviz-operator": "cli", "zrouter": "router", "site-b": "router"}


@pytest.fixture
def secured(definitions: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, Any]]:
    """`erni router --acl KEYS --team rosacl` over TLS (its access control from the team authority's
    certificates, all issued before it starts), and the SDK's registry reading `definitions`."""
    from erni.commands.router import serve
    from erni.transport.zenoh_acl import access_control, team_roles

    paths = {name: identity(name, role) for name, role in CERTS.items()}
    agents, routers = team_roles(str(authority().dir))
    access = access_control(TEAM, sorted(agents), routers, roles=agents)
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    stop = threading.Event()
    threads: list[threading.Thread] = []

    def router(listen: str, connect: list[str], name: str) -> None:
        out = io.StringIO()
        thread = threading.Thread(target=serve, args=([listen], connect, False, stop, out),
                                  kwargs={"identity": load_identity(paths[name]), "access": access, "team": TEAM})
        thread.start()
        threads.append(thread)
        wait_until(lambda: "listening" in out.getvalue(), timeout=10, message=f"router {name} did not start")

    router(endpoint, [], "zrouter")
    monkeypatch.setenv("ZENOH_ROS2_SDK_CACHE", str(definitions / "no-cache"))
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    message_registry._registry = None
    message_registry.get_registry(str(definitions))
    sessions: list[ZenohSession] = []
    yield {"endpoint": endpoint, "port": port, "paths": paths, "access": access, "sessions": sessions,
           "definitions": definitions, "router": router}
    for session in sessions:
        session.close()
    ZenohSession._instance = None
    message_registry._registry = None
    stop.set()
    for thread in threads:
        thread.join(10)


def ros_client(secured: dict[str, Any], monkeypatch: pytest.MonkeyPatch, name: str,
               endpoint: str | None = None) -> ZenohSession:
    """The SDK's shared session, on the TLS router (at `endpoint`, by default the first one) with the
    certificate of `name` (as rmw_zenoh is given one: ZENOH_CONFIG_OVERRIDE), made the one its
    publishers and subscribers use from now on (whatever router_port they are given)."""
    from erni.transport.zenoh_wire import tls_config

    tls = json.dumps(tls_config(load_identity(secured["paths"][name])))
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", f'mode="client";connect/endpoints=["{endpoint or secured["endpoint"]}"];'
                       f"transport/link/tls={tls}")
    ZenohSession._instance = None
    message_registry._registry = None  # it remembers which types it gave a session: a new one needs them again
    message_registry.get_registry(str(secured["definitions"]))
    session = ZenohSession.get_instance("127.0.0.1", secured["port"])
    secured["sessions"].append(session)
    return session


@pytest.fixture
def team(secured: dict[str, Any]) -> Iterator[Callable[..., Agent]]:
    agents: list[Agent] = []

    def spawn(name: str, plugins: Callable[[Agent], None]) -> Agent:
        agent = make_agent(name, 0, echo=False, start=False, wire="zenoh", role=CERTS[name],
                           zenoh={"team": TEAM, "mode": "client", "connect": [secured["endpoint"]]})
        plugins(agent)
        agents.append(agent)
        return agent.start()

    yield spawn
    for agent in agents:
        agent.stop()


def test_the_routers_access_control_admits_ros2_by_role(secured: dict[str, Any]) -> None:
    """What `erni router --acl` generates: the control node's certificate may do anything in domain 0,
    a watcher's subscribe, an operator's publish commands; a robot's certificate none of it."""
    subjects = {s["id"]: s["cert_common_names"] for s in secured["access"]["subjects"]}
    assert "control" in subjects["ROS 2 node"] and "robot1" not in subjects["ROS 2 node"]
    assert {"rviz-viewer", "rviz-operator"} <= set(subjects["ROS 2 watchers"])
    assert "rviz-operator" in subjects["ROS 2 drivers"] and "rviz-viewer" not in subjects["ROS 2 drivers"]
    everyone = {n for names in subjects.values() if isinstance(names, list) for n in names}
    rosless = {n for g, names in subjects.items() if g.startswith("ROS 2") for n in names}
    assert {"robot1", "robot2"} <= everyone - rosless


def test_a_watcher_sees_the_team_through_the_acl_router_and_only_an_operator_drives_it(
        secured: dict[str, Any], team: Callable[..., Agent], monkeypatch: pytest.MonkeyPatch) -> None:
    control = team("control", lambda a: a.add_plugin(ROS2Plugin, name="ros2"))  # on the transport's session
    robot = team("robot1", lambda a: a.add_plugin("motion", settings=fake_robot("robot1"), name="motion"))
    wait_until(lambda: any(p.name == "robot1" and p.up for p in control.query(Peer)), timeout=15)
    wait_until(lambda: control.blackboard.get("pose:robot1"), timeout=10, message="no Pose of robot1 at control")
    plugin = control.plugin("ros2")
    assert isinstance(plugin, ROS2Plugin)
    wait_until(lambda: plugin.node is not None, timeout=10, message="no ROS 2 node")
    port = secured["port"]

    # a robot's certificate: a TLS link, but no ROS 2 topic, token or sample; what it is refused, a
    # watcher's session beside it (a witness) gets from the same router
    witness = zenoh_client(secured, "rviz-viewer")
    try:
        ros_client(secured, monkeypatch, "robot2")
        wait_until(lambda: odom_token(witness), timeout=10, message="the router has no token of robot1's odometry")
        assert not dict(get_topic_names_and_types(router_port=port)), "a robot's certificate saw ROS 2 tokens"
        denied: list[Any] = []
        sub = ROS2Subscriber("/robot1/odom", messages.ODOMETRY, denied.append, router_port=port)
        witnessed: list[Any] = []
        witness.declare_subscriber("0/robot1/odom/**", witnessed.append)  # declared after the robot's
        wait_until(lambda: len(witnessed) >= 3, timeout=15, message="the witness received no odometry")
        sub.close()
        assert not denied, "a robot's certificate received odometry"
    finally:
        witness.close()

    # a watcher's certificate (role observer): the team's topics and odometry
    ros_client(secured, monkeypatch, "rviz-viewer")
    wait_until(lambda: dict(get_topic_names_and_types(router_port=port)).get("/robot1/odom"), timeout=10,
               message="the watcher does not see robot1's odometry topic")
    got: list[Any] = []
    sub = ROS2Subscriber("/robot1/odom", messages.ODOMETRY, got.append, router_port=port)
    wait_until(lambda: got, timeout=10, message="the watcher received no odometry")
    x0 = robot.query(Pose)[0].x
    teleop = Teleop(port)  # the watcher's cmd_vel: refused at the router
    try:
        teleop.v = 0.25
        teleop.running.set()
        # 20 Twists sent (2 s), and odometry through the same router to the same session meanwhile
        heard = len(got)
        wait_until(lambda: teleop.sent >= 20 and len(got) >= heard + 2, timeout=30,
                   message="the watcher's teleop did not run, or its odometry stopped")
        teleop.running.clear()
        assert "robot1" not in plugin._drives, "the watcher's cmd_vel reached the ros2 plugin"
        assert not [t for t in robot.query(Task) if t.preposition == "velocity"]
        assert abs(robot.query(Pose)[0].x - x0) < 0.01
        # it sees the stop service, but its call is not let through (an operator's is, below)
        assert "/robot1/stop" in dict(get_service_names_and_types(router_port=port))
        assert stop_client(port, timeout=2.0).call() is None
        assert not [t for t in robot.query(Task) if t.preposition == "stop"]
    finally:
        teleop.close()
        sub.close()

    # an operator's certificate (role cli): its cmd_vel drives robot1, as a task of the control node
    ros_client(secured, monkeypatch, "rviz-operator")
    teleop = Teleop(port)
    try:
        teleop.v = 0.25
        teleop.running.set()
        wait_until(lambda: robot.query(Pose)[0].x > x0 + 0.2, timeout=15, message="the operator's cmd_vel did "
                   "not move robot1")
        tasks = [t for t in robot.query(Task) if t.preposition == "velocity"]
        assert tasks and tasks[0].source == "control"
        response = stop_client(port).call()  # the operator's stop, while its teleop goes on
        assert response is not None and response.success is True and response.message == "halted: robot1"
        wait_until(lambda: abs(robot.query(Pose)[0].v) < 0.02, timeout=5, message="robot1 kept going")
    finally:
        teleop.close()


def zenoh_client(secured: dict[str, Any], name: str) -> Any:
    """A Zenoh client session of its own (not the SDK's shared one) on the TLS router, with the
    certificate of `name`."""
    import zenoh

    from erni.transport.zenoh_wire import tls_config

    conf = zenoh.Config()
    for key, value in (("mode", "client"), ("connect/endpoints", [secured["endpoint"]]),
                       ("transport/link/tls", tls_config(load_identity(secured["paths"][name])))):
        conf.insert_json5(key, json.dumps(value))
    return zenoh.open(conf)


def odom_token(session: Any) -> bool:
    """Whether the router answers `session`'s liveliness query with the token of a publisher of
    /robot1/odom (rmw_zenoh's, '/' written '%')."""
    replies = session.liveliness().get("@ros2_lv/0/**", timeout=1.0)
    return any(r.ok is not None and "/MP/" in str(r.ok.key_expr) and "%robot1%odom/" in str(r.ok.key_expr)
               for r in replies)


def stop_client(port: int, timeout: float = 10.0) -> Any:
    """The SDK's client of std_srvs/Trigger on /robot1/stop (its definitions given, as rosidl makes them)."""
    return ROS2ServiceClient("/robot1/stop", messages.TRIGGER, router_port=port, timeout=timeout,
                             request_definition="uint8 structure_needs_at_least_one_member\n",
                             response_definition="bool success\nstring message\n")


def test_at_another_site_a_watcher_sees_the_team_and_an_operator_drives_it_through_both_routers(
        secured: dict[str, Any], team: Callable[..., Agent], monkeypatch: pytest.MonkeyPatch) -> None:
    """Site B's router (a certificate of role router) linked to site A's, both with the access control:
    ROS 2 clients at site B, the control node and robot1 at site A."""
    site_b = f"tls/127.0.0.1:{free_port()}"
    secured["router"](site_b, [secured["endpoint"]], "site-b")
    control = team("control", lambda a: a.add_plugin(ROS2Plugin, name="ros2"))
    robot = team("robot1", lambda a: a.add_plugin("motion", settings=fake_robot("robot1"), name="motion"))
    wait_until(lambda: any(p.name == "robot1" and p.up for p in control.query(Peer)), timeout=15)
    plugin = control.plugin("ros2")
    assert isinstance(plugin, ROS2Plugin)
    wait_until(lambda: plugin.node is not None, timeout=10, message="no ROS 2 node")
    ros_client(secured, monkeypatch, "rviz-viewer", site_b)
    wait_until(lambda: dict(get_topic_names_and_types(router_port=0)).get("/robot1/odom"), timeout=10,
               message="the watcher at site B does not see robot1's odometry topic")
    got: list[Any] = []
    sub = ROS2Subscriber("/robot1/odom", messages.ODOMETRY, got.append, router_port=0)
    try:
        wait_until(lambda: got, timeout=10, message="the watcher at site B received no odometry")
    finally:
        sub.close()
    ros_client(secured, monkeypatch, "rviz-operator", site_b)
    x0 = robot.query(Pose)[0].x
    teleop = Teleop(0)
    try:
        teleop.v = 0.25
        teleop.running.set()
        wait_until(lambda: robot.query(Pose)[0].x > x0 + 0.2, timeout=15,
                   message="the operator's cmd_vel at site B did not move robot1")
        teleop.running.clear()
        wait_until(lambda: abs(robot.query(Pose)[0].v) < 0.01, timeout=5, message="robot1 kept going")
    finally:
        teleop.close()


def test_a_client_without_a_team_certificate_gets_no_link(secured: dict[str, Any]) -> None:
    """A ROS 2 client that trusts the team's authority but shows no certificate of it: the router's
    mutual TLS refuses the link, so a client session does not even open."""
    import zenoh

    from erni.transport.zenoh_wire import tls_config

    def config(tls: dict[str, Any]) -> zenoh.Config:
        conf = zenoh.Config()
        for key, value in (("mode", "client"), ("connect/endpoints", [secured["endpoint"]]),
                           ("transport/link/tls", tls)):
            conf.insert_json5(key, json.dumps(value))
        return conf

    tls = tls_config(load_identity(secured["paths"]["rviz-viewer"]))
    zenoh.open(config(tls)).close()  # with its certificate it connects
    with pytest.raises(zenoh.ZError):
        zenoh.open(config({"root_ca_certificate_base64": tls["root_ca_certificate_base64"],
                           "verify_name_on_connect": False})).close()
