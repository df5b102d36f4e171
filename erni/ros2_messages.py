"""ERNI's objects as ROS 2 (Jazzy) messages, and ROS 2 commands as ERNI task parameters.

The message classes, their CDR serialisation and their RIHS01 type hashes are `rosbags`' (its
built-in Jazzy definitions: no ROS 2 install). Every function here is pure: an ERNI object and a
time in, a `rosbags` message object out (or the reverse for commands), so that the live plugin,
bag writers and viewers share one conversion.

Conventions (REP 103/105): metres, radians, counter-clockwise headings; a robot's frame is
`<robot>/base_link`; poses are given in one world frame for the whole team (`map` unless told).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from decimal import Decimal
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from erni.blackboard.errors import TaskError, UsageError
from erni.blackboard.tasks import Link, NetInfo, Pose, Task

#: the Jazzy type store every conversion uses (message classes, CDR, type hashes)
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

#: a `rosbags` message object (a dataclass made by the type store: typed only at run time)
Message = Any

ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
LASER_SCAN = "sensor_msgs/msg/LaserScan"
TWIST = "geometry_msgs/msg/Twist"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
GOAL_STATUS_ARRAY = "action_msgs/msg/GoalStatusArray"
TRIGGER = "std_srvs/srv/Trigger"
CANCEL_GOAL = "action_msgs/srv/CancelGoal"
NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
SEND_GOAL = f"{NAVIGATE_TO_POSE}_SendGoal"
GET_RESULT = f"{NAVIGATE_TO_POSE}_GetResult"
FEEDBACK_MESSAGE = f"{NAVIGATE_TO_POSE}_FeedbackMessage"

# rosbags' Jazzy store has messages only: the services and the action ERNI serves are defined here from
# their interface files (std_srvs/srv/Trigger.srv, action_msgs/srv/CancelGoal.srv, and Nav2 Jazzy's
# nav2_msgs/action/NavigateToPose.action), constants left out (they are not on the wire nor in the hash)
SERVICES = {
    TRIGGER: ("", "bool success\nstring message\n"),
    CANCEL_GOAL: ("action_msgs/GoalInfo goal_info\n", "int8 return_code\naction_msgs/GoalInfo[] goals_canceling\n"),
}
ACTIONS = {
    NAVIGATE_TO_POSE: ("geometry_msgs/PoseStamped pose\nstring behavior_tree\n",
                       "uint16 error_code\nstring error_msg\n",
                       "geometry_msgs/PoseStamped current_pose\nbuiltin_interfaces/Duration navigation_time\n"
                       "builtin_interfaces/Duration estimated_time_remaining\nint16 number_of_recoveries\n"
                       "float32 distance_remaining\n"),
}

_NUMPY = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
          "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64,
          "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


def _default(node: tuple[Any, Any]) -> Any:
    kind, detail = node
    if kind == Nodetype.BASE:
        base = detail[0]
        if base == "string":
            return ""
        if base == "bool":
            return False
        return 0.0 if base.startswith("float") else 0
    if kind == Nodetype.NAME:
        return make(detail)
    inner, count = detail
    if inner[0] == Nodetype.BASE and inner[1][0] in _NUMPY:
        return np.zeros(count if kind == Nodetype.ARRAY else 0, dtype=_NUMPY[inner[1][0]])
    if kind == Nodetype.ARRAY:
        return [_default(inner) for _ in range(count)]
    return []


def _interface_types(typename: str, text: str) -> dict[str, Any]:
    """Field definitions of a service's or an action's part from its text, named as ROS 2 names it
    ('std_srvs/srv/Trigger_Request': rosbags would file it under 'std_srvs/srv/msg/...')."""
    def fix(name: str) -> str:
        return name.replace("/srv/msg/", "/srv/").replace("/action/msg/", "/action/")

    def fix_node(node: Any) -> Any:
        kind, detail = node
        if kind == Nodetype.NAME:
            return kind, fix(detail)
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            return kind, (fix_node(detail[0]), detail[1])
        return node

    return {fix(name): (consts, [(field, fix_node(node)) for field, node in fields])
            for name, (consts, fields) in get_types_from_msg(text, typename).items()}


def _service_types(service: str, request: str, response: str) -> dict[str, Any]:
    """A service's request, response and event types, and the service itself as the type whose RIHS01
    hash rmw_zenoh writes (REP 2011: request_message, response_message, event_message)."""
    types = {**_interface_types(f"{service}_Request", request), **_interface_types(f"{service}_Response", response)}
    types.update(_interface_types(f"{service}_Event", f"service_msgs/ServiceEventInfo info\n"
                                  f"{service}_Request[<=1] request\n{service}_Response[<=1] response\n"))
    types.update(_interface_types(service, f"{service}_Request request_message\n{service}_Response response_message\n"
                                  f"{service}_Event event_message\n"))
    return types


def _register_interfaces() -> None:
    types: dict[str, Any] = {}
    for service, (request, response) in SERVICES.items():
        types.update(_service_types(service, request, response))
    for action, (goal, result, feedback) in ACTIONS.items():
        types.update(_interface_types(f"{action}_Goal", goal))
        types.update(_interface_types(f"{action}_Result", result))
        types.update(_interface_types(f"{action}_Feedback", feedback))
        types.update(_service_types(f"{action}_SendGoal", f"unique_identifier_msgs/UUID goal_id\n{action}_Goal goal\n",
                                    "bool accepted\nbuiltin_interfaces/Time stamp\n"))
        types.update(_service_types(f"{action}_GetResult", "unique_identifier_msgs/UUID goal_id\n",
                                    f"int8 status\n{action}_Result result\n"))
        types.update(_interface_types(f"{action}_FeedbackMessage",
                                      f"unique_identifier_msgs/UUID goal_id\n{action}_Feedback feedback\n"))
    for store in (TYPESTORE, _HASHING):
        store.register({k: v for k, v in types.items() if k not in store.types})


def _char_as_uint8(node: Any) -> Any:
    kind, detail = node
    if kind == Nodetype.BASE and detail[0] == "char":
        return kind, ("uint8", detail[1])
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return kind, (_char_as_uint8(detail[0]), detail[1])
    return node


#: the store type hashes are computed from: rosidl reads a .msg's `char` as `uint8` before hashing
#: (service_msgs/ServiceEventInfo's `char[16] client_gid`, in every service's hash)
_HASHING = get_typestore(Stores.ROS2_JAZZY)
for _name, (_consts, _fields) in list(_HASHING.fielddefs.items()):
    _HASHING.fielddefs[_name] = (_consts, [(field, _char_as_uint8(node)) for field, node in _fields])
_register_interfaces()


def make(typename: str, **fields: Any) -> Message:
    """A message of `typename` ('nav_msgs/msg/Odometry') with `fields` set and every other field at
    its ROS default (zero, empty, nested defaults). KeyError for a type Jazzy does not have, UsageError
    for a field the type does not have."""
    cls = TYPESTORE.types[typename]
    _, defs = TYPESTORE.fielddefs[typename]
    values = {name: fields[name] if name in fields else _default(node) for name, node in defs}
    unknown = set(fields) - set(values)
    if unknown:
        raise UsageError(f"{typename} has no field {', '.join(sorted(unknown))}")
    return cls(**values)


def serialize(msg: Message) -> bytes:
    """The message as rmw_zenoh and rosbag2 carry it: CDR, little-endian, with its 4-byte header."""
    return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


def deserialize(data: bytes, typename: str) -> Message:
    """The message of `typename` in CDR `data` (as `serialize` writes it); UsageError (a ValueError) for
    bytes that are not one."""
    try:
        return TYPESTORE.deserialize_cdr(data, typename)
    except SerdeError as err:
        raise UsageError(f"not a {typename}: {str(err).split(': ')[-1]}") from None


def type_hash(typename: str) -> str:
    """The type's RIHS01 hash as rmw_zenoh writes it in key expressions ('RIHS01_<64 hex>')."""
    return _HASHING.hash_rihs01(typename)


