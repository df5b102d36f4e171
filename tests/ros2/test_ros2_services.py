"""The ros2 plugin's services and action against ROBOTIS' zenoh-ros2-sdk (an independent rmw_zenoh client):
its service client calls `/robot1/stop` (std_srvs/Trigger) and the simulated robot halts, whether a
cmd_vel or a goto moved it; its discovery lists the services with their types; its service clients
drive Nav2's NavigateToPose action (send_goal, get_result, cancel_goal) and its subscribers read the
action's feedback and status; and what was learnt of rmw_zenoh's services, pinned as bytes."""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

from zenoh_ros2_sdk import ROS2Publisher, ROS2ServiceClient, ROS2Subscriber  # noqa: E402
from zenoh_ros2_sdk.discovery import get_service_names_and_types  # noqa: E402
from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity  # noqa: E402
from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr  # noqa: E402
from zenoh_ros2_sdk.qos import QosProfile  # noqa: E402
from zenoh_ros2_sdk.utils import compute_service_type_hash  # noqa: E402

from erni import ros2_messages as messages  # noqa: E402
from erni import ros2_rmw as rmw  # noqa: E402
from erni.blackboard import Agent, Pose, Task, TaskState  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.testing import fake_robot, wait_for_task  # noqa: E402
from tests.ros2.conftest import (  # noqa: E402
    commands_heard,
    erni_publisher_matched,
    sdk_publisher_matched,
    write_definitions,
)
from tests.ros2.test_ros2_team import team  # noqa: E402, F401  # the fixture: agents on the Zenoh wire

TRIGGER_HASH = "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
ZID = "98517b73ab05dcb895c1c42cdfe891cd"

# the action's requests and responses written flat for the SDK's own CDR code (a nested struct adds no
# bytes in CDR), so that its serialiser, not ERNI's, checks the layout
SEND_GOAL_REQUEST = "unique_identifier_msgs/UUID goal_id\ngeometry_msgs/PoseStamped pose\nstring behavior_tree\n"
SEND_GOAL_RESPONSE = "bool accepted\nbuiltin_interfaces/Time stamp\n"
GET_RESULT_REQUEST = "unique_identifier_msgs/UUID goal_id\n"
GET_RESULT_RESPONSE = "int8 status\nuint16 error_code\nstring error_msg\n"
CANCEL_REQUEST = "unique_identifier_msgs/UUID goal_id\nbuiltin_interfaces/Time stamp\n"
CANCEL_RESPONSE = "int8 return_code\naction_msgs/GoalInfo[] goals_canceling\n"
FEEDBACK_MESSAGE = ("unique_identifier_msgs/UUID goal_id\ngeometry_msgs/PoseStamped current_pose\n"
                    "builtin_interfaces/Duration navigation_time\nbuiltin_interfaces/Duration estimated_time_remaining\n"
                    "int16 number_of_recoveries\nfloat32 distance_remaining\n")


# --- what was learnt, pinned ------------------------------------------------------------------


