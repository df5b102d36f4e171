"""rosbag2 MCAP bags of a team's run, written as `ros2 bag record` (Jazzy) writes them and read with
`rosbags` (no ROS 2 install needed).

A bag holds what `erni record` sees, as ROS 2 Jazzy messages a lab's tools open (`ros2 bag`,
Foxglove, PlotJuggler), on the topics and types the live ros2 plugin uses where it has them:

| topic | type | what |
|---|---|---|
| `/<robot>/odom` | `nav_msgs/msg/Odometry` | each robot's Pose: position, heading, v and w, in frame `map` (`messages.odometry`) |
| `/tf` | `tf2_msgs/msg/TFMessage` | `map` -> `<robot>/base_link` for each Pose |
| `/diagnostics` | `diagnostic_msgs/msg/DiagnosticArray` | tasks and results, robots' health, network info, peers: one status each (below) |
| `/erni/network` | `visualization_msgs/msg/MarkerArray` | the network drawn in 3D: nodes, names, links coloured by quality (`messages.network_markers`) |
| `/erni/record` | `diagnostic_msgs/msg/DiagnosticArray` | the recording's header: who was recorded, when it started |

Tasks, network and peers are diagnostics rather than JSON in a `std_msgs/msg/String`: `/diagnostics`
is where rqt_robot_monitor and Foxglove's Diagnostics panels look by default; they list each status
by robot (`hardware_id`) with its level as a colour (a failed task or a stalled wheel red, a
cancelled task or a degraded network source yellow, a removed object or a lost peer stale), and
PlotJuggler plots the numeric values (a task's progress, a link's quality, a battery) as series;
a String shows only as text. Each status also carries the ERNI object itself as JSON under the key
`erni`, so `erni replay` plays a bag back as exactly as its own JSON-lines logs.

The file is what rosbag2's MCAP storage writes, written by Foxglove's own MCAP writer (`mcap.writer`;
rosbags' writer puts no type hash in a channel and no lz4 chunks): profile `ros2`, each type's `ros2msg`
schema, each channel's `topic_type_hash` (RIHS01, which rosbag2's reader takes from there only) and
`offered_qos_profiles` (the QoS the live plugin's publisher offers: `offered_qos`), the `rosbag2`
metadata record (format 9, `ros_distro: jazzy`), chunks with their message indexes and the summary;
rosbag2's metadata is YAML written by PyYAML. Chunks are stored uncompressed, as rosbag2's default MCAP
preset (`none`) writes them, or compressed with zstd or lz4 when asked (`COMPRESSIONS`). A name ending in `.mcap` is one file; any
other is the directory `ros2 bag record -o NAME` writes (`NAME/metadata.yaml`, `NAME/NAME_0.mcap`):
rosbags takes a lone file for a bag only by its `.mcap` suffix.

A bag without ERNI's statuses replays too: the poses of its `nav_msgs/msg/Odometry` on
`/<robot>/odom` and the tasks of its `/erni/task_status` (the live plugin's topics, as `ros2 bag
record` saves them), and a single robot's own bag (Odometry on `/odom`, no namespace) as the robot
named by `robot` (`erni replay --robot NAME`). A topic whose `<robot>` is no robot's name
(`erni.blackboard.text`) is skipped and named; an Odometry whose numbers are not finite is a skipped
message. Before any of it is read, the file is held to `mcap_bounds`' bounds (a chunk's and a
message's decompressed size).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import yaml  # type: ignore[import-untyped,unused-ignore]
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, IndexType, Writer
from pydantic import ValidationError

from erni import mcap_bounds
from erni import ros2_messages as ros
from erni.blackboard import BBObject, NetInfo, Pose, Task
from erni.blackboard.clock import SYSTEM, Clock
from erni.blackboard.errors import ErniError, shown
from erni.blackboard.schemas import Peer
from erni.blackboard.tasks import AllocationResult
from erni.blackboard.text import NAME_CHARS, is_name, printable
from erni.replay import FORMAT, MCAP_MAGIC, Event, LogError, problem_of, read_log
from erni.transport.wire import TYPES

FRAME = "map"
ODOMETRY = ros.ODOMETRY
DIAGNOSTICS = ros.DIAGNOSTIC_ARRAY
HEADER_TOPIC = "/erni/record"
DIAGNOSTICS_TOPIC = "/diagnostics"
MARKERS_TOPIC = "/erni/network"
TASK_STATUS_TOPIC = "/erni/task_status"
SINGLE_ODOM = "/odom"  # a robot's own ROS 2 stack: its odometry without a robot's namespace
OK, WARN, ERROR, STALE = 0, 1, 2, 3
_STATUS = "diagnostic_msgs/msg/DiagnosticStatus"
_KV = "diagnostic_msgs/msg/KeyValue"


def pose_from_odometry(robot: str, msg: Any) -> Pose:
    """The Pose an Odometry message says (what a bag without ERNI's diagnostics gives)."""
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9
    return Pose(robot=robot, x=float(msg.pose.pose.position.x), y=float(msg.pose.pose.position.y),
                theta=ros.yaw(msg.pose.pose.orientation), v=float(msg.twist.twist.linear.x),
                w=float(msg.twist.twist.angular.z), stamp=stamp)


def _text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, str):
        return value
    return json.dumps(value, separators=(",", ":"))


