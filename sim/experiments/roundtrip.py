"""Paper 002, Table II: round-trip delay of sensor data from one robot to 1-5 consumers at once.

One robot agent (transport, motion on a simulated ARCOS robot, and `SensorSource`) publishes
a `SensorReading` on its blackboard, as paper 002's BP sends its two kinds of data: "other
sensory data" as plain values (the location of a detected obstacle, the ambient temperature,
and the robot's Pose), and an "image": a camera frame (`image_size`, a synthetic scene with
sensor noise) compressed to JPEG when it is sent, inside the timed round trip (the paper's BP
compresses each frame before it goes), and decoded by each consumer before it answers (the
paper's SCP decompresses it to render it). The transport shares it (UDP status)
with every peer in role "consumer"; each consumer agent (transport and `SensorSink`) answers by
changing its `SensorAck`, which its transport shares back. The round trip is timed by the
robot's plugin from just before it publishes the reading to the run of `execute()` that sees
the last consumer's acknowledgement: blackboard -> transport -> consumer's blackboard ->
consumer plugin -> ... and back, the path paper 002 times from the BP's SM layer to the SCPs'
application layer and back. A reading not acknowledged by all within `timeout` counts as lost.
Every agent is its own process on loopback (127.0.1.x), so the network part is loopback UDP,
not the paper's WLAN; the figure says so.

Where the time goes: each acknowledgement carries the moment its consumer's plugin saw the
reading (`time.perf_counter()`, one clock for every process of the machine), so each round
trip is split into the first and the last consumer seeing the reading, the first
acknowledgement back, and the last. Measured (loopback, 2 cores, load average 2-3): the first
consumer sees the reading as soon with 5 consumers as with 1 (0.6-1.4 ms); the last one
later, by 0.4-0.6 ms per consumer; the acknowledgements follow. The robot's transport sends
the reading to every consumer as one burst (`Endpoint.send_fanout`, since 5f80bfd; about 30 us
a consumer, where one consumer after the other took about 0.15 ms each), and the spread is
CPU: per round trip each consumer process spends about 0.6 ms of CPU on receiving,
decoding, acknowledging and sending back, and the robot about 0.25 ms more per consumer, so
5 consumers ask for about 4.6 ms of CPU per round trip from a 2-core machine. The paper's
SCPs each had a machine of their own, and its WLAN round trip (67-91 ms) hides a fan-out of
a fraction of a millisecond.
"""

from __future__ import annotations

import base64
import io
import json
import math
import os
import random
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import ConfigDict, Field

from erni.blackboard import BBObject, Plugin, Pose
from erni.blackboard.objects import Model
from erni.blackboard.schemas import Peer
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.scenario import Scenario, ScenarioError

PAPER_IMAGE = {3: (89.2, 90.6), 4: (89.5, 89.1), 5: (91.3, 90.5)}  # ms: MCRLab, MIRaM
PAPER_OTHER = {5: (67.5, 67.5)}
STAGES = ("first consumer sees it", "last consumer sees it", "first acknowledgement back")


def camera_frames(width: int, height: int, seed: int, count: int = 8) -> list[NDArray[np.uint8]]:
    """`count` RGB frames of a synthetic scene (smooth shading, an object that moves, sensor
    noise): compressed as a camera's frames are, neither trivially nor not at all."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    scene = np.stack([x * 255 // max(1, width), y * 255 // max(1, height),
                      (x + y) * 255 // max(1, width + height)], axis=-1).astype(np.float64)
    frames = []
    for k in range(count):
        f = scene.copy()
        top, left = height // 4 + 2 * k, width // 3 + 4 * k
        f[top:top + height // 3, left:left + width // 5] = (200.0, 180.0, 150.0)
        f += rng.normal(0.0, 6.0, f.shape)
        frames.append(np.clip(f, 0, 255).astype(np.uint8))
    return frames


def compress(frame: NDArray[np.uint8], quality: int) -> bytes:
    """The frame as JPEG (Pillow, which matplotlib brings)."""
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(frame).save(out, format="JPEG", quality=quality)
    return out.getvalue()


def decode(jpeg: bytes) -> tuple[int, int]:
    """Decompress a JPEG frame; return its width and height."""
    from PIL import Image

    with Image.open(io.BytesIO(jpeg)) as im:
        im.load()
        return im.size


class SensorReading(BBObject):
    """A robot's sensor data sent to its consumers: values ("sensor") or a JPEG camera frame ("image")."""

    robot: str
    seq: int
    kind: str = "sensor"
    pose: Pose | None = None
    obstacle: tuple[float, float] | None = None  # where the detected obstacle is (m, the map's frame)
    temperature: float | None = None  # ambient temperature (degrees C)
    image: str = ""   # base64 JPEG frame ("image" readings)


