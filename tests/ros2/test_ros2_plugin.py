"""The ros2 plugin against ROBOTIS' zenoh-ros2-sdk (an independent rmw_zenoh client, no ROS 2 install):
its discovery lists ERNI's topics with their types, its subscriber decodes ERNI's Odometry, its
publishers drive an ERNI robot through cmd_vel (an ERNI stop still halts it) and goal_pose; and what
was learnt of rmw_zenoh's wire, pinned as bytes."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

from pydantic import ValidationError  # noqa: E402
from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, get_topic_info, get_topic_names_and_types  # noqa: E402
from zenoh_ros2_sdk.attachment import Attachment  # noqa: E402
from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity  # noqa: E402
from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, topic_keyexpr  # noqa: E402
from zenoh_ros2_sdk.qos import QosProfile  # noqa: E402

from erni import ros2_messages as messages  # noqa: E402
from erni import ros2_rmw as rmw  # noqa: E402
from erni.blackboard import Agent, Pose, Task, TaskState  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.plugins.ros2 import ROS2Settings  # noqa: E402
from erni.plugins.ros2 import plugin as plugin_module  # noqa: E402
from erni.testing import find_task, post_task, run_task, wait_for_task  # noqa: E402
from tests.ros2.conftest import commands_heard, erni_publisher_matched, sdk_publisher_matched  # noqa: E402

ODOM_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
ZID = "98517b73ab05dcb895c1c42cdfe891cd"


# --- what was learnt, pinned ------------------------------------------------------------------


def test_key_expressions_tokens_and_hashes_are_rmw_zenohs() -> None:
    assert messages.type_hash(messages.ODOMETRY) == ODOM_HASH
    assert messages.type_hash(messages.TWIST) == TWIST_HASH
    assert messages.dds_type_name(messages.ODOMETRY) == "nav_msgs::msg::dds_::Odometry_"
    key = rmw.topic_key(0, "/robot1/odom", messages.ODOMETRY)
    assert key == f"0/robot1/odom/nav_msgs::msg::dds_::Odometry_/{ODOM_HASH}"
    assert rmw.node_token(0, ZID, 7, "/", "erni_control") == f"@ros2_lv/0/{ZID}/7/7/NN/%/%/erni_control"
    token = rmw.endpoint_token(3, ZID, 7, 9, "MS", "/", "erni_control", "/robot1/cmd_vel", messages.TWIST,
                               rmw.DEFAULT_QOS)
    assert token == (f"@ros2_lv/3/{ZID}/7/9/MS/%/%/erni_control/%robot1%cmd_vel/"
                     f"geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}/::,10:,:,:,,")
    assert rmw.QoS(reliable=False, depth=5).encode() == "2::,5:,:,:,,"
    assert rmw.QoS(transient_local=True, depth=1).encode() == ":1:,1:,:,:,,"
    assert rmw.QoS(depth=42).encode() == "::,:,:,:,,"  # rmw_zenoh's default depth is left out
    # the independent client builds the same strings
    assert topic_keyexpr(0, "/robot1/odom", "nav_msgs::msg::dds_::Odometry_", ODOM_HASH) == key
    node = NodeEntity(domain_id=3, session_id=ZID, node_id=7, node_name="erni_control", namespace="/")
    ep = EndpointEntity(node=node, entity_id=9, kind=EntityKind.SUBSCRIPTION, name="/robot1/cmd_vel",
                        dds_type_name="geometry_msgs::msg::dds_::Twist_", type_hash=TWIST_HASH,
                        qos=QosProfile().encode())
    assert endpoint_liveliness_keyexpr(ep) == token


def test_the_sdk_computes_the_same_type_hashes_from_the_definitions(ros: dict[str, Any]) -> None:
    """The SDK hashes the .msg text itself (its own RIHS01 code); rosbags hashes its built-in store."""
    for typename in (messages.ODOMETRY, messages.TWIST, messages.POSE_STAMPED, messages.TF_MESSAGE):
        pub = ROS2Publisher(f"/hash_check/{typename.split('/')[-1].lower()}", typename,
                            router_port=ros["router_port"])
        try:
            assert pub.type_hash == messages.type_hash(typename), typename
        finally:
            pub.close()


def test_attachment_bytes() -> None:
    gid = bytes(range(16))
    data = rmw.attachment(5, 1_700_000_000_123_456_789, gid)
    assert data.hex() == "0500000000000000" "15cd853dfe9c9717" "10" "000102030405060708090a0b0c0d0e0f"
    assert rmw.parse_attachment(data) == (5, 1_700_000_000_123_456_789, gid)
    assert Attachment.from_bytes(data) == Attachment(5, 1_700_000_000_123_456_789, gid)
    # zenoh's own serialiser writes the same: two int64, then the GID as a length-prefixed sequence
    from zenoh.ext import Int64, z_serialize
    assert z_serialize((Int64(5), Int64(1_700_000_000_123_456_789), gid)).to_bytes() == data


ODOM_CDR = (
    "00010000" "4cb2ab65" "15cd5b07" "04000000" "6d617000" "11000000" "726f626f74312f626173655f6c696e6b00000000"
    "000000000000f83f" "000000000000e0bf" "0000000000000000"
    "0000000000000000" "0000000000000000" "5941a5178d11e23f" "155b483c2669ea3f"
    + "0000000000000000" * 36
    + "333333333333d33f" "0000000000000000" "0000000000000000"
    + "0000000000000000" "0000000000000000" "9a9999999999b93f"
    + "0000000000000000" * 36
)


def test_odometry_cdr_bytes() -> None:
    pose = Pose(robot="robot1", x=1.5, y=-0.5, theta=1.2, v=0.3, w=0.1, stamp=1705751116.123456789)
    msg = messages.odometry(pose, 1_705_751_116_123_456_789)
    data = messages.serialize(msg)
    assert data.hex() == ODOM_CDR
    back = messages.deserialize(data, messages.ODOMETRY)
    assert back.header.frame_id == "map" and back.child_frame_id == "robot1/base_link"
    assert math.isclose(messages.yaw(back.pose.pose.orientation), 1.2)


def test_settings_refuse_bad_values_in_one_line() -> None:
    assert plugin_module.ros_name("robot-1") == "robot_1" and plugin_module.ros_name("2nd") == "r2nd"
    for bad, words in (({"domain_id": 300}, "domain_id"), ({"connect": ["localhost"]}, "PROTOCOL/HOST:PORT"),
                       ({"robots": [" "]}, "an empty name"), ({"node_name": "erni-1"}, "letters, digits and '_'"),
                       ({"mode": "client", "connect": []}, "needs connect"), ({"tf": "maybe"}, "tf")):
        with pytest.raises(ValidationError) as err:
            ROS2Settings(**bad)
        assert words in str(err.value), (bad, str(err.value))


# --- against the independent client --------------------------------------------------------------


def test_the_sdks_topic_list_shows_erni_topics_with_their_types(robot: Callable[..., Agent],
                                                                 ros: dict[str, Any]) -> None:
    robot()
    want = {"/robot1/odom": ["nav_msgs/msg/Odometry"], "/robot1/cmd_vel": ["geometry_msgs/msg/Twist"],
            "/robot1/goal_pose": ["geometry_msgs/msg/PoseStamped"], "/tf": ["tf2_msgs/msg/TFMessage"],
            "/robot1/sonar": ["sensor_msgs/msg/LaserScan"],
            "/erni/task_status": ["std_msgs/msg/String"], "/erni/network": ["visualization_msgs/msg/MarkerArray"],
            "/diagnostics": ["diagnostic_msgs/msg/DiagnosticArray"]}

    def listed() -> dict[str, list[str]] | None:
        topics = dict(get_topic_names_and_types(router_port=ros["router_port"]))
        return topics if all(topics.get(k) == v for k, v in want.items()) else None

    topics = wait_until(listed, timeout=5, message="ERNI's topics not listed")
    assert topics is not None
    info = get_topic_info("/robot1/odom", router_port=ros["router_port"], verbose=True)
    assert info.publisher_count == 1 and info.publishers[0].node_name == "erni_robot1"
    assert info.publishers[0].type_hash == ODOM_HASH and info.publishers[0].qos == "::,10:,:,:,,"
    info = get_topic_info("/robot1/cmd_vel", router_port=ros["router_port"], verbose=True)
    assert info.subscriber_count == 1 and info.subscribers[0].topic_type == "geometry_msgs/msg/Twist"


def test_the_sdks_subscriber_decodes_erni_odometry(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    agent = robot()
    got: list[Any] = []
    raw: list[tuple[bytes, bytes | None]] = []
    sub = ROS2Subscriber("/robot1/odom", messages.ODOMETRY, got.append, router_port=ros["router_port"])
    key = rmw.topic_key(0, "/robot1/odom", messages.ODOMETRY)
    tap = ros["session"].session.declare_subscriber(key, lambda s: raw.append(
        (s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment is not None else None)))
    try:
        done = run_task(agent, "BotMotion", "goto", x=0.6, y=0.4, timeout=20)
        assert done.state is TaskState.SUCCEEDED, done.result

        def matching() -> tuple[Any, Pose] | None:  # the Odometry of the Pose on the blackboard now
            pose = agent.query(Pose)[0]
            stamp = messages.stamp_ns_of(pose.stamp)
            msg = next((m for m in reversed(got) if m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == stamp),
                       None)
            return (msg, pose) if msg is not None else None

        found = wait_until(matching, timeout=5, message="no Odometry with the Pose's stamp")
        assert found is not None
        msg, pose = found
    finally:
        sub.close()
        tap.undeclare()
    assert msg.header.frame_id == "robot1/odom" and msg.child_frame_id == "robot1/base_link"  # REP 105
    assert msg.pose.pose.position.x == pytest.approx(pose.x) and msg.pose.pose.position.y == pytest.approx(pose.y)
    assert messages.yaw(msg.pose.pose.orientation) == pytest.approx(pose.theta)
    assert msg.twist.twist.linear.x == pytest.approx(pose.v) and msg.twist.twist.angular.z == pytest.approx(pose.w)
    assert math.hypot(pose.x - 0.6, pose.y - 0.4) <= 0.1
    # attachments: increasing sequence numbers, one 16-byte GID, the header's stamp as source time
    assert raw and all(a is not None for _, a in raw)
    parsed = [rmw.parse_attachment(a) for _, a in raw if a is not None]
    assert [p[0] for p in parsed] == sorted(p[0] for p in parsed) and len({p[2] for p in parsed}) == 1
    last = messages.deserialize(raw[-1][0], messages.ODOMETRY)
    assert parsed[-1][1] == last.header.stamp.sec * 10**9 + last.header.stamp.nanosec


class Teleop:
    """A ROS 2 teleop (the SDK's publisher) sending one Twist every 0.1 s from its own thread."""

    def __init__(self, port: int, topic: str = "/robot1/cmd_vel") -> None:
        self.pub = ROS2Publisher(topic, messages.TWIST, router_port=port)
        self.v, self.w = 0.0, 0.0
        self.sent = 0  # Twists published
        self.running = threading.Event()
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="test-teleop")
        self.thread.start()

    def _loop(self) -> None:
        while not self.closing.is_set():
            if self.running.is_set():
                self.pub.publish(linear=messages.make("geometry_msgs/msg/Vector3", x=self.v),
                                 angular=messages.make("geometry_msgs/msg/Vector3", z=self.w))
                self.sent += 1
            self.closing.wait(0.1)

    def close(self) -> None:
        self.closing.set()
        self.thread.join()
        self.pub.close()


