"""rosbag2 MCAP bags of a run: `erni record --format mcap`, `--convert`, and `erni replay` of a bag.

Bags are read back with `rosbags`' own Reader and its ROS 2 Jazzy type store (not through ERNI's
reader) for the types and values, and replayed into a control node that `erni watch` observes.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from erni import ros2_messages as messages
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


def plain(value: Any) -> Any:
    """A message as nested dicts and lists of its fields (rosbags' and mcap_ros2's classes alike)."""
    names = getattr(value, "__dataclass_fields__", None) or getattr(value, "__slots__", None)
    if names and not isinstance(value, (str, bytes)):
        return {k: plain(getattr(value, k)) for k in names if not k.startswith("_") and not k.isupper()}
    if isinstance(value, np.ndarray):
        return [plain(x) for x in value.tolist()]
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (list, tuple)):
        return [plain(x) for x in value]
    return value


def mcap_messages(path: Path) -> list[tuple[str, int, Any]]:
    """Every message as Foxglove's mcap reader (CRCs checked) and mcap-ros2-support decode it from the
    file's own schemas."""
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()], validate_crcs=True)
        return [(c.topic, m.log_time, plain(d)) for _, c, m, d in reader.iter_decoded_messages(log_time_order=True)]


def chunk_compressions(path: Path) -> list[str]:
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted({c.compression for c in summary.chunk_indexes})


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
    assert chunk_compressions(bag) == [""], "its chunks are stored as they are: rosbag2's default MCAP preset"
    topics, msgs = bag_messages(bag)
    assert topics == {"/erni/record": "diagnostic_msgs/msg/DiagnosticArray",
                      "/robot1/odom": "nav_msgs/msg/Odometry", "/tf": "tf2_msgs/msg/TFMessage",
                      "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
                      "/erni/network": "visualization_msgs/msg/MarkerArray"}
    # the type hash rosbag2 (Jazzy) checks, in the rosbag2 metadata record the MCAP file carries
    found = re.search(rb"name: /robot1/odom\n.*?type_description_hash:\s+(RIHS01_\w+)", bag.read_bytes(), re.S)
    assert found and found.group(1).decode() == JAZZY.hash_rihs01("nav_msgs/msg/Odometry")
    # Foxglove's mcap reader, checking every CRC, and its own ROS 2 decoder read the same values
    assert mcap_messages(bag) == [(topic, t, plain(m)) for topic, t, m in msgs]

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


INFINITE = {"sec": 9223372036, "nsec": 854775807}  # RMW_DURATION_INFINITE


def live_qos(typename: str) -> dict[str, Any]:
    """The QoS the live ros2 plugin's publisher of a type offers (its own `_qos`), in rosbag2's form."""
    from erni.plugins.ros2.plugin import ROS2Plugin

    qos = ROS2Plugin._qos(typename)
    return {"history": "keep_last", "depth": qos.depth, "reliability": "reliable" if qos.reliable else "best_effort",
            "durability": "transient_local" if qos.transient_local else "volatile", "deadline": INFINITE,
            "lifespan": INFINITE, "liveliness": "automatic", "liveliness_lease_duration": INFINITE,
            "avoid_ros_namespace_conventions": False}


