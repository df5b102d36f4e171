"""The `ros2` plugin: the team as ROS 2 topics over rmw_zenoh, and ROS 2 commands as ERNI tasks.

Serves std_srvs/Trigger on `/<robot>/stop` and `/erni/stop` (a BotMotion stop, answered once the robot
halted) and Nav2's NavigateToPose action on `/<robot>/navigate_to_pose` (a goto, then a turn).
Publishes each robot's Pose as nav_msgs/Odometry on `/<robot>/odom`, as transforms on `/tf` (REP 105's
map → odom → base_link, or a flat map → base_link) and its
sonar echoes as a sensor_msgs/LaserScan on `/<robot>/sonar`, task
results as std_msgs/String (JSON) on `/erni/task_status`, the network as a MarkerArray on
`/erni/network` and a DiagnosticArray on `/diagnostics`; listens to geometry_msgs/Twist on `/<robot>/cmd_vel` (a BotMotion velocity task, so the
behaviour stack, stop, obstacle avoidance and the receiving agent's role policy decide, as for any
task) and geometry_msgs/PoseStamped on `/<robot>/goal_pose` (a BotMotion goto, then a turn to the pose's
heading). See docs/tutorials/ros2-foxglove.md.
"""

from __future__ import annotations

import json
import math
import queue
import threading
from dataclasses import dataclass, field
from typing import Any, Literal

import zenoh
from pydantic import ConfigDict, Field, field_validator, model_validator

from erni import ros2_messages as messages
from erni.blackboard.errors import NetworkError
from erni.blackboard.objects import BBObject, Model
from erni.blackboard.plugin import Plugin
from erni.blackboard.tasks import NetInfo, Pose, Task, TaskState
from erni.plugins.ros2.navigate import CANCELED, Navigator
from erni.ros2_rmw import DEFAULT_QOS, QoS, Request, RmwNode
from erni.transport.zenoh_keys import check_endpoints

NAME_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_"
RECONNECT = 2.0  # s between attempts to open a session of its own whose router is not reachable


