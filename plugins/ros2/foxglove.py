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
that a client that just subscribed sees a team standing still. Every message carries the time of
the Poses it draws (their `stamp`), as its log time and in its timestamps: a replay shows the
recorded times, not the time it is watched.

Both names of the protocol are accepted: `foxglove.sdk.v1` (foxglove-sdk, Foxglove's app) and
`foxglove.websocket.v1` (the published ws-protocol and its clients). foxglove-sdk accepts only its
own names, so the plugin listens itself and relays each connection byte for byte to the SDK's server
on a private loopback port, naming the protocol `foxglove.sdk.v1` to the SDK and back to the client
in the name the client offered (`Relay`).
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import socket
import threading
from collections import deque
from collections.abc import Iterable
from decimal import Decimal
from typing import Any

from pydantic import Field

from erni.blackboard import ErniError, NetInfo, Plugin, Pose
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


SDK_NAMES = ("foxglove.sdk.v1", "foxglove.sdk.v1.1")  # the names foxglove-sdk 0.30 accepts itself
OLD_NAME = "foxglove.websocket.v1"  # the name of the published ws-protocol (foxglove/ws-protocol)
HEAD_LIMIT = 64 * 1024  # the most an HTTP head may take, and the relay's read size
HANDSHAKE_TIMEOUT = 10.0  # s for a client's request head and the SDK's answer
CLOSE_GRACE = 5.0  # s the other direction may go on after one side closed
STOP_GRACE = 1.0  # s open connections may take to finish their closing handshakes when the relay stops


def _head_lines(head: bytes) -> list[bytes]:
    return head.split(b"\r\n")


def offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocols an HTTP head names in its `Sec-WebSocket-Protocol` headers, in order."""
    names = []
    for line in _head_lines(head)[1:]:
        key, sep, value = line.partition(b":")
        if sep and key.strip().lower() == b"sec-websocket-protocol":
            names += [v.strip() for v in value.decode("latin-1").split(",") if v.strip()]
    return names


def with_subprotocol(head: bytes, name: str) -> bytes:
    """The HTTP head with its `Sec-WebSocket-Protocol` headers replaced by one naming `name`."""
    lines = [line for line in _head_lines(head)
             if line.partition(b":")[0].strip().lower() != b"sec-websocket-protocol"]
    while lines and not lines[-1]:
        lines.pop()
    return b"\r\n".join([*lines, b"Sec-WebSocket-Protocol: " + name.encode(), b"", b""])


def refusal(offered: Iterable[str]) -> bytes:
    """The 400 answer to a request that offers no name of the Foxglove protocol."""
    names = ", ".join(offered)
    body = (f"Foxglove WebSocket: offer the subprotocol {SDK_NAMES[0]} or {OLD_NAME} "
            f"({'offered: ' + names[:200] if names else 'this request offered none'})\n").encode()
    return (b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain; charset=utf-8\r\nConnection: close\r\n"
            b"Content-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body)


class Relay:
    """Listens on HOST:PORT and relays each connection that offers a name of the Foxglove protocol,
    byte for byte, to foxglove-sdk's server on 127.0.0.1:`upstream`; a client offering only
    `foxglove.websocket.v1` is announced to the SDK as `foxglove.sdk.v1` and told `foxglove.websocket.v1`
    back (the two are the same protocol; only the name differs). Anything else gets a 400 naming both.
    One asyncio loop on a thread of its own does all the relaying."""

    def __init__(self, host: str, port: int, upstream: int, log: logging.Logger, name: str = "foxglove"):
        try:
            family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
            self.sock = socket.create_server((host, port), family=family)
        except OSError as err:
            why = os.strerror(err.errno) if err.errno else str(err)
            raise ErniError(f"foxglove: cannot listen on {host}:{port}: {why}") from None
        self.port: int = self.sock.getsockname()[1]
        self.upstream, self.log = upstream, log
        self.loop = asyncio.new_event_loop()
        self._connections: set[asyncio.Task[None]] = set()
        self._started = threading.Event()
        self._failed: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"erni-{name}-relay", daemon=True)
        self._thread.start()
        self._started.wait()
        if self._failed is not None:
            raise ErniError(f"foxglove: cannot serve on {host}:{port}: {self._failed}")

    def stop(self, grace: float = STOP_GRACE) -> None:
        """Close the listener, give open connections `grace` s to finish (the SDK's server stopped
        first closes them), then cut the rest and end the thread."""
        try:
            self.loop.call_soon_threadsafe(lambda: self.loop.create_task(self._shutdown(grace)))
        except RuntimeError:  # the loop has ended already
            pass
        self._thread.join(grace + 5)

    async def _shutdown(self, grace: float) -> None:
        self._server.close()
        if self._connections:
            _, left = await asyncio.wait(set(self._connections), timeout=grace)
            for task in left:
                task.cancel()
            await asyncio.gather(*left, return_exceptions=True)
        self.loop.stop()

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        try:
            self._server = self.loop.run_until_complete(asyncio.start_server(self._serve, sock=self.sock,
                                                                             limit=HEAD_LIMIT))
        except Exception as err:  # told to the thread that started the relay
            self._failed = err
            self.sock.close()
            self.loop.close()
            return
        finally:
            self._started.set()
        try:
            self.loop.run_forever()
        finally:
            self._server.close()
            self.loop.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._connections.add(task)
        try:
            await self._relay(reader, writer)
        except asyncio.CancelledError:  # the relay stops: end quietly (asyncio would log a cancelled task)
            pass
        finally:
            self._connections.discard(task)

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        client = writer.get_extra_info("peername")
        upstream: asyncio.StreamWriter | None = None
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HANDSHAKE_TIMEOUT)
            offered = offered_subprotocols(head)
            rename = None
            if not any(name in SDK_NAMES for name in offered):
                if OLD_NAME not in offered:
                    self.log.info("refused a client at %s: it offered %s", client, offered or "no subprotocol")
                    writer.write(refusal(offered))
                    await writer.drain()
                    return
                rename, head = OLD_NAME, with_subprotocol(head, SDK_NAMES[0])
            up_reader, upstream = await asyncio.open_connection("127.0.0.1", self.upstream, limit=HEAD_LIMIT)
            upstream.write(head)
            await upstream.drain()
            answer = await asyncio.wait_for(up_reader.readuntil(b"\r\n\r\n"), HANDSHAKE_TIMEOUT)
            if rename and offered_subprotocols(answer) == [SDK_NAMES[0]]:
                answer = with_subprotocol(answer, rename)
            writer.write(answer)
            await writer.drain()
            await self._pipe(reader, writer, up_reader, upstream)
        except (OSError, TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError) as err:
            self.log.debug("client at %s: %s", client, err)
        finally:
            for end in (writer, upstream):
                if end is not None:
                    end.close()

    @staticmethod
    async def _pipe(client_reader: asyncio.StreamReader, client: asyncio.StreamWriter,
                    sdk_reader: asyncio.StreamReader, sdk: asyncio.StreamWriter) -> None:
        async def copy(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            try:
                while data := await src.read(HEAD_LIMIT):
                    dst.write(data)
                    await dst.drain()
                if dst.can_write_eof():
                    dst.write_eof()  # a half close, as the sender made it
            except OSError:
                pass

        ways = [asyncio.ensure_future(copy(client_reader, sdk)), asyncio.ensure_future(copy(sdk_reader, client))]
        try:
            _, left = await asyncio.wait(ways, return_when=asyncio.FIRST_COMPLETED)
            if left:
                _, left = await asyncio.wait(left, timeout=CLOSE_GRACE)
        finally:
            for way in ways:
                way.cancel()


def _stamp(seconds: float) -> tuple[int, Any]:
    """A time in seconds since the epoch as nanoseconds (a log time) and a Foxglove Timestamp; the
    nanoseconds of the shortest decimal that is the float (a stamp ...0.25 is ...250_000_000 ns, not
    `seconds * 1e9`, which is 256 ns coarse today), as the bags and the ROS 2 plugin stamp."""
    from foxglove.messages import Timestamp

    ns = max(0, int((Decimal(repr(seconds)) * 1_000_000_000).to_integral_value()))
    return ns, Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


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
        self._team_time: float | None = None  # the newest Pose's stamp last sent
        # the SDK's server on a private loopback port, behind the plugin's own listener (`Relay`)
        self.server = foxglove.start_server(name=f"ERNI {self.agent_name}", host="127.0.0.1", port=0,
                                            context=self.context)
        try:
            self.relay = Relay(host, port, self.server.port, self.log, name=self.agent_name)
        except BaseException:
            self.server.stop()
            raise
        self.port = self.relay.port
        self.log.info("Foxglove WebSocket: ws://%s:%d", host, self.port)
        # no server callbacks into Python: a new subscriber gets the team at the next refresh
        self.wake_every(s.refresh)

    def teardown(self) -> None:
        if hasattr(self, "relay"):  # else setup failed, and stopped the SDK's server
            self.server.stop()  # it closes its clients' connections; the relay passes that on, then stops
            self.relay.stop()

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
            Vector3,
        )

        frame, now = self.settings.frame, self.clock.wall()  # now: how old network info is
        poses = {p.robot: p for p in self.poses}
        peers = {p.name: p for p in self.peers}
        # each robot's things carry its Pose's time, a message of the team the newest Pose's time (with no
        # Pose, the time last sent: a replay that clears its team stays on the recorded time line)
        self._team_time = max((p.stamp for p in poses.values()), default=self._team_time)
        team_ns, team_stamp = _stamp(now if self._team_time is None else self._team_time)
        transforms, robots, trails = [], [], []
        for name, pose in sorted(poses.items()):
            colour, why = self._state(pose, peers.get(name))
            pose_ns, stamp = _stamp(pose.stamp)
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
            channel.log(PoseInFrame(timestamp=stamp, frame_id=frame, pose=_pose(pose.x, pose.y, pose.theta)),
                        log_time=pose_ns)
        gone = [SceneEntityDeletion(timestamp=team_stamp, type=SceneEntityDeletionType.MatchingId, id=name)
                for name in sorted(self._drawn - set(poses))]
        self._drawn = set(poses)
        self.tf.log(FrameTransforms(transforms=transforms), log_time=team_ns)
        self.robots.log(SceneUpdate(deletions=gone, entities=robots), log_time=team_ns)
        self.trail_channel.log(SceneUpdate(deletions=gone, entities=trails), log_time=team_ns)
        points, colours = [], []
        for a, b, quality, stale in self.link_list(poses, peers, now):
            for end in (a, b):
                points.append(Point3(x=poses[end].x, y=poses[end].y, z=0.05))
                colours.append(_color(GREY if stale else quality_color(quality)))
        every = SceneEntityDeletion(timestamp=team_stamp, type=SceneEntityDeletionType.All, id="")
        self.links.log(SceneUpdate(deletions=[every], entities=[SceneEntity(
            timestamp=team_stamp, frame_id=frame, id="links",
            lines=[LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=0.05, points=points,
                                 colors=colours)])] if points else []), log_time=team_ns)

    def link_list(self, poses: dict[str, Pose], peers: dict[str, Peer],
                  now: float) -> list[tuple[str, str, float, bool]]:
        """Links between placed robots from their NetInfo (a, b, quality, stale), the best of each pair."""
        best = best_links(self.netinfo, poses, lambda end: end in peers and not peers[end].up,
                          self.settings.netinfo_max_age, now)
        return [(a, b, q, stale) for (a, b), (q, stale) in sorted(best.items())]