def test_service_key_expression_token_and_hash_are_rmw_zenohs() -> None:
    """A service is keyed like a topic of the service's type; its token is an `SS`; the hash is the
    service type's (request_message, response_message, event_message), `char` hashed as `uint8`."""
    assert messages.type_hash(messages.TRIGGER) == TRIGGER_HASH
    key = rmw.topic_key(0, "/robot1/stop", messages.TRIGGER)
    assert key == f"0/robot1/stop/std_srvs::srv::dds_::Trigger_/{TRIGGER_HASH}"
    token = rmw.endpoint_token(0, ZID, 7, 12, "SS", "/", "erni_robot1", "/robot1/stop", messages.TRIGGER,
                               rmw.DEFAULT_QOS)
    assert token == (f"@ros2_lv/0/{ZID}/7/12/SS/%/%/erni_robot1/%robot1%stop/"
                     f"std_srvs::srv::dds_::Trigger_/{TRIGGER_HASH}/::,10:,:,:,,")
    node = NodeEntity(domain_id=0, session_id=ZID, node_id=7, node_name="erni_robot1", namespace="/")
    ep = EndpointEntity(node=node, entity_id=12, kind=EntityKind.SERVICE, name="/robot1/stop",
                        dds_type_name="std_srvs::srv::dds_::Trigger_", type_hash=TRIGGER_HASH,
                        qos=QosProfile().encode())
    assert endpoint_liveliness_keyexpr(ep) == token
    # the action's services and topics, as rcl_action names them under the action's name
    action = "/robot1/navigate_to_pose/_action"
    assert rmw.topic_key(0, f"{action}/send_goal", messages.SEND_GOAL).startswith(
        "0/robot1/navigate_to_pose/_action/send_goal/nav2_msgs::action::dds_::NavigateToPose_SendGoal_/RIHS01_")
    assert rmw.topic_key(0, f"{action}/cancel_goal", messages.CANCEL_GOAL).startswith(
        "0/robot1/navigate_to_pose/_action/cancel_goal/action_msgs::srv::dds_::CancelGoal_/RIHS01_")
    assert rmw.topic_key(0, f"{action}/status", messages.GOAL_STATUS_ARRAY).startswith(
        "0/robot1/navigate_to_pose/_action/status/action_msgs::msg::dds_::GoalStatusArray_/RIHS01_")
    assert messages.dds_type_name(messages.FEEDBACK_MESSAGE) == "nav2_msgs::action::dds_::NavigateToPose_FeedbackMessage_"


def test_the_sdk_hashes_a_service_as_erni_does() -> None:
    """The SDK's own RIHS01 code over the .srv text (ServiceEventInfo's client_gid as uint8[16]), also for a
    service with nested types (CancelGoal). The SDK files an action's service parts under `srv/`, where
    rosidl keeps them in `action/`, so its hashes of `NavigateToPose_SendGoal` and `_GetResult` differ:
    those are pinned as the plugin computes them."""
    assert compute_service_type_hash("std_srvs/srv/SetBool", "bool data", "bool success\nstring message") == \
        _hash_of("std_srvs/srv/SetBool", "bool data\n", "bool success\nstring message\n")
    deps = {"action_msgs/msg/GoalInfo": "unique_identifier_msgs/UUID goal_id\nbuiltin_interfaces/Time stamp",
            "unique_identifier_msgs/msg/UUID": "uint8[16] uuid", "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec"}
    assert compute_service_type_hash(messages.CANCEL_GOAL, "action_msgs/GoalInfo goal_info",
                                     "int8 return_code\naction_msgs/GoalInfo[] goals_canceling",
                                     dependencies=deps) == messages.type_hash(messages.CANCEL_GOAL)
    assert messages.type_hash(messages.CANCEL_GOAL) == \
        "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a"
    assert messages.type_hash(messages.SEND_GOAL) == \
        "RIHS01_a4fcb3bee1bf32e21a0e541a943b221aa0826996e2c98f079b47022b256f48b5"
    assert messages.type_hash(messages.GET_RESULT) == \
        "RIHS01_c407920357d566771e8882b4ef4d1f1a84ee922d609920ccd57faa6d6e391dc5"
    assert messages.type_hash(messages.FEEDBACK_MESSAGE) == \
        "RIHS01_9d1f6fa2eb975ce733b419ac2e97b134d8ff92b6478b6559feed9a50bdfd82b3"


def _hash_of(service: str, request: str, response: str) -> str:
    types = messages._service_types(service, request, response)
    messages._HASHING.register({k: v for k, v in types.items() if k not in messages._HASHING.types})
    return messages.type_hash(service)