class SensorAck(BBObject):
    """A consumer's acknowledgement of the newest reading it received."""

    consumer: str
    robot: str
    seq: int
    seen: float = 0.0  # time.perf_counter() when the consumer's plugin saw the reading (one clock per machine)


try:
    from erni.transport.wire import register_type
except ImportError:  # pragma: no cover - the transport is part of the distribution
    pass
else:
    register_type(SensorReading)
    register_type(SensorAck)


class SourceSettings(Model):
    """Settings of `SensorSource`."""

    model_config = ConfigDict(extra="forbid")

    consumers: int = Field(1, ge=1, description="acknowledgements a round trip waits for")
    count: int = Field(200, ge=1, description="round trips per kind")
    warmup: int = Field(20, ge=0, description="round trips discarded first")
    kinds: list[str] = Field(default_factory=lambda: ["sensor", "image"])
    image_size: tuple[int, int] = Field((320, 240), description="camera frame, width and height (pixels)")
    jpeg_quality: int = Field(75, ge=1, le=95, description="JPEG quality the frame is compressed with")
    gap: float = Field(0.03, ge=0, description="mean pause between round trips (s), randomised")
    timeout: float = Field(1.0, gt=0, description="a reading not acknowledged by all within this is lost (s)")
    out: str = Field(description="file the round trips are written to when the agent stops (JSON)")