def _readable(op: str, obj: BBObject | None) -> tuple[int, str, str, str, dict[str, Any]]:
    """Level, name, hardware id, message and values a diagnostics viewer shows for one object."""
    match obj:
        case Pose():
            trouble = [w for w, on in (("left wheel stalled", obj.stall_left), ("right wheel stalled",
                       obj.stall_right), ("motors off", not obj.motors_enabled), ("bumper", obj.bumpers)) if on]
            battery = "" if obj.battery is None else f", battery {obj.battery:.1f} V"
            return (ERROR if trouble else OK, f"erni/robot/{obj.robot}", obj.robot,
                    "; ".join(trouble) or f"x {obj.x:.2f} y {obj.y:.2f} heading "
                    f"{math.degrees(obj.theta):.0f} deg{battery}",
                    {"x": obj.x, "y": obj.y, "heading_deg": math.degrees(obj.theta), "v": obj.v, "w": obj.w,
                     "battery": obj.battery, "stall_left": obj.stall_left, "stall_right": obj.stall_right,
                     "bumpers": obj.bumpers, "motors_enabled": obj.motors_enabled, "sonar": obj.sonar})
        case Task():
            result = obj.result
            state = obj.state.value
            level = {"failed": ERROR, "cancelled": WARN}.get(state, OK)
            values: dict[str, Any] = {"uid": obj.uid, "state": state, "verb": obj.verb,
                                      "preposition": obj.preposition, "source": obj.source,
                                      "params": obj.params.model_dump(mode="json", exclude_none=True)}
            if result is not None:
                values |= {"progress": result.progress, "confidence": result.confidence}
                values |= {f"value.{k}": v for k, v in result.values.items()}
            message = state + (f": {result.message}" if result and result.message else "")
            return level, f"erni/task/{obj.uid} {obj.describe()}", obj.destination or "", message, values
        case NetInfo():
            values = {f"link {link.a}-{link.b}": link.quality for link in obj.links}
            values |= {f"neighbor {n.name}": n.quality for n in obj.neighbors}
            values |= {f"route {r.destination}": f"via {r.next_hop}, {r.hops} hops, cost {r.cost:g}"
                       for r in obj.routes}
            values["articulation_points"] = " ".join(obj.articulation_points)
            message = obj.message or (f"{len(obj.links)} links, {len(obj.neighbors)} neighbours, "
                                      f"articulation points: {', '.join(obj.articulation_points) or 'none'}")
            return WARN if obj.degraded else OK, f"erni/network/{obj.node}/{obj.kind}", obj.node, message, values
        case Peer():
            state = "up" if obj.up else "down"
            message = state + (f" (degraded: {obj.degraded})" if obj.degraded else "")
            return (OK if obj.up else STALE, f"erni/peer/{obj.name}", obj.name, message,
                    {"address": obj.address, "role": obj.role, "epoch": obj.epoch, "last_heard": obj.last_heard})
    return OK, f"erni/{type(obj).__name__}", "", op, {}


