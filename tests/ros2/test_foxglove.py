"""The control node serves Foxglove's WebSocket protocol: a client written here (the `websockets`
library) reads serverInfo and the advertised channels, subscribes, and decodes the binary
messageData frames (opcode 1) with a protobuf reader of its own, driven by the FileDescriptorSet each
channel advertises (no foxglove code decodes anything here).

foxglove-sdk 0.30 names the protocol `foxglove.sdk.v1` (and `foxglove.sdk.v1.1`, where schemas are
advertised apart from channels) and refuses a client that offers only the published name
`foxglove.websocket.v1`, as foxglove/ws-protocol's clients do; the plugin's own listener accepts
both names (the messages are the same) and refuses a client offering neither."""

from __future__ import annotations

import base64
import json
import math
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from decimal import Decimal
from pathlib import Path
from typing import Any

import pytest
import websockets.sync.client as websockets_sync

from erni.blackboard import Agent, NetInfo, Pose
from erni.blackboard.schemas import Peer
from erni.blackboard.tasks import Link
from erni.blackboard.testing import wait_until

PLUGIN = "erni.plugins.ros2.foxglove:FoxglovePlugin"

# --- a small protobuf reader ------------------------------------------------------------------


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = buf[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, i


def _fields(buf: bytes) -> list[tuple[int, int, Any]]:
    out, i = [], 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 1:
            value, i = buf[i:i + 8], i + 8
        elif wire == 2:
            size, i = _varint(buf, i)
            value, i = buf[i:i + size], i + size
        elif wire == 5:
            value, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"wire type {wire}")
        out.append((number, wire, value))
    return out


class Protobuf:
    """Messages of a FileDescriptorSet: full name -> field number -> (name, type, type name, repeated)."""

    def __init__(self, descriptor_set: bytes):
        self.messages: dict[str, dict[int, tuple[str, int, str, bool]]] = {}
        for number, _, file in _fields(descriptor_set):
            assert number == 1
            package = next((v.decode() for n, _, v in _fields(file) if n == 2), "")
            for n, _, message in _fields(file):
                if n == 4:
                    self._message(f".{package}" if package else "", message)

    def _message(self, scope: str, message: bytes) -> None:
        parts = _fields(message)
        name = f"{scope}.{next(v.decode() for n, _, v in parts if n == 1)}"
        fields = self.messages.setdefault(name, {})
        for n, _, value in parts:
            if n == 2:
                f = {k: v for k, _, v in _fields(value)}
                fields[f[3]] = (f[1].decode(), f[5], f.get(6, b"").decode(), f.get(4) == 3)
            elif n == 3:
                self._message(name, value)

    def decode(self, data: bytes, type_name: str) -> dict[str, Any]:
        spec, out = self.messages[type_name], {}
        for number, wire, raw in _fields(data):
            if number not in spec:
                continue
            name, kind, sub, repeated = spec[number]
            if kind == 11:
                values: list[Any] = [self.decode(raw, sub)]
            elif kind == 9:
                values = [raw.decode()]
            elif kind == 12:
                values = [raw]
            elif kind in (1, 2):  # double, float; packed when repeated
                fmt = "<d" if kind == 1 else "<f"
                values = [v for (v,) in struct.iter_unpack(fmt, raw)]
            elif kind in (3, 4, 5, 8, 13, 14):
                if wire == 2:
                    values, i = [], 0
                    while i < len(raw):
                        v, i = _varint(raw, i)
                        values.append(v)
                else:
                    values = [raw]
                if kind in (3, 5):
                    values = [v - (1 << 64) if v >= 1 << 63 else v for v in values]
            else:
                raise ValueError(f"{name}: protobuf type {kind} not read here")
            if repeated:
                out.setdefault(name, []).extend(values)
            else:
                out[name] = values[0]
        return out


# --- a Foxglove WebSocket client --------------------------------------------------------------