@pytest.fixture
def teleop(ros: dict[str, Any]) -> Iterator[Teleop]:
    t = Teleop(ros["router_port"])
    yield t
    t.close()


def _velocity_tasks(agent: Agent) -> list[Task]:
    return [t for t in agent.query(Task) if t.preposition == "velocity"]


def test_cmd_vel_moves_the_robot_and_an_erni_stop_halts_it(robot: Callable[..., Agent], teleop: Teleop) -> None:
    agent = robot()
    teleop.v, teleop.w = 0.3, 0.0
    teleop.running.set()
    wait_until(lambda: agent.query(Pose)[0].v > 0.25, timeout=5, message="cmd_vel did not move the robot")
    x0 = agent.query(Pose)[0].x
    wait_until(lambda: agent.query(Pose)[0].x > x0 + 0.1, timeout=5, message="the robot did not drive on")
    (task,) = [t for t in _velocity_tasks(agent) if not t.done]  # one task carries the stream
    assert task.source == "robot1" and task.params.model_dump(include={"v", "w"}) == {"v": 0.3, "w": 0.0}
    # an ERNI stop ends the motion although the teleop keeps publishing
    stop = run_task(agent, "BotMotion", "stop", timeout=5)
    assert stop.state is TaskState.SUCCEEDED, stop.result
    ended = wait_for_task(agent, task.uid, timeout=5)
    assert ended.state is TaskState.CANCELLED and "stopped by" in (ended.result.message if ended.result else "")
    commands_heard(agent, 10)  # ten more commands came
    pose = agent.query(Pose)[0]
    assert abs(pose.v) < 0.01, pose
    assert not [t for t in _velocity_tasks(agent) if not t.done]
    # once the operator lets go (a pause longer than cmd_vel_timeout), a new command drives again
    teleop.running.clear()
    drive = agent.plugin("ros2")._drives["robot1"]
    wait_until(lambda: not drive.latched, timeout=20, message="the stream stays latched after the pause")
    teleop.running.set()
    wait_until(lambda: agent.query(Pose)[0].v > 0.25, timeout=5, message="cmd_vel after the pause did not drive")
    # and when the stream stops, so does the robot (the velocity task is removed)
    teleop.running.clear()
    wait_until(lambda: abs(agent.query(Pose)[0].v) < 0.01, timeout=5, message="the robot kept going")
    wait_until(lambda: not [t for t in _velocity_tasks(agent) if not t.done], timeout=2)