class SensorSource(Plugin[SourceSettings]):
    """Publishes readings one at a time and times each until every consumer acknowledged it."""

    def setup(self) -> None:
        self.acks = self.subscribe(SensorAck)
        self.peers = self.subscribe(Peer)
        self.poses = self.subscribe(Pose, where=lambda p: p.robot == self.agent_name)
        self.rng = random.Random(7)
        self.frames = camera_frames(*self.settings.image_size, seed=7)
        self.image_bytes: list[int] = []
        self.seq = 0
        self.kind_index = 0
        self.done_in_kind = 0
        self.sent_at: float | None = None
        self.sent_at_last: float | None = None
        self.got: set[str] = set()
        self.next_at = 0.0
        self.ready_since: float | None = None
        self.published = False
        self.rtts: dict[str, list[float]] = {k: [] for k in self.settings.kinds}
        # where the time goes, per round trip (ms from the publish): the first and the last consumer's
        # plugin seeing the reading, the first acknowledgement seen back here
        self.stages: dict[str, dict[str, list[float]]] = {k: {s: [] for s in STAGES} for k in self.settings.kinds}
        self.seen_at: list[float] = []
        self.back_at: list[float] = []
        self.lost: dict[str, int] = {k: 0 for k in self.settings.kinds}
        self.wake_every(0.25)

    def execute(self) -> None:
        now = time.perf_counter()
        s = self.settings
        for ack in self.acks.added + self.acks.changed:
            if self.sent_at is not None and ack.seq == self.seq and ack.robot == self.agent_name \
                    and ack.consumer not in self.got:
                self.got.add(ack.consumer)
                self.seen_at.append(ack.seen)
                self.back_at.append(now)
        if self.sent_at is not None:
            if len(self.got) >= s.consumers:
                self._record(now - self.sent_at)
            elif now - self.sent_at > s.timeout:
                self._record(None)
        if self.kind_index >= len(s.kinds):
            return
        if self.sent_at is None:
            up = sum(1 for p in self.peers if p.up and p.role == "consumer")
            if up < s.consumers:
                self.ready_since = None
                return
            self.ready_since = self.ready_since or now
            if now - self.ready_since < 2.0:  # let every consumer learn where this robot is
                self.wake_in(2.0)
                return
            if now < self.next_at:
                self.wake_in(self.next_at - now)
                return
            self._send(now)

    def _send(self, now: float) -> None:
        kind = self.settings.kinds[self.kind_index]
        self.seq += 1
        self.got = set()
        self.sent_at = time.perf_counter()  # the BP's processing (the frame's compression) is part of the trip
        if kind == "image":
            jpeg = compress(self.frames[self.seq % len(self.frames)], self.settings.jpeg_quality)
            self.image_bytes.append(len(jpeg))
            reading = SensorReading(uid=f"reading:{self.agent_name}", robot=self.agent_name, seq=self.seq,
                                    kind=kind, image=base64.b64encode(jpeg).decode())
        else:
            pose = next(iter(self.poses), None)
            x, y, th = (pose.x, pose.y, pose.theta) if pose else (0.0, 0.0, 0.0)
            reading = SensorReading(uid=f"reading:{self.agent_name}", robot=self.agent_name, seq=self.seq,
                                    kind=kind, pose=pose, temperature=round(21.0 + self.rng.gauss(0.0, 0.3), 1),
                                    obstacle=(round(x + 0.8 * math.cos(th), 2), round(y + 0.8 * math.sin(th), 2)))
        self.seen_at, self.back_at = [], []
        if self.published:
            self.change(reading)
        else:
            self.add(reading)
            self.published = True
        self.wake_in(self.settings.timeout + 0.01)

    def _record(self, rtt: float | None) -> None:
        s = self.settings
        kind = s.kinds[self.kind_index]
        self.sent_at_last, self.sent_at = self.sent_at, None
        self.done_in_kind += 1
        if self.done_in_kind > s.warmup:
            if rtt is None:
                self.lost[kind] += 1
            else:
                self.rtts[kind].append(rtt * 1000.0)
                assert self.sent_at_last is not None
                for stage, at in zip(STAGES, (min(self.seen_at), max(self.seen_at), min(self.back_at))):
                    self.stages[kind][stage].append((at - self.sent_at_last) * 1000.0)
        if self.done_in_kind >= s.warmup + s.count:
            self.kind_index += 1
            self.done_in_kind = 0
            if self.kind_index >= len(s.kinds):  # all measured: write them now (on a thread, not in here)
                threading.Thread(target=self._write, args=(True,), daemon=True).start()
        self.next_at = time.perf_counter() + self.rng.uniform(0.5, 1.5) * s.gap
        self.wake_in(max(0.001, self.next_at - time.perf_counter()))

    def _write(self, complete: bool) -> None:
        data = {"rtt_ms": self.rtts, "stages_ms": self.stages, "lost": self.lost,
                "image_bytes": float(np.mean(self.image_bytes)) if self.image_bytes else 0.0,
                "consumers": self.settings.consumers, "complete": complete}
        tmp = Path(self.settings.out + ".tmp")
        tmp.write_text(json.dumps(data), encoding="utf-8")
        tmp.replace(self.settings.out)

    def teardown(self) -> None:
        if not Path(self.settings.out).exists():
            self._write(False)


class SensorSink(Plugin):
    """Acknowledges every reading it receives by changing its `SensorAck` (shared back by the transport)."""

    def setup(self) -> None:
        self.readings = self.subscribe(SensorReading)
        self.ack: SensorAck | None = None

    def execute(self) -> None:
        newest = None
        for r in self.readings.added + self.readings.changed:
            if newest is None or r.seq > newest.seq:
                newest = r
        if newest is None:
            return
        if newest.image:  # decompressed to be shown, as the paper's SCP renders it
            decode(base64.b64decode(newest.image))
        ack = SensorAck(uid=f"ack:{self.agent_name}", consumer=self.agent_name, robot=newest.robot, seq=newest.seq,
                        seen=time.perf_counter())
        if self.ack is None:
            self.add(ack)
        else:
            self.change(ack)
        self.ack = ack