def _validated(type_name: str, data: dict[str, Any]) -> BBObject | None:
    cls = TYPES.get(type_name)
    try:
        return cls.model_validate(data) if cls is not None and issubclass(cls, BBObject) else None
    except ValidationError:
        return None


def diagnostics(agent: str, op: str, type_name: str, data: dict[str, Any], when: float,
                obj: BBObject | None = None) -> Any:
    """One ERNI event as a DiagnosticArray, the event itself under the key `erni` of its first status
    (`obj`: `data` already validated, if it was).

    A NetInfo is the network's diagnostics as the live ros2 plugin publishes them (one status for the
    node, one per neighbour: `messages.diagnostics`), its links and routes added to the node's status."""
    if obj is None:
        obj = _validated(type_name, data)
    level, name, hardware, message, values = _readable(op, obj)
    if op == "remove":
        level, message = STALE, "removed"
    pairs = [ros.make(_KV, key=k, value=_text(v)) for k, v in values.items() if v is not None]
    pairs.append(ros.make(_KV, key="erni", value=json.dumps(
        {"agent": agent, "op": op, "type": type_name, "data": data}, separators=(",", ":"))))
    stamp = getattr(obj, "stamp", None) or when
    if isinstance(obj, Task):  # when the performer said it (or the task was made)
        stamp = obj.result.stamp if obj.result else obj.created
    if isinstance(obj, NetInfo) and op != "remove":
        array = ros.diagnostics(obj, ros.stamp_ns_of(stamp))
        own = array.status[0]
        have = {kv.key for kv in own.values}
        own.values = own.values + [kv for kv in pairs if kv.key not in have]
        return array
    status = ros.make(_STATUS, level=level, name=name, message=message, hardware_id=hardware, values=pairs)
    return ros.make(DIAGNOSTICS, header=ros.header(ros.stamp_ns_of(stamp), ""), status=[status])


# --- writing: an MCAP file as rosbag2's MCAP storage (Jazzy) writes it -------------------------

ROS_DISTRO = "jazzy"  # the distribution whose message types (and hashes) the bag holds
_COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}
COMPRESSIONS = tuple(_COMPRESSION)
"""Chunk compressions of `erni record --compression`: none is rosbag2's default MCAP preset (`none`:
chunks stored as they are); zstd is its `zstd_fast`/`zstd_small` presets' choice; lz4 its other one.
Each chunk carries its CRC (as `zstd_small` writes), which readers check."""
CHUNK_SIZE = 768 * 1024  # the MCAP writer's chunk size, which rosbag2's presets (but zstd_small) keep
# the file's indexes: chunks, messages and metadata (a bag has no attachments, and the C++ MCAP writer of
# rosbag2 leaves an empty index group out of the summary)
_INDEXES = IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA
_INFINITE = {"sec": 9223372036, "nsec": 854775807}  # RMW_DURATION_INFINITE, rmw_zenoh's default durations
_DEPTHS = {"/tf": 100}  # the live plugin's publishers: keep last 10, /tf keep last 100 (plugins/ros2)


def _yaml(value: Any) -> str:
    """Block YAML of rosbag2's metadata (PyYAML's): keys in their order, as rosbag2 writes them."""
    return str(yaml.safe_dump(value, sort_keys=False, default_flow_style=False))


def offered_qos(topic: str) -> dict[str, Any]:
    """The QoS profile ERNI's ros2 plugin offers on `topic`, as rosbag2 (format 9) writes a profile:
    reliable, volatile, keep last 10 (100 on /tf), rmw_zenoh's infinite durations, automatic liveliness."""
    return {"history": "keep_last", "depth": _DEPTHS.get(topic, 10), "reliability": "reliable",
            "durability": "volatile", "deadline": dict(_INFINITE), "lifespan": dict(_INFINITE),
            "liveliness": "automatic", "liveliness_lease_duration": dict(_INFINITE),
            "avoid_ros_namespace_conventions": False}


