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
no MAC retransmissions and no queueing on air, so it cannot show what a WLAN adds.

Real-mesh tier (`--netns`): S, R and D are three network namespaces on one bridge segment
(`erni.sim.netns.Mesh`), babeld runs in each, and the radio model's loss is the kernel's: nftables
rules on the bridge drop each frame of a link with 1 - its delivery ratio (rounded to 5 %), babeld's
Hellos and updates as much as the video. S and D cannot hear each other (16 m > 12 m), so the
stream goes S -> D as plain UDP datagrams (frame, part, send time and the JPEG bytes; no ERNI
envelope) and R forwards them in its kernel, along the route babeld installed. The loss of a
datagram is then the kernel's drop on each hop plus whatever routing adds (no route while babeld
has lost the relay: sends refused at S), and the delay is the kernel's forwarding through R's
namespace (veth, bridge, IP forwarding; still no radio airtime or MAC retransmission).
"""

from __future__ import annotations

import base64
import ctypes
import math
import os
import secrets
import shutil
import socket
import struct
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.experiments.relay import ends
from erni.sim.experiments.roundtrip import camera_frames, compress
from erni.sim.manet import RadioModel
from erni.sim.scenario import Scenario, ScenarioError

HEADER = struct.Struct("!IIId")  # frame, part, parts of the frame, send time (perf_counter, s)
PORT = 47100                    # the destination's port on the mesh (netns tier)
CLONE_NEWNET = 0x40000000


def _positions(s: dict[str, Any], length: float) -> list[float]:
    """The relay's positions (m from the source): `strategy.positions`, else every metre; each strictly
    between the ends (ScenarioError)."""
    positions = [float(x) for x in s.get("positions", list(np.arange(1.0, length, 1.0)))]
    if not positions or min(positions) <= 0 or max(positions) >= length:
        raise ScenarioError(f"strategy.positions: expected distances from the source inside (0, {length:g}) m")
    return positions


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, netns: bool = False,
        **_: Any) -> Result:
    """Stream through the relay at each position; return figure and table."""
    from erni.transport import Endpoint

    s = scenario.strategy
    src, dst = ends(scenario, "relay-video")
    length = float(np.hypot(*(dst - src)))
    radio = RadioModel(scenario.radio.comm_range, scenario.radio.lossless_range, scenario.radio.min_quality)
    positions = _positions(s, length)
    fps = float(s.get("fps", 25.0))
    seconds = float(s.get("seconds", 2.0))
    packet = int(s.get("packet", 1400))
    width, height = (int(v) for v in s.get("image_size", [320, 240]))
    quality = int(s.get("jpeg_quality", 75))
    jpegs = [compress(f, quality) for f in camera_frames(width, height, seed=scenario.seed)]
    if netns:
        settle = float(s.get("netns_settle", 2.0))
        route_wait = float(s.get("netns_route_wait", 10.0))
        pinned = bool(s.get("netns_static_arp", True))
        channel = scenario.radio.channel
        on_mesh = _stream_netns(positions, length, radio, jpegs, fps, seconds, packet, settle, route_wait, pinned,
                                progress, channel)
        return _result(scenario, experiment, mode, *on_mesh, length, fps, packet, len(jpegs[0]),
                       tier="netns" if channel == "nftables" else "ns3")
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


def _setns(name: str) -> None:
    """Move the calling thread into network namespace `name` (`ip netns` names it /run/netns/NAME)."""
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    fd = os.open(f"/run/netns/{name}", os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            from erni.sim.netns import NetnsError

            raise NetnsError(f"setns into network namespace {name}: {os.strerror(ctypes.get_errno())}")
    finally:
        os.close(fd)


def _udp_in(netns_name: str, bind: tuple[str, int]) -> socket.socket:
    """A UDP socket of namespace `netns_name` bound to `bind` (made by a thread that enters it and ends;
    the socket stays in that namespace whichever thread uses it)."""
    made: list[socket.socket | BaseException] = []

    def make() -> None:
        try:
            _setns(netns_name)
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(bind)
            made.append(sock)
        except BaseException as err:  # handed to the caller
            made.append(err)

    t = threading.Thread(target=make, name=f"netns-{netns_name}")
    t.start()
    t.join()
    if isinstance(made[0], BaseException):
        raise made[0]
    return made[0]


def _pin_neighbours(mesh: Any) -> None:
    """Static ARP entries on every node's mesh link for every other node."""
    import json
    import subprocess

    def ip(*args: str) -> str:
        return subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=10).stdout

    nodes = list(mesh.nodes.values())
    macs = {n.name: json.loads(ip("-n", n.netns, "-j", "link", "show", "mesh0"))[0]["address"] for n in nodes}
    for a in nodes:
        for b in nodes:
            if a is not b:
                ip("-n", a.netns, "neigh", "replace", b.address, "lladdr", macs[b.name], "dev", "mesh0",
                   "nud", "permanent")