class ROS2Settings(Model):
    """`[plugin.settings]` of the ros2 plugin."""

    model_config = ConfigDict(extra="forbid")

    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the ROS 2 side (0-232)")
    session: Literal["auto", "own"] = Field("auto", description="auto: the transport's Zenoh session when it runs "
                                            "wire = \"zenoh\", else one of its own; own: always its own")
    mode: Literal["peer", "client"] = Field("peer", description="its own session's Zenoh mode")
    connect: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"],
                               description="its own session: routers to connect to (rmw_zenoh's zenohd)")
    listen: list[str] = Field(default_factory=list, description="its own session (peer mode): endpoints to listen on")
    robots: list[str] | None = Field(None, description="whose topics (agent names; in topics, characters other than "
                                     "letters, digits and '_' become '_'); default: every robot whose Pose the "
                                     "agent has on a control node, the agent itself elsewhere")
    node_name: str | None = Field(None, description="the ROS 2 node's name (default erni_<agent>)")
    frame: str = Field("map", min_length=1, description="the world frame: the root of /tf, and the frame of "
                       "markers and of a goal's feedback")
    frames: Literal["rep105", "flat"] = Field("rep105", description="rep105: /tf is frame → <robot>/odom → "
                                              "<robot>/base_link, odometry in <robot>/odom (REP 105; frame → "
                                              "<robot>/odom is the identity, published with each pose); flat: "
                                              "frame → <robot>/base_link, odometry in frame")
    odom_rate_hz: float = Field(10.0, gt=0, le=100, description="at most this many Odometry messages a second per "
                                "robot on average (two may come in a row); a robot whose Pose comes no faster "
                                "has each sent at once")
    tf: bool = Field(True, description="publish each robot's transform on /tf")
    sonar: bool = Field(True, description="publish each robot's sonar echoes as a LaserScan on /<robot>/sonar")
    status: bool = Field(True, description="publish task results on /erni/task_status")
    network: bool = Field(True, description="publish the network as a MarkerArray on /erni/network and "
                          "its links as a DiagnosticArray on /diagnostics")
    cmd_vel: bool = Field(True, description="take geometry_msgs/Twist on /<robot>/cmd_vel")
    goal_pose: bool = Field(True, description="take geometry_msgs/PoseStamped on /<robot>/goal_pose")
    cmd_vel_timeout: float = Field(0.5, gt=0, le=10, description="no cmd_vel for this long (s) ends the motion")
    cmd_vel_rate_hz: float = Field(5.0, gt=0, le=50, description="at most this many new velocity tasks a second "
                                   "per robot (a changed command waits for the next slot)")
    goal_speed: float = Field(0.3, gt=0, le=2.0, description="cruise speed of a goal_pose's goto (m/s)")
    goal_tolerance: float = Field(0.1, gt=0, description="arrival radius of a goal_pose's goto (m)")
    goal_heading: bool = Field(True, description="after a goal_pose's goto, turn to the pose's heading")
    heading_tolerance: float = Field(2.0, gt=0, le=45, description="a goal's heading needs no turn within this "
                                     "(deg); the turn's accepted error")
    stop_service: bool = Field(True, description="serve std_srvs/Trigger on /<robot>/stop and /erni/stop")
    stop_timeout: float = Field(5.0, gt=0, le=60, description="a stop's answer is a failure when the robot has not "
                                "halted within this (s)")
    navigate_to_pose: bool = Field(True, description="serve Nav2's nav2_msgs/action/NavigateToPose on "
                                   "/<robot>/navigate_to_pose")

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, values: list[str]) -> list[str]:
        return check_endpoints(values)

    @field_validator("robots")
    @classmethod
    def _robots(cls, values: list[str] | None) -> list[str] | None:
        for value in values or []:
            if not value.strip():
                raise ValueError("robots: an empty name; expected agent names (robot1)")
        return values

    @field_validator("node_name")
    @classmethod
    def _node_name(cls, value: str | None) -> str | None:
        if value is not None and (not value or any(c not in NAME_CHARS for c in value) or value[0].isdigit()):
            raise ValueError(f"node_name {value[:80]!r}: letters, digits and '_', not starting with a digit")
        return value

    @model_validator(mode="after")
    def _check(self) -> ROS2Settings:
        if self.mode == "client" and not self.connect:
            raise ValueError("mode = \"client\" needs connect = [\"tcp/ROUTER:7447\"]")
        return self


def ros_name(name: str) -> str:
    """An ERNI agent name as a ROS 2 name chunk: other characters than letters, digits and '_' become '_'."""
    out = "".join(c if c in NAME_CHARS else "_" for c in name)
    return out if out and not out[0].isdigit() else f"r{out}"


class RateBudget:
    """At most `rate` events a second per key on average, without delaying a source that keeps to it.

    A token bucket of 2 tokens filled at `rate`: a source at `rate` with jitter almost always finds a
    token, and any window of T s lets at most rate * T + 2 through. An event that finds none is held,
    not sent the moment a token comes: a newer event that finds a token goes at once in its place, and
    the held one goes only when none came within one and a half periods after its token (so a source's
    last event is never lost, and an on-time successor with jitter comes first). Sending each held
    event at its token instead would spend the token of the next on-time event and keep every later
    one late by that lag for as long as the source keeps to the rate (a source at `rate` loads the
    bucket fully). Pure: time is passed in."""

    BURST = 2.0

    def __init__(self, rate: float) -> None:
        self.rate, self.grace = rate, 1.5 / rate
        self._tokens: dict[str, tuple[float, float]] = {}  # key -> (tokens, when counted)
        self._held: dict[str, float] = {}  # key -> when its held event goes, newer or not

    def offer(self, key: str, now: float, fresh: bool) -> float:
        """An event of `key` waiting at `now` (`fresh`: it has just come): 0 when it goes now (and is
        counted), else the seconds after which to offer it (or a newer one) again."""
        tokens, then = self._tokens.get(key, (self.BURST, now))
        tokens = min(self.BURST, tokens + max(0.0, now - then) * self.rate)
        held = self._held.get(key)
        if tokens >= 1.0 and (fresh or held is None or now >= held):
            self._tokens[key] = (tokens - 1.0, now)
            self._held.pop(key, None)
            return 0.0
        self._tokens[key] = (tokens, now)
        short = max(0.0, (1.0 - tokens) / self.rate)
        if held is None:
            held = self._held[key] = now + short + self.grace
        return max(held - now, short, 1e-3)