def test_velocity_tasks_end_on_task_status_when_the_teleop_stops(robot: Callable[..., Agent], teleop: Teleop,
                                                                 ros: dict[str, Any]) -> None:
    """Each velocity task a cmd_vel stream made has a final status on /erni/task_status once the stream
    stops: the one replaced by a changed command and the last one, removed by the plugin's watchdog."""
    import json

    agent = robot()
    statuses: list[dict[str, Any]] = []
    sub = ROS2Subscriber("/erni/task_status", messages.STRING, lambda m: statuses.append(json.loads(m.data)),
                         router_port=ros["router_port"])
    try:
        erni_publisher_matched(agent, "/erni/task_status")
        sdk_publisher_matched(teleop.pub)
        teleop.v = 0.2
        teleop.running.set()
        wait_until(lambda: any(s["preposition"] == "velocity" and s["state"] == "running" for s in statuses),
                   timeout=5, message="no running velocity task on /erni/task_status")
        teleop.v = 0.3  # a changed command: a new task replaces the first
        wait_until(lambda: len({s["uid"] for s in statuses if s["preposition"] == "velocity"
                                and s["state"] == "running"}) >= 2, timeout=5, message="the change made no task")
        teleop.running.clear()  # the teleop stops publishing
        wait_until(lambda: abs(agent.query(Pose)[0].v) < 0.01, timeout=5, message="the robot kept going")

        def last_states() -> dict[str, dict[str, Any]]:
            last: dict[str, dict[str, Any]] = {}
            for s in statuses:
                if s["preposition"] == "velocity":
                    last[s["uid"]] = s
            return last

        wait_until(lambda: all(s["state"] != "running" for s in last_states().values()), timeout=5,
                   message=f"a velocity task stays running on /erni/task_status: {last_states()}")
    finally:
        sub.close()
    last = last_states()
    assert len(last) >= 2 and {s["state"] for s in last.values()} == {"succeeded"}, last
    *replaced, final = sorted(last.values(), key=lambda s: s["stamp"])
    assert final["params"]["v"] == 0.3 and "stream stopped" in final["message"] and final["progress"] == 1.0
    assert all(s["message"] == "replaced by a newer cmd_vel" for s in replaced)
    assert not [t for t in _velocity_tasks(agent) if not t.done]  # and gone from the blackboard