def _via(mesh: Any, a: str, b: str) -> bool:
    """Node a's kernel routes b's mesh address through the relay (babeld's route)."""
    prefix = f"{mesh.node(b).address} via {mesh.node('relay').address}"
    return any(line.startswith(prefix) for line in mesh.kernel_routes(a))


def _await_relay_routes(mesh: Any) -> None:
    """Wait until babeld routes S -> D and D -> S through the relay (ScenarioError after 30 s)."""
    end = time.monotonic() + 30.0
    while not (_via(mesh, "source", "destination") and _via(mesh, "destination", "source")):
        if time.monotonic() > end:
            raise ScenarioError("relay-video --netns: babeld did not route S -> D through the relay within 30 s")
        time.sleep(0.2)


def _route_after(mesh: Any, settle: float, route_wait: float) -> float:
    """After the links changed (now): wait `settle` s, and up to `route_wait` s more until babeld routes
    S -> D through the relay; the seconds that took (NaN: no such route by then)."""
    changed = time.monotonic()
    time.sleep(settle)  # babeld sees the new links (Hellos every 0.5 s)
    while not (routed_before := _via(mesh, "source", "destination")) and \
            time.monotonic() - changed < settle + route_wait:
        time.sleep(0.2)
    return time.monotonic() - changed if routed_before else math.nan


