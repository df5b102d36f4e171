"""rosbag2 MCAP bags of a run: `erni record --format mcap`, `--convert`, and `erni replay` of a bag.

Bags are read back with `rosbags`' own Reader and its ROS 2 Jazzy type store (not through ERNI's
reader) for the types and values, and replayed into a control node that `erni watch` observes.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from erni.bags import BagRecorder, read_bag
from erni.blackboard import NetInfo, Pose, Task
from erni.blackboard.schemas import Peer
from erni.blackboard.tasks import Link, Neighbor
from erni.blackboard.testing import wait_until
from erni.replay import FORMAT, LogError, read_log
from erni.transport import Peer as TransportPeer
from tests.transport.helpers import free_port, identity, make_agent, two_tasks_recorded

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli"), "PYTHONUNBUFFERED": "1"}
JAZZY = get_typestore(Stores.ROS2_JAZZY)


def erni(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "erni", *args], cwd=ROOT, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def erni_run(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "erni", *args], cwd=ROOT, env=ENV, capture_output=True,
                          text=True, timeout=timeout)


def bag_messages(path: Path) -> tuple[dict[str, str], list[tuple[str, int, Any]]]:
    """Topics -> types, and every message deserialised with rosbags' Jazzy types."""
    with Reader(path) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        msgs = [(c.topic, t, JAZZY.deserialize_cdr(d, c.msgtype)) for c, t, d in reader.messages()]
    return topics, msgs


def erni_values(status: Any) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


POSE = Pose(robot="robot1", x=1.25, y=-2.5, theta=math.radians(120), v=0.3, w=-0.2, battery=11.2,
            stall_left=True, sonar=[0.5, 1.5], stamp=1_700_000_000.125)
TASK = Task(verb="BotMotion", preposition="goto", params={"x": 3.0, "y": 4.0}, source="control",
            destination="robot1", created=1_700_000_000.0)
DONE = TASK.with_result("failed", progress=0.4, message="blocked", values={"distance_left": 2.5})
NET = NetInfo(node="robot1", kind="network_topology", links=[Link(a="robot1", b="control", quality=0.75)],
              neighbors=[Neighbor(name="control", quality=0.75)], articulation_points=["robot1"],
              stamp=1_700_000_001.0)
PEER = Peer(name="robot2", address="10.0.0.2:47100", role="robot", up=False)


def write_sample(path: Path) -> list[tuple[str, Any]]:
    recorder = BagRecorder(path, "127.0.0.1:47100", started=1_700_000_000.0)
    events = [("add", POSE), ("add", TASK), ("change", DONE), ("add", NET), ("change", PEER),
              ("change", POSE.evolve(x=2.0, theta=-math.pi / 2)), ("remove", TASK)]
    for i, (op, obj) in enumerate(events):
        recorder.write("control", op, type(obj).__name__, obj.model_dump(mode="json"), t=0.5 * i)
    recorder.close()
    return events