def test_a_zero_twist_is_a_velocity_not_a_stop_bypass(robot: Callable[..., Agent], teleop: Teleop) -> None:
    """A zero cmd_vel holds the robot still through the behaviour stack; it does not end an ERNI stop
    that holds (`hold=true`), and a held robot does not move for a non-zero one either."""
    agent = robot()
    hold = post_task(agent, "BotMotion", "stop", hold=True)
    wait_for_task(agent, hold, state=TaskState.RUNNING, timeout=5)
    teleop.v = 0.3
    teleop.running.set()
    (moving,) = wait_until(lambda: _velocity_tasks(agent), timeout=5, message="no velocity task from cmd_vel")
    wait_for_task(agent, moving, state=TaskState.RUNNING, timeout=10)  # taken by the motion plugin, under the hold
    sips = agent.plugin("motion").resource.driver.stats
    seen = sips.sips
    wait_until(lambda: sips.sips >= seen + 10, timeout=20)  # ten SIPs of the robot since
    assert abs(agent.query(Pose)[0].v) < 0.01  # the hold has priority over the command
    assert find_task(agent, moving.uid).state is TaskState.RUNNING  # type: ignore[union-attr]
    teleop.v = 0.0

    def zero() -> list[Task]:
        return [t for t in _velocity_tasks(agent) if not t.done and t.params.model_dump(include={"v", "w"}) ==
                {"v": 0.0, "w": 0.0}]

    wait_until(zero, timeout=20, message="the zero twist made no velocity task")
    (task,) = [t for t in _velocity_tasks(agent) if not t.done]
    assert task.params.model_dump(include={"v", "w"}) == {"v": 0.0, "w": 0.0}
    still = find_task(agent, hold.uid)  # still holding
    assert still is not None and still.state is TaskState.RUNNING