def _stream_netns(positions: list[float], length: float, radio: RadioModel, jpegs: list[bytes], fps: float,
                  seconds: float, packet: int, settle: float, route_wait: float, pinned: bool,
                  progress: Progress, channel: str = "nftables") -> tuple[list[dict[str, float]], dict[float, list[float]]]:
    """The stream on the real-mesh tier: S -> D as UDP, forwarded by R's kernel on babeld's route; each
    hop's loss the kernel's radio rules'. At each position the stream starts `settle` s after the links
    change, or once babeld routes S -> D through R if that takes longer (at most `route_wait` s more).
    Rows as the loopback tier's, with the kernel's counts and the routing beside. `pinned`: each node
    knows the others' link addresses (static ARP entries), as a WLAN's MAC retries would let ARP
    succeed; without them ARP itself crosses the lossy link, frame by frame with no retry below it.
    `channel` "ns3": ns-3's 802.11a channel carries the frames instead, S, R and D placed on a line at
    their distances, so each hop's loss, the MAC's retries and the airtime are ns-3's (measured)."""
    from erni.sim.netns import Mesh, NetnsError
    from erni.sim.ns3_channel import reach

    run_dir = Path(tempfile.mkdtemp(prefix="erni-relay-video-"))
    mesh = Mesh(["source", "relay", "destination"], run_dir, channel=channel, range_m=reach(radio.comm_range))
    on_air = channel == "ns3"
    try:
        mesh.create()
    except NetnsError as err:
        shutil.rmtree(run_dir, ignore_errors=True)
        raise ScenarioError(f"relay-video --netns: {err}") from None
    sr, rd = frozenset(("source", "relay")), frozenset(("relay", "destination"))
    stop = threading.Event()
    lock = threading.Lock()
    arrived: dict[tuple[int, int], float] = {}
    rows: list[dict[str, float]] = []
    delays: dict[float, list[float]] = {}
    socks: list[socket.socket] = []
    try:
        # S and D out of each other's range: no link between them (no rule; on ns-3, 16 m apart)
        mesh.apply({sr: 1.0, rd: 1.0}, {"source": (0.0, 0.0), "relay": (length / 2, 0.0),
                                        "destination": (length, 0.0)} if on_air else None)
        if pinned:
            _pin_neighbours(mesh)
        mesh.start_babel()
        _await_relay_routes(mesh)
        dst = (mesh.node("destination").address, PORT)
        rx = _udp_in(mesh.node("destination").netns, ("0.0.0.0", PORT))
        tx = _udp_in(mesh.node("source").netns, ("0.0.0.0", 0))
        socks += [rx, tx]
        rx.settimeout(0.2)

        def receive() -> None:
            while not stop.is_set():
                try:
                    data = rx.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    return
                now = time.perf_counter()
                if len(data) >= HEADER.size:
                    frame, part, _, _ = HEADER.unpack_from(data)
                    with lock:
                        arrived[(frame, part)] = now

        receiver = threading.Thread(target=receive, name="relay-video-destination", daemon=True)
        receiver.start()
        frame_no = 0
        for k, x in enumerate(positions):
            q1, q2 = radio.quality(x), radio.quality(length - x)
            links = {sr: q1, rd: q2}
            mesh.apply(links, {"relay": (x, 0.0)} if on_air else None)  # the rules (counters from 0), or the move
            mac_before = _mac(mesh)
            route_after = _route_after(mesh, settle, route_wait)
            routed_before = not math.isnan(route_after)
            sent: dict[tuple[int, int], float] = {}
            refused = 0
            first = frame_no
            t_next = time.perf_counter()
            for f in range(max(1, int(round(fps * seconds)))):
                data = jpegs[f % len(jpegs)]
                parts = [data[i:i + packet] for i in range(0, len(data), packet)]
                for p, part in enumerate(parts):
                    t0 = time.perf_counter()
                    sent[(frame_no, p)] = t0
                    try:
                        tx.sendto(HEADER.pack(frame_no, p, len(parts), t0) + part, dst)
                    except OSError:  # no route: babeld has lost the relay
                        refused += 1
                frame_no += 1
                t_next += 1.0 / fps
                time.sleep(max(0.0, t_next - time.perf_counter()))
            time.sleep(0.3)  # the last datagrams through
            routed_after = _via(mesh, "source", "destination")
            counts = {} if on_air else mesh.counters()
            with lock:
                got = {key_: at for key_, at in arrived.items() if first <= key_[0] < frame_no}
            d = [1000.0 * (got[key_] - t0) for key_, t0 in sent.items() if key_ in got]
            whole = sum(1 for fr in range(first, frame_no) if all((fr, p) in got for p in range(_parts(sent, fr))))
            applied = [q1, q2] if on_air else [1.0 - mesh.loss(links, "source", "relay"),
                                               1.0 - mesh.loss(links, "relay", "destination")]

            delays[x] = d
            rows.append({"x": x, "q1": q1, "q2": q2, "packets": float(len(sent)),
                         "packet_loss": 1 - len(d) / len(sent), "frame_loss": 1 - whole / (frame_no - first),
                         "model_loss": 1 - applied[0] * applied[1], "refused": refused / len(sent),
                         "kernel_loss_sr": math.nan if on_air else _kernel_loss(counts, "source", "relay"),
                         "kernel_loss_rd": math.nan if on_air else _kernel_loss(counts, "relay", "destination"),
                         **_mac_shares(mac_before, _mac(mesh)),
                         "routed": float(routed_before and routed_after), "route_after": route_after,
                         "delay_median": float(np.median(d)) if d else math.nan,
                         "delay_p95": float(np.percentile(d, 95)) if d else math.nan})
            progress("relay positions (netns)", k + 1, len(positions))
    finally:
        stop.set()
        for sock in socks:
            sock.close()
        mesh.destroy()
        shutil.rmtree(run_dir, ignore_errors=True)
    return rows, delays


def _mac(mesh: Any) -> tuple[int, int, int, int]:
    """The ns-3 channel's MAC counts so far (frames handed to it, dropped: queue full, expired, retries
    out), or zeros on the nftables channel."""
    m = mesh.ns3.mac if mesh.ns3 is not None else None
    return (m.sent, m.queue_full, m.expired, m.retry_limit) if m is not None else (0, 0, 0, 0)


def _mac_shares(before: tuple[int, int, int, int], after: tuple[int, int, int, int]) -> dict[str, float]:
    """The frames the ns-3 MACs dropped at one position, as shares of the frames handed to them there
    (NaN without the ns-3 channel)."""
    sent = after[0] - before[0]
    names = ("mac_queue_full", "mac_expired", "mac_retry_limit")
    return {n: (after[i + 1] - before[i + 1]) / sent if sent else math.nan for i, n in enumerate(names)}