class Client:
    def __init__(self, ws: Any):
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[int, dict[str, Any]] = {}
        self.schemas: dict[int, Protobuf] = {}
        self.subscribed: dict[int, int] = {}  # subscription id -> channel id
        self.latest: dict[str, tuple[int, dict[str, Any]]] = {}  # topic -> (log time, message)
        self.received: dict[str, int] = {}
        self.history: list[tuple[str, int, dict[str, Any]]] = []  # every message: (topic, log time, message)

    def pump(self, seconds: float) -> None:
        """Read frames for `seconds`: subscribe to every channel advertised, decode every message."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                frame = self.ws.recv(timeout=left)
            except TimeoutError:
                return
            if isinstance(frame, str):
                self._control(json.loads(frame))
            else:
                assert frame[0] == 1, f"opcode {frame[0]}"  # messageData
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                channel = self.channels[self.subscribed[sub]]
                message = self.schemas[channel["id"]].decode(frame[13:], "." + channel["schemaName"])
                self.latest[channel["topic"]] = (log_time, message)
                self.history.append((channel["topic"], log_time, message))
                self.received[channel["topic"]] = self.received.get(channel["topic"], 0) + 1

    def _control(self, msg: dict[str, Any]) -> None:
        if msg["op"] == "serverInfo":
            self.server_info = msg
        elif msg["op"] == "advertise":
            new = []
            for channel in msg["channels"]:
                assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
                self.channels[channel["id"]] = channel
                self.schemas[channel["id"]] = Protobuf(base64.b64decode(channel["schema"]))
                new.append(channel["id"])
            subs = [{"id": 100 + cid, "channelId": cid} for cid in new]
            self.subscribed.update({s["id"]: s["channelId"] for s in subs})
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def topics(self) -> dict[str, str]:
        return {c["topic"]: c["schemaName"] for c in self.channels.values()}


SDK, OLD = "foxglove.sdk.v1", "foxglove.websocket.v1"


@contextmanager
def foxglove_client(port: int, offer: tuple[str, ...] = (SDK, OLD)) -> Iterator[Client]:
    """A client offering `offer` (by default both names of the protocol, as Foxglove's app does); the
    server must choose the first name of the protocol offered (websockets refuses a name not offered)."""
    with websockets_sync.connect(f"ws://127.0.0.1:{port}", proxy=None, open_timeout=10,
                                 subprotocols=list(offer)) as ws:  # type: ignore[arg-type]
        assert ws.subprotocol == next(name for name in offer if name in (SDK, OLD))
        yield Client(ws)


def ns(seconds: float) -> int:
    """The exact nanoseconds of a time the tests give in quarters of a second (exact in a float)."""
    exact = Decimal(seconds) * 1_000_000_000
    assert exact == exact.to_integral_value(), seconds
    return int(exact)


def timestamp_ns(t: dict[str, Any]) -> int:
    return t.get("seconds", 0) * 1_000_000_000 + t.get("nanos", 0)


def colour(c: dict[str, Any]) -> tuple[float, ...]:
    return tuple(round(c.get(k, 0.0), 3) for k in ("r", "g", "b", "a"))


def xy(p: dict[str, Any]) -> tuple[float, float]:
    return round(p.get("x", 0.0), 6), round(p.get("y", 0.0), 6)


def heading(q: dict[str, Any]) -> float:
    return 2 * math.atan2(q.get("z", 0.0), q.get("w", 0.0))


@pytest.fixture
def control():
    agent = Agent("control", workers=2)
    plugin = agent.add_plugin(PLUGIN, settings={"listen": "127.0.0.1:0", "rate_hz": 20, "trail_step": 0.05},
                              name="foxglove")
    agent.start()
    try:
        yield agent, plugin
    finally:
        agent.stop()


def test_foxglove_client_sees_robots_headings_trails_and_links(control):
    agent, plugin = control
    r1 = Pose(robot="robot1", x=1.0, y=2.0, theta=math.pi / 2, battery=12.6, stamp=1_750_000_001.25)
    r2 = Pose(robot="robot2", x=4.0, y=2.0, theta=0.0, battery=10.9, stamp=1_750_000_000.5)  # low: drawn pink
    with agent.transaction() as tx:
        tx.add(r1)
        tx.add(r2)
        tx.add(Peer(name="robot1", up=True, role="robot"))
        tx.add(peer2 := Peer(name="robot2", up=True, role="robot"))
        tx.add(NetInfo(node="robot1", kind="network_topology", links=[Link(a="robot1", b="robot2", quality=0.75)]))
    with foxglove_client(plugin.port) as client:  # type: ignore[attr-defined]
        client.pump(1.0)
        assert client.server_info["name"] == "ERNI control"
        assert {"/tf": "foxglove.FrameTransforms", "/erni/robots": "foxglove.SceneUpdate",
                "/erni/trails": "foxglove.SceneUpdate", "/erni/links": "foxglove.SceneUpdate",
                "/robot1/pose": "foxglove.PoseInFrame", "/robot2/pose": "foxglove.PoseInFrame"}.items() \
            <= client.topics().items()
        def seen_at(x: float) -> bool:  # the plugin has run on the Pose at x (its trail took it) and sent it
            client.pump(0.05)
            pose = client.latest.get("/robot1/pose", (0, {}))[1].get("pose", {})
            return xy(pose.get("position", {})) == (x, 2.0)

        for x in (1.2, 1.4, 1.6):  # robot1 drives along +x: its trail grows
            with agent.transaction() as tx:
                tx.change(r1.evolve(x=x))
            wait_until(lambda x=x: seen_at(x), timeout=10)
        with agent.transaction() as tx:
            tx.change(r1.evolve(x=1.6, y=2.0, theta=math.radians(30)))

        def seen_last_pose() -> bool:
            client.pump(0.2)
            pose = client.latest.get("/robot1/pose", (0, {}))[1].get("pose", {})
            return xy(pose.get("position", {})) == (1.6, 2.0) and \
                heading(pose.get("orientation", {})) == pytest.approx(math.radians(30))

        wait_until(seen_last_pose, timeout=10)
        client.pump(0.3)
        log_time, pose = client.latest["/robot1/pose"]
        # stamped with the Pose's own time (evolve keeps r1's), as the log time and in the message
        assert pose["frame_id"] == "map" and log_time == ns(r1.stamp)
        assert timestamp_ns(pose["timestamp"]) == log_time

        tf_time, tf = client.latest["/tf"]
        frames = {t["child_frame_id"]: t for t in tf["transforms"]}
        assert set(frames) == {"robot1/base_link", "robot2/base_link"}
        assert tf_time == ns(max(r1.stamp, r2.stamp))  # the team's message: its newest Pose
        assert timestamp_ns(frames["robot2/base_link"]["timestamp"]) == ns(r2.stamp)
        assert frames["robot1/base_link"]["parent_frame_id"] == "map"
        assert xy(frames["robot1/base_link"]["translation"]) == (1.6, 2.0)
        assert heading(frames["robot1/base_link"]["rotation"]) == pytest.approx(math.radians(30))
        assert xy(frames["robot2/base_link"]["translation"]) == (4.0, 2.0)

        _, scene = client.latest["/erni/robots"]
        robots = {e["id"]: e for e in scene["entities"]}
        assert set(robots) == {"robot1", "robot2"} and robots["robot1"]["frame_id"] == "map"
        arrow = robots["robot1"]["arrows"][0]
        assert xy(arrow["pose"]["position"]) == (1.6, 2.0)
        assert heading(arrow["pose"]["orientation"]) == pytest.approx(math.radians(30))
        assert colour(robots["robot1"]["cylinders"][0]["color"]) == (0.2, 0.75, 0.3, 1.0)
        assert colour(robots["robot2"]["cylinders"][0]["color"]) == (1.0, 0.45, 0.7, 1.0)
        assert robots["robot2"]["texts"][0]["text"] == "robot2 (battery 10.9 V)"

        _, trails = client.latest["/erni/trails"]
        line = {e["id"]: e for e in trails["entities"]}["robot1"]["lines"][0]
        assert [xy(p) for p in line["points"]] == [(1.0, 2.0), (1.2, 2.0), (1.4, 2.0), (1.6, 2.0)]

        _, links = client.latest["/erni/links"]
        link = links["entities"][0]["lines"][0]
        assert link.get("type") == 2  # LINE_LIST
        assert [xy(p) for p in link["points"]] == [(1.6, 2.0), (4.0, 2.0)]
        assert [colour(c) for c in link["colors"]] == [(0.5, 1.0, 0.0, 1.0)] * 2  # quality 0.75

        # robot2's link is lost: it and its link turn grey; then it leaves and is deleted
        with agent.transaction() as tx:
            tx.change(peer2.evolve(up=False))

        def grey() -> bool:
            client.pump(0.2)
            entities = {e["id"]: e for e in client.latest["/erni/robots"][1].get("entities", [])}
            return entities["robot2"]["texts"][0]["text"] == "robot2 (LINK LOST)"

        wait_until(grey, timeout=10)
        client.pump(0.3)
        robots = {e["id"]: e for e in client.latest["/erni/robots"][1]["entities"]}
        assert colour(robots["robot2"]["cylinders"][0]["color"]) == (0.55, 0.55, 0.55, 0.6)
        link = client.latest["/erni/links"][1]["entities"][0]["lines"][0]
        assert [colour(c) for c in link["colors"]] == [(0.55, 0.55, 0.55, 0.6)] * 2

        with agent.transaction() as tx:
            tx.remove(r2.uid)

        def deleted() -> bool:
            client.pump(0.2)
            update = client.latest["/erni/robots"][1]
            return [d.get("id") for d in update.get("deletions", [])] == ["robot2"]

        wait_until(deleted, timeout=10)
        assert [e["id"] for e in client.latest["/erni/robots"][1]["entities"]] == ["robot1"]
        assert "entities" not in client.latest["/erni/links"][1], "no link without both ends placed"


@pytest.mark.parametrize("offer", [(OLD,), (SDK,), (SDK, OLD), ("x.v2", OLD)],
                         ids=["published-name-only", "sdk-name-only", "both", "other-then-published"])
def test_a_client_gets_a_team_standing_still(control, offer):
    """Nothing changes after the client connects: it still gets the robots as they stand, whichever
    name of the protocol it offers (foxglove/ws-protocol's clients offer only foxglove.websocket.v1)."""
    agent, plugin = control
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot1", x=-1.0, y=0.5, theta=math.pi))
    # published to no one: the plugin has drawn robot1, with nothing left pending
    wait_until(lambda: "robot1" in plugin._drawn and not plugin._pending, timeout=10)
    with foxglove_client(plugin.port, offer) as client:  # type: ignore[attr-defined]
        wait_until(lambda: client.pump(0.2) or "/erni/robots" in client.latest and "/tf" in client.latest, timeout=10)
        assert client.server_info["name"] == "ERNI control"
        arrow = client.latest["/erni/robots"][1]["entities"][0]["arrows"][0]
        assert xy(arrow["pose"]["position"]) == (-1.0, 0.5)
        assert abs(heading(arrow["pose"]["orientation"])) == pytest.approx(math.pi)
        transform = client.latest["/tf"][1]["transforms"][0]
        assert transform["child_frame_id"] == "robot1/base_link" and xy(transform["translation"]) == (-1.0, 0.5)


@pytest.mark.parametrize("offer", [(), ("foxglove.websocket.v2", "x.v1")], ids=["none", "other-names"])
def test_a_client_offering_neither_name_is_refused(control, offer):
    """HTTP 400 with a line naming both accepted names; the server goes on serving others."""
    from websockets.exceptions import InvalidStatus

    _, plugin = control
    with pytest.raises(InvalidStatus) as refused:
        websockets_sync.connect(f"ws://127.0.0.1:{plugin.port}", proxy=None, open_timeout=10,
                                subprotocols=list(offer) or None)
    response = refused.value.response
    assert response.status_code == 400
    said = ", ".join(offer) if offer else "none"
    assert response.body.decode() == (f"Foxglove WebSocket: offer the subprotocol {SDK} or {OLD} "
                                      f"({'offered: ' + said if offer else 'this request offered none'})\n")
    with foxglove_client(plugin.port, (OLD,)) as client:
        wait_until(lambda: client.pump(0.1) or bool(client.server_info), timeout=10)


def test_a_port_in_use_is_one_clear_error(caplog):
    """The plugin cannot listen: its setup fails with the address and the reason, and stops the SDK's
    server it had started; the agent goes on without it."""
    import socket

    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        agent = Agent("control", workers=2)
        plugin = agent.add_plugin(PLUGIN, settings={"listen": f"127.0.0.1:{port}"}, name="foxglove")
        agent.start()
        try:
            errors = [r.exc_info[1] for r in caplog.records if r.exc_info and r.exc_info[1]]
            assert [str(e) for e in errors] == [f"foxglove: cannot listen on 127.0.0.1:{port}: Address already in use"]
            assert not hasattr(plugin, "port")
        finally:
            agent.stop()
    assert not [r for r in caplog.records if "teardown" in r.getMessage()]


def test_a_connected_client_sees_a_clean_close_when_the_agent_stops():
    """The SDK's server closes its clients; the relay passes the closing handshake on and ends."""
    from websockets.exceptions import ConnectionClosedOK

    agent = Agent("control", workers=2)
    plugin = agent.add_plugin(PLUGIN, settings={"listen": "127.0.0.1:0"}, name="foxglove")
    agent.start()
    with foxglove_client(plugin.port, (OLD,)) as client:  # type: ignore[attr-defined]
        wait_until(lambda: client.pump(0.1) or bool(client.server_info), timeout=10)
        agent.stop()
        with pytest.raises(ConnectionClosedOK):
            while True:
                client.ws.recv(timeout=5)
    assert not plugin.relay._thread.is_alive()  # type: ignore[attr-defined]


def test_updates_are_rate_limited():
    """On the agent's clock (a ManualClock moved 10 ms after each change has been taken): 100 changes in
    a second make 20 updates a second at most."""
    from erni.testing import ManualClock
    from tests.core.helpers import scheduler_idle

    clock = ManualClock()
    agent = Agent("control", workers=2, clock=clock)
    plugin = agent.add_plugin(PLUGIN, settings={"listen": "127.0.0.1:0", "rate_hz": 20, "trail_step": 0.05},
                              name="foxglove")
    agent.start()
    try:
        pose = Pose(robot="robot1")
        with agent.transaction() as tx:
            tx.add(pose)
        with foxglove_client(plugin.port) as client:  # type: ignore[attr-defined]
            wait_until(lambda: client.pump(0.05) or "/erni/robots" in client.topics(), timeout=10)
            client.pump(0.2)  # its subscriptions sent
            before = client.received.get("/erni/robots", 0)
            start = clock()
            for i in range(100):  # 100 changes in a second, 20 updates a second at most
                with agent.transaction() as tx:
                    tx.change(pose.evolve(x=i * 0.01))
                wait_until(lambda: scheduler_idle(plugin), timeout=10)  # the plugin's run on it is over
                clock.advance(0.01)

            def the_last_came() -> bool:
                client.pump(0.05)
                if xy(client.latest.get("/erni/robots", (0, {}))[1].get("entities", [{}])[0].get("arrows", [{}])[0]
                      .get("pose", {}).get("position", {})) == (0.99, 0.0):
                    return True
                clock.advance(0.01)  # a publication held back by the rate goes when its time comes
                return False

            wait_until(the_last_came, timeout=10)
            took = clock() - start
            client.pump(0.2)
            sent = client.received["/erni/robots"] - before
    finally:
        agent.stop()
    assert 2 <= sent <= 21 * took + 2, (sent, took)  # and a refresh a second at most
    assert sent >= 15 * took, (sent, took)  # the changes kept coming: about 20 updates a second went


@pytest.mark.parametrize("form", ["jsonl", "mcap"])
def test_replay_serves_a_log_to_foxglove(tmp_path: Path, form: str) -> None:
    """`erni replay LOG --foxglove HOST:PORT`: a recorded run (ERNI's log, or the rosbag2 bag
    `erni record --convert` makes of it), seen live in Foxglove at its recorded times: each message's
    log time and timestamps are the stamps of the Poses it draws."""
    from tests.transport.helpers import free_port

    log = tmp_path / "run.jsonl"
    started = 1_700_000_000.0  # November 2023: far from the time the test runs
    poses = [Pose(robot="robot1", x=0.5 * i, y=1.0, theta=0.25 * i, stamp=started + 0.25 * (i + 1))
             for i in range(4)]
    recorded = {(p.x, p.y): ns(p.stamp) for p in poses}
    lines = [{"erni_record": 1, "via": "x", "started": started}]
    lines += [{"t": 0.4 * i, "agent": "control", "op": "add" if i == 0 else "change", "type": "Pose",
               "data": p.model_dump(mode="json")} for i, p in enumerate(poses)]
    # the last pose stands 0.4 s too, before --loop clears the board and starts again
    lines.append({"t": 1.6, "agent": "control", "op": "add", "type": "Peer",
                  "data": Peer(name="robot1", up=True).model_dump(mode="json")})
    log.write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    root = Path(__file__).resolve().parents[2]
    if form == "mcap":  # the poses' stamps become the odometry's header stamps, and back
        pytest.importorskip("rosbags")
        bag = tmp_path / "run.mcap"
        out = subprocess.run([sys.executable, "-m", "erni", "record", "--convert", str(log), str(bag)], cwd=root,
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        log = bag
    proc = subprocess.Popen([sys.executable, "-m", "erni", "replay", str(log), "--no-gui", "--insecure", "--loop",
                             "--listen", f"127.0.0.1:{free_port()}", "--foxglove", "127.0.0.1:0"],
                            cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        port = None
        for line in proc.stderr:  # "Foxglove: ws://127.0.0.1:PORT"
            if line.startswith("Foxglove: ws://127.0.0.1:"):
                port = int(line.rsplit(":", 1)[1])
                break
        assert port, "no Foxglove line"
        with foxglove_client(port, (OLD,)) as client:
            seen: set[tuple[float, float]] = set()

            def all_poses() -> bool:
                client.pump(0.2)
                seen.update(xy(m["pose"]["position"]) for topic, _, m in client.history if topic == "/robot1/pose")
                return set(recorded) <= seen

            wait_until(all_poses, timeout=20)
            assert client.topics()["/erni/robots"] == "foxglove.SceneUpdate"

            def looped() -> bool:  # --loop cleared the board and the first pose came again after the last
                client.pump(0.2)
                at = [xy(m["pose"]["position"]) for topic, _, m in client.history if topic == "/robot1/pose"]
                return (1.5, 1.0) in at and (0.0, 1.0) in at[at.index((1.5, 1.0)):]

            wait_until(looped, timeout=20)
            times: dict[str, set[int]] = {}
            for topic, log_time, message in client.history:
                if topic == "/robot1/pose":
                    at = xy(message["pose"]["position"])
                    assert log_time == timestamp_ns(message["timestamp"]) == recorded[at], (at, log_time)
                elif topic == "/tf" and message.get("transforms"):
                    (transform,) = message["transforms"]
                    at = xy(transform["translation"])
                    assert log_time == timestamp_ns(transform["timestamp"]) == recorded[at], (at, log_time)
                elif topic == "/erni/robots" and message.get("entities"):
                    (robot,) = message["entities"]
                    at = xy(robot["arrows"][0]["pose"]["position"])
                    assert log_time == timestamp_ns(robot["timestamp"]) == recorded[at], (at, log_time)
                times.setdefault(topic, set()).add(log_time)
            # every message at a recorded time, each recorded time seen: none at the time of watching, not
            # even when --loop clears the board
            assert times["/robot1/pose"] == times["/tf"] == set(recorded.values()), times
            assert set().union(*times.values()) == set(recorded.values()), times
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