def test_goal_pose_is_a_goto_that_reaches_the_point_then_a_turn_to_its_heading(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    agent = robot()
    pub = ROS2Publisher("/robot1/goal_pose", messages.POSE_STAMPED, router_port=ros["router_port"])
    statuses: list[str] = []
    sub = ROS2Subscriber("/erni/task_status", messages.STRING, lambda m: statuses.append(m.data),
                         router_port=ros["router_port"])
    try:
        sdk_publisher_matched(pub)  # ERNI's subscription is known to the publisher's session
        erni_publisher_matched(agent, "/erni/task_status")  # and the status subscriber to ERNI's
        goal = messages.make(messages.POSE_STAMPED, header=messages.header(time.time_ns(), "map"),
                             pose=messages.make("geometry_msgs/msg/Pose",
                                                position=messages.make("geometry_msgs/msg/Point", x=1.0, y=-0.5),
                                                orientation=messages.quaternion(math.pi / 2)))
        pub.publish(header=goal.header, pose=goal.pose)
        gotos = wait_until(lambda: [t for t in agent.query(Task) if t.preposition == "goto"], timeout=5,
                           message="goal_pose made no goto")
        done = wait_for_task(agent, gotos[0].uid, timeout=20)
        assert done.state is TaskState.SUCCEEDED, done.result
        pose = agent.query(Pose)[0]
        assert math.hypot(pose.x - 1.0, pose.y + 0.5) <= 0.1
        # then a turn to the goal's heading (90 deg), relative to where the goto left the robot heading
        turns = wait_until(lambda: [t for t in agent.query(Task) if t.preposition == "turn"], timeout=5,
                           message="no turn to the goal's heading")
        assert turns[0].params.angle == pytest.approx(math.degrees(math.pi / 2 - pose.theta), abs=0.5)
        turned = wait_for_task(agent, turns[0].uid, timeout=20)
        assert turned.state is TaskState.SUCCEEDED, turned.result
        assert math.degrees(agent.query(Pose)[0].theta) == pytest.approx(90, abs=3)
        assert math.hypot(agent.query(Pose)[0].x - 1.0, agent.query(Pose)[0].y + 0.5) <= 0.1
        import json
        wait_until(lambda: any(json.loads(s)["uid"] == done.uid and json.loads(s)["state"] == "succeeded"
                               for s in statuses), timeout=5, message="no succeeded status on /erni/task_status")
    finally:
        pub.close()
        sub.close()


def test_the_network_as_markers_and_diagnostics_and_the_robot_on_tf(robot: Callable[..., Agent],
                                                                    ros: dict[str, Any]) -> None:
    from erni.blackboard.tasks import Link, Neighbor, NetInfo, Position

    agent = robot()
    markers: list[Any] = []
    diags: list[Any] = []
    tfs: list[Any] = []
    subs = [ROS2Subscriber("/erni/network", messages.MARKER_ARRAY, markers.append, router_port=ros["router_port"]),
            ROS2Subscriber("/diagnostics", messages.DIAGNOSTIC_ARRAY, diags.append, router_port=ros["router_port"]),
            ROS2Subscriber("/tf", messages.TF_MESSAGE, tfs.append, router_port=ros["router_port"])]
    try:
        for topic in ("/erni/network", "/diagnostics", "/tf"):  # the subscriptions are known to ERNI's publishers
            erni_publisher_matched(agent, topic)
        with agent.transaction() as tx:
            tx.add(NetInfo(node="robot1", kind="network_topology", links=[Link(a="robot1", b="robot2", quality=0.8)],
                           neighbors=[Neighbor(name="robot2", quality=0.3)], positions={"robot2": Position(x=2, y=1)},
                           articulation_points=["robot1"]))
        wait_until(lambda: markers and diags, timeout=5, message="no MarkerArray or DiagnosticArray")
        run_task(agent, "BotMotion", "goto", x=0.3, y=0.0, timeout=20)
        wait_until(lambda: tfs, timeout=5, message="no /tf")
    finally:
        for sub in subs:
            sub.close()
    by_ns = {}
    for m in markers[-1].markers:
        by_ns.setdefault(m.ns, []).append(m)
    assert [m.action for m in by_ns["erni"]] == [3]  # DELETEALL first: nodes and links gone since disappear
    names = {m.text: m for m in by_ns["erni_names"]}
    assert set(names) == {"robot1", "robot2"}
    nodes = {(round(m.pose.position.x, 3), round(m.pose.position.y, 3)): m for m in by_ns["erni_nodes"]}
    assert nodes[(2.0, 1.0)].color.b > 0.5 and nodes[(2.0, 1.0)].type == 2  # a blue sphere
    (line,) = by_ns["erni_links"]
    assert line.type == 5 and len(line.points) == 2 and line.points[1].x == 2.0 and line.points[1].y == 1.0
    assert line.colors[0].g == pytest.approx(0.8) and line.colors[0].r == pytest.approx(0.2)
    cut = [m for m in by_ns["erni_nodes"] if m.color.r > 0.5]
    assert len(cut) == 1  # robot1, the articulation point, is red
    status = {s.name: s for s in diags[-1].status}
    assert set(status) == {"erni/robot1/network", "erni/robot1/neighbor/robot2"}
    assert status["erni/robot1/neighbor/robot2"].level == 1  # WARN: quality 0.3
    assert {kv.key: kv.value for kv in status["erni/robot1/network"].values}["articulation_points"] == "robot1"
    odom, tf = tfs[-1].transforms  # map → robot1/odom → robot1/base_link (tests/ros2/test_frames.py)
    assert (odom.header.frame_id, odom.child_frame_id) == ("map", "robot1/odom")
    assert tf.header.frame_id == "robot1/odom" and tf.child_frame_id == "robot1/base_link"
    assert tf.transform.translation.x == pytest.approx(agent.query(Pose)[0].x, abs=0.05)


def test_sonar_echoes_as_a_laser_scan() -> None:
    ring = ((0.2, 0.0, 0.0), (0.0, 0.1, 90.0), None, (-0.2, 0.0, 180.0))
    pose = Pose(robot="robot1", sonar=[1.0, 5.0, 0.3, 0.5])
    scan = messages.sonar_echo_scan(pose, ring, 5)
    assert scan.header.frame_id == "robot1/base_link" and len(scan.ranges) == 360
    assert scan.angle_min == pytest.approx(-math.pi) and scan.angle_increment == pytest.approx(math.pi / 180)
    assert scan.ranges[180] == pytest.approx(1.2)  # ahead: 0.2 m out and 1.0 m on, from the centre
    assert math.isinf(scan.ranges[270])  # left: nothing within 5 m
    assert scan.ranges[0] == pytest.approx(0.7)  # behind (-180 deg): 0.2 + 0.5
    assert sum(not math.isnan(r) for r in scan.ranges) == 3  # no beam for the missing transducer


def test_the_sdks_subscriber_decodes_the_sonar_of_the_simulated_robot(robot: Callable[..., Agent],
                                                                      ros: dict[str, Any]) -> None:
    robot()
    got: list[Any] = []
    sub = ROS2Subscriber("/robot1/sonar", messages.LASER_SCAN, got.append, router_port=ros["router_port"])
    def complete() -> list[float] | None:  # the simulated firmware reports its ring a few sonars per SIP at first
        ranges = [float(r) for r in got[-1].ranges] if got else []
        return ranges if sum(not math.isnan(r) for r in ranges) >= 16 else None

    try:
        ranges = wait_until(complete, timeout=5, message="no LaserScan with the whole ring on /robot1/sonar")
    finally:
        sub.close()
    # an empty world: each of the Pioneer's 16 sonars sees nothing (+inf) in a beam of its own (the two
    # pointing left, 0.23 m apart, 5 m out differ by 2.5 deg); the other beams have no sonar (NaN)
    assert sum(math.isinf(r) for r in ranges) == 16 and sum(math.isnan(r) for r in ranges) == 360 - 16
    assert math.isinf(ranges[269]) and math.isinf(ranges[91])  # left and right (89.2 deg from the centre)


def test_a_client_whose_router_comes_later_declares_its_topics_once_it_does(
        caplog: pytest.LogCaptureFixture) -> None:
    from erni.plugins.ros2 import ROS2Plugin
    from erni.sim.team import free_port
    from erni.testing import agent_with
    from erni.transport.zenoh_wire import open_router

    port = free_port()
    with agent_with(ROS2Plugin, settings={"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"],
                                          "robots": ["robot1"]}) as agent:
        plugin = agent.plugin("ROS2Plugin")
        assert isinstance(plugin, ROS2Plugin)
        wait_until(lambda: any("cannot open a Zenoh session" in r.getMessage() for r in caplog.records),
                   timeout=20, message="no word of the missing router")
        assert plugin.node is None  # no router: no session yet, the agent runs all the same
        late = open_router([f"tcp/127.0.0.1:{port}"])
        session = None
        try:
            wait_until(lambda: plugin.node is not None, timeout=5, message="no session once the router came")
            session = zenoh.open(zenoh.Config.from_json5(
                f'{{mode: "client", connect: {{endpoints: ["tcp/127.0.0.1:{port}"]}}}}'))

            def tokens() -> list[str]:
                assert session is not None
                return [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**", timeout=1.0)
                        if r.ok is not None]

            found = wait_until(lambda: [t for t in tokens() if "/MS/" in t and "%robot1%cmd_vel" in t],
                               timeout=5, message="robot1's cmd_vel subscription not declared")
            assert plugin.node is not None and found[0].startswith(f"@ros2_lv/0/{plugin.node.zid}/")
        finally:
            if session is not None:
                session.close()
            agent.stop()
            late.close()