class BagRecorder:
    """Write events into a rosbag2 bag in MCAP storage as they arrive (the interface of erni.replay.Recorder),
    as `ros2 bag record` (Jazzy) writes one.

    A `path` ending in `.mcap` is one MCAP file, which holds rosbag2's metadata itself (`ros2 bag info`,
    Foxglove and `rosbags` open it alone); any other name is a rosbag2 directory as `ros2 bag record -o
    path` writes: `path/metadata.yaml` and `path/<name>_0.mcap`. Either is written beside `path` under a
    hidden name and moved there on close. Each channel carries the type's hash (`topic_type_hash`) and the
    QoS the live plugin offers (`offered_qos_profiles`); chunks are compressed as `compression` says
    (`COMPRESSIONS`; none by default, as rosbag2's default MCAP preset).
    """

    def __init__(self, path: str | Path, via: str, started: float | None = None, clock: Clock = SYSTEM,
                 compression: str = "none"):
        from erni import __version__

        if compression not in COMPRESSIONS:
            raise LogError(f"compression {shown(compression)}: expected one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        self.directory = self.path.suffix.lower() != ".mcap"
        self.file_name = f"{self.path.name}_0.mcap" if self.directory else self.path.name
        self.compression = compression
        self.count = 0
        self.clock = clock  # the recorder's: changes are stamped by it
        self.started = clock.wall() if started is None else started
        self._start = clock()
        self._poses: dict[str, Pose] = {}
        if self.directory and self.path.exists():
            raise LogError(f"{self.path}: exists already; a bag directory is written anew (as ros2 bag record "
                           f"does), or give a name ending in .mcap for one file")
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
            self._file = (self._tmp / self.file_name).open("xb")
        except OSError as err:
            if hasattr(self, "_tmp"):
                shutil.rmtree(self._tmp, ignore_errors=True)
            raise LogError(f"{self.path}: cannot write: {err.strerror or err}") from None
        self._writer = Writer(self._file, chunk_size=CHUNK_SIZE, compression=_COMPRESSION[compression],
                              index_types=_INDEXES)
        self._writer.start(profile="ros2", library=f"erni {__version__} ({LIBRARY_IDENTIFIER})")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._topics: dict[str, str] = {}  # topic -> its type, in the order of the channels
        self._counts: dict[str, int] = {}  # topic -> messages written
        self._span: tuple[int, int] | None = None  # the first and last log time (ns)
        header = {"erni_record": FORMAT, "via": via, "started": self.started}
        status = ros.make(_STATUS, level=OK, name="erni/record", message=via,
                          values=[ros.make(_KV, key="erni", value=json.dumps(header))])
        stamp_ns = ros.stamp_ns_of(self.started)
        self._put(HEADER_TOPIC, ros.make(DIAGNOSTICS, header=ros.header(stamp_ns, ""), status=[status]), stamp_ns)

    def _put(self, topic: str, msg: Any, stamp_ns: int) -> None:
        cid = self._channels.get(topic)
        if cid is None:
            typename = msg.__msgtype__
            schema = self._schemas.get(typename)
            if schema is None:
                schema = self._schemas[typename] = self._writer.register_schema(
                    typename, "ros2msg", ros.message_definition(typename).encode("utf-8"))
            cid = self._channels[topic] = self._writer.register_channel(topic, "cdr", schema, {
                "offered_qos_profiles": _yaml([offered_qos(topic)]), "topic_type_hash": ros.type_hash(typename)})
            self._topics[topic], self._counts[topic] = typename, 0
        self._writer.add_message(cid, stamp_ns, ros.serialize(msg), stamp_ns)
        self._counts[topic] += 1
        first, last = self._span or (stamp_ns, stamp_ns)
        self._span = (min(first, stamp_ns), max(last, stamp_ns))

    def write(self, agent: str, op: str, type_name: str, data: dict[str, Any], t: float | None = None) -> None:
        """Record one change at `t` seconds since the recording started (now when None)."""
        if t is None:
            t = self.clock() - self._start
        self.write_object(agent, op, type_name, data, _validated(type_name, data), t)

    def write_object(self, agent: str, op: str, type_name: str, data: dict[str, Any], obj: BBObject | None,
                     t: float) -> None:
        """Record one change whose `data` is `obj` (None: not a valid object of `type_name`)."""
        when = ros.stamp_ns_of(self.started + t)
        drawn = obj if op != "remove" else None  # a removed Pose or NetInfo draws nothing
        if isinstance(obj, Pose) and drawn is None:
            self._poses.pop(obj.robot, None)
        if isinstance(drawn, Pose):
            self._poses[drawn.robot] = drawn
            stamp = ros.stamp_ns_of(drawn.stamp)
            self._put(f"/{drawn.robot}/odom", ros.odometry(drawn, stamp, FRAME), when)
            self._put("/tf", ros.tf_message([drawn], stamp, FRAME), when)
        self._put(DIAGNOSTICS_TOPIC, diagnostics(agent, op, type_name, data, when / 1e9, obj), when)
        if isinstance(drawn, NetInfo):
            places = {name: (p.x, p.y) for name, p in self._poses.items()}
            places |= {name: (p.x, p.y) for name, p in drawn.positions.items()}
            self._put(MARKERS_TOPIC, ros.network_markers(drawn.links, places, ros.stamp_ns_of(drawn.stamp), FRAME,
                                                         drawn.articulation_points), when)
        self.count += 1

    def metadata(self) -> dict[str, Any]:
        """rosbag2's metadata of the bag (format 9): what `metadata.yaml` and the file's `rosbag2` record hold."""
        first, last = self._span or (0, 0)
        duration = last - first
        count = sum(self._counts.values())
        topics = [{"topic_metadata": {"name": topic, "type": typename, "serialization_format": "cdr",
                                      "offered_qos_profiles": [offered_qos(topic)],
                                      "type_description_hash": ros.type_hash(typename)},
                   "message_count": self._counts[topic]} for topic, typename in self._topics.items()]
        return {"version": 9, "storage_identifier": "mcap", "duration": {"nanoseconds": duration},
                "starting_time": {"nanoseconds_since_epoch": first}, "message_count": count,
                "topics_with_message_count": topics, "compression_format": "", "compression_mode": "",
                "relative_file_paths": [self.file_name],
                "files": [{"path": self.file_name, "starting_time": {"nanoseconds_since_epoch": first},
                           "duration": {"nanoseconds": duration}, "message_count": count}],
                "custom_data": {}, "ros_distro": ROS_DISTRO}

    def close(self) -> None:
        """Finish the bag and move it to the path asked for."""
        try:
            info = self.metadata()
            try:
                # the last chunk, so that rosbag2's record follows every message; then the summary (schemas,
                # channels, statistics, chunk and metadata indexes, offsets) and the footer. mcap's flush and
                # finish are not annotated
                self._writer.flush()  # type: ignore[no-untyped-call]
                self._writer.add_metadata("rosbag2", {"serialized_metadata": _yaml(info)})
                self._writer.finish()  # type: ignore[no-untyped-call]
            finally:
                self._file.close()
            if self.directory:
                (self._tmp / "metadata.yaml").write_text(_yaml({"rosbag2_bagfile_information": info}),
                                                         encoding="utf-8")
                os.rename(self._tmp, self.path)
            else:
                os.replace(self._tmp / self.file_name, self.path)
        except OSError as err:
            raise LogError(f"{self.path}: cannot write: {err.strerror or err}") from None
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)


