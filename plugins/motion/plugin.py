"""RobotMotionControl: performs BotMotion tasks on an ARCOS robot and publishes its Pose.

The plugin subscribes to BotMotion tasks addressed to its agent (or to nobody), hands them
to its RobotMotionResource (whose threads do all robot I/O), and publishes, from the
resource's poll thread, each task's AllocationResult and the robot's `Pose` in short
transactions of their own.
"""

from __future__ import annotations

import math
import re
from typing import Any, Literal

from pydantic import ConfigDict, Field, field_validator

from erni.blackboard import AllocationResult, ConfigError, Plugin, Pose, Task, TaskState, TransactionError
from erni.blackboard.objects import FiniteAny, Model
from erni.plugins.motion.driver import ArcosDriver, RobotState, known_url_schemes
from erni.plugins.motion.resource import RobotMotionResource, TaskUpdate
from erni.plugins.motion.robots import ModelSpec, model_spec
from erni.plugins.motion.ros2_base import Ros2BaseDriver, is_ros2_url, parse_url

_URL = re.compile(r"^([a-zA-Z][a-zA-Z0-9+.-]*://.*|/dev/\S+|COM\d+|/\S+)$")


class MotionSettings(Model):
    """Settings of RobotMotionControl (the `[plugin.settings]` table)."""

    model_config = ConfigDict(extra="forbid")

    url: str = Field("simrobot://", description="serial device (/dev/ttyUSB0) or pyserial URL: "
                     "socket://host:8101 (MobileSim/AMRISim), simrobot:// (a simulated robot in this process)")
    model: str | dict[str, FiniteAny] = Field(
        "auto", description="'auto' (the model the robot names in SYNC2), a model such as 'p3dx-sh', 'amigo', "
        "'pioneer3', 'amigobot', or a table: a base and the values to override")
    baudrate: int = Field(9600, gt=0, description="serial rate to connect at (ARCOS starts at 9600)")
    switch_baud: bool = Field(True, description="on a serial line, switch to the model's faster rate (HOSTBAUD)")
    config_timeout: float = Field(1.0, ge=0, description="wait this long for the CONFIG reply at connect (s)")
    latency: float | None = Field(None, ge=0, le=2, description="command latency to plan stops with (s); "
                                  "default: the SIP's age + one SIP period + one stack cycle")
    rate_hz: float = Field(20.0, gt=0, le=200, description="behaviour stack cycles a second at most (it "
                           "cycles on each SIP while it steers)")
    pose_rate_hz: float = Field(10.0, gt=0, le=100, description="Pose publishing rate (Hz)")
    pose_keepalive: float = Field(1.0, gt=0, le=60, description="a Pose that only a newer stamp would change "
                                  "(a standing robot) is published this often (s)")
    progress_interval: float = Field(0.5, ge=0, le=60, description="a running task's result is republished for "
                                     "progress alone at most this often (s); a new state goes at once")
    avoid_distance: float = Field(0.4, ge=0, le=5, description="built-in obstacle avoidance (m); 0 = off")
    blocked_timeout: float = Field(10.0, gt=0, description="fail a task held by avoidance this long (s)")
    stall_timeout: float = Field(1.0, gt=0, description="fail a task whose wheels stall this long (s)")
    link_timeout: float = Field(1.0, gt=0, description="no SIP for this long = link lost (s)")
    link_grace: float = Field(2.0, ge=0, description="fail tasks after the link is lost this long (s)")
    default_timeout: float | None = Field(None, gt=0, description="time limit of goto/turn/forward/backward (s)")
    sync_timeout: float = Field(0.5, gt=0, description="wait for each SYNC reply (s)")
    sync_attempts: int = Field(5, ge=1, description="SYNC tries at connect before the robot counts as not answering")
    pulse_interval: float = Field(0.5, gt=0, description="PULSE when idle this long (s)")
    teleport: Literal["auto", "sim", "odometry"] = Field(
        "auto", description="sim: SIM_SET_POSE moves the robot; odometry: re-localise; auto: sim when the "
        "robot's CONFIG says it is a simulator (serial number SIM), else odometry")

    @field_validator("url")
    @classmethod
    def _check_url(cls, url: str) -> str:
        url = url.strip()
        if not _URL.match(url):
            raise ValueError(f"expected a serial device (/dev/ttyUSB0) or a pyserial URL (socket://host:8101, "
                             f"simrobot://), got {url!r}")
        scheme = url.split("://", 1)[0].lower() if "://" in url else None
        if scheme is not None and scheme not in (known := known_url_schemes()):
            raise ValueError(f"unknown URL scheme {scheme + '://'!r} in {url!r}; expected one of "
                             f"{', '.join(s + '://' for s in known)}")
        if is_ros2_url(url):
            parse_url(url)  # a ROS 2 base: its namespace and link parameters (ConfigError, a ValueError)
        return url

    @field_validator("model")
    @classmethod
    def _check_model(cls, model: str | dict[str, Any]) -> str | dict[str, Any]:
        try:
            model_spec(model)
        except ConfigError as err:
            raise ValueError(str(err).removeprefix("model: ")) from None
        return model

    def model_spec(self) -> ModelSpec:
        """The model setting, parsed: resolved against the robot's subtype at connect."""
        return model_spec(self.model)