def test_bag_has_ros2_types_and_values_that_rosbags_reads(tmp_path: Path) -> None:
    bag = tmp_path / "run.mcap"
    events = write_sample(bag)
    assert bag.is_file() and bag.read_bytes()[:8] == b"\x89MCAP0\r\n"
    assert [p.name for p in tmp_path.iterdir()] == ["run.mcap"], "the writer's directory is gone"
    assert b"\x04\x00\x00\x00zstd" in bag.read_bytes(), "its chunks are zstd-compressed"
    topics, msgs = bag_messages(bag)
    assert topics == {"/erni/record": "diagnostic_msgs/msg/DiagnosticArray",
                      "/robot1/odom": "nav_msgs/msg/Odometry", "/tf": "tf2_msgs/msg/TFMessage",
                      "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
                      "/erni/network": "visualization_msgs/msg/MarkerArray"}
    # the type hash rosbag2 (Jazzy) checks, in the rosbag2 metadata record the MCAP file carries
    found = re.search(rb"name: /robot1/odom\n.*?type_description_hash:\s+(RIHS01_\w+)", bag.read_bytes(), re.S)
    assert found and found.group(1).decode() == JAZZY.hash_rihs01("nav_msgs/msg/Odometry")

    # the file describes itself: the definitions it carries (ros2msg) decode it to the same values,
    # as Foxglove and PlotJuggler decode a bag without ROS 2 installed
    with AnyReader([bag]) as any_reader:
        own = [(c.topic, t, any_reader.deserialize(d, c.msgtype)) for c, t, d in any_reader.messages()]
    assert type(own[1][2]).__module__ == "rosbags.usertypes"
    assert [(topic, t, repr(m)) for topic, t, m in own] == [(topic, t, repr(m)) for topic, t, m in msgs]

    odoms = [(t, m) for topic, t, m in msgs if topic == "/robot1/odom"]
    assert len(odoms) == 2
    t0, odom = odoms[0]
    assert t0 == 1_700_000_000_000_000_000  # the log time: started + t
    # the Pose's stamp (a float: 0.24 us steps at this epoch)
    assert odom.header.stamp.sec == 1_700_000_000 and abs(odom.header.stamp.nanosec - 125_000_000) < 1000
    assert odom.header.frame_id == "map" and odom.child_frame_id == "robot1/base_link"
    pos, q = odom.pose.pose.position, odom.pose.pose.orientation
    assert (pos.x, pos.y, pos.z) == (1.25, -2.5, 0.0)
    assert (q.x, q.y) == (0.0, 0.0) and q.z == pytest.approx(math.sin(math.radians(60)))
    assert q.w == pytest.approx(math.cos(math.radians(60)))
    assert odom.twist.twist.linear.x == 0.3 and odom.twist.twist.angular.z == -0.2
    q2 = odoms[1][1].pose.pose.orientation
    assert 2 * math.atan2(q2.z, q2.w) == pytest.approx(-math.pi / 2) and odoms[1][0] == t0 + 2_500_000_000
    tf = next(m for topic, _, m in msgs if topic == "/tf").transforms[0]
    assert tf.header.frame_id == "map" and tf.child_frame_id == "robot1/base_link"
    assert (tf.transform.translation.x, tf.transform.translation.y) == (1.25, -2.5)

    diagnostics = [(t, m) for topic, t, m in msgs if topic == "/diagnostics"]
    robots = [m.status[0] for _, m in diagnostics if m.status[0].name == "erni/robot/robot1"]
    assert robots[0].level == 2 and "left wheel stalled" in robots[0].message  # a stalled wheel is an error
    assert robots[0].hardware_id == "robot1" and erni_values(robots[0])["battery"] == "11.2"

    tasks = [(t, m) for t, m in diagnostics if m.status[0].name.startswith(f"erni/task/{TASK.uid} ")]
    assert [t for t, _ in tasks] == [t0 + 500_000_000, t0 + 1_000_000_000, t0 + 3_000_000_000]
    pending, failed, removed = (m.status[0] for _, m in tasks)
    assert pending.level == 0 and pending.message == "pending" and pending.hardware_id == "robot1"
    assert failed.level == 2 and failed.message == "failed: blocked"
    values = erni_values(failed)
    assert values["state"] == "failed" and values["progress"] == "0.4" and values["value.distance_left"] == "2.5"
    assert json.loads(values["params"]) == {"x": 3.0, "y": 4.0, "speed": 0.3, "tolerance": 0.1}
    assert json.loads(values["erni"])["data"]["uid"] == TASK.uid
    assert removed.level == 3 and removed.message == "removed"
    stamp = tasks[1][1].header.stamp
    assert stamp.sec + stamp.nanosec / 1e9 == pytest.approx(DONE.result.stamp, abs=1e-6)  # type: ignore[union-attr]

    net = next(m for _, m in diagnostics if m.status[0].name == "erni/robot1/network")
    own, neighbour = net.status
    assert own.hardware_id == "robot1" and erni_values(own)["link robot1-control"] == "0.75"
    assert erni_values(own)["articulation_points"] == "robot1"
    assert neighbour.name == "erni/robot1/neighbor/control" and erni_values(neighbour)["quality"] == "0.750"
    markers = next(m for topic, _, m in msgs if topic == "/erni/network").markers
    links = [mk for mk in markers if mk.ns == "erni_links"][0]
    assert [(p.x, p.y) for p in links.points] == [], "control's position is not known: no line is drawn"
    peer = next(m for _, m in diagnostics if m.status[0].name == "erni/peer/robot2").status[0]
    assert peer.level == 3 and peer.message == "down" and peer.hardware_id == "robot2"

    # ERNI's reader gives back the very objects, ops and times
    header, replayed, problems = read_bag(bag)
    assert problems == [] and header == {"erni_record": FORMAT, "via": "127.0.0.1:47100", "started": 1_700_000_000.0}
    assert [(e.op, e.obj, e.t) for e in replayed] == [(op, obj, 0.5 * i) for i, (op, obj) in enumerate(events)]