def _kernel_loss(counts: dict[tuple[str, str], tuple[int, int]], a: str, b: str) -> float:
    """The share of a -> b frames the kernel's radio rules dropped (1: no rule passes any, out of range)."""
    dropped, passed = counts.get((a, b), (0, 0))
    return dropped / (dropped + passed) if dropped + passed else 1.0


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
            delays: dict[float, list[float]], length: float, fps: float, packet: int, frame_bytes: int,
            tier: str = "loopback") -> Result:
    if tier == "ns3":
        return _result_ns3(scenario, experiment, mode, rows, delays, length, fps, packet, frame_bytes)
    if tier == "netns":
        return _result_netns(scenario, experiment, mode, rows, delays, length, fps, packet, frame_bytes)
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


def _mesh_rows(res: Result, rows: list[dict[str, float]], extra: tuple[str, ...], length: float, fps: float,
               packet: int, frame_bytes: int) -> dict[str, float]:
    """What both channels of the real-mesh tier report: the series (the common ones and `extra`), the
    least loss and where, the positions babeld routed, and the stream; returns the row of least loss."""
    xs = [r["x"] for r in rows]
    for q in ("packet_loss", "frame_loss", "model_loss", "refused", *extra, "routed", "route_after",
              "delay_median", "delay_p95"):
        unit = "ms" if q.startswith("delay") else "s" if q == "route_after" else "share"
        res.series[f"relay/{q}"] = (xs, [r[q] for r in rows], unit)
    best = min(rows, key=lambda r: r["packet_loss"])
    res.metrics["source-destination distance"] = (length, "m")
    res.metrics["relay position with the least packet loss"] = (best["x"], "m from the source")
    res.metrics["least packet loss"] = (best["packet_loss"], "share")
    res.metrics["positions where babeld's route through the relay held from the stream's start to its end"] = (
        ", ".join(f"{r['x']:g}" for r in rows if r["routed"]) or "none", "m from the source")
    res.compare("stream", "video, S -> relay -> D (WLAN)", f"{fps:g} JPEG frames/s of {frame_bytes / 1000:.1f} kB, "
                f"UDP datagrams of <= {packet} B of frame", "", "synthetic camera frames, plain UDP (no ERNI "
                "envelope); R forwards in its kernel on babeld's route", "input")
    return best


def _result_netns(scenario: Scenario, experiment: Experiment, mode: str, rows: list[dict[str, float]],
                  delays: dict[float, list[float]], length: float, fps: float, packet: int,
                  frame_bytes: int) -> Result:
    res = Result(experiment.name, f"{experiment.title}, real-mesh tier", mode)
    res.mode_note = ("real-mesh tier: S, R, D in network namespaces on one bridge, babeld routing S -> D through "
                     "R's kernel; each link's frames dropped by nftables with the radio model's loss (an input); "
                     "the delay is the kernel's forwarding, no radio airtime")
    best = _mesh_rows(res, rows, ("kernel_loss_sr", "kernel_loss_rd"), length, fps, packet, frame_bytes)
    res.compare("loss of a hop", "measured on the WLAN", "1 - delivery ratio of the radio model, per frame, "
                "in the kernel (nftables on the bridge, rounded to 5 %)", "",
                f"lossless to {scenario.radio.lossless_range:g} m, none beyond {scenario.radio.comm_range:g} m; "
                "babeld's own packets lose as much", "input")
    res.compare("lowest loss where", "the middle (section 5.2, Fig. 7: 'exactly the middle region')",
                f"{best['x']:g} m of {length:g} m", "m", "datagrams S -> D that arrived, per position: the "
                "kernel's drop on both hops and routing (no route: sends refused)")
    excess = [r["packet_loss"] - r["model_loss"] for r in rows if r["model_loss"] < 1.0]
    res.compare("loss beyond the two hops' drop", "-", f"{min(excess):+.2f} to {max(excess):+.2f}" if excess
                else "-", "share", "measured loss - (1 - product of the applied delivery ratios), at the "
                "positions where both hops exist: what routing adds")
    med = [r["delay_median"] for r in rows if math.isfinite(r["delay_median"])]
    res.compare("delay against the relay's position", "not stated as numbers",
                f"median {min(med):.2f}-{max(med):.2f} ms" if med else "-", "ms",
                "S's send to D's receipt, per datagram (one clock): veth, bridge and R's IP forwarding; no radio "
                "airtime or MAC retransmission, so flat")
    res.notes.append("real-mesh tier: the loss is applied by the kernel per frame with the radio model's "
                     "probability (an input) and routed by babeld (a finding where it withdraws the route); the "
                     "delay has no radio in it")
    res.draw = lambda fig: _draw(fig, rows, delays, length, tier="netns")
    return res


