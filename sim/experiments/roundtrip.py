"""Paper 002, Table II: round-trip delay of sensor data from one robot to 1, 3 and 5 consumers at once.

One robot agent (transport, motion on a simulated ARCOS robot, and `SensorSource`) publishes
a `SensorReading` on its blackboard: its latest Pose (odometry, battery, sonar) as "other
sensory data", or that plus a 16 kB frame as an "image". The transport shares it (UDP status)
with every peer in role "consumer"; each consumer agent (transport and `SensorSink`) answers by
changing its `SensorAck`, which its transport shares back. The round trip is timed by the
robot's plugin from just before it publishes the reading to the run of `execute()` that sees
the last consumer's acknowledgement: blackboard -> transport -> consumer's blackboard ->
consumer plugin -> ... and back, the path paper 002 times from the BP's SM layer to the SCPs'
application layer and back. A reading not acknowledged by all within `timeout` counts as lost.
Every agent is its own process on loopback (127.0.1.x), so the network part is loopback UDP,
not the paper's WLAN; the figure says so.
"""

from __future__ import annotations

import base64
import json
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
from pydantic import BaseModel, ConfigDict, Field

from erni.blackboard import BBObject, Plugin, Pose
from erni.blackboard.schemas import Peer
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.scenario import Scenario, ScenarioError

PAPER_IMAGE = {3: (89.2, 90.6), 4: (89.5, 89.1), 5: (91.3, 90.5)}  # ms: MCRLab, MIRaM
PAPER_OTHER = {5: (67.5, 67.5)}


class SensorReading(BBObject):
    """A robot's sensor data sent to its consumers: its pose (with sonar), optionally an image frame."""

    robot: str
    seq: int
    kind: str = "sensor"
    pose: Pose | None = None
    image: str = ""   # base64 frame ("image" readings)


class SensorAck(BBObject):
    """A consumer's acknowledgement of the newest reading it received."""

    consumer: str
    robot: str
    seq: int


try:
    from erni.transport.wire import register_type
except ImportError:  # pragma: no cover - the transport is part of the distribution
    pass
else:
    register_type(SensorReading)
    register_type(SensorAck)