def test_trigger_request_and_response_cdr_bytes() -> None:
    request = messages.serialize(messages.make(f"{messages.TRIGGER}_Request"))
    assert request.hex() == "00010000" "00"  # an empty request: rosidl's one uint8 member
    response = messages.serialize(messages.make(f"{messages.TRIGGER}_Response", success=True, message="ok"))
    assert response.hex() == "00010000" "01" "000000" "03000000" "6f6b00"
    back = messages.deserialize(response, f"{messages.TRIGGER}_Response")
    assert back.success is True and back.message == "ok"


def test_send_goal_request_cdr_bytes() -> None:
    goal = messages.make(f"{messages.NAVIGATE_TO_POSE}_Goal", pose=messages.make(
        messages.POSE_STAMPED, header=messages.header(1_000_000_005, "map"),
        pose=messages.ros_pose(1.0, -0.5, 0.0)))
    data = messages.serialize(messages.make(f"{messages.SEND_GOAL}_Request", goal_id=messages.uuid(bytes(range(16))),
                                            goal=goal))
    assert data.hex() == (
        "00010000" "000102030405060708090a0b0c0d0e0f"  # goal_id
        "01000000" "05000000" "04000000" "6d617000"  # stamp 1 s 5 ns, frame_id "map"
        "000000000000f03f" "000000000000e0bf" "0000000000000000"  # position
        "0000000000000000" "0000000000000000" "0000000000000000" "000000000000f03f"  # orientation
        "01000000" "00")  # behavior_tree ""


# --- against the independent client --------------------------------------------------------------


def wait_served(port: int, name: str) -> None:
    """Until the SDK's discovery sees the service (the plugin declares a robot's services once its node is up)."""
    wait_until(lambda: name in dict(get_service_names_and_types(router_port=port, include_hidden_services=True)),
               timeout=5, message=f"{name} not served")


def _stop_client(ros: dict[str, Any], name: str = "/robot1/stop") -> Any:
    """The SDK's client of std_srvs/Trigger. Its registry refuses the .srv's empty request, so the request
    is given as rosidl makes it (the one uint8 member an empty struct gets): the same bytes, and the SDK
    hashes it to the same type hash itself."""
    wait_served(ros["router_port"], name)
    return ROS2ServiceClient(name, messages.TRIGGER, router_port=ros["router_port"], timeout=10.0,
                             request_definition="uint8 structure_needs_at_least_one_member\n",
                             response_definition="bool success\nstring message\n")


class Teleop:
    """A ROS 2 teleop (the SDK's publisher) sending one Twist every 0.1 s from its own thread."""

    def __init__(self, port: int) -> None:
        self.pub = ROS2Publisher("/robot1/cmd_vel", messages.TWIST, router_port=port)
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="test-teleop")
        self.thread.start()

    def _loop(self) -> None:
        while not self.closing.is_set():
            self.pub.publish(linear=messages.make("geometry_msgs/msg/Vector3", x=0.3),
                             angular=messages.make("geometry_msgs/msg/Vector3", z=0.0))
            self.closing.wait(0.1)

    def close(self) -> None:
        self.closing.set()
        self.thread.join()
        self.pub.close()