def test_convert_a_log_and_replay_the_bag_like_the_log(tmp_path: Path) -> None:
    log = tmp_path / "team.jsonl"
    lines = [{"erni_record": FORMAT, "via": "10.1.1.1:47100", "started": 1_750_000_000.5}]
    objs = [("add", POSE), ("add", TASK), ("change", DONE), ("change", POSE.evolve(x=4.0)), ("change", NET)]
    lines += [{"t": 0.2 * i, "agent": "control", "op": op, "type": type(o).__name__, "data": o.model_dump(mode="json")}
              for i, (op, o) in enumerate(objs)]
    log.write_text("\n".join(json.dumps(line) for line in lines) + "\n{broken\n")
    out = erni_run("record", "--convert", str(log), str(tmp_path / "team.mcap"))
    assert out.returncode == 0, out.stderr
    assert "converted 5 events" in out.stderr and "skipping" in out.stderr and "Traceback" not in out.stderr
    topics, msgs = bag_messages(tmp_path / "team.mcap")
    odom_times = [t for topic, t, _ in msgs if topic == "/robot1/odom"]
    assert odom_times == [1_750_000_000_500_000_000, 1_750_000_001_100_000_000]
    assert [m.pose.pose.position.x for topic, _, m in msgs if topic == "/robot1/odom"] == [1.25, 4.0]
    from_log, from_bag = read_log(log), read_log(tmp_path / "team.mcap")
    assert from_bag[0] == from_log[0]
    assert [(e.t, e.agent, e.op, e.obj) for e in from_bag[1]] == \
        [(pytest.approx(e.t, abs=1e-9), e.agent, e.op, e.obj) for e in from_log[1]]

    # the bag replays into a control node as the log does
    out = erni_run("replay", str(tmp_path / "team.mcap"), "--no-gui", "--insecure", "--speed", "20",
                   "--listen", f"127.0.0.1:{free_port()}")
    assert out.returncode == 0 and "replay finished (5 events)" in out.stderr, out.stderr

    # --convert writes bags only
    out = erni_run("record", "--convert", str(log), str(tmp_path / "x.jsonl"))
    assert out.returncode == 2 and "--convert writes an MCAP bag" in out.stderr


def test_record_a_live_team_as_mcap_then_replay_it(tmp_path: Path) -> None:
    disc, port = free_port(), free_port()
    control = make_agent("control", disc, echo=False, role="control", listen=f"127.0.0.1:{port}")
    robot = make_agent("robot1", disc)
    bag = tmp_path / "live.mcap"
    try:
        wait_until(lambda: any(p.up and p.role == "control" for p in robot.query(TransportPeer)))
        rec = erni("record", "--via", f"127.0.0.1:{port}", "--seconds", "4", "--format", "mcap", str(bag))
        # warm-up: the recorder has loaded the types and leased its watch
        tasks, _, err = two_tasks_recorded(control, robot, rec, theta=0.5)
    finally:
        control.stop()
        robot.stop()
    assert f"into {bag}" in err

    topics, msgs = bag_messages(bag)
    assert topics["/robot1/odom"] == "nav_msgs/msg/Odometry" and topics["/diagnostics"].endswith("DiagnosticArray")
    xs = [m.pose.pose.position.x for topic, _, m in msgs if topic == "/robot1/odom"]
    assert xs[-1] == 2.0 and xs == sorted(xs)
    finals = {erni_values(m.status[0])["uid"]: m.status[0].message for topic, _, m in msgs
              if topic == "/diagnostics" and m.status[0].name.startswith("erni/task/")}
    assert finals[tasks[0].uid].startswith("succeeded") and finals[tasks[1].uid].startswith("succeeded")

    replay_port = free_port()
    replay = erni("replay", str(bag), "--speed", "2", "--listen", f"127.0.0.1:{replay_port}", "--no-gui",
                  "--identity", identity("control", "control"))
    try:
        # kept: the two start-ups overlap on purpose. A watch started only once the replay says it listens
        # comes too late for this 2 s replay in half the runs (its start-up takes a second or more), and one
        # started before it listens loses its lease request, sent once per 5 s
        time.sleep(1.0)
        watch = erni_run("watch", "--via", f"127.0.0.1:{replay_port}", "--json", "--seconds", "5")
        replay.communicate(timeout=30)
    finally:
        if replay.poll() is None:
            replay.kill()
            replay.wait()
    seen = [json.loads(line) for line in watch.stdout.splitlines()]
    states = [(e["data"]["uid"], (e["data"].get("result") or {}).get("state", "pending"))
              for e in seen if e["type"] == "Task"]
    assert (tasks[0].uid, "succeeded") in states and (tasks[1].uid, "succeeded") in states
    poses = [e["data"]["x"] for e in seen if e["type"] == "Pose"]
    assert poses and poses[-1] == 2.0 and poses == sorted(poses)