def convert(log: str | Path, out: str | Path, compression: str = "none") -> tuple[int, list[str]]:
    """Write an ERNI JSON-lines log as an MCAP bag; return the number of events and the lines skipped."""
    header, events, problems = read_log(log)
    started = header.get("started")
    if isinstance(started, bool) or not isinstance(started, (int, float)) or not math.isfinite(started):
        started = None
    recorder = BagRecorder(out, str(header.get("via", "")), started, compression=compression)
    try:
        for event in events:
            recorder.write_object(event.agent, event.op, type(event.obj).__name__,
                                  event.obj.model_dump(mode="json"), event.obj, event.t)
    finally:
        recorder.close()
    return recorder.count, problems


def read_bag(path: str | Path, max_chunk: int = mcap_bounds.MAX_CHUNK,
             max_message: int = mcap_bounds.MAX_MESSAGE, robot: str | None = None
             ) -> tuple[dict[str, Any], list[Event], list[str]]:
    """Return a bag's header, its ERNI events and one problem line per message that could not be read.

    Poses come from ERNI's statuses on `/diagnostics` when the bag has them (every field), else from the
    Odometry on `/<robot>/odom` (position, heading, velocities and stamp), so bags from other tools replay
    too; a single robot's own bag (Odometry on `/odom`) replays as `robot`, and is refused without it.
    A bag beyond `max_chunk` or `max_message` (`mcap_bounds`) is refused whole (LogError).
    """
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if robot is not None and not is_name(robot):
        raise LogError(f"--robot {shown(robot)}: expected a robot's name of {NAME_CHARS}")
    if not path.exists():
        raise LogError(f"{path}: no such file")
    if path.is_dir() and not (path / "metadata.yaml").exists():
        raise LogError(f"{path}: a directory without metadata.yaml; expected an MCAP file or a rosbag2 directory")
    link_dir: str | None = None
    if path.is_file():
        try:
            with path.open("rb") as f:
                magic = f.read(len(MCAP_MAGIC))
        except OSError as err:
            raise LogError(f"{path}: cannot read: {err.strerror or err}") from None
        if magic != MCAP_MAGIC:
            raise LogError(f"{path}: not an MCAP file (it does not start with MCAP's magic bytes)")
        if path.suffix != ".mcap":  # rosbags picks its reader by the name
            link_dir = tempfile.mkdtemp(prefix="erni-bag-")
            os.symlink(path.resolve(), Path(link_dir) / "bag.mcap")
    try:
        for one in sorted(path.glob("*.mcap")) if path.is_dir() else [path]:
            mcap_bounds.check(one, max_chunk, max_message)
        with Reader(Path(link_dir) / "bag.mcap" if link_dir else path) as reader:
            return _events(path, reader, robot)
    except mcap_bounds.BagBoundError as err:
        raise LogError(str(err)) from None
    except LogError:
        raise
    except Exception as err:  # rosbags raises its own errors, struct and index errors on damaged files
        raise LogError(f"{path}: cannot read the bag: {str(err).splitlines()[0] if str(err) else type(err).__name__}"
                       ) from None
    finally:
        if link_dir:
            shutil.rmtree(link_dir, ignore_errors=True)