def test_the_sdks_client_stops_a_robot_driven_by_cmd_vel(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    agent = robot()
    client = _stop_client(ros)
    assert client.type_hash == TRIGGER_HASH  # the SDK hashed the .srv itself
    teleop = Teleop(ros["router_port"])
    try:
        wait_until(lambda: agent.query(Pose)[0].v > 0.25, timeout=5, message="cmd_vel did not move the robot")
        (velocity,) = [t for t in agent.query(Task) if t.preposition == "velocity" and not t.done]
        response = client.call()
        assert response is not None, "no answer from /robot1/stop"
        assert response.success is True, response.message
        assert response.message == "halted: robot1"
        # answered once the robot stands (its stop succeeded: "halted"), although the teleop still publishes;
        # the Pose on the blackboard follows within a SIP or two
        (stop,) = [t for t in agent.query(Task) if t.preposition == "stop"]
        assert stop.state is TaskState.SUCCEEDED and stop.result is not None and stop.result.values["halted"]
        wait_until(lambda: abs(agent.query(Pose)[0].v) < 0.02, timeout=1, message="the Pose does not stand")
        ended = wait_for_task(agent, velocity.uid, timeout=5)
        assert ended.state is TaskState.CANCELLED
        assert stop.source == "robot1"
        commands_heard(agent, 10)  # ten more commands came: the stream is latched until the teleop pauses
        assert abs(agent.query(Pose)[0].v) < 0.02
        assert not [t for t in agent.query(Task) if t.preposition == "velocity" and not t.done]
    finally:
        teleop.close()
        client.close()


def test_erni_stop_halts_a_goto_from_goal_pose(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    agent = robot()
    pub = ROS2Publisher("/robot1/goal_pose", messages.POSE_STAMPED, router_port=ros["router_port"])
    client = _stop_client(ros, "/erni/stop")
    try:
        sdk_publisher_matched(pub)  # ERNI's goal_pose subscription is known to the publisher's session
        pub.publish(header=messages.header(time.time_ns(), "map"), pose=messages.ros_pose(3.0, 0.0, 0.0))
        gotos = wait_until(lambda: [t for t in agent.query(Task) if t.preposition == "goto"], timeout=5,
                           message="goal_pose made no goto")
        wait_until(lambda: agent.query(Pose)[0].v > 0.2, timeout=10, message="the goto did not move the robot")
        response = client.call()
        assert response is not None and response.success is True, response
        wait_until(lambda: abs(agent.query(Pose)[0].v) < 0.02, timeout=1, message="the Pose does not stand")
        x = agent.query(Pose)[0].x
        assert x < 2.5
        assert wait_for_task(agent, gotos[0].uid, timeout=5).state is TaskState.CANCELLED
        # the ros2 plugin's runs after the cancel (a turn would follow a goto's end in the next one) and
        # ten more SIPs of the robot: no turn, no resumed goto
        ros2, sips = agent.plugin("ros2"), agent.plugin("motion").resource.driver.stats
        runs, seen = ros2._run, sips.sips
        wait_until(lambda: ros2._run > runs + 1 and sips.sips >= seen + 10, timeout=20)
        assert agent.query(Pose)[0].x == pytest.approx(x, abs=0.02)
        assert not [t for t in agent.query(Task) if t.preposition == "turn"]
        assert not [t for t in agent.query(Task) if t.preposition == "goto" and not t.done]
    finally:
        pub.close()
        client.close()


def test_a_stop_that_cannot_halt_in_time_answers_failure(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    """The answer is success only when the robot halted: a robot nothing drives (here one this agent serves
    but cannot reach: no transport) cannot, and the answer says so."""
    robot(stop_timeout=1.0, robots=["robot1", "ghost"])
    client = _stop_client(ros, "/ghost/stop")
    try:
        response = client.call()
    finally:
        client.close()
    assert response is not None and response.success is False
    assert response.message.startswith("ghost: "), response.message


def test_the_sdks_discovery_lists_the_services_with_their_types(robot: Callable[..., Agent],
                                                               ros: dict[str, Any]) -> None:
    robot()
    want = {"/robot1/stop": ["std_srvs/srv/Trigger"], "/erni/stop": ["std_srvs/srv/Trigger"],
            "/robot1/navigate_to_pose/_action/send_goal": ["nav2_msgs/action/NavigateToPose_SendGoal"],
            "/robot1/navigate_to_pose/_action/get_result": ["nav2_msgs/action/NavigateToPose_GetResult"],
            "/robot1/navigate_to_pose/_action/cancel_goal": ["action_msgs/srv/CancelGoal"]}

    def listed() -> dict[str, list[str]] | None:
        services = dict(get_service_names_and_types(router_port=ros["router_port"], include_hidden_services=True))
        return services if all(services.get(k) == v for k, v in want.items()) else None

    services = wait_until(listed, timeout=5, message="ERNI's services not listed")
    assert services is not None


class Navigator:
    """A NavigateToPose client made of the SDK's service clients and subscribers (rclpy's ActionClient does
    the same over rmw: send_goal, then get_result, and cancel_goal to cancel)."""

    def __init__(self, port: int, robot: str = "robot1") -> None:
        self.port = port
        action = self.action = f"/{robot}/navigate_to_pose/_action"
        from zenoh_ros2_sdk.session import ZenohSession
        for typename in (messages.POSE_STAMPED, "unique_identifier_msgs/msg/UUID", "builtin_interfaces/msg/Duration",
                         "action_msgs/msg/GoalInfo"):  # the nested types of the flat definitions, from its registry
            ZenohSession.get_instance("127.0.0.1", port).register_message_type(None, typename)
        self.send = ROS2ServiceClient(f"{action}/send_goal", messages.SEND_GOAL, router_port=port, timeout=10.0,
                                      request_definition=SEND_GOAL_REQUEST, response_definition=SEND_GOAL_RESPONSE,
                                      type_hash=messages.type_hash(messages.SEND_GOAL))
        self.result = ROS2ServiceClient(f"{action}/get_result", messages.GET_RESULT, router_port=port, timeout=60.0,
                                        request_definition=GET_RESULT_REQUEST,
                                        response_definition=GET_RESULT_RESPONSE,
                                        type_hash=messages.type_hash(messages.GET_RESULT))
        self.cancel = ROS2ServiceClient(f"{action}/cancel_goal", messages.CANCEL_GOAL, router_port=port,
                                        timeout=10.0, request_definition=CANCEL_REQUEST,
                                        response_definition=CANCEL_RESPONSE,
                                        type_hash=messages.type_hash(messages.CANCEL_GOAL))
        self.feedback: list[Any] = []
        self.status: list[Any] = []
        self.subs = [ROS2Subscriber(f"{action}/feedback", messages.FEEDBACK_MESSAGE, self.feedback.append,
                                    msg_definition=FEEDBACK_MESSAGE, router_port=port,
                                    type_hash=messages.type_hash(messages.FEEDBACK_MESSAGE)),
                     ROS2Subscriber(f"{action}/status", messages.GOAL_STATUS_ARRAY, self.status.append,
                                    router_port=port)]

    def heard_by(self, agent: Agent) -> None:
        """Until the agent's feedback and status publishers know this navigator's subscribers."""
        for topic in ("feedback", "status"):
            erni_publisher_matched(agent, f"{self.action}/{topic}")

    def uuid(self, goal_id: bytes) -> Any:
        return self.send.session_mgr.store.types["unique_identifier_msgs/msg/UUID"](
            uuid=__import__("numpy").frombuffer(goal_id, dtype="uint8").copy())

    def goal(self, goal_id: bytes, x: float, y: float, theta: float) -> Any:
        wait_served(self.port, f"{self.action}/send_goal")
        return self.send.call(goal_id=self.uuid(goal_id), pose=messages.make(
            messages.POSE_STAMPED, header=messages.header(time.time_ns(), "map"),
            pose=messages.ros_pose(x, y, theta)), behavior_tree="")

    def close(self) -> None:
        for entity in (self.send, self.result, self.cancel, *self.subs):
            entity.close()


@pytest.fixture
def navigator(ros: dict[str, Any], definitions: Path) -> Iterator[Navigator]:
    write_definitions(definitions, (messages.GOAL_STATUS_ARRAY, "builtin_interfaces/msg/Duration"))
    nav = Navigator(ros["router_port"])
    yield nav
    nav.close()


def test_a_navigate_to_pose_goal_reaches_the_point_and_succeeds(robot: Callable[..., Agent],
                                                               navigator: Navigator) -> None:
    agent = robot()
    navigator.heard_by(agent)
    goal_id = os.urandom(16)
    accepted = navigator.goal(goal_id, 1.0, 0.5, math.pi / 2)
    assert accepted is not None and accepted.accepted is True
    assert abs(accepted.stamp.sec - time.time()) < 300  # the wall clock's seconds (not 0, ns or another epoch)
    result = navigator.result.call(goal_id=navigator.uuid(goal_id))
    assert result is not None, "no result"
    assert result.status == 4 and result.error_code == 0, result  # SUCCEEDED
    pose = agent.query(Pose)[0]
    assert math.hypot(pose.x - 1.0, pose.y - 0.5) <= 0.1
    assert math.degrees(pose.theta) == pytest.approx(90, abs=3)  # then turned to the goal's heading
    # feedback while it ran: the goal's id, the robot's pose, the distance left shrinking
    mine = [f for f in navigator.feedback if bytes(f.goal_id.uuid) == goal_id]
    assert len(mine) >= 5
    distances = [f.distance_remaining for f in mine]
    assert distances[0] > 0.9 and min(distances) < 0.2
    assert mine[-1].current_pose.header.frame_id == "map"
    assert mine[-1].navigation_time.sec + mine[-1].navigation_time.nanosec * 1e-9 > 1.0
    # the status topic went from executing to succeeded
    def seen() -> list[int]:
        return [s.status for a in navigator.status for s in a.status_list
                if bytes(s.goal_info.goal_id.uuid) == goal_id]

    wait_until(lambda: seen() and seen()[-1] == 4, timeout=2, message=f"no SUCCEEDED status: {seen()}")
    assert seen()[0] == 1 and 2 in seen()  # ACCEPTED, EXECUTING
    # a goal id already used is rejected; so is a goal that is not finite
    again = navigator.goal(goal_id, 0.0, 0.0, 0.0)
    assert again is not None and again.accepted is False
    assert navigator.goal(os.urandom(16), math.nan, 0.0, 0.0).accepted is False
    # an unknown goal's result: status UNKNOWN at once
    unknown = navigator.result.call(goal_id=navigator.uuid(bytes(16)))
    assert unknown is not None and unknown.status == 0


def test_cancel_goal_stops_the_robot_and_the_result_is_canceled(robot: Callable[..., Agent],
                                                               navigator: Navigator) -> None:
    agent = robot()
    navigator.heard_by(agent)
    goal_id = os.urandom(16)
    accepted = navigator.goal(goal_id, 4.0, 0.0, 0.0)
    assert accepted is not None and accepted.accepted is True
    results: list[Any] = []
    navigator.result.call_async(results.append, goal_id=navigator.uuid(goal_id))
    wait_until(lambda: agent.query(Pose)[0].v > 0.2, timeout=10, message="the goal did not move the robot")
    info = navigator.cancel.request_msg_class(goal_id=navigator.uuid(goal_id),
                                              stamp=messages.stamp(0))
    response = navigator.cancel.call(goal_id=info.goal_id, stamp=info.stamp)
    assert response is not None and response.return_code == 0 and len(response.goals_canceling) == 1
    assert bytes(response.goals_canceling[0].goal_id.uuid) == goal_id
    wait_until(lambda: results, timeout=10, message="no result after the cancel")
    assert results[0] is not None and results[0].status == 5, results  # CANCELED
    wait_until(lambda: abs(agent.query(Pose)[0].v) < 0.02, timeout=5, message="the robot kept going")
    assert agent.query(Pose)[0].x < 3.5
    assert not [t for t in agent.query(Task) if t.preposition == "goto" and not t.done]  # the goto was removed
    # cancelling it again: the goal has ended
    again = navigator.cancel.call(goal_id=info.goal_id, stamp=info.stamp)
    assert again is not None and again.return_code == 3


def test_a_stop_aborts_a_navigate_to_pose_goal(robot: Callable[..., Agent], navigator: Navigator,
                                              ros: dict[str, Any]) -> None:
    agent = robot()
    navigator.heard_by(agent)
    goal_id = os.urandom(16)
    assert navigator.goal(goal_id, 4.0, 0.0, 0.0).accepted is True
    wait_until(lambda: agent.query(Pose)[0].v > 0.2, timeout=10, message="the goal did not move the robot")
    client = _stop_client(ros)
    try:
        response = client.call()
    finally:
        client.close()
    assert response is not None and response.success is True
    result = navigator.result.call(goal_id=navigator.uuid(goal_id))
    assert result is not None and result.status == 6 and "stopped by" in result.error_msg, result  # ABORTED


def test_a_request_that_does_not_decode_gets_an_error_reply(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    """A raw Zenoh query: without rmw_zenoh's attachment, or with a payload that is not the request's CDR,
    the answer is a Zenoh error reply naming what is wrong, and no goal is taken."""
    agent = robot()
    key = rmw.topic_key(0, "/robot1/navigate_to_pose/_action/send_goal", messages.SEND_GOAL)
    session = ros["session"].session

    def ask(**options: Any) -> list[str]:
        errors = []
        for reply in session.get(key, timeout=5.0, **options):
            assert reply.ok is None, "a reply to a bad request"
            errors.append(reply.err.payload.to_bytes().decode())
        return errors

    token = "@ros2_lv/0/**/SS/%/%/erni_robot1/%robot1%navigate_to_pose%_action%send_goal/**"
    wait_until(lambda: list(session.liveliness().get(token, timeout=1.0)), timeout=5, message="send_goal not served")
    assert ask(payload=b"\x00\x01\x00\x00") == ["/robot1/navigate_to_pose/_action/send_goal: request refused: "
                                                 "no attachment"]
    errors = ask(payload=b"\x00\x01\x00\x00\x01", attachment=rmw.attachment(1, time.time_ns(), bytes(16)))
    assert len(errors) == 1 and errors[0].startswith("send_goal: the request does not decode"), errors
    assert not [t for t in agent.query(Task) if t.preposition == "goto"]


def test_a_control_nodes_erni_stop_halts_a_robot_through_the_transport(team: Callable[..., Agent],  # noqa: F811
                                                                       ros: dict[str, Any]) -> None:
    """On a control node (transport on `wire = "zenoh"`), `/erni/stop` posts the stop for each robot it
    serves; the stop reaches robot1 through ERNI's transport, and the answer waits until robot1 halted."""
    from erni.plugins.ros2 import ROS2Plugin
    from erni.transport import Peer
    from tests.ros2.test_ros2_plugin import Teleop as Stick

    control = team("control", lambda a: a.add_plugin(ROS2Plugin, name="ros2"))
    robot1 = team("robot1", lambda a: a.add_plugin("motion", settings=fake_robot("robot1"), name="motion"))
    wait_until(lambda: any(p.name == "robot1" and p.up for p in control.query(Peer)), timeout=10)
    wait_until(lambda: control.blackboard.get("pose:robot1"), timeout=10, message="no Pose of robot1 at control")
    wait_served(ros["router_port"], "/robot1/stop")
    stick = Stick(ros["router_port"])
    client = _stop_client(ros, "/erni/stop")
    try:
        stick.v = 0.3
        stick.running.set()
        wait_until(lambda: robot1.query(Pose)[0].v > 0.25, timeout=10, message="cmd_vel did not reach robot1")
        response = client.call()
        assert response is not None and response.success is True, response
        assert response.message == "halted: robot1"
        wait_until(lambda: abs(robot1.query(Pose)[0].v) < 0.02, timeout=1, message="robot1's Pose does not stand")
        (stop,) = [t for t in robot1.query(Task) if t.preposition == "stop"]
        assert stop.source == "control" and stop.state is TaskState.SUCCEEDED
        commands_heard(control, 10)  # the stick still pushes: the stream is latched at the control node
        assert abs(robot1.query(Pose)[0].v) < 0.02
        assert not [t for t in control.query(Task) if t.preposition == "velocity" and not t.done]
    finally:
        stick.close()
        client.close()