@dataclass
class Measured:
    """Round trips of one team size."""

    consumers: int
    rtt_ms: dict[str, list[float]] = field(default_factory=dict)
    stages_ms: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    image_bytes: float = 0.0  # mean size of a compressed frame
    lost: dict[str, int] = field(default_factory=dict)


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, netns: bool = False,
        **_: Any) -> Result:
    """Measure the round trips for each number of consumers; return figure and table. `netns`: every
    agent in a network namespace of its own, one hop apart on the real-mesh tier's channel (the
    scenario's `radio.channel`: nftables rules passing every frame, or ns-3's 802.11a)."""
    s = scenario.strategy
    counts = [int(c) for c in s.get("consumers", [1, 2, 3, 4, 5])]
    per = int(s.get("count", 200))
    if not counts or min(counts) < 1 or max(counts) > 20:
        raise ScenarioError("strategy.consumers: expected numbers of consumers between 1 and 20")
    measured = []
    for k, n in enumerate(counts):
        tag = f"{n} consumer(s) ({k + 1}/{len(counts)})"

        def told(what: str, done: float, total: float, tag: str = tag) -> None:
            progress(f"{tag}: {what}", done, total)

        measured.append(_measure(scenario, n, per, told, netns=netns))
    return _result(scenario, experiment, mode, measured, per, tier=scenario.radio.channel if netns else "loopback")


def _wlan(scenario: Scenario, names: list[str], run_dir: Path) -> Any:
    """The real-mesh tier for the round trips: a namespace per agent, every pair one hop apart (the
    nftables channel passes every frame; on ns-3's channel the consumers stand on a circle of
    `strategy.netns_radius` m, default 3, around the robot). No routing daemon: one hop needs none."""
    from erni.sim.netns import Mesh, NetnsError
    from erni.sim.ns3_channel import reach

    channel = scenario.radio.channel
    mesh = Mesh(names, run_dir, channel=channel, range_m=reach(scenario.radio.comm_range), seed=scenario.seed)
    if channel == "ns3":  # the places are kept until the channel starts with the mesh
        radius = float(scenario.strategy.get("netns_radius", 3.0))
        step = 2 * math.pi / max(1, len(names) - 1)
        mesh.apply(positions={names[0]: (0.0, 0.0), **{n: (radius * math.cos(k * step), radius * math.sin(k * step))
                                                       for k, n in enumerate(names[1:])}})
    try:
        mesh.create()
    except NetnsError as err:
        raise ScenarioError(f"roundtrip --netns: {err}") from None
    mesh.apply({frozenset((a, b)): 1.0 for i, a in enumerate(names) for b in names[i + 1:]})  # nftables: every pair
    return mesh


def _configs(names: list[str], address: dict[str, str], common: dict[str, Any], robot_url: str,
             source: dict[str, Any]) -> dict[str, list[tuple[str, dict[str, Any]]]]:
    """The agents' plugins: the robot (transport, motion, SensorSource) and each consumer (transport,
    SensorSink), each listening on its own address."""
    configs: dict[str, list[tuple[str, dict[str, Any]]]] = {names[0]: [
        ("transport", {"listen": f"{address[names[0]]}:0", "role": "robot", **common,
                       "share": ["Pose", "NetInfo", "SensorReading"], "share_with": {"SensorReading": ["consumer"]}}),
        ("motion", {"url": robot_url}),
        ("erni.sim.experiments.roundtrip:SensorSource", source)]}
    for name in names[1:]:
        configs[name] = [("transport", {"listen": f"{address[name]}:0", "role": "consumer", **common,
                                        "share": ["SensorAck"], "share_with": {"SensorAck": ["robot"]}}),
                         ("erni.sim.experiments.roundtrip:SensorSink", {})]
    return configs