def _events(path: Path, reader: Any, robot: str | None) -> tuple[dict[str, Any], list[Event], list[str]]:
    topics = {c.topic: c.msgtype for c in reader.connections}
    problems: list[str] = []
    connections = _erni_connections(path, reader.connections, HEADER_TOPIC in topics, problems, robot)

    def nothing() -> LogError:
        found = ", ".join(f"{printable(t)} ({printable(m)})" for t, m in sorted(topics.items())) or "no topics"
        return LogError(f"{path}: no ERNI topics (expected ERNI's statuses on {DIAGNOSTICS_TOPIC}, {ODOMETRY} on "
                        f"/<robot>/odom or {TASK_STATUS_TOPIC}); it has {found}")

    if not connections:
        raise nothing()
    header: dict[str, Any] = {}
    raw: list[tuple[int, str, str, BBObject]] = []
    for conn, stamp, data in reader.messages(connections=connections):
        try:
            _message(conn, stamp, data, raw, header, robot)
        except (ErniError, ValueError, KeyError, TypeError, AttributeError, RecursionError) as err:
            problems.append(f"{path}: {conn.topic} at {stamp / 1e9:.3f}: {problem_of(err)}")
    if not raw and not header and not problems:
        raise nothing()
    start = _start(reader.start_time, header, raw)
    header.setdefault("erni_record", FORMAT)
    header.setdefault("via", str(path))
    events = [Event(max(0.0, (s - start) / 1e9), agent, op, obj) for s, agent, op, obj in raw]
    events.sort(key=lambda e: e.t)
    return header, events, problems