def pose_of(robot: str, s: RobotState) -> Pose:
    """Return the blackboard Pose for a robot state."""
    sonar = [round(s.sonar[i], 3) for i in sorted(s.sonar)] if s.sonar else []
    return Pose(robot=robot, x=s.x, y=s.y, theta=s.theta, v=s.v, w=s.w, battery=s.battery,
                stall_left=s.stall_left, stall_right=s.stall_right, bumpers=s.bumpers,
                motors_enabled=s.motors_enabled, sonar=sonar)


RELATIVE = frozenset({"forward", "backward", "turn", "say"})
"""Prepositions whose effect depends on where the robot was when they started."""


class RobotMotionControl(Plugin[MotionSettings]):
    """Performs BotMotion tasks with a behaviour stack on an ARCOS robot; publishes its Pose."""


    def setup(self) -> None:
        s = self.settings
        me = self.agent_name
        # tasks come and go here; their results are this plugin's own (the resource's outcomes, a few a
        # second while one runs), which must not run it again
        self.tasks = self.subscribe(Task, where=lambda t: t.verb == "BotMotion" and t.destination in (None, "", me),
                                    ignore=("result",))
        if is_ros2_url(s.url):  # a ROS 2 base (cmd_vel, odom, scan) behind the same driver interface
            driver: ArcosDriver = Ros2BaseDriver(s.url, s.model_spec(), name=me, link_timeout=s.link_timeout)
        else:
            driver = ArcosDriver(s.url, s.model_spec(), name=me, baudrate=s.baudrate, sync_timeout=s.sync_timeout,
                                 sync_attempts=s.sync_attempts, pulse_interval=s.pulse_interval,
                                 link_timeout=s.link_timeout, config_timeout=s.config_timeout,
                                 switch_baud=s.switch_baud)
        self.pose: Pose | None = None
        self.resource = RobotMotionResource(
            driver, self._publish, name=me, rate_hz=s.rate_hz, pose_rate_hz=s.pose_rate_hz,
            pose_keepalive=s.pose_keepalive, progress_interval=s.progress_interval,
            avoid_distance=s.avoid_distance, blocked_timeout=s.blocked_timeout,
            stall_timeout=s.stall_timeout, link_grace=s.link_grace, default_timeout=s.default_timeout,
            teleport=s.teleport, latency=s.latency)
        self.resource.start()
        # what the ROS 2 edge publishes of this robot beyond its Pose: the sonar ranges the driver reads
        self.provide("motion.sonar", lambda: tuple(self.resource.driver.model.sonar))

    def execute(self) -> None:
        for task in self.tasks.added:
            if task.done:
                continue
            if self.rehydrated(task) and task.preposition in RELATIVE:
                # after a crash we cannot know how much of a relative move was done: never repeat it
                self.change(task.with_result(
                    TaskState.FAILED, message=f"interrupted by a restart of agent {self.agent_name}; "
                    f"a relative {task.preposition} is not repeated"))
                continue
            self.resource.submit(task)  # absolute tasks (goto, velocity, stop, ...) resume
        for task in self.tasks.removed:
            self.resource.cancel(task.uid)

    def teardown(self) -> None:
        self.resource.close()

    def _publish(self, updates: list[TaskUpdate], state: RobotState | None) -> None:
        """Publish the pose and the outcome changes in one short transaction (the resource's poll or
        stack thread, one at a time): one commit, so the plugins that follow both (the transport
        sends the Pose and the results) run once for them. The pose goes first: whoever sees an
        outcome ("stop succeeded: halted") finds the pose of the state it was decided on, or a newer
        one, already on the blackboard, never the one before it."""
        pose = pose_of(self.agent_name, state) if state is not None else None
        with self.transaction():
            if pose is not None:
                if self.pose is None and not self.query(Pose, where=lambda p: p.uid == pose.uid):
                    self.add(pose)
                else:
                    self.change(pose)
            for u in updates:
                current = self._current(u.uid)
                if current is None or current.done:
                    continue
                result = AllocationResult(state=u.state, progress=u.progress,
                                          values=_jsonable(u.values), message=u.message)
                try:
                    self.change(current.evolve(result=result), reports=[u.state.value])
                except TransactionError:
                    pass  # the task was removed (cancelled) meanwhile: nothing to report to
        if pose is not None:
            self.pose = pose

    def _current(self, uid: str) -> Task | None:
        found = self.get(uid)
        return found if isinstance(found, Task) else None


def _jsonable(values: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in values.items():
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        out[k] = v
    return out
