"""The team live in Foxglove: a control node serves the Foxglove WebSocket protocol (foxglove-sdk).

Open Foxglove (app or https://app.foxglove.dev), *Open connection* → *Foxglove WebSocket* →
`ws://HOST:8765`, and add a 3D panel with the fixed frame `map`. Channels, all in schemas the 3D
panel draws by itself (protobuf, as foxglove-sdk encodes them):

| topic | schema | what |
|---|---|---|
| `/tf` | `foxglove.FrameTransforms` | `map` -> `<robot>/base_link` for every robot |
| `/erni/robots` | `foxglove.SceneUpdate` | each robot: a disc coloured by state (green ok, pink low battery, stalled, motors off or bumper, grey lost), an arrow along its heading, its name |
| `/erni/trails` | `foxglove.SceneUpdate` | each robot's recent path, a line strip |
| `/erni/links` | `foxglove.SceneUpdate` | network links between placed robots, coloured by quality from red (0) to green (1), grey when stale |
| `/<robot>/pose` | `foxglove.PoseInFrame` | each robot's pose (x, y, heading) in `map`, for plots and the 3D panel's pose display |

Poses, links and peers are read from the blackboard, as the web GUI reads them; updates go out
at most `rate_hz` times a second when something changed, and again every `refresh` seconds (1) so
that a client that just subscribed sees a team standing still.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

from pydantic import Field

from erni.blackboard import NetInfo, Plugin, Pose
from erni.blackboard.objects import Model
from erni.blackboard.schemas import Peer
from erni.blackboard.tasks import best_links
from erni.transport import parse_address

GREEN, PINK, GREY = (0.2, 0.75, 0.3, 1.0), (1.0, 0.45, 0.7, 1.0), (0.55, 0.55, 0.55, 0.6)


class FoxgloveSettings(Model):
    """The `[plugin.settings]` of the foxglove plugin."""

    listen: str = Field("127.0.0.1:8765", description="HOST:PORT of the Foxglove WebSocket server (port 0: any "
                        "free port)")
    frame: str = Field("map", min_length=1, description="the fixed frame robots, trails and links are given in")
    rate_hz: float = Field(10.0, gt=0, le=100, description="most updates a second")
    trail: int = Field(300, ge=0, le=100_000, description="points kept in each robot's trail (0: no trails)")
    trail_step: float = Field(0.02, ge=0, description="a trail point only after the robot moved this far (m)")
    low_battery: float = Field(11.5, description="volts below which a robot is drawn pink")
    netinfo_max_age: float = Field(10.0, ge=0, description="network info older than this (s) is drawn grey; "
                                   "0 = never")
    refresh: float = Field(1.0, gt=0, le=3600, description="the team is sent again after this long (s) without "
                           "a change, so a client that just subscribed sees a team standing still")


def _quaternion(theta: float) -> Any:
    from foxglove.messages import Quaternion

    return Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2))


def _pose(x: float, y: float, theta: float = 0.0, z: float = 0.0) -> Any:
    from foxglove.messages import Pose as FoxPose
    from foxglove.messages import Vector3

    return FoxPose(position=Vector3(x=x, y=y, z=z), orientation=_quaternion(theta))


def _color(rgba: tuple[float, float, float, float]) -> Any:
    from foxglove.messages import Color

    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def quality_color(quality: float) -> tuple[float, float, float, float]:
    """Red at quality 0, yellow at 0.5, green at 1."""
    q = min(max(quality, 0.0), 1.0)
    return min(1.0, 2 * (1 - q)), min(1.0, 2 * q), 0.0, 1.0


class FoxglovePlugin(Plugin[FoxgloveSettings]):
    """Serves the team's robots, headings, trails and links to Foxglove over its WebSocket protocol."""

    def setup(self) -> None:
        import foxglove
        from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel

        s = self.settings
        self.poses = self.subscribe(Pose)
        self.netinfo = self.subscribe(NetInfo)
        self.peers = self.subscribe(Peer)
        self.trails: dict[str, deque[tuple[float, float]]] = {}
        self._last = 0.0
        self._pending = True
        host, port = parse_address(s.listen)
        # a context of its own: several agents in one process each serve their own team
        self.context = foxglove.Context()
        self.tf = FrameTransformsChannel("/tf", context=self.context)
        self.robots = SceneUpdateChannel("/erni/robots", context=self.context)
        self.trail_channel = SceneUpdateChannel("/erni/trails", context=self.context)
        self.links = SceneUpdateChannel("/erni/links", context=self.context)
        self.pose_channels: dict[str, Any] = {}
        self._drawn: set[str] = set()
        self.server = foxglove.start_server(name=f"ERNI {self.agent_name}", host=host, port=port,
                                            context=self.context)
        self.port = self.server.port
        self.log.info("Foxglove WebSocket: ws://%s:%d", host, self.port)
        # no server callbacks into Python: a new subscriber gets the team at the next refresh
        self.wake_every(s.refresh)

    def teardown(self) -> None:
        self.server.stop()

    def execute(self) -> None:
        changed = bool(self.poses.added or self.poses.changed or self.poses.removed or self.netinfo.added
                       or self.netinfo.changed or self.netinfo.removed or self.peers.added or self.peers.changed
                       or self.peers.removed)
        for pose in self.poses.added + self.poses.changed:
            self._extend_trail(pose)
        for pose in self.poses.removed:
            self.trails.pop(pose.robot, None)
        now = self.clock()
        self._pending = self._pending or changed or now - self._last >= self.settings.refresh
        if not self._pending:
            return
        wait = self._last + 1.0 / self.settings.rate_hz - now
        if wait > 0:
            self.wake_in(wait)
            return
        self._last, self._pending = now, False
        self.publish()

    def _extend_trail(self, pose: Pose) -> None:
        if not self.settings.trail:
            return
        trail = self.trails.setdefault(pose.robot, deque(maxlen=self.settings.trail))
        if not trail or math.dist(trail[-1], (pose.x, pose.y)) >= self.settings.trail_step:
            trail.append((pose.x, pose.y))

    def _state(self, pose: Pose, peer: Peer | None) -> tuple[tuple[float, float, float, float], str]:
        if peer is not None and not peer.up:
            return GREY, "LINK LOST"
        reasons = [f"battery {pose.battery:.1f} V"] if pose.battery is not None and \
            pose.battery < self.settings.low_battery else []
        reasons += [why for why, on in (("stalled", pose.stalled), ("motors off", not pose.motors_enabled),
                                        ("bumper", bool(pose.bumpers))) if on]
        return (PINK if reasons else GREEN), ", ".join(reasons)

    def publish(self) -> None:
        """Send the team as it is now on every channel."""
        from foxglove.channels import PoseInFrameChannel
        from foxglove.messages import (
            ArrowPrimitive,
            CylinderPrimitive,
            FrameTransform,
            FrameTransforms,
            LinePrimitive,
            LinePrimitiveLineType,
            Point3,
            PoseInFrame,
            SceneEntity,
            SceneEntityDeletion,
            SceneEntityDeletionType,
            SceneUpdate,
            TextPrimitive,
            Timestamp,
            Vector3,
        )

        frame, now = self.settings.frame, self.clock.wall()
        stamp = Timestamp.from_epoch_secs(now)
        poses = {p.robot: p for p in self.poses}
        peers = {p.name: p for p in self.peers}
        transforms, robots, trails = [], [], []
        for name, pose in sorted(poses.items()):
            colour, why = self._state(pose, peers.get(name))
            transforms.append(FrameTransform(timestamp=stamp, parent_frame_id=frame,
                                             child_frame_id=f"{name}/base_link",
                                             translation=Vector3(x=pose.x, y=pose.y, z=0.0),
                                             rotation=_quaternion(pose.theta)))
            label = f"{name} ({why})" if why else name
            robots.append(SceneEntity(
                timestamp=stamp, frame_id=frame, id=name,
                cylinders=[CylinderPrimitive(pose=_pose(pose.x, pose.y, 0.0, 0.1), size=Vector3(x=0.4, y=0.4, z=0.2),
                                             bottom_scale=1.0, top_scale=1.0, color=_color(colour))],
                arrows=[ArrowPrimitive(pose=_pose(pose.x, pose.y, pose.theta, 0.25), shaft_length=0.35,
                                       shaft_diameter=0.06, head_length=0.15, head_diameter=0.14,
                                       color=_color(colour))],
                texts=[TextPrimitive(pose=_pose(pose.x, pose.y, 0.0, 0.6), billboard=True, font_size=14.0,
                                     scale_invariant=True, color=_color((1.0, 1.0, 1.0, 1.0)), text=label)]))
            trail = self.trails.get(name, ())
            if len(trail) > 1:
                trails.append(SceneEntity(
                    timestamp=stamp, frame_id=frame, id=name,
                    lines=[LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=0.04,
                                         points=[Point3(x=x, y=y, z=0.02) for x, y in trail],
                                         color=_color(colour[:3] + (0.7,)))]))
            channel = self.pose_channels.get(name)
            if channel is None:
                channel = self.pose_channels[name] = PoseInFrameChannel(f"/{name}/pose", context=self.context)
            channel.log(PoseInFrame(timestamp=stamp, frame_id=frame, pose=_pose(pose.x, pose.y, pose.theta)))
        gone = [SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.MatchingId, id=name)
                for name in sorted(self._drawn - set(poses))]
        self._drawn = set(poses)
        self.tf.log(FrameTransforms(transforms=transforms))
        self.robots.log(SceneUpdate(deletions=gone, entities=robots))
        self.trail_channel.log(SceneUpdate(deletions=gone, entities=trails))
        points, colours = [], []
        for a, b, quality, stale in self.link_list(poses, peers, now):
            for end in (a, b):
                points.append(Point3(x=poses[end].x, y=poses[end].y, z=0.05))
                colours.append(_color(GREY if stale else quality_color(quality)))
        every = SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All, id="")
        self.links.log(SceneUpdate(deletions=[every], entities=[SceneEntity(
            timestamp=stamp, frame_id=frame, id="links",
            lines=[LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=0.05, points=points,
                                 colors=colours)])] if points else []))

    def link_list(self, poses: dict[str, Pose], peers: dict[str, Peer],
                  now: float) -> list[tuple[str, str, float, bool]]:
        """Links between placed robots from their NetInfo (a, b, quality, stale), the best of each pair."""
        best = best_links(self.netinfo, poses, lambda end: end in peers and not peers[end].up,
                          self.settings.netinfo_max_age, now)
        return [(a, b, q, stale) for (a, b), (q, stale) in sorted(best.items())]