class SourceSettings(BaseModel):
    """Settings of `SensorSource`."""

    model_config = ConfigDict(extra="forbid")

    consumers: int = Field(1, ge=1, description="acknowledgements a round trip waits for")
    count: int = Field(200, ge=1, description="round trips per kind")
    warmup: int = Field(20, ge=0, description="round trips discarded first")
    kinds: list[str] = Field(default_factory=lambda: ["sensor", "image"])
    image_bytes: int = Field(16000, ge=0, description="size of an image frame")
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
        self.frame = base64.b64encode(os.urandom(self.settings.image_bytes)).decode()
        self.seq = 0
        self.kind_index = 0
        self.done_in_kind = 0
        self.sent_at: float | None = None
        self.got: set[str] = set()
        self.next_at = 0.0
        self.ready_since: float | None = None
        self.published = False
        self.rtts: dict[str, list[float]] = {k: [] for k in self.settings.kinds}
        self.lost: dict[str, int] = {k: 0 for k in self.settings.kinds}
        self.wake_every(0.25)

    def execute(self) -> None:
        now = time.perf_counter()
        s = self.settings
        for ack in self.acks.added + self.acks.changed:
            if self.sent_at is not None and ack.seq == self.seq and ack.robot == self.agent_name:
                self.got.add(ack.consumer)
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
        pose = next(iter(self.poses), None)
        reading = SensorReading(uid=f"reading:{self.agent_name}", robot=self.agent_name, seq=self.seq, kind=kind,
                                pose=pose, image=self.frame if kind == "image" else "")
        self.got = set()
        if self.published:
            self.change(reading)
        else:
            self.add(reading)
            self.published = True
        self.sent_at = time.perf_counter()
        self.wake_in(self.settings.timeout + 0.01)

    def _record(self, rtt: float | None) -> None:
        s = self.settings
        kind = s.kinds[self.kind_index]
        self.sent_at = None
        self.done_in_kind += 1
        if self.done_in_kind > s.warmup:
            if rtt is None:
                self.lost[kind] += 1
            else:
                self.rtts[kind].append(rtt * 1000.0)
        if self.done_in_kind >= s.warmup + s.count:
            self.kind_index += 1
            self.done_in_kind = 0
            if self.kind_index >= len(s.kinds):  # all measured: write them now (on a thread, not in here)
                threading.Thread(target=self._write, args=(True,), daemon=True).start()
        self.next_at = time.perf_counter() + self.rng.uniform(0.5, 1.5) * s.gap
        self.wake_in(max(0.001, self.next_at - time.perf_counter()))

    def _write(self, complete: bool) -> None:
        data = {"rtt_ms": self.rtts, "lost": self.lost, "consumers": self.settings.consumers, "complete": complete}
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
        ack = SensorAck(uid=f"ack:{self.agent_name}", consumer=self.agent_name, robot=newest.robot, seq=newest.seq)
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
    lost: dict[str, int] = field(default_factory=dict)


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, **_: Any) -> Result:
    """Measure the round trips for each number of consumers; return figure and table."""
    s = scenario.strategy
    counts = [int(c) for c in s.get("consumers", [1, 3, 5])]
    per = int(s.get("count", 200))
    if not counts or min(counts) < 1 or max(counts) > 20:
        raise ScenarioError("strategy.consumers: expected numbers of consumers between 1 and 20")
    measured = []
    for k, n in enumerate(counts):
        tag = f"{n} consumer(s) ({k + 1}/{len(counts)})"

        def told(what: str, done: float, total: float, tag: str = tag) -> None:
            progress(f"{tag}: {what}", done, total)

        measured.append(_measure(scenario, n, per, told))
    return _result(scenario, experiment, mode, measured, per)


def _measure(scenario: Scenario, consumers: int, count: int, progress: Progress) -> Measured:
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
    common = {"discovery_port": discovery, "beacon_to": ["127.255.255.255"], "peer_timeout": 3.0,
              "beacon_period": 0.5}
    host = RobotHost(World(robot=[RobotStart(name="robot1")]), physics_hz=50.0)
    host.add_robot(SimRobotConfig(name="robot1", seed=scenario.seed), port=0)
    host.start()
    source = {"consumers": consumers, "count": count, "warmup": int(s.get("warmup", 20)),
              "kinds": list(s.get("kinds", ["sensor", "image"])), "image_bytes": int(s.get("image_bytes", 16000)),
              "gap": float(s.get("gap", 0.03)), "timeout": float(s.get("timeout", 1.0)), "out": str(out)}
    configs: dict[str, list[tuple[str, dict[str, Any]]]] = {"robot1": [("transport", {"listen": "127.0.1.1:0", "role": "robot", **common,
                                         "share": ["Pose", "NetInfo", "SensorReading"],
                                         "share_with": {"SensorReading": ["consumer"]}}),
                          ("motion", {"url": host.url(0)}),
                          ("erni.sim.experiments.roundtrip:SensorSource", source)]}
    for i in range(consumers):
        configs[f"consumer{i + 1}"] = [("transport", {"listen": f"127.0.1.{i + 2}:0", "role": "consumer", **common,
                                                      "share": ["SensorAck"], "share_with": {"SensorAck": ["robot"]}}),
                                       ("erni.sim.experiments.roundtrip:SensorSink", {})]
    procs: list[subprocess.Popen[bytes]] = []
    env = {**os.environ, "ERNI_TEAM_KEY": key, "PYTHONUNBUFFERED": "1"}
    expected = (int(s.get("warmup", 20)) + count) * len(source["kinds"])  # type: ignore[arg-type]
    try:
        for name, plugins in configs.items():
            path = run_dir / f"{name}.toml"
            path.write_text(agent_toml(name, plugins, workers=2), encoding="utf-8")
            with open(run_dir / f"{name}.log", "ab") as log:
                procs.append(subprocess.Popen([sys.executable, "-m", "erni", "agent", str(path), "--log-level",
                                               "WARNING"], stdout=log, stderr=subprocess.STDOUT, env=env,
                                              start_new_session=True))
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
    if not out.exists():
        raise ScenarioError(f"the robot agent wrote no measurements; logs in {run_dir}")
    data = json.loads(out.read_text(encoding="utf-8"))
    shutil.rmtree(run_dir, ignore_errors=True)  # kept when the run failed: its error names the logs
    return Measured(consumers, {k: [float(x) for x in v] for k, v in data["rtt_ms"].items()},
                    {k: int(v) for k, v in data["lost"].items()})