def dds_type_name(typename: str) -> str:
    """'nav_msgs/msg/Odometry' as the DDS-style name rmw_zenoh uses: 'nav_msgs::msg::dds_::Odometry_'."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def message_definition(typename: str) -> str:
    """The type's definition in ROS 2 `.msg` text with its dependencies (the form rosbag2 stores)."""
    text, _ = TYPESTORE.generate_msgdef(typename, ros_version=2)
    return text


# --- times and frames ---------------------------------------------------------------------


def stamp(stamp_ns: int) -> Message:
    """builtin_interfaces/Time of a time in nanoseconds since the epoch."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def stamp_ns_of(seconds: float) -> int:
    """An ERNI time (float seconds) in nanoseconds: the shortest decimal that is this float, so a
    time written 1750000001.1 is ...1_100_000_000 ns, and any other within the float's own
    resolution (`seconds * 1e9` of a time today is a float 256 ns apart)."""
    return int((Decimal(repr(seconds)) * 1_000_000_000).to_integral_value())


def header(stamp_ns: int, frame: str) -> Message:
    """std_msgs/Header."""
    return make("std_msgs/msg/Header", stamp=stamp(stamp_ns), frame_id=frame)


def base_frame(robot: str) -> str:
    """A robot's body frame: '<robot>/base_link'."""
    return f"{robot}/base_link"