def test_the_file_says_what_ros2_bag_record_writes(tmp_path: Path) -> None:
    """Channel metadata (`topic_type_hash`, `offered_qos_profiles`), the profile, the `rosbag2` metadata
    record (format 9, `ros_distro: jazzy`) as rosbag2's MCAP storage (Jazzy) writes them, read with
    Foxglove's mcap reader, PyYAML and rosbags."""
    bag = tmp_path / "run.mcap"
    write_sample(bag)
    with bag.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        header, summary = reader.get_header(), reader.get_summary()
        records = list(reader.iter_metadata())
    assert summary is not None and summary.statistics is not None
    assert header.profile == "ros2" and re.fullmatch(r"erni \S+ \(mcap-python/[0-9.]+\)", header.library), header
    channels = {c.topic: c for c in summary.channels.values()}
    assert list(channels) == ["/erni/record", "/robot1/odom", "/tf", "/diagnostics", "/erni/network"]
    for topic, channel in channels.items():
        schema = summary.schemas[channel.schema_id]
        assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
        assert set(channel.metadata) == {"offered_qos_profiles", "topic_type_hash"}
        # ERNI's own RIHS01 (erni.ros2_messages) is rosbags' Jazzy hash of the schema's type
        assert channel.metadata["topic_type_hash"] == JAZZY.hash_rihs01(schema.name) == messages.type_hash(schema.name)
        assert yaml.safe_load(channel.metadata["offered_qos_profiles"]) == [live_qos(schema.name)], topic
        assert schema.data.decode() == JAZZY.generate_msgdef(schema.name, ros_version=2)[0]
    assert yaml.safe_load(channels["/tf"].metadata["offered_qos_profiles"])[0]["depth"] == 100
    assert yaml.safe_load(channels["/robot1/odom"].metadata["offered_qos_profiles"])[0]["depth"] == 10

    assert [r.name for r in records] == ["rosbag2"] and list(records[0].metadata) == ["serialized_metadata"]
    info = yaml.safe_load(records[0].metadata["serialized_metadata"])
    assert info["version"] == 9 and info["storage_identifier"] == "mcap" and info["ros_distro"] == "jazzy"
    assert info["relative_file_paths"] == ["run.mcap"] and info["files"][0]["path"] == "run.mcap"
    assert (info["compression_format"], info["compression_mode"]) == ("", "")
    stats = summary.statistics
    assert info["message_count"] == stats.message_count == 13
    assert info["starting_time"]["nanoseconds_since_epoch"] == stats.message_start_time == 1_700_000_000 * 10**9
    assert info["duration"]["nanoseconds"] == stats.message_end_time - stats.message_start_time == 3 * 10**9
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    for topic, channel in channels.items():
        meta = topics[topic]["topic_metadata"]
        assert topics[topic]["message_count"] == stats.channel_message_counts[channel.id]
        assert meta["type_description_hash"] == channel.metadata["topic_type_hash"]
        assert meta["offered_qos_profiles"] == yaml.safe_load(channel.metadata["offered_qos_profiles"])

    # read as a stream too, record by record (CRCs checked): chunks with message indexes, rosbag2's record
    # after every message, then the summary
    with bag.open("rb") as f:
        order = [type(r).__name__ for r in StreamReader(f, emit_chunks=True, validate_crcs=True).records]
    kinds = Counter(order)
    assert order.index("Metadata") > max(i for i, kind in enumerate(order) if kind in ("Chunk", "MessageIndex"))
    assert kinds == {"Header": 1, "Chunk": 1, "MessageIndex": 5, "Metadata": 1, "DataEnd": 1, "Schema": 4,
                     "Channel": 5, "Statistics": 1, "ChunkIndex": 1, "MetadataIndex": 1, "SummaryOffset": 5,
                     "Footer": 1}, kinds

    # rosbags reads the QoS as rosbag2 would replay it
    with Reader(bag) as reader:
        odom = next(c for c in reader.connections if c.topic == "/robot1/odom")
        (qos,) = odom.ext.offered_qos_profiles  # type: ignore[union-attr]
    assert (qos.history.name, qos.depth, qos.reliability.name, qos.durability.name, qos.liveliness.name) == (
        "KEEP_LAST", 10, "RELIABLE", "VOLATILE", "AUTOMATIC")
    assert (qos.deadline.sec, qos.deadline.nsec) == (INFINITE["sec"], INFINITE["nsec"])


def test_any_name_is_a_rosbag2_directory_and_compression_is_asked_for(tmp_path: Path) -> None:
    """A name without `.mcap` is a bag directory as `ros2 bag record -o NAME` writes (rosbags picks its
    reader by a file's suffix, so an MCAP file named otherwise is no bag to it); chunks are compressed
    only when asked, and every compression reads back to the same messages."""
    plain_bag = tmp_path / "plain.mcap"
    write_sample(plain_bag)
    expected = mcap_messages(plain_bag)
    sizes = {"none": plain_bag.stat().st_size}
    for compression in ("zstd", "lz4"):
        out = tmp_path / f"run-{compression}"
        recorder = BagRecorder(out, "127.0.0.1:47100", started=1_700_000_000.0, compression=compression)
        recorder.close()  # only the header: written and read like any other
        assert [topic for topic, _, _ in mcap_messages(out / f"run-{compression}_0.mcap")] == ["/erni/record"]
        out = tmp_path / f"team-{compression}"
        recorder = BagRecorder(out, "127.0.0.1:47100", started=1_700_000_000.0, compression=compression)
        events = [("add", POSE), ("add", TASK), ("change", DONE), ("add", NET), ("change", PEER),
                  ("change", POSE.evolve(x=2.0, theta=-math.pi / 2)), ("remove", TASK)]
        for i, (op, obj) in enumerate(events):
            recorder.write("control", op, type(obj).__name__, obj.model_dump(mode="json"), t=0.5 * i)
        recorder.close()
        assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", f"team-{compression}_0.mcap"]
        file = out / f"team-{compression}_0.mcap"
        assert chunk_compressions(file) == [compression]
        assert mcap_messages(file) == expected
        sizes[compression] = file.stat().st_size
        with Reader(out) as reader:  # the directory, through its metadata.yaml
            assert reader.ros_distro == "jazzy" and reader.message_count == 13
            assert {c.topic: c.digest for c in reader.connections}["/robot1/odom"] == \
                JAZZY.hash_rihs01("nav_msgs/msg/Odometry")
            assert [(c.topic, t, plain(JAZZY.deserialize_cdr(d, c.msgtype))) for c, t, d in reader.messages()] \
                == expected
        meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert meta["relative_file_paths"] == [file.name] and meta["version"] == 9
        with AnyReader([out]) as any_reader:
            assert len(list(any_reader.messages())) == 13
        assert [(e.op, e.obj) for e in read_log(out)[1]] == [(op, obj) for op, obj in events]
    assert sizes["zstd"] < sizes["none"] and sizes["lz4"] < sizes["none"], sizes
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == [], "no writer's directory is left"

    with pytest.raises(LogError, match="exists already"):
        BagRecorder(tmp_path / "team-zstd", "v")
    with pytest.raises(LogError, match="compression 'gzip': expected one of none, zstd, lz4"):
        BagRecorder(tmp_path / "g.mcap", "v", compression="gzip")

    # from the command line: --convert into a directory, --compression
    log = tmp_path / "team.jsonl"
    log.write_text(json.dumps({"erni_record": FORMAT, "via": "10.1.1.1:47100", "started": 1_750_000_000.5}) + "\n"
                   + json.dumps({"t": 0.5, "agent": "control", "op": "add", "type": "Pose",
                                 "data": POSE.model_dump(mode="json")}) + "\n")
    out = erni_run("record", "--convert", str(log), "--format", "mcap", "--compression", "zstd", str(tmp_path / "conv"))
    assert out.returncode == 0 and "converted 1 events" in out.stderr, out.stderr
    assert chunk_compressions(tmp_path / "conv" / "conv_0.mcap") == ["zstd"]
    assert [e.obj for e in read_log(tmp_path / "conv")[1]] == [POSE]
    out = erni_run("record", "--convert", str(log), "--format", "mcap", str(tmp_path / "conv"))
    assert out.returncode == 2 and "exists already" in out.stderr and len(out.stderr.strip().splitlines()) == 1
    out = erni_run("record", "--compression", "zstd", str(tmp_path / "x.jsonl"))
    assert out.returncode == 2 and "--compression" in out.stderr and len(out.stderr.strip().splitlines()) == 1