def _result_ns3(scenario: Scenario, experiment: Experiment, mode: str, rows: list[dict[str, float]],
                delays: dict[float, list[float]], length: float, fps: float, packet: int,
                frame_bytes: int) -> Result:
    """The real-mesh tier on the ns-3 channel: the loss and the delay are both measured."""
    res = Result(experiment.name, f"{experiment.title}, real-mesh tier, ns-3 channel", mode)
    res.mode_note = ("real-mesh tier on ns-3's 802.11a channel: S, R, D in network namespaces placed on a line, "
                     "babeld routing S -> D through R's kernel; each hop's loss, retries, rate and airtime are "
                     "ns-3's (measured); the radio model's 1 - q1 q2 is drawn for reference only")
    best = _mesh_rows(res, rows, ("mac_queue_full", "mac_expired", "mac_retry_limit"), length, fps, packet,
                      frame_bytes)
    res.compare("the channel", "an 802.11 WLAN", "802.11a ad hoc in ns-3: LogDistance + Nakagami fading, Minstrel, "
                "CSMA/CA and retries", "", f"reach set so that ns-3 delivers about 10 % of unicast datagrams at "
                f"R = {scenario.radio.comm_range:g} m", "input")
    res.compare("lowest loss where", "the middle (section 5.2, Fig. 7: 'exactly the middle region')",
                f"{best['x']:g} m of {length:g} m", "m", "datagrams S -> D that arrived, per position, through "
                "ns-3's channel (measured)")
    low = [r["x"] for r in rows if r["packet_loss"] <= best["packet_loss"] + 0.02]
    res.compare("positions within 2 points of the least loss", "-", f"{min(low):g}-{max(low):g} m", "m",
                "the band where the relay serves the stream about as well as it can")
    med = [r["delay_median"] for r in rows if math.isfinite(r["delay_median"])]
    res.compare("delay against the relay's position", "grows towards the ends (Figure 6)",
                f"median {min(med):.2f}-{max(med):.2f} ms" if med else "-", "ms",
                "S's send to D's receipt, per datagram (one clock): airtime at Minstrel's rate, the MAC's "
                "backoff, retries and queue, and R's forwarding")
    res.notes.append("ns-3 channel: loss and delay are measured; the radio model's line is the scenario's input, "
                     "drawn beside for reference; the MAC's drops are counted over each position's window")
    res.draw = lambda fig: _draw(fig, rows, delays, length, tier="ns3")
    return res


def _draw(fig: Any, rows: list[dict[str, float]], delays: dict[float, list[float]], length: float,
          tier: str = "loopback") -> None:
    gs = fig.add_gridspec(1, 2)
    xs = [r["x"] for r in rows]
    ax = fig.add_subplot(gs[0, 0])
    ax.set_xticks(range(0, int(length) + 1, 2))
    ax.plot(xs, [100 * r["packet_loss"] for r in rows], "o-", color=color(0), label="datagrams lost (measured)")
    ax.plot(xs, [100 * r["frame_loss"] for r in rows], "s-", color=color(1), label="frames with a datagram lost")
    ax.plot(xs, [100 * r["model_loss"] for r in rows], ":", color="#444444",
            label="radio model: 1 - q1 q2 (" + ("reference, not applied)" if tier == "ns3" else "input)"))
    if tier in ("netns", "ns3"):
        ax.plot(xs, [100 * r["refused"] for r in rows], "x--", color=color(2),
                label="sends refused: no route (babeld)")
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
    where = {"netns": "kernel forwarding through R, no radio airtime", "ns3": "ns-3's 802.11a: airtime, MAC, "
             "forwarding"}.get(tier, "loopback: no radio")
    ax.set_title(f"Delay of the datagrams that arrived ({where})\n(box: quartiles; none arrive "
                 "where a hop is out of range)", fontsize=10)
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    what = {"netns": "real-mesh tier: namespaces, babeld, the kernel's drop",
            "ns3": "real-mesh tier: namespaces, babeld, ns-3's 802.11a channel"}.get(tier, "loopback tier, first cut")
    fig.suptitle(f"Paper 000, Figure 6: video through one relay, loss and delay against its position ({what})",
                 fontsize=12)