def _erni_connections(path: Path, connections: list[Any], erni_bag: bool, problems: list[str],
                      robot: str | None = None) -> list[Any]:
    """The connections whose messages are ERNI's: its statuses, and (in a bag not written by ERNI, whose
    poses are in its statuses with every field) the robots' odometry and the live plugin's task status.
    An odometry topic that names no robot is skipped, and named in `problems`; a single robot's `/odom`
    is `robot`'s (LogError without it when the bag has nothing else to replay)."""
    odom = [c for c in connections if c.msgtype == ODOMETRY and c.topic.endswith("/odom")
            and c.topic.count("/") == 2 and not erni_bag]
    single = [c for c in connections if c.msgtype == ODOMETRY and c.topic == SINGLE_ODOM and not erni_bag]
    for conn in [c for c in odom if not is_name(c.topic.split("/")[1])]:  # /r\x1b[2J/odom names no robot
        odom.remove(conn)
        problems.append(f"{path}: topic {shown(conn.topic)}: skipped; a robot's topic is /<robot>/odom with the "
                        f"robot's name of {NAME_CHARS}")
    diag = [c for c in connections if c.msgtype == DIAGNOSTICS]
    status = [c for c in connections if c.topic == TASK_STATUS_TOPIC and c.msgtype == ros.STRING
              and not erni_bag]
    if single and robot is None:
        if not odom and not status:
            raise LogError(f"{path}: {SINGLE_ODOM} names no robot (one robot's own bag); give --robot NAME to "
                           f"replay it as robot NAME")
        problems.append(f"{path}: topic {SINGLE_ODOM}: skipped; it names no robot (give --robot NAME)")
        single = []
    return odom + single + diag + status


def _message(conn: Any, stamp: int, data: bytes, raw: list[tuple[int, str, str, BBObject]],
             header: dict[str, Any], robot: str | None = None) -> None:
    """Decode one message into `raw`'s events, or into `header` when it is the recording's header
    (`robot`: whose a single robot's `/odom` is)."""
    msg = ros.deserialize(data, conn.msgtype)
    if conn.msgtype == ODOMETRY:
        name = robot if conn.topic == SINGLE_ODOM and robot else conn.topic.split("/")[1]
        raw.append((stamp, name, "change", pose_from_odometry(name, msg)))
        return
    if conn.topic == TASK_STATUS_TOPIC:
        raw.append((stamp, "", "change", task_from_status(msg.data)))
        return
    for one in msg.status:
        event = next((json.loads(kv.value) for kv in one.values if kv.key == "erni"), None)
        if event is None:
            continue
        if conn.topic == HEADER_TOPIC:
            header.clear()
            header.update(event if isinstance(event, dict) else {})
            continue
        raw.append(_event(stamp, event))


def _start(bag_start: int, header: dict[str, Any], raw: list[tuple[int, str, str, BBObject]]) -> int:
    """When the recording started (ns): the header's statement when it is a finite number and earlier than
    the first event, else the first event's stamp (the bag's start without events); the header says so."""
    start = bag_start if not raw else min(s for s, *_ in raw)
    started = header.get("started")
    if isinstance(started, (int, float)) and not isinstance(started, bool) and math.isfinite(started):
        return min(start, int(started * 1e9))
    header["started"] = start / 1e9
    return start


def task_from_status(text: str) -> Task:
    """The Task a `/erni/task_status` String of the live plugin describes (`messages.task_status`)."""
    body = json.loads(text)
    if not isinstance(body, dict):
        raise LogError(f"expected a JSON object, got {type(body).__name__}")
    result = AllocationResult(state=body.get("state", "pending"), progress=body.get("progress", 0.0),
                              message=body.get("message", ""), values=body.get("values") or {},
                              stamp=body.get("stamp", 0.0))
    return Task(uid=body["uid"], verb=body["verb"], preposition=body["preposition"], params=body.get("params") or {},
                source=body.get("source") or "", destination=body.get("destination"), result=result,
                created=result.stamp)  # the status does not say when the task was made


def _event(stamp: int, event: Any) -> tuple[int, str, str, BBObject]:
    if not isinstance(event, dict):
        raise LogError(f"expected a JSON object under 'erni', got {type(event).__name__}")
    kind = event.get("type")
    cls = TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None or not issubclass(cls, BBObject):
        raise LogError(f"unknown object type {str(kind)[:60]!r}")
    if event.get("op") not in ("add", "change", "remove"):
        raise LogError(f"unknown op {str(event.get('op'))[:60]!r}")
    agent = event.get("agent", "")
    if agent != "" and not is_name(agent):
        raise LogError(f"agent {shown(agent)}: expected a name of {NAME_CHARS}")
    return stamp, agent, str(event["op"]), cls.model_validate(event.get("data"))