def _replay(budget: plugin_module.RateBudget, arrivals: list[float]) -> list[tuple[float, float | None]]:
    """Each event's (arrival, when it was sent, None if a newer one replaced it), the plugin's way: a fresh
    offer at each arrival, a held one offered again when the budget said (the plugin's wake_in)."""
    sent: dict[int, float] = {}
    held: tuple[int, float] | None = None  # (event, when to offer it again)
    for i, t in enumerate([*arrivals, math.inf]):
        while held is not None and held[1] <= t:
            j, at = held
            wait = budget.offer("r", at, fresh=False)
            held = (j, at + wait) if wait > 0 else None
            if held is None:
                sent[j] = at
        if i == len(arrivals):
            break
        held = None  # a newer one replaces it
        wait = budget.offer("r", t, fresh=True)
        if wait <= 0:
            sent[i] = t
        else:
            held = (i, t + wait)
    return [(t, sent.get(i)) for i, t in enumerate(arrivals)]


def test_the_odom_rate_holds_back_no_pose_of_a_robot_that_keeps_to_it() -> None:
    """A robot whose Pose comes at odom_rate_hz (with jitter, after a burst of three): each Odometry goes as
    its Pose comes; a pose that finds no token is replaced by the next, never sent late (a strict interval,
    or a held pose sent at its slot, kept every later pose late by the same lag)."""
    import random

    rng = random.Random(56)
    arrivals = [0.0, 0.005, 0.01, *(0.1 * k + rng.uniform(-0.01, 0.01) for k in range(1, 600))]
    events = _replay(plugin_module.RateBudget(10.0), arrivals)
    assert not [(t, sent) for t, sent in events if sent is not None and sent != t]
    assert events[2][1] is None  # the burst's third, replaced
    assert sum(sent == t for t, sent in events) >= 0.97 * len(events)
    # a source slower than the rate is never held at all
    slow = _replay(plugin_module.RateBudget(10.0), [0.12 * k for k in range(300)])
    assert all(sent == t for t, sent in slow)


