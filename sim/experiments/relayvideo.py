"""Paper 000, section 5.2 and Figure 6: a video stream from S to D through one relay, its delay and
loss against where the relay stands.

Loopback tier, a first cut: S, the relay R and D are three transport endpoints of ERNI in one
process (loopback UDP, sealed sessions, the team key). S sends a video-like stream: `fps`
camera frames a second (a synthetic scene with sensor noise, compressed to JPEG), each frame
cut into datagrams of at most `packet` bytes, as fast messages; R forwards each datagram to D
as it comes. For each position of R along S-D, every hop drops datagrams with the probability
the simulated radio gives its length (1 - delivery ratio: the same model that relay1 and
relay2 measure link quality with), through the endpoint's own loss injection. So the loss is
the radio model's, realised packet by packet: an input of the simulation, not a finding; the
delay is measured (S's send to D's receipt, one clock), but on loopback it holds no radio,
no MAC retransmissions and no queueing on air, so it cannot show what a WLAN adds. The real
mesh tier (namespaces, babeld) would measure both; this experiment does not run there yet.
"""

from __future__ import annotations

import base64
import math
import secrets
import threading
import time
from typing import Any

import numpy as np

from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.experiments.relay import ends
from erni.sim.experiments.roundtrip import camera_frames, compress
from erni.sim.manet import RadioModel
from erni.sim.scenario import Scenario, ScenarioError


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, **_: Any) -> Result:
    """Stream through the relay at each position; return figure and table."""
    from erni.transport import Endpoint

    s = scenario.strategy
    src, dst = ends(scenario, "relay-video")
    length = float(np.hypot(*(dst - src)))
    radio = RadioModel(scenario.radio.comm_range, scenario.radio.lossless_range, scenario.radio.min_quality)
    positions = [float(x) for x in s.get("positions", list(np.arange(1.0, length, 1.0)))]
    fps = float(s.get("fps", 25.0))
    seconds = float(s.get("seconds", 2.0))
    packet = int(s.get("packet", 1400))
    width, height = (int(v) for v in s.get("image_size", [320, 240]))
    quality = int(s.get("jpeg_quality", 75))
    if not positions or min(positions) <= 0 or max(positions) >= length:
        raise ScenarioError(f"strategy.positions: expected distances from the source inside (0, {length:g}) m")
    jpegs = [compress(f, quality) for f in camera_frames(width, height, seed=scenario.seed)]
    key = secrets.token_bytes(32)
    s_end = Endpoint("source", key=key, role="robot", seed=scenario.seed)
    r_end = Endpoint("relay", key=key, role="robot", seed=scenario.seed + 1)
    d_end = Endpoint("destination", key=key, role="robot", seed=scenario.seed + 2)
    lock = threading.Lock()
    arrived: dict[tuple[int, int], float] = {}  # (frame, packet) -> receipt time at D

    def forward(msg: Any) -> None:
        if msg.kind == "video":
            r_end.send(d_end.address, "video", msg.body, reliable=False, to="destination")

    def receive(msg: Any) -> None:
        if msg.kind == "video":
            now = time.perf_counter()
            with lock:
                arrived[(int(msg.body["frame"]), int(msg.body["packet"]))] = now

    r_end.on_message = forward
    d_end.on_message = receive
    rows: list[dict[str, float]] = []
    delays: dict[float, list[float]] = {}
    try:
        for e in (s_end, r_end, d_end):
            e.start()
        _warm_up(s_end, r_end, d_end, arrived, lock)
        frame_no = 1_000_000  # the warm-up's frames are below
        for k, x in enumerate(positions):
            q1, q2 = radio.quality(x), radio.quality(length - x)
            s_end.udp_loss, r_end.udp_loss = 1.0 - q1, 1.0 - q2
            sent: dict[tuple[int, int], float] = {}
            frames = max(1, int(round(fps * seconds)))
            t_next = time.perf_counter()
            first = frame_no
            for f in range(frames):
                data = jpegs[f % len(jpegs)]
                parts = [data[i:i + packet] for i in range(0, len(data), packet)]
                for p, part in enumerate(parts):
                    body = {"frame": frame_no, "packet": p, "of": len(parts), "t": time.perf_counter(),
                            "data": base64.b64encode(part).decode()}
                    sent[(frame_no, p)] = body["t"]  # type: ignore[assignment]
                    s_end.send(r_end.address, "video", body, reliable=False, to="relay")
                frame_no += 1
                t_next += 1.0 / fps
                time.sleep(max(0.0, t_next - time.perf_counter()))
            time.sleep(0.2)  # the last datagrams through
            with lock:
                got = {key_: at for key_, at in arrived.items() if first <= key_[0] < frame_no}
            d = [1000.0 * (got[key_] - t0) for key_, t0 in sent.items() if key_ in got]
            whole = sum(1 for fr in range(first, frame_no)
                        if all((fr, p) in got for p in range(_parts(sent, fr))))
            delays[x] = d
            rows.append({"x": x, "q1": q1, "q2": q2, "packets": float(len(sent)), "packet_loss": 1 - len(d) / len(sent),
                         "frame_loss": 1 - whole / (frame_no - first), "model_loss": 1 - q1 * q2,
                         "delay_median": float(np.median(d)) if d else math.nan,
                         "delay_p95": float(np.percentile(d, 95)) if d else math.nan})
            progress("relay positions", k + 1, len(positions))
    finally:
        for e in (s_end, r_end, d_end):
            e.stop()
    return _result(scenario, experiment, mode, rows, delays, length, fps, packet, len(jpegs[0]))