def _start_agent(mesh: Any, name: str, config: Path, log_path: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    """`erni agent CONFIG`, in node `name`'s namespace when there is a mesh."""
    argv = [sys.executable, "-m", "erni", "agent", str(config), "--log-level", "WARNING"]
    if mesh is not None:
        proc: subprocess.Popen[bytes] = mesh.popen(name, argv, log_path, env=env)
        return proc
    with open(log_path, "ab") as log:
        return subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def _measure(scenario: Scenario, consumers: int, count: int, progress: Progress, *, netns: bool = False) -> Measured:
    """Start the robot agent and `consumers` consumer agents; return the robot's measurements."""
    from erni.sim.robot import SimRobotConfig
    from erni.sim.robot_host import RobotHost
    from erni.sim.team import agent_toml, free_port
    from erni.sim.world import RobotStart, World

    s = scenario.strategy
    run_dir = Path(tempfile.mkdtemp(prefix="erni-roundtrip-"))
    out = run_dir / "roundtrips.json"
    key = secrets.token_hex(16)
    discovery = free_port()
    names = ["robot1", *(f"consumer{i + 1}" for i in range(consumers))]
    mesh = _wlan(scenario, names, run_dir) if netns else None
    address = {n: mesh.node(n).address if mesh is not None else f"127.0.1.{k + 1}" for k, n in enumerate(names)}
    common = {"discovery_port": discovery, "beacon_to": [mesh.broadcast if mesh is not None else "127.255.255.255"],
              "peer_timeout": 3.0, "beacon_period": 0.5}
    host = RobotHost(World(robot=[RobotStart(name="robot1")]), physics_hz=50.0,
                     host=mesh.service_address if mesh is not None else "127.0.0.1")
    host.add_robot(SimRobotConfig(name="robot1", seed=scenario.seed), port=0)
    host.start()
    source = {"consumers": consumers, "count": count, "warmup": int(s.get("warmup", 20)),
              "kinds": list(s.get("kinds", ["sensor", "image"])),
              "image_size": tuple(int(v) for v in s.get("image_size", [320, 240])),
              "jpeg_quality": int(s.get("jpeg_quality", 75)),
              "gap": float(s.get("gap", 0.03)), "timeout": float(s.get("timeout", 1.0)), "out": str(out)}
    configs = _configs(names, address, common, host.url(0), source)
    procs: list[subprocess.Popen[bytes]] = []
    env = {**os.environ, "ERNI_TEAM_KEY": key, "PYTHONUNBUFFERED": "1"}
    expected = (int(s.get("warmup", 20)) + count) * len(source["kinds"])  # type: ignore[arg-type]
    try:
        for name, plugins in configs.items():
            path = run_dir / f"{name}.toml"
            path.write_text(agent_toml(name, plugins, workers=2), encoding="utf-8")
            procs.append(_start_agent(mesh, name, path, run_dir / f"{name}.log", env))
        # the robot writes its measurements when it stops; give it the time the round trips need
        budget = 20.0 + expected * (float(s.get("gap", 0.03)) + 0.05)
        t0 = time.monotonic()
        while time.monotonic() - t0 < budget:
            if any(p.poll() is not None for p in procs):
                raise ScenarioError(f"an agent of the round-trip team exited early; logs in {run_dir}")
            progress("round trips", round(time.monotonic() - t0), round(budget))
            time.sleep(0.5)
            if out.exists():
                break
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        host.stop()
        if mesh is not None:
            mesh.destroy()
    if not out.exists():
        raise ScenarioError(f"the robot agent wrote no measurements; logs in {run_dir}")
    data = json.loads(out.read_text(encoding="utf-8"))
    shutil.rmtree(run_dir, ignore_errors=True)  # kept when the run failed: its error names the logs
    return Measured(consumers, rtt_ms={k: [float(x) for x in v] for k, v in data["rtt_ms"].items()},
                    stages_ms={k: {st: [float(x) for x in xs] for st, xs in v.items()}
                               for k, v in data["stages_ms"].items()},
                    lost={k: int(v) for k, v in data["lost"].items()},
                    image_bytes=float(data.get("image_bytes", 0.0)))


def _stats(xs: list[float]) -> tuple[float, float, float, float]:
    if not xs:
        return (np.nan, np.nan, np.nan, np.nan)
    a = np.array(xs)
    return float(a.mean()), float(np.median(a)), float(np.percentile(a, 95)), float(a.max())


TIERS = {"loopback": ("on loopback", "loopback UDP, ERNI transport"),
         "nftables": ("in a network namespace of its own, one hop apart on the real-mesh tier (a bridge whose rules "
                      "pass every frame)", "UDP through namespaces and a bridge, ERNI transport"),
         "ns3": ("in a network namespace of its own, one hop apart on ns-3's 802.11a channel (the consumers 3 m "
                 "around the robot)", "802.11a ad hoc in ns-3 (airtime, CSMA/CA, retries), ERNI transport")}


def _result(scenario: Scenario, experiment: Experiment, mode: str, measured: list[Measured], per: int,
            tier: str = "loopback") -> Result:
    res = Result(experiment.name, experiment.title if tier == "loopback" else
                 f"{experiment.title}, real-mesh tier, {tier} channel", mode)
    where, path = TIERS[tier]
    res.mode_note = (f"one robot agent and N consumer agents, each its own process {where}; readings and "
                     "acknowledgements are blackboard objects the transport shares (UDP, authenticated)")
    kinds = sorted({k for m in measured for k in m.rtt_ms}, key=lambda k: k != "sensor")
    for m in measured:
        for k in kinds:
            mean, med, p95, top = _stats(m.rtt_ms.get(k, []))
            res.metrics[f"{m.consumers} consumer(s), {k}: mean / median / p95"] = (
                f"{mean:.2f} / {med:.2f} / {p95:.2f}", "ms")
            stages = m.stages_ms.get(k, {})
            res.metrics[f"{m.consumers} consumer(s), {k}: median ms to " + " / ".join(STAGES) + " / last"] = (
                " / ".join(f"{float(np.median(stages[st])):.2f}" if stages.get(st) else "-" for st in STAGES)
                + f" / {med:.2f}", "ms")
            res.metrics[f"{m.consumers} consumer(s), {k}: lost (no answer within the timeout)"] = (
                float(m.lost.get(k, 0)), f"of {per}")
            res.series[f"{m.consumers}/{k}_rtt_ms"] = (list(range(len(m.rtt_ms.get(k, [])))), m.rtt_ms.get(k, []),
                                                         "ms")
    res.compare("data path", "WLAN, P2P overlay (JXTA)", path, "",
                "every agent a process on one 2-core machine", "input")
    res.compare("round trips averaged", "11000 per kind", f"{per} per kind and team size", "", "after "
                f"{int(scenario.strategy.get('warmup', 20))} discarded", "input")
    for m in measured:
        for k in kinds:
            mean = _stats(m.rtt_ms.get(k, []))[0]
            if k == "image":
                paper = PAPER_IMAGE.get(m.consumers)
                theirs = f"{paper[0]:g} / {paper[1]:g}" if paper else "not measured"
                w, h = (int(v) for v in scenario.strategy.get("image_size", [320, 240]))
                what = f"image ({w}x{h} JPEG, {m.image_bytes / 1000:.1f} kB, compressed when sent)"
            else:
                paper = PAPER_OTHER.get(m.consumers)
                theirs = f"{paper[0]:g}" if paper else "not measured"
                what = "other sensory data (pose, sonar, battery)"
            res.compare(f"{m.consumers} consumer(s): {what}", theirs, round(mean, 2), "ms",
                        "mean round trip: from making the reading on the robot (an image's compression "
                        "included; sensor data: the Pose with an obstacle's location and the temperature) to "
                        "the last acknowledgement seen there (paper: MCRLab / MIRaM)")
    big = max(measured, key=lambda m: m.consumers)
    for k in kinds:
        st = big.stages_ms.get(k, {})
        if all(st.get(name) for name in STAGES) and big.rtt_ms.get(k):
            first, last, back = (float(np.median(st[name])) for name in STAGES)
            res.compare(f"{big.consumers} consumer(s), {k}: where the time goes", "not stated",
                        f"{first:.2f} / {last:.2f} / {back:.2f} / {float(np.median(big.rtt_ms[k])):.2f}", "ms",
                        "median from the reading's making to: the first, the last consumer's plugin seeing it; "
                        "the first, the last acknowledgement back")
    res.notes.append("paper 002 measured 3, 4 and 5 consumers of image frames and 5 of other sensory data; "
                     "our 1 and 2 consumers are the baseline of the same path")
    res.notes.append("our round trip grows with the consumers where the paper's is flat: the robot sends to one "
                     "consumer after the other (about 0.15 ms each), and every consumer is a process needing "
                     "about 0.6 ms of CPU per reading on this one 2-core machine, where each of the paper's "
                     "SCPs had its own and a 67-91 ms WLAN round trip hid the rest")
    res.draw = lambda fig: _draw(fig, measured, kinds, "loopback" if tier == "loopback" else f"{tier} channel")
    return res


def _draw(fig: Any, measured: list[Measured], kinds: list[str], tier: str = "loopback") -> None:
    gs = fig.add_gridspec(1, 2, width_ratios=[1.2, 1])
    ax = fig.add_subplot(gs[0, 0])
    positions, data, labels, colours = [], [], [], []
    for i, m in enumerate(measured):
        for j, k in enumerate(kinds):
            positions.append(i * (len(kinds) + 1) + j)
            data.append(m.rtt_ms.get(k, []) or [np.nan])
            labels.append(f"{m.consumers}\n{k}")
            colours.append(color(j))
    parts = ax.boxplot(data, positions=positions, widths=0.7, showfliers=False, patch_artist=True)
    for patch, c in zip(parts["boxes"], colours):
        patch.set_facecolor(c)
        patch.set_alpha(0.45)
    ax.set_xticks(positions, labels, fontsize=8)
    ax.set_xlabel("consumers, and kind of data")
    ax.set_ylabel("round trip (ms)")
    ax.set_title("Our round trips\n(box: quartiles, whiskers: 1.5 IQR)", fontsize=10)
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    ax = fig.add_subplot(gs[0, 1])
    ns = [m.consumers for m in measured]
    for j, k in enumerate(kinds):
        ax.plot(ns, [_stats(m.rtt_ms.get(k, []))[0] for m in measured], "o-", color=color(j), label=f"ours: {k}")
    pn = sorted(PAPER_IMAGE)
    ax.plot(pn, [PAPER_IMAGE[n][0] for n in pn], "s--", color="#444444", label="paper: image (MCRLab)")
    ax.plot(pn, [PAPER_IMAGE[n][1] for n in pn], "^--", color="#888888", label="paper: image (MIRaM)")
    ax.plot([5], [PAPER_OTHER[5][0]], "D", color="#444444", mfc="white", label="paper: other sensory data")
    ax.set_yscale("log")
    counts = sorted(set(ns) | set(pn) | {5})
    ax.set_xticks(counts, [str(n) for n in counts])  # consumers come whole: a tick at each count drawn
    ax.set_xlim(min(counts) - 0.5, max(counts) + 0.5)
    ax.set_xlabel("consumers at once")
    ax.set_ylabel("mean round trip (ms, log scale)")
    ax.set_title(f"Mean round trip: ours ({tier})\nand paper 002 (WLAN)", fontsize=10)
    ax.grid(True, which="both", color="#e0e0e0", lw=0.6)
    ax.legend(fontsize=8)
    fig.suptitle("Paper 002, Table II: sensor data from one robot to several consumers, round trip", fontsize=13)