def test_the_odom_rate_thins_a_faster_robot_to_fresh_poses() -> None:
    """A robot at 25 Hz, odom_rate_hz 10: 10 a second on average, at most rate * T + 2 in any window of T s,
    each sent the moment its Pose came; a pose held with none after it (the robot stands) still goes."""
    arrivals = [0.04 * k for k in range(250)]  # 10 s
    events = _replay(plugin_module.RateBudget(10.0), arrivals)
    sent = [s for _, s in events if s is not None]
    assert 99 <= len(sent) <= 102
    assert all(s == t for t, s in events[:-1] if s is not None)
    assert events[-1][1] is not None  # the last pose is not lost
    assert all(sum(1 for u in sent if a <= u < a + 1.0) <= 12 for a in sent)
    budget = plugin_module.RateBudget(10.0)
    assert budget.offer("r", 0.0, fresh=True) == 0 and budget.offer("r", 0.001, fresh=True) == 0
    wait = budget.offer("r", 0.002, fresh=True)  # a third at once: held, and the robot then stands still
    assert 0 < wait <= 0.25
    assert budget.offer("r", 0.002 + wait / 2, fresh=False) > 0  # not before its time
    assert budget.offer("r", 0.002 + wait, fresh=False) == 0  # then it goes, without a newer pose


def test_goal_heading_of_a_pose_stamped() -> None:
    goal = messages.make(messages.POSE_STAMPED)  # a zero quaternion: no heading asked
    assert messages.goal_heading(goal) is None
    goal.pose.orientation = messages.quaternion(-2.0)
    assert messages.goal_heading(goal) == pytest.approx(-2.0)