def _parts(sent: dict[tuple[int, int], float], frame: int) -> int:
    return sum(1 for (f, _) in sent if f == frame)


def _warm_up(s_end: Any, r_end: Any, d_end: Any, arrived: dict[tuple[int, int], float], lock: threading.Lock) -> None:
    """Sessions up on both hops before anything is dropped: until a datagram goes S -> R -> D."""
    end = time.monotonic() + 10.0
    n = 0
    while time.monotonic() < end:
        s_end.send(r_end.address, "video", {"frame": n, "packet": 0, "of": 1, "t": 0.0, "data": ""},
                   reliable=False, to="relay")
        time.sleep(0.05)
        with lock:
            if any(f < 1_000_000 for f, _ in arrived):
                return
        n += 1
    raise ScenarioError("relay-video: no datagram went from the source through the relay within 10 s")


def _result(scenario: Scenario, experiment: Experiment, mode: str, rows: list[dict[str, float]],
            delays: dict[float, list[float]], length: float, fps: float, packet: int, frame_bytes: int) -> Result:
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = ("loopback tier, a first cut: three transport endpoints in one process; each hop drops "
                     "datagrams with the simulated radio's loss (an input); the delay holds no radio")
    xs = [r["x"] for r in rows]
    for q in ("packet_loss", "frame_loss", "model_loss", "delay_median", "delay_p95"):
        res.series[f"relay/{q}"] = (xs, [r[q] for r in rows], "ms" if q.startswith("delay") else "share")
    best = min(rows, key=lambda r: r["packet_loss"])
    res.metrics["source-destination distance"] = (length, "m")
    res.metrics["relay position with the least packet loss"] = (best["x"], "m from the source")
    res.metrics["least packet loss"] = (best["packet_loss"], "share")
    res.compare("stream", "video, S -> relay -> D (WLAN)", f"{fps:g} JPEG frames/s of {frame_bytes / 1000:.1f} kB, "
                f"datagrams of <= {packet} B", "", "synthetic camera frames through ERNI's transport", "input")
    res.compare("loss of a hop", "measured on the WLAN", "1 - delivery ratio of the radio model", "",
                f"lossless to {scenario.radio.lossless_range:g} m, none beyond {scenario.radio.comm_range:g} m; "
                "drawn per datagram", "input")
    res.compare("lowest loss where", "the middle (section 5.2, Fig. 7: 'exactly the middle region')",
                f"{best['x']:g} m of {length:g} m", "m", "follows from the radio model (an input): the product of "
                "two hops' delivery ratios is largest where they are equal", "input")
    med = [r["delay_median"] for r in rows if math.isfinite(r["delay_median"])]
    res.compare("delay against the relay's position", "not stated as numbers",
                f"median {min(med):.2f}-{max(med):.2f} ms" if med else "-", "ms",
                "S's send to D's receipt, per datagram; loopback: no radio, no retransmission, so flat")
    res.notes.append("a first cut on the loopback tier: the loss is the radio model's, realised per datagram; the "
                     "paper's WLAN delay and loss need the real-mesh tier")
    res.draw = lambda fig: _draw(fig, rows, delays, length)
    return res


def _draw(fig: Any, rows: list[dict[str, float]], delays: dict[float, list[float]], length: float) -> None:
    gs = fig.add_gridspec(1, 2)
    xs = [r["x"] for r in rows]
    ax = fig.add_subplot(gs[0, 0])
    ax.set_xticks(range(0, int(length) + 1, 2))
    ax.plot(xs, [100 * r["packet_loss"] for r in rows], "o-", color=color(0), label="datagrams lost (measured)")
    ax.plot(xs, [100 * r["frame_loss"] for r in rows], "s-", color=color(1), label="frames with a datagram lost")
    ax.plot(xs, [100 * r["model_loss"] for r in rows], ":", color="#444444", label="radio model: 1 - q1 q2 (input)")
    ax.set_xlim(0, length)
    ax.set_ylim(-2, 102)
    ax.set_xlabel("relay's distance from the source (m)")
    ax.set_ylabel("loss (%)")
    ax.set_title("Loss against the relay's position", fontsize=10)
    ax.grid(True, color="#e0e0e0", lw=0.6)
    ax.legend(fontsize=8, loc="lower center")
    ax = fig.add_subplot(gs[0, 1])
    kept = [x for x in xs if delays.get(x)]
    if kept:
        ax.boxplot([delays[x] for x in kept], positions=kept, widths=0.5, showfliers=False, manage_ticks=False)
    ax.set_xlim(0, length)
    ax.set_xticks(range(0, int(length) + 1, 2))
    ax.set_xlabel("relay's distance from the source (m)")
    ax.set_ylabel("delay S -> D (ms)")
    ax.set_title("Delay of the datagrams that arrived (loopback: no radio)\n(box: quartiles; none arrive "
                 "where a hop is out of range)", fontsize=10)
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    fig.suptitle("Paper 000, Figure 6: video through one relay, loss and delay against its position "
                 "(loopback tier, first cut)", fontsize=12)