def _stats(xs: list[float]) -> tuple[float, float, float, float]:
    if not xs:
        return (np.nan, np.nan, np.nan, np.nan)
    a = np.array(xs)
    return float(a.mean()), float(np.median(a)), float(np.percentile(a, 95)), float(a.max())


def _result(scenario: Scenario, experiment: Experiment, mode: str, measured: list[Measured], per: int) -> Result:
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = ("one robot agent and N consumer agents, each its own process on loopback; readings and "
                     "acknowledgements are blackboard objects the transport shares (UDP, authenticated)")
    kinds = sorted({k for m in measured for k in m.rtt_ms}, key=lambda k: k != "sensor")
    for m in measured:
        for k in kinds:
            mean, med, p95, top = _stats(m.rtt_ms.get(k, []))
            res.metrics[f"{m.consumers} consumer(s), {k}: mean / median / p95"] = (
                f"{mean:.2f} / {med:.2f} / {p95:.2f}", "ms")
            res.metrics[f"{m.consumers} consumer(s), {k}: lost (no answer within the timeout)"] = (
                float(m.lost.get(k, 0)), f"of {per}")
            res.series[f"{m.consumers}/{k}_rtt_ms"] = (list(range(len(m.rtt_ms.get(k, [])))), m.rtt_ms.get(k, []),
                                                         "ms")
    res.compare("data path", "WLAN, P2P overlay (JXTA)", "loopback UDP, ERNI transport", "",
                "every agent a process on one 2-core machine", "input")
    res.compare("round trips averaged", "11000 per kind", f"{per} per kind and team size", "", "after "
                f"{int(scenario.strategy.get('warmup', 20))} discarded", "input")
    for m in measured:
        for k in kinds:
            mean = _stats(m.rtt_ms.get(k, []))[0]
            if k == "image":
                paper = PAPER_IMAGE.get(m.consumers)
                theirs = f"{paper[0]:g} / {paper[1]:g}" if paper else "not measured"
                what = f"image ({int(scenario.strategy.get('image_bytes', 16000)) // 1000} kB frame + pose)"
            else:
                paper = PAPER_OTHER.get(m.consumers)
                theirs = f"{paper[0]:g}" if paper else "not measured"
                what = "other sensory data (pose, sonar, battery)"
            res.compare(f"{m.consumers} consumer(s): {what}", theirs, round(mean, 2), "ms",
                        "mean round trip: publish on the robot's blackboard to the last acknowledgement seen "
                        "there (paper: MCRLab / MIRaM)")
    res.notes.append("paper 002 measured 3, 4 and 5 consumers of image frames and 5 of other sensory data; "
                     "our 1 consumer is the baseline of the same path")
    res.draw = lambda fig: _draw(fig, measured, kinds)
    return res


def _draw(fig: Any, measured: list[Measured], kinds: list[str]) -> None:
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
    ax.set_title("Mean round trip: ours (loopback)\nand paper 002 (WLAN)", fontsize=10)
    ax.grid(True, which="both", color="#e0e0e0", lw=0.6)
    ax.legend(fontsize=8)
    fig.suptitle("Paper 002, Table II: sensor data from one robot to several consumers, round trip", fontsize=13)