def quaternion(theta: float) -> Message:
    """geometry_msgs/Quaternion of a heading about +z (rad)."""
    return make("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2))


def yaw(q: Message) -> float:
    """The heading about +z (rad) of a geometry_msgs/Quaternion."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def duration(seconds: float) -> Message:
    """builtin_interfaces/Duration of a time span (s)."""
    sec, nanosec = divmod(round(seconds * 1e9), 1_000_000_000)
    return make("builtin_interfaces/msg/Duration", sec=sec, nanosec=nanosec)


def uuid(data: bytes) -> Message:
    """unique_identifier_msgs/UUID of 16 bytes (an action goal's id)."""
    return make("unique_identifier_msgs/msg/UUID", uuid=np.frombuffer(bytes(data), dtype=np.uint8).copy())


def ros_pose(x: float, y: float, theta: float) -> Message:
    """geometry_msgs/Pose at (x, y) heading theta (rad)."""
    return _ros_pose(x, y, theta)


def _ros_pose(x: float, y: float, theta: float) -> Message:
    return make("geometry_msgs/msg/Pose", position=make("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
                orientation=quaternion(theta))


# --- ERNI -> ROS 2 ------------------------------------------------------------------------


def odometry(pose: Pose, stamp_ns: int, frame: str = "map") -> Message:
    """nav_msgs/Odometry of a robot's Pose: position and heading in `frame`, velocity (v m/s, w rad/s)
    in the robot's frame `<robot>/base_link`; covariances zero (unknown)."""
    twist = make("geometry_msgs/msg/Twist", linear=make("geometry_msgs/msg/Vector3", x=pose.v),
                 angular=make("geometry_msgs/msg/Vector3", z=pose.w))
    return make(ODOMETRY, header=header(stamp_ns, frame), child_frame_id=base_frame(pose.robot),
                pose=make("geometry_msgs/msg/PoseWithCovariance", pose=_ros_pose(pose.x, pose.y, pose.theta)),
                twist=make("geometry_msgs/msg/TwistWithCovariance", twist=twist))


def transform(pose: Pose, stamp_ns: int, frame: str = "map") -> Message:
    """geometry_msgs/TransformStamped from `frame` to the robot's `<robot>/base_link`."""
    tf = make("geometry_msgs/msg/Transform",
              translation=make("geometry_msgs/msg/Vector3", x=pose.x, y=pose.y, z=0.0),
              rotation=quaternion(pose.theta))
    return make("geometry_msgs/msg/TransformStamped", header=header(stamp_ns, frame),
                child_frame_id=base_frame(pose.robot), transform=tf)


def tf_message(poses: Iterable[Pose], stamp_ns: int, frame: str = "map") -> Message:
    """tf2_msgs/TFMessage with one transform per robot (for /tf)."""
    return make(TF_MESSAGE, transforms=[transform(p, stamp_ns, frame) for p in poses])


def task_status(task: Task) -> Message:
    """std_msgs/String holding a JSON object of a task and its result: uid, verb, preposition, params,
    source, destination, state, progress, message, values, stamp (s)."""
    result = task.result
    body = {
        "uid": task.uid, "verb": task.verb, "preposition": task.preposition,
        "params": task.params.model_dump(mode="json", exclude_none=True),
        "source": task.source, "destination": task.destination, "state": task.state.value,
        "progress": result.progress if result else 0.0, "message": result.message if result else "",
        "values": result.values if result else {}, "stamp": result.stamp if result else task.created,
    }
    return make(STRING, data=json.dumps(body, sort_keys=True))


def sonar_scan(pose: Pose, angles_deg: Sequence[float], stamp_ns: int, max_range: float = 5.0) -> Message:
    """sensor_msgs/LaserScan of a robot's sonar ranges in its `<robot>/base_link` frame.

    `angles_deg` are the sonars' directions (deg, counter-clockwise from ahead), one per range, evenly
    spaced (a Pioneer's front ring); a range beyond `max_range` is reported as +inf (nothing seen)."""
    ranges = list(pose.sonar)[:len(angles_deg)]
    n = len(ranges)
    first = math.radians(angles_deg[0]) if n else 0.0
    step = (math.radians(angles_deg[n - 1]) - first) / (n - 1) if n > 1 else 0.0
    values = np.array([r if 0.0 < r <= max_range else math.inf for r in ranges], dtype=np.float32)
    return make(LASER_SCAN, header=header(stamp_ns, base_frame(pose.robot)), angle_min=first,
                angle_max=first + step * max(n - 1, 0), angle_increment=step, range_min=0.0,
                range_max=max_range, ranges=values)


def sonar_echo_scan(pose: Pose, transducers: Sequence[tuple[float, float, float] | None], stamp_ns: int,
                    max_range: float = 5.0, beams: int = 360) -> Message:
    """sensor_msgs/LaserScan of a robot's sonar echoes in its `<robot>/base_link` frame, for transducers
    anywhere on the body: `beams` beams round the centre (from -180 deg), each echo (range i of
    `pose.sonar` from transducer i at (x, y, bearing deg)) in the beam of its direction from the
    centre, at its distance from the centre. A beam with no transducer is NaN (no measurement); a
    range at or beyond `max_range` is +inf (nothing seen), as REP 117 has it."""
    step = 2 * math.pi / beams
    values = np.full(beams, np.nan, dtype=np.float32)
    for reading, where in zip(pose.sonar, transducers):
        if where is None:
            continue
        sx, sy, deg = where
        a = math.radians(deg)
        echo = min(reading, max_range)
        px, py = sx + echo * math.cos(a), sy + echo * math.sin(a)
        beam = round((math.atan2(py, px) + math.pi) / step) % beams
        value = math.inf if reading >= max_range else math.hypot(px, py)
        if not (value >= values[beam]):  # the nearest echo of a beam (NaN: none yet)
            values[beam] = value
    return make(LASER_SCAN, header=header(stamp_ns, base_frame(pose.robot)), angle_min=-math.pi,
                angle_max=-math.pi + step * (beams - 1), angle_increment=step, range_min=0.0,
                range_max=max_range + 0.5, ranges=values)


def _color(r: float, g: float, b: float, a: float = 1.0) -> Message:
    return make("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a)


def _quality_color(quality: float) -> Message:
    q = min(max(quality, 0.0), 1.0)
    return _color(1.0 - q, q, 0.0)


def network_markers(links: Sequence[Link], positions: Mapping[str, tuple[float, float]], stamp_ns: int,
                    frame: str = "map", articulation_points: Iterable[str] = ()) -> Message:
    """visualization_msgs/MarkerArray of the network: namespace `erni_nodes` a sphere per node (red for an
    articulation point, blue otherwise) with its name above it (`erni_names`), and `erni_links` one
    LINE_LIST of the links between placed nodes, each coloured from red (quality 0) to green (1).
    The first marker is a DELETEALL so that nodes and links gone since the last array disappear."""
    cut = set(articulation_points)
    head = header(stamp_ns, frame)
    point = "geometry_msgs/msg/Point"
    markers = [make("visualization_msgs/msg/Marker", header=head, ns="erni", id=0, action=3)]
    for i, (name, (x, y)) in enumerate(sorted(positions.items())):
        markers.append(make("visualization_msgs/msg/Marker", header=head, ns="erni_nodes", id=i, type=2, action=0,
                            pose=_ros_pose(x, y, 0.0), scale=make("geometry_msgs/msg/Vector3", x=0.3, y=0.3, z=0.3),
                            color=_color(0.9, 0.1, 0.1) if name in cut else _color(0.1, 0.3, 0.9)))
        markers.append(make("visualization_msgs/msg/Marker", header=head, ns="erni_names", id=i, type=9, action=0,
                            pose=_ros_pose(x, y + 0.4, 0.0), scale=make("geometry_msgs/msg/Vector3", z=0.25),
                            color=_color(1.0, 1.0, 1.0), text=name))
    points, colors = [], []
    for link in links:
        if link.a in positions and link.b in positions:
            for end in (link.a, link.b):
                x, y = positions[end]
                points.append(make(point, x=x, y=y, z=0.0))
                colors.append(_quality_color(link.quality))
    markers.append(make("visualization_msgs/msg/Marker", header=head, ns="erni_links", id=0, type=5, action=0,
                        pose=_ros_pose(0.0, 0.0, 0.0), scale=make("geometry_msgs/msg/Vector3", x=0.05),
                        color=_color(0.0, 1.0, 0.0), points=points, colors=colors))
    return make(MARKER_ARRAY, markers=markers)


def diagnostics(info: NetInfo, stamp_ns: int) -> Message:
    """diagnostic_msgs/DiagnosticArray of a NetInfo: one status per neighbour (OK, WARN below quality 0.5,
    ERROR when not symmetric) and one for the node itself (WARN when degraded), named `erni/<node>/...`."""
    status = "diagnostic_msgs/msg/DiagnosticStatus"
    kv = "diagnostic_msgs/msg/KeyValue"
    own = make(status, level=1 if info.degraded else 0, name=f"erni/{info.node}/network", hardware_id=info.node,
               message=info.message or info.kind,
               values=[make(kv, key="neighbors", value=str(len(info.neighbors))),
                       make(kv, key="links", value=str(len(info.links))),
                       make(kv, key="articulation_points", value=",".join(info.articulation_points))])
    statuses = [own]
    for n in info.neighbors:
        level = 2 if not n.symmetric else (1 if n.quality < 0.5 else 0)
        statuses.append(make(status, level=level, name=f"erni/{info.node}/neighbor/{n.name}", hardware_id=n.name,
                             message=f"quality {n.quality:.2f}",
                             values=[make(kv, key="quality", value=f"{n.quality:.3f}"),
                                     make(kv, key="address", value=n.address),
                                     make(kv, key="symmetric", value=str(n.symmetric).lower())]))
    return make(DIAGNOSTIC_ARRAY, header=header(stamp_ns, ""), status=statuses)


# --- ROS 2 -> ERNI task parameters --------------------------------------------------------


def velocity_params(twist: Message) -> dict[str, float]:
    """BotMotion velocity parameters of a geometry_msgs/Twist: v (m/s) from linear.x, w (deg/s) from
    angular.z (rad/s), each clipped to the task language's range (|v| <= 2 m/s, |w| <= 360 deg/s);
    TaskError (a ValueError) if not finite."""
    v, w = float(twist.linear.x), math.degrees(float(twist.angular.z))
    if not (math.isfinite(v) and math.isfinite(w)):
        raise TaskError(f"cmd_vel: velocity ({v}, {w}) is not finite")
    return {"v": min(max(v, -2.0), 2.0), "w": min(max(w, -360.0), 360.0)}


def goto_params(pose_stamped: Message) -> dict[str, float]:
    """BotMotion goto parameters (x, y in m) of a geometry_msgs/PoseStamped; TaskError (a ValueError) if not finite."""
    x, y = float(pose_stamped.pose.position.x), float(pose_stamped.pose.position.y)
    if not (math.isfinite(x) and math.isfinite(y)):
        raise TaskError(f"goal_pose: position ({x}, {y}) is not finite")
    return {"x": x, "y": y}


def goal_heading(pose_stamped: Message) -> float | None:
    """The heading (rad) a geometry_msgs/PoseStamped asks for, or None when its orientation is no rotation at
    all (a zero quaternion: unset) or not finite."""
    q = pose_stamped.pose.orientation
    parts = [float(q.x), float(q.y), float(q.z), float(q.w)]
    if not all(math.isfinite(v) for v in parts) or sum(v * v for v in parts) < 1e-12:
        return None
    return yaw(q)