def test_a_bag_of_the_live_topics_replays_odometry_and_task_status(tmp_path: Path) -> None:
    """A bag of the live ros2 plugin's topics, as `ros2 bag record` saves them (Odometry on
    /<robot>/odom, JSON Strings on /erni/task_status), replays its poses and tasks."""
    from erni import ros2_messages as messages

    path = tmp_path / "tb3"
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    odom = writer.add_connection("/tb3/odom", "nav_msgs/msg/Odometry", typestore=JAZZY)
    status = writer.add_connection("/erni/task_status", "std_msgs/msg/String", typestore=JAZZY)
    task = Task(verb="BotMotion", preposition="forward", params={"distance": 0.2}, source="control",
                destination="tb3")
    for i in range(3):
        pose = Pose(robot="tb3", x=0.1 * i, theta=0.3 * i, v=0.1, stamp=1_700_000_000 + i)
        writer.write(odom, (1_700_000_000 + i) * 10**9, messages.serialize(messages.odometry(pose, pose.stamp * 10**9)))
    done = task.with_result("succeeded", progress=1.0, message="arrived", values={"moved": 0.2})
    writer.write(status, 1_700_000_002_500_000_000, messages.serialize(messages.task_status(done)))
    writer.close()
    for where in (path, path / "tb3.mcap"):  # the rosbag2 directory and its MCAP file alone
        header, events, problems = read_log(where)
        assert problems == [] and [e.t for e in events] == [0.0, 1.0, 2.0, 2.5]
        assert [(e.obj.robot, e.obj.x, round(e.obj.theta, 9)) for e in events[:3]] == [  # type: ignore[attr-defined]
            ("tb3", 0.0, 0.0), ("tb3", 0.1, 0.3), ("tb3", 0.2, 0.6)]
        assert events[3].obj == done.evolve(created=done.result.stamp)  # type: ignore[union-attr]
        assert header["started"] == 1_700_000_000.0


def test_bad_bags_are_one_line_errors(tmp_path: Path) -> None:
    not_mcap = tmp_path / "log.mcap"
    not_mcap.write_text('{"erni_record": 1}\n')
    with pytest.raises(LogError, match="not an MCAP file"):
        read_log(not_mcap)
    chatter = tmp_path / "chatter"
    writer = Writer(chatter, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=JAZZY)
    writer.write(conn, 1, bytes(JAZZY.serialize_cdr(JAZZY.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String")))
    writer.close()
    with pytest.raises(LogError, match=r"no ERNI topics .* it has /chatter \(std_msgs/msg/String\)"):
        read_log(chatter / "chatter.mcap")
    robot_diagnostics = tmp_path / "diag"  # a ROS 2 robot's own /diagnostics, no ERNI status among them
    writer = Writer(robot_diagnostics, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conn = writer.add_connection("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", typestore=JAZZY)
    array = JAZZY.types["diagnostic_msgs/msg/DiagnosticArray"](
        header=JAZZY.types["std_msgs/msg/Header"](stamp=JAZZY.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                                 frame_id=""),
        status=[JAZZY.types["diagnostic_msgs/msg/DiagnosticStatus"](level=0, name="motors", message="ok",
                                                                   hardware_id="tb3", values=[])])
    writer.write(conn, 1, bytes(JAZZY.serialize_cdr(array, "diagnostic_msgs/msg/DiagnosticArray")))
    writer.close()
    with pytest.raises(LogError, match=r"no ERNI topics .* it has /diagnostics"):
        read_log(robot_diagnostics)
    cut = tmp_path / "cut.mcap"
    write_sample(tmp_path / "whole.mcap")
    cut.write_bytes((tmp_path / "whole.mcap").read_bytes()[:300])
    with pytest.raises(LogError, match="cannot read the bag"):
        read_log(cut)
    for bad, says in ((not_mcap, "not an MCAP file"), (chatter / "chatter.mcap", "no ERNI topics"),
                      (cut, "cannot read the bag")):
        out = erni_run("replay", str(bad), "--no-gui", "--insecure", "--listen", f"127.0.0.1:{free_port()}")
        assert out.returncode == 2 and says in out.stderr and "Traceback" not in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr
    out = erni_run("record", "--convert", str(not_mcap), str(tmp_path / "out.mcap"))
    assert out.returncode == 2 and "not an MCAP file" in out.stderr and "Traceback" not in out.stderr