@dataclass
class _Drive:
    """What the plugin knows of one robot's cmd_vel stream."""

    params: dict[str, float] | None = None  # the newest command
    heard: float = -math.inf  # when it came
    previous: float = -math.inf  # when the one before it came
    task: Task | None = None  # the velocity task that carries the stream, while it runs
    started: float = -math.inf  # when that task was posted
    latched: bool = False  # ended by someone else: take no command until the stream pauses
    goal: Task | None = None  # the goto of the newest goal_pose
    heading: float | None = None  # the heading (rad) to turn to once that goto succeeds
    turn: Task | None = None  # that turn
    goals: list[tuple[dict[str, float], float | None, bytes | None]] = field(default_factory=list)
    action: bytes | None = None  # the NavigateToPose goal that goal is, if it is one


@dataclass
class _Stop:
    """A call of a stop service: the stop task posted for each robot, answered once all halted (or not)."""

    request: Request
    uids: dict[str, str]
    deadline: float
    run: int


class ROS2Plugin(Plugin[ROS2Settings]):
    """The team in ROS 2 (rmw_zenoh, Jazzy): odometry, /tf, task status and network out; cmd_vel, goal_pose in."""

    def setup(self) -> None:
        s = self.settings
        self.poses = self.subscribe(Pose)
        self.tasks = self.subscribe(Task, where=lambda t: t.verb == "BotMotion")
        self.nets = self.subscribe(NetInfo)
        self.node: RmwNode | None = None
        self._own: zenoh.Session | None = None
        self._outbox: queue.Queue[tuple[str, str, bytes, int] | None] = queue.Queue(maxsize=1000)
        self._drives: dict[str, _Drive] = {}
        self._calls: list[tuple[str, str | None, Request]] = []  # service calls from Zenoh's threads
        self._stops: list[_Stop] = []
        self._ending: dict[str, tuple[TaskState, str]] = {}  # uid -> the end of a task this plugin removes
        self.navigator = Navigator(get=self.get, send=self._send, wake_in=self.wake_in,
                                   remove=lambda task: self._end(task, TaskState.CANCELLED,
                                                                 "cancelled through NavigateToPose's cancel_goal"),
                                   topic=lambda robot: f"/{ros_name(robot)}/navigate_to_pose/_action",
                                   frame=s.frame, feedback_hz=s.odom_rate_hz, log=self.log)
        self._run = 0
        self._lock = threading.Lock()
        self._odom_budget = RateBudget(s.odom_rate_hz)
        self._pending_odom: dict[str, Pose] = {}
        self._robots_fixed = s.robots
        self._declared: set[str] = set()
        self._closing = threading.Event()
        self._agent_set_up = threading.Event()  # set on the first run: every plugin's setup has run by then
        self._sender = threading.Thread(target=self._send_loop, name=f"erni-{self.agent_name}-ros2", daemon=True)
        self._sender.start()
        self.wake_every(min(0.1, s.cmd_vel_timeout / 2))

    # --- the Zenoh side (sender thread) -----------------------------------------------------

    def _session(self) -> zenoh.Session | None:
        """The transport's Zenoh session (auto, wire = zenoh, once started) or a session of the plugin's own."""
        s = self.settings
        if s.session == "auto":
            # what the transport offers is known once every plugin has been set up, whatever their order
            if not self._agent_set_up.is_set():
                return None  # asked again
            offered = self.provided("transport.zenoh_session")  # the transport's, on the Zenoh wire
            if offered is not None:
                try:
                    session: zenoh.Session = offered()
                    return session
                except NetworkError:
                    return None  # not started yet: asked again
        conf = zenoh.Config()
        values: dict[str, Any] = {"mode": s.mode, "connect/endpoints": s.connect,
                                  "scouting/multicast/enabled": False}
        if s.listen:
            values["listen/endpoints"] = s.listen
        for key, value in values.items():
            conf.insert_json5(key, json.dumps(value))
        try:
            self._own = zenoh.open(conf)
        except zenoh.ZError as err:
            raise NetworkError(f"ros2: cannot open a Zenoh session ({s.mode}, {', '.join(s.connect)}): "
                               f"{str(err).splitlines()[0] if str(err) else err!r}") from None
        return self._own

    def _send_loop(self) -> None:
        warned = False
        while not self._closing.is_set():
            if self.node is None:
                try:
                    session = self._session()
                except NetworkError as err:  # a client whose router is not up yet: tried again
                    if not warned:
                        self.log.warning("%s; trying again every %g s", err, RECONNECT)
                        warned = True
                    self._closing.wait(RECONNECT)
                    continue
                if session is None:
                    self._closing.wait(0.2)
                    continue
                self.node = RmwNode(session, self.settings.node_name or f"erni_{ros_name(self.agent_name)}",
                                    domain_id=self.settings.domain_id, clock=self.clock)
                self.log.info("ROS 2 node %s on Zenoh session %s (domain %d)", self.node.name, self.node.zid,
                              self.settings.domain_id)
                for typename, topic, wanted in ((messages.TF_MESSAGE, "/tf", self.settings.tf),
                                                (messages.STRING, "/erni/task_status", self.settings.status),
                                                (messages.MARKER_ARRAY, "/erni/network", self.settings.network),
                                                (messages.DIAGNOSTIC_ARRAY, "/diagnostics", self.settings.network)):
                    if wanted:  # declared at once: ROS 2 tools list them before the first message
                        self.node.publisher(topic, typename, self._qos(typename))
                if self.settings.stop_service:
                    self.node.service("/erni/stop", messages.TRIGGER, lambda r: self._on_call("stop", None, r))
                self.wake()  # declare the robots known so far
            try:
                item = self._outbox.get(timeout=0.2)
            except queue.Empty:
                continue
            if item is None:
                break
            kind, topic, payload, stamp_ns = item
            try:
                if kind == "declare":
                    self._declare(topic)
                else:
                    self.node.publisher(topic, kind, self._qos(kind)).put(payload, stamp_ns)
            except zenoh.ZError as err:
                self.log.warning("ros2: %s on %s not sent: %s", kind, topic, err)

    @staticmethod
    def _qos(typename: str) -> QoS:
        return QoS(depth=100) if typename == messages.TF_MESSAGE else DEFAULT_QOS

    def _declare(self, robot: str) -> None:
        """A robot's topics: its odom publisher and its cmd_vel and goal_pose subscriptions."""
        assert self.node is not None
        base = f"/{ros_name(robot)}"
        self.node.publisher(f"{base}/odom", messages.ODOMETRY)
        if self.settings.sonar:
            self.node.publisher(f"{base}/sonar", messages.LASER_SCAN)
        if self.settings.cmd_vel:
            self.node.subscribe(f"{base}/cmd_vel", messages.TWIST, lambda data: self._on_cmd_vel(robot, data))
        if self.settings.goal_pose:
            self.node.subscribe(f"{base}/goal_pose", messages.POSE_STAMPED, lambda data: self._on_goal(robot, data))
        if self.settings.stop_service:
            self.node.service(f"{base}/stop", messages.TRIGGER, lambda r: self._on_call("stop", robot, r))
        if self.settings.navigate_to_pose:
            action = f"{base}/navigate_to_pose/_action"
            for name, srvtype in (("send_goal", messages.SEND_GOAL), ("get_result", messages.GET_RESULT),
                                  ("cancel_goal", messages.CANCEL_GOAL)):
                self.node.service(f"{action}/{name}", srvtype,
                                  lambda r, name=name: self._on_call(name, robot, r))  # type: ignore[misc]
            self.node.publisher(f"{action}/feedback", messages.FEEDBACK_MESSAGE)
            self.node.publisher(f"{action}/status", messages.GOAL_STATUS_ARRAY)

    def _send(self, typename: str, topic: str, msg: Any, stamp_ns: int) -> None:
        try:
            self._outbox.put_nowait((typename, topic, messages.serialize(msg), stamp_ns))
        except queue.Full:
            self.log.warning("ros2: outbox full, %s on %s dropped", typename, topic)

    # --- commands from ROS 2 (Zenoh's threads) ------------------------------------------------

    def _on_cmd_vel(self, robot: str, data: bytes) -> None:
        try:
            params = messages.velocity_params(messages.deserialize(data, messages.TWIST))
        except (ValueError, KeyError, IndexError) as err:
            self.log.warning("ros2: cmd_vel for %s refused: %s", robot, err)
            return
        now = self.clock()
        with self._lock:
            d = self._drives.setdefault(robot, _Drive())
            d.previous, d.heard, d.params = d.heard, now, params
            if d.latched and now - d.previous >= self.settings.cmd_vel_timeout:
                d.latched = False  # the stream paused after the stop: a new command is a new intent
        self.wake()

    def _on_goal(self, robot: str, data: bytes) -> None:
        try:
            msg = messages.deserialize(data, messages.POSE_STAMPED)
            params = messages.goto_params(msg)
        except (ValueError, KeyError, IndexError) as err:
            self.log.warning("ros2: goal_pose for %s refused: %s", robot, err)
            return
        heading = messages.goal_heading(msg) if self.settings.goal_heading else None
        with self._lock:
            self._drives.setdefault(robot, _Drive()).goals.append((params, heading, None))
        self.wake()

    def _on_call(self, kind: str, robot: str | None, request: Request) -> None:
        """A service call (stop, or one of NavigateToPose's): answered by the plugin's thread."""
        with self._lock:
            self._calls.append((kind, robot, request))
        self.wake()

    # --- the blackboard side ------------------------------------------------------------------

    def _robots(self) -> set[str]:
        if self._robots_fixed is not None:
            return set(self._robots_fixed)
        role = self.provided("transport.role")
        if role is not None and role != "control":
            return {self.agent_name}
        return {p.robot for p in self.poses}

    def execute(self) -> None:
        self._agent_set_up.set()
        self._run += 1
        robots = self._robots()
        with self._lock:
            calls, self._calls = self._calls, []
        for kind, robot, request in calls:
            try:
                if kind == "stop":
                    self._call_stop(robot, request, robots)
                elif kind == "send_goal":
                    self._call_send_goal(str(robot), request)
                elif kind == "get_result":
                    self.navigator.get_result(request)
                else:
                    self.navigator.cancel_goal(str(robot), request, self._now_ns())
            except (ValueError, KeyError, IndexError, AssertionError) as err:  # a request that does not decode
                self.log.warning("ros2: %s for %s refused: %s", kind, robot or "every robot", err)
                request.fail(f"{kind}: the request does not decode: {err}")
        for robot in sorted(robots - self._declared):
            if self.node is not None:
                self._declared.add(robot)
                self._outbox.put(("declare", robot, b"", 0))
        self._publish_poses(robots)
        if self.settings.status:
            for task in [*self.tasks.added, *self.tasks.changed]:
                if task.result is not None:
                    self._send(messages.STRING, "/erni/task_status", messages.task_status(task),
                               messages.stamp_ns_of(task.result.stamp))
            for task in self.tasks.removed:
                self._status_of_removed(task)
        self._ending = {uid: why for uid, why in self._ending.items() if self.get(uid) is not None}
        if self.settings.network and (self.nets.added or self.nets.changed):
            self._publish_network()
            for info in [*self.nets.added, *self.nets.changed]:
                stamp_ns = messages.stamp_ns_of(info.stamp)
                self._send(messages.DIAGNOSTIC_ARRAY, "/diagnostics", messages.diagnostics(info, stamp_ns), stamp_ns)
        self._drive(robots)
        self._answer_stops()
        self.navigator.update(self.clock(), self._now_ns(), self._run)

    def _status_of_removed(self, task: Task) -> None:
        """The last status of a task removed before it ended (its performer reports nothing more): what this
        plugin removed it for (a velocity task whose cmd_vel stream stopped or changed succeeded: it held its
        command as long as it was given), else cancelled."""
        state, message = self._ending.pop(task.uid, (TaskState.CANCELLED, "removed before it ended"))
        if task.done:
            return
        ended = task.with_result(state, message=message, stamp=self.clock.wall(),
                                 progress=1.0 if state is TaskState.SUCCEEDED else
                                 (task.result.progress if task.result else 0.0))
        assert ended.result is not None
        self._send(messages.STRING, "/erni/task_status", messages.task_status(ended),
                   messages.stamp_ns_of(ended.result.stamp))

    def _end(self, task: BBObject, state: TaskState, message: str) -> None:
        """Remove a task this plugin posted, with the status /erni/task_status gives it once it is gone."""
        self._ending[task.uid] = (state, message)
        self.remove(task)

    def _publish_poses(self, robots: set[str]) -> None:
        """Odometry (and /tf) of the robots' new poses, at most odom_rate_hz per robot (`RateBudget`): a pose
        held back by the rate is replaced by a newer one, or goes out itself when none came (a robot's last
        state is never lost)."""
        fresh = set()
        for pose in [*self.poses.added, *self.poses.changed]:
            if pose.robot in robots:
                self._pending_odom[pose.robot] = pose
                fresh.add(pose.robot)
        if self.node is None or not self._pending_odom:
            return
        now = self.clock()
        due = []
        for robot, pose in list(self._pending_odom.items()):
            wait = self._odom_budget.offer(robot, now, robot in fresh)
            if wait <= 0:
                due.append(pose)
                del self._pending_odom[robot]
            else:
                self.wake_in(wait)
        if not due:
            return
        for pose in due:
            stamp_ns = messages.stamp_ns_of(pose.stamp)
            self._send(messages.ODOMETRY, f"/{ros_name(pose.robot)}/odom",
                       messages.odometry(pose, stamp_ns, self._odom_frame(pose.robot)), stamp_ns)
        if self.settings.sonar:
            for pose in due:
                if pose.sonar:
                    stamp_ns = messages.stamp_ns_of(pose.stamp)
                    self._send(messages.LASER_SCAN, f"/{ros_name(pose.robot)}/sonar",
                               messages.sonar_echo_scan(pose, self._transducers(pose.robot), stamp_ns), stamp_ns)
        if self.settings.tf:
            stamp_ns = max(messages.stamp_ns_of(p.stamp) for p in due)
            self._send(messages.TF_MESSAGE, "/tf", self._tf_message(due), stamp_ns)

    def _odom_frame(self, robot: str) -> str:
        """The frame a robot's odometry is given in: '<robot>/odom' (rep105) or the world frame (flat)."""
        return f"{robot}/odom" if self.settings.frames == "rep105" else self.settings.frame

    def _tf_message(self, poses: list[Pose]) -> Any:
        """/tf of the robots' poses, each transform stamped with its Pose's time. rep105: world →
        <robot>/odom (the identity: an ERNI Pose is already in the world frame, so odometry and map
        coincide and nothing drifts between them) and <robot>/odom → <robot>/base_link (the Pose); both
        with the Pose's stamp, so a lookup at any time the odometry is known finds the whole chain. flat:
        world → <robot>/base_link."""
        world = self.settings.frame
        transforms = []
        for pose in poses:
            stamp_ns = messages.stamp_ns_of(pose.stamp)
            if self.settings.frames == "rep105":
                odom = self._odom_frame(pose.robot)
                identity = messages.make(
                    "geometry_msgs/msg/Transform", translation=messages.make("geometry_msgs/msg/Vector3"),
                    rotation=messages.quaternion(0.0))
                transforms.append(messages.make("geometry_msgs/msg/TransformStamped",
                                                header=messages.header(stamp_ns, world), child_frame_id=odom,
                                                transform=identity))
                transforms.append(messages.transform(pose, stamp_ns, odom))
            else:
                transforms.append(messages.transform(pose, stamp_ns, world))
        return messages.make(messages.TF_MESSAGE, transforms=transforms)

    def _transducers(self, robot: str) -> tuple[tuple[float, float, float] | None, ...]:
        """Where a robot's sonars sit: its motion plugin's model when it runs in this agent, else a Pioneer 3-DX's."""
        from erni.plugins.motion.robots import MODELS

        sonar = self.provided("motion.sonar") if robot == self.agent_name else None
        if sonar is not None and (found := sonar()):
            return tuple(found)
        return tuple(MODELS["p3dx-sh"].sonar)

    def _publish_network(self) -> None:
        infos = sorted(self.nets, key=lambda n: n.stamp)
        links = {(min(l.a, l.b), max(l.a, l.b)): l for n in infos for l in n.links}
        positions: dict[str, tuple[float, float]] = {}
        for n in infos:
            positions.update({name: (p.x, p.y) for name, p in n.positions.items()})
        positions.update({p.robot: (p.x, p.y) for p in self.poses})
        cut = {a for n in infos for a in n.articulation_points}
        stamp_ns = int(self.clock.wall() * 1_000_000_000)
        self._send(messages.MARKER_ARRAY, "/erni/network",
                   messages.network_markers(list(links.values()), positions, stamp_ns, self.settings.frame, cut),
                   stamp_ns)

    def _task(self, robot: str, preposition: str, params: dict[str, float]) -> Task:
        return Task(verb="BotMotion", preposition=preposition, params=params, source=self.agent_name,
                    destination=None if robot == self.agent_name else robot)

    def _drive(self, robots: set[str]) -> None:
        """cmd_vel and goal_pose as tasks: one velocity task per robot carries its cmd_vel stream, replaced
        when the command changes (at most cmd_vel_rate_hz a second), removed (the robot stops) when the
        stream stops for cmd_vel_timeout. A task ended by anyone else (an ERNI stop, a failure) latches
        the stream: commands are ignored until it pauses for cmd_vel_timeout."""
        now = self.clock()
        with self._lock:
            drives = {r: d for r, d in self._drives.items() if r in robots}
            pending: dict[str, list[tuple[dict[str, float], float | None, bytes | None]]] = {}
            for robot, d in drives.items():
                pending[robot], d.goals = d.goals, []
            for robot, d in drives.items():
                self._stream(robot, d, now)
                self._start_goals(robot, d, pending[robot])
                self._turn_after_goal(robot, d)

    def _stream(self, robot: str, d: _Drive, now: float) -> None:
        """A robot's cmd_vel stream as its velocity task (called holding the lock)."""
        s = self.settings
        if d.task is not None:
            current = self.get(d.task.uid)
            if not isinstance(current, Task) or current.done:
                d.task = None
                d.latched = True  # ended by a stop, a failure or a canceller: not restarted behind its back
        if d.latched and now - d.heard >= s.cmd_vel_timeout:
            d.latched = False
            d.params = None
        if d.task is not None and now - d.heard >= s.cmd_vel_timeout:
            self._end(d.task, TaskState.SUCCEEDED,  # the stream stopped: so does the robot
                      f"the cmd_vel stream stopped (none for {s.cmd_vel_timeout:g} s)")
            d.task, d.params = None, None
        elif d.params is not None and not d.latched and now - d.heard < s.cmd_vel_timeout:
            same = d.task is not None and d.task.params.model_dump(include={"v", "w"}) == d.params
            if not same and now - d.started >= 1.0 / s.cmd_vel_rate_hz:
                if d.task is not None:
                    self._end(d.task, TaskState.SUCCEEDED, "replaced by a newer cmd_vel")
                d.task = self._task(robot, "velocity", d.params)
                d.started = now
                self.add(d.task)

    def _start_goals(self, robot: str, d: _Drive,
                     goals: list[tuple[dict[str, float], float | None, bytes | None]]) -> None:
        """A robot's new goals (goal_pose or NavigateToPose) as gotos, each replacing the one before."""
        s = self.settings
        for goal, heading, goal_id in goals:
            action = self.navigator.goal(goal_id)
            if action is not None and action.cancel:  # cancelled in the run that accepted it
                self.navigator.end(action, CANCELED, "canceled before it started")
                continue
            for earlier in (d.goal, d.turn):
                current = self.get(earlier.uid) if earlier is not None else None
                if isinstance(current, Task) and not current.done:
                    self._end(current, TaskState.CANCELLED, "replaced by a newer goal")  # the one being driven to
            d.goal = self._task(robot, "goto", {**goal, "speed": s.goal_speed, "tolerance": s.goal_tolerance})
            d.heading, d.turn, d.action = heading, None, goal_id
            self.add(d.goal)
            if action is not None:
                action.goto, action.run = d.goal.uid, self._run
                if heading is None:
                    action.turn = ""

    def _turn_after_goal(self, robot: str, d: _Drive) -> None:
        """Once a goal's goto succeeded, a turn to the goal's heading (relative to where the robot heads now)."""
        if d.goal is None or d.heading is None:
            return
        current = self.get(d.goal.uid)
        if not isinstance(current, Task) or not current.done:
            return  # not committed yet (posted in this run), running, or removed (then a new goal resets it)
        heading, d.heading = d.heading, None
        pose = self.get(f"pose:{robot}")
        action = self.navigator.goal(d.action)
        if action is not None:
            action.turn = ""
        if current.state is not TaskState.SUCCEEDED or not isinstance(pose, Pose):
            return  # the goto failed or was cancelled: no turn
        angle = math.degrees(math.atan2(math.sin(heading - pose.theta), math.cos(heading - pose.theta)))
        if abs(angle) > self.settings.heading_tolerance:
            d.turn = self._task(robot, "turn", {"angle": angle, "tolerance": self.settings.heading_tolerance})
            self.add(d.turn)
            if action is not None:
                action.turn, action.run = d.turn.uid, self._run

    # --- services: stop, and NavigateToPose ------------------------------------------------------

    def _call_stop(self, robot: str | None, request: Request, robots: set[str]) -> None:
        """A BotMotion stop for the robot (or every robot served): it ends every motion, whatever posted it."""
        targets = [robot] if robot is not None else sorted(robots)
        if not targets:
            request.reply(messages.serialize(messages.make(f"{messages.TRIGGER}_Response", success=False,
                                                           message="no robots to stop")))
            return
        uids = {}
        for name in targets:
            task = self._task(name, "stop", {})
            self.add(task)
            uids[name] = task.uid
        self.log.info("ros2: stop called for %s", ", ".join(targets))
        self._stops.append(_Stop(request, uids, self.clock() + self.settings.stop_timeout, self._run))

    def _answer_stops(self) -> None:
        """A stop's answer: success once every robot's stop task succeeded (the robot halted); a failure as soon
        as one failed or was refused, or when one has not halted within stop_timeout."""
        now = self.clock()
        waiting = []
        for stop in self._stops:
            failed: list[str] = []
            halted = []
            for robot, uid in stop.uids.items():
                task = self.get(uid)
                if not isinstance(task, Task):
                    if stop.run != self._run:
                        failed.append(f"{robot}: the stop task is gone")
                elif task.state is TaskState.SUCCEEDED:
                    halted.append(robot)
                elif task.done:
                    failed.append(f"{robot}: stop {task.state.value}"
                                  + (f": {task.result.message}" if task.result and task.result.message else ""))
            if not failed and len(halted) < len(stop.uids) and now >= stop.deadline:
                failed = [f"{r}: not halted within {self.settings.stop_timeout:g} s" for r in stop.uids
                          if r not in halted]
            if failed or len(halted) == len(stop.uids):
                message = "; ".join(failed) if failed else f"halted: {', '.join(halted)}"
                stop.request.reply(messages.serialize(messages.make(f"{messages.TRIGGER}_Response",
                                                                    success=not failed, message=message)))
            else:
                waiting.append(stop)
                self.wake_in(0.05)
        self._stops = waiting

    def _call_send_goal(self, robot: str, request: Request) -> None:
        accepted = self.navigator.send_goal(robot, request, goal_heading=self.settings.goal_heading, now=self.clock(),
                                            now_ns=self._now_ns(), run=self._run)
        if accepted is not None:
            with self._lock:
                self._drives.setdefault(robot, _Drive()).goals.append(accepted)

    def _now_ns(self) -> int:
        return int(self.clock.wall() * 1_000_000_000)

    def teardown(self) -> None:
        self._closing.set()
        try:
            self._outbox.put_nowait(None)
        except queue.Full:
            pass
        self._sender.join(timeout=5)
        if self.node is not None:
            self.node.close()
        if self._own is not None:
            self._own.close()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs


__all__ = ["ROS2Plugin", "ROS2Settings"]
