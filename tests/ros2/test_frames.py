"""The ros2 plugin's frames as a tf2 listener sees them: zenoh-ros2-sdk subscribers (an independent
rmw_zenoh client) on `/tf` and `/robot1/odom` through a Zenoh router, a transform tree built from what
arrives, and map → robot1/base_link composed from it and compared with the robot's Pose."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pytest

pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")

from zenoh_ros2_sdk import ROS2Subscriber  # noqa: E402

from erni import ros2_messages as messages  # noqa: E402
from erni.blackboard import Agent, Pose, TaskState  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.testing import run_task  # noqa: E402
from tests.ros2.conftest import erni_publisher_matched  # noqa: E402


@dataclass(frozen=True)
class Frame:
    """A rigid transform: translation and unit quaternion (x, y, z, w)."""

    t: tuple[float, float, float]
    q: tuple[float, float, float, float]

    def then(self, child: Frame) -> Frame:
        """This transform followed by `child` (parent→a composed with a→child)."""
        rotated = _rotate(self.q, child.t)
        return Frame((self.t[0] + rotated[0], self.t[1] + rotated[1], self.t[2] + rotated[2]), _mul(self.q, child.q))

    def yaw(self) -> float:
        x, y, z, w = self.q
        return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)


def _rotate(q: tuple[float, ...], v: tuple[float, float, float]) -> tuple[float, float, float]:
    x, y, z, w = _mul(_mul(q, (*v, 0.0)), (-q[0], -q[1], -q[2], q[3]))
    return x, y, z


class TfTree:
    """What a tf2 buffer keeps of /tf: per child frame, its parent and its transforms by stamp."""

    def __init__(self) -> None:
        self.parents: dict[str, str] = {}
        self.by_stamp: dict[str, dict[int, Frame]] = {}

    def add(self, msg: Any) -> None:
        for tf in msg.transforms:
            child, parent = tf.child_frame_id, tf.header.frame_id
            assert self.parents.setdefault(child, parent) == parent, f"{child} has two parents"
            t, r = tf.transform.translation, tf.transform.rotation
            stamp = tf.header.stamp.sec * 10**9 + tf.header.stamp.nanosec
            self.by_stamp.setdefault(child, {})[stamp] = Frame((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))

    def chain(self, root: str, frame: str) -> list[str]:
        """The frames from `root` down to `frame`."""
        out = [frame]
        while out[-1] != root:
            parent = self.parents.get(out[-1])
            assert parent is not None, f"{out[-1]} is not connected to {root}"
            out.append(parent)
        return out[::-1]

    def lookup(self, root: str, frame: str, stamp: int) -> Frame:
        """root → frame at `stamp` (each link's transform of exactly that time, as a static-free tree needs)."""
        result = Frame((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
        for child in self.chain(root, frame)[1:]:
            result = result.then(self.by_stamp[child][stamp])
        return result


def _stamp(pose: Pose) -> int:
    return messages.stamp_ns_of(pose.stamp)


def _drive_and_listen(agent: Agent, ros: dict[str, Any]) -> tuple[TfTree, list[Any], Pose]:
    """A goto, with /tf and /robot1/odom heard; then the tree, the odometry and the Pose of the last stamp
    both carry."""
    tree = TfTree()
    odoms: list[Any] = []
    subs = [ROS2Subscriber("/tf", messages.TF_MESSAGE, tree.add, router_port=ros["router_port"]),
            ROS2Subscriber("/robot1/odom", messages.ODOMETRY, odoms.append, router_port=ros["router_port"])]
    try:
        for topic in ("/tf", "/robot1/odom"):
            erni_publisher_matched(agent, topic)
        done = run_task(agent, "BotMotion", "goto", x=0.5, y=0.4, timeout=20)
        assert done.state is TaskState.SUCCEEDED, done.result
        done = run_task(agent, "BotMotion", "turn", angle=60.0, timeout=20)
        assert done.state is TaskState.SUCCEEDED, done.result

        def heard() -> Pose | None:  # the Pose on the blackboard now, once its odometry and /tf came
            pose = agent.query(Pose)[0]
            stamp = _stamp(pose)
            if any(stamp in stamps for stamps in tree.by_stamp.values()) and any(
                    o.header.stamp.sec * 10**9 + o.header.stamp.nanosec == stamp for o in odoms):
                return pose
            return None

        pose = wait_until(heard, timeout=5, message="no /tf and Odometry with the Pose's stamp")
        assert pose is not None
    finally:
        for sub in subs:
            sub.close()
    return tree, odoms, pose


def test_rep105_tree_map_odom_base_link_composes_to_the_pose(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    agent = robot()
    tree, odoms, pose = _drive_and_listen(agent, ros)
    assert tree.chain("map", "robot1/base_link") == ["map", "robot1/odom", "robot1/base_link"]
    stamp = _stamp(pose)
    found = tree.lookup("map", "robot1/base_link", stamp)
    assert found.t[0] == pytest.approx(pose.x, abs=1e-9) and found.t[1] == pytest.approx(pose.y, abs=1e-9)
    assert found.t[2] == 0.0
    assert found.yaw() == pytest.approx(pose.theta, abs=1e-9)
    assert math.hypot(pose.x - 0.5, pose.y - 0.4) <= 0.1 and abs(pose.theta) > 0.5  # the robot did move and turn
    # map → odom is the identity, at every stamp it was sent
    for frame in tree.by_stamp["robot1/odom"].values():
        assert frame.t == (0.0, 0.0, 0.0) and frame.q == (0.0, 0.0, 0.0, 1.0)
    # the odometry of that Pose: in robot1/odom, of robot1/base_link, equal to odom → base_link
    (odom,) = [o for o in odoms if o.header.stamp.sec * 10**9 + o.header.stamp.nanosec == stamp]
    assert odom.header.frame_id == "robot1/odom" and odom.child_frame_id == "robot1/base_link"
    link = tree.by_stamp["robot1/base_link"][stamp]
    assert (odom.pose.pose.position.x, odom.pose.pose.position.y) == (link.t[0], link.t[1])
    assert messages.yaw(odom.pose.pose.orientation) == pytest.approx(link.yaw(), abs=1e-12)
    assert all(o.header.frame_id == "robot1/odom" for o in odoms)


def test_flat_tree_is_map_to_base_link_with_odometry_in_map(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    agent = robot(frames="flat")
    tree, odoms, pose = _drive_and_listen(agent, ros)
    assert tree.chain("map", "robot1/base_link") == ["map", "robot1/base_link"]
    assert "robot1/odom" not in tree.parents
    found = tree.lookup("map", "robot1/base_link", _stamp(pose))
    assert (found.t[0], found.t[1]) == pytest.approx((pose.x, pose.y), abs=1e-9)
    assert found.yaw() == pytest.approx(pose.theta, abs=1e-9)
    assert {(o.header.frame_id, o.child_frame_id) for o in odoms} == {("map", "robot1/base_link")}


def test_a_world_frame_of_another_name_roots_the_tree(robot: Callable[..., Agent], ros: dict[str, Any]) -> None:
    agent = robot(frame="world")
    tree, _, pose = _drive_and_listen(agent, ros)
    assert tree.chain("world", "robot1/base_link") == ["world", "robot1/odom", "robot1/base_link"]
    found = tree.lookup("world", "robot1/base_link", _stamp(pose))
    assert (found.t[0], found.t[1]) == pytest.approx((pose.x, pose.y), abs=1e-9)


def test_frames_refuses_another_value_in_one_line() -> None:
    from pydantic import ValidationError

    from erni.plugins.ros2 import ROS2Settings

    with pytest.raises(ValidationError, match="frames") as err:
        ROS2Settings(frames="rep103")  # type: ignore[arg-type]
    assert "'rep105' or 'flat'" in str(err.value)