def single_robot_bag(path: Path, xs: list[float]) -> Path:
    """A robot's own bag as `ros2 bag record` writes it on the robot: Odometry on /odom, /tf, no namespace."""
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=JAZZY)
    writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=JAZZY)
    for i, x in enumerate(xs):
        pose = Pose(robot="base", x=x, theta=0.1 * i, v=0.2, stamp=1_700_000_000 + i)
        writer.write(odom, (1_700_000_000 + i) * 10**9, messages.serialize(messages.odometry(pose, pose.stamp * 10**9)))
    writer.close()
    return path


def test_a_single_robots_bag_replays_as_the_robot_named(tmp_path: Path) -> None:
    bag = single_robot_bag(tmp_path / "tb3_run", [0.0, 0.5, 1.0])
    _, events, problems = read_log(bag, robot="tb3")
    assert problems == [] and [(e.t, e.agent, e.obj.robot, e.obj.x) for e in events] == [  # type: ignore[attr-defined]
        (0.0, "tb3", "tb3", 0.0), (1.0, "tb3", "tb3", 0.5), (2.0, "tb3", "tb3", 1.0)]
    with pytest.raises(LogError, match=r"/odom names no robot .*give --robot NAME"):
        read_log(bag)
    with pytest.raises(LogError, match="--robot 'a b': expected a robot's name"):
        read_log(bag, robot="a b")

    out = erni_run("replay", str(bag), "--no-gui", "--insecure", "--listen", f"127.0.0.1:{free_port()}")
    assert out.returncode == 2 and "--robot NAME" in out.stderr and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr

    out = erni_run("replay", str(bag), "--robot", "tb3", "--speed", "20", "--no-gui", "--insecure",
                   "--listen", f"127.0.0.1:{free_port()}")
    assert out.returncode == 0 and "replay finished (3 events)" in out.stderr, out.stderr

    # looping, so that the watch sees it whenever its lease is granted
    port = free_port()
    replay = erni("replay", str(bag), "--robot", "tb3", "--loop", "--speed", "4", "--no-gui",
                  "--listen", f"127.0.0.1:{port}", "--identity", identity("control", "control"))
    try:
        watch = erni_run("watch", "--via", f"127.0.0.1:{port}", "--json", "--seconds", "8")
    finally:
        replay.send_signal(signal.SIGINT)
        try:
            replay.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            replay.kill()
            replay.wait()
    poses = [(e["data"]["robot"], e["data"]["x"]) for e in map(json.loads, watch.stdout.splitlines())
             if e["type"] == "Pose"]
    # (a loop removes its objects right after its last event: a watch may see that pose or not)
    assert {r for r, _ in poses} == {"tb3"} and {0.0, 0.5} <= {x for _, x in poses} <= {0.0, 0.5, 1.0}, watch.stdout
