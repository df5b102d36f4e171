"""ERNI's frames over Zenoh beside ERNI's own wire and raw Zenoh, on loopback, in the same run.

Rows (each two endpoints in this process, a Pose as the payload):

- `erni udp`: two endpoints on ERNI's UDP/TCP wire (the floor this wire is measured against);
- `erni zenoh router`: two `ZenohEndpoint`s in client mode through a Zenoh router in this process;
- `erni zenoh peer`: the same in peer mode, one connected to the other, no router;
- `raw zenoh router` / `raw zenoh peer`: a Zenoh `put` -> subscriber and `get` -> queryable with
  the same bytes and nothing of ERNI's (no session, no sealing, no validation).

Measured per row: status one-way (send -> the receiver's callback, p50 and p99), task -> ack
(a reliable send -> its acknowledgement; raw: `get` -> reply) and status throughput (a burst,
messages received per second). Every ERNI frame is sealed in a session with per-agent
identities. The last lines give ERNI-on-Zenoh's ratios to ERNI's UDP and to raw Zenoh.

    python bench/bench_zenoh_wire.py [--pings 300] [--burst 5000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh  # noqa: E402

from erni.blackboard import Pose  # noqa: E402
from erni.sim.team import free_port  # noqa: E402
from erni.transport import Endpoint  # noqa: E402
from erni.transport.identity import Authority, Identity, load_identity  # noqa: E402
from erni.transport.wire import Message  # noqa: E402
from erni.transport.zenoh_keys import ZenohSettings, address_of  # noqa: E402
from erni.transport.zenoh_wire import ZenohEndpoint, open_router, open_session  # noqa: E402

KEYS = tempfile.TemporaryDirectory(prefix="erni-bench-keys-")
AUTHORITY = Authority.create(KEYS.name, team="bench")
POSE = Pose(robot="r1", x=1.0, y=2.0, theta=0.5, v=0.3, battery=12.5)
PAYLOAD = POSE.model_dump_json().encode()


def identity(name: str) -> Identity:
    return load_identity(AUTHORITY.issue(name, "robot", Path(KEYS.name) / f"{name}.pem"))


@dataclass
class Result:
    one_way: list[float]
    ack: list[float]
    rate: float


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


class Arrivals:
    """Counts what arrives at the receiver and wakes the waiting sender."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.count = 0
        self.target = 1
        self.last = 0.0

    def hit(self) -> None:
        self.last = time.perf_counter()
        self.count += 1
        if self.count >= self.target:
            self.event.set()

    def expect(self, n: int) -> None:
        self.event.clear()
        self.target = self.count + n

    def settle(self, quiet: float = 0.3) -> None:
        seen = -1
        while seen != self.count:
            seen = self.count
            time.sleep(quiet)


def measure(send_status: Callable[[], None], send_task: Callable[[], Callable[[float], bool]],
            arrivals: Arrivals, pings: int, burst: int) -> Result:
    """One round: warm up, one-way pings, request/acknowledgement pings, a burst."""
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:  # until the two have met (handshake, declarations)
        arrivals.expect(1)
        send_status()
        if arrivals.event.wait(0.2):
            break
    one_way = []
    for _ in range(pings):
        arrivals.expect(1)
        t0 = time.perf_counter()
        send_status()
        if arrivals.event.wait(1):
            one_way.append(arrivals.last - t0)
    ack = []
    for _ in range(pings):
        t0 = time.perf_counter()
        wait = send_task()
        if wait(2.0):
            ack.append(time.perf_counter() - t0)
    arrivals.settle(0.1)
    start_count = arrivals.count
    t0 = time.perf_counter()
    for i in range(burst):
        send_status()
        if i % 500 == 499:
            time.sleep(0.001)  # a stream, not a flood the receiver cannot read
    arrivals.settle()
    got = arrivals.count - start_count
    return Result(one_way, ack, got / max(1e-9, arrivals.last - t0))


def erni_round(kind: str, pings: int, burst: int, router: str) -> Result:
    """ERNI endpoints: 'udp', 'zenoh router' or 'zenoh peer'."""
    a: Endpoint
    b: Endpoint
    if kind == "udp":
        a, b = Endpoint("a", identity=identity("a"), senders=2), Endpoint("b", identity=identity("b"), senders=2)
    elif kind == "zenoh router":
        site = ZenohSettings(team="bench", mode="client", connect=[router])
        a = ZenohEndpoint("a", zenoh_settings=site, identity=identity("a"), senders=2)
        b = ZenohEndpoint("b", zenoh_settings=site, identity=identity("b"), senders=2)
    else:
        port = free_port()
        b = ZenohEndpoint("b", zenoh_settings=ZenohSettings(team="bench-p", listen=[f"tcp/127.0.0.1:{port}"],
                                                             scouting=False), identity=identity("b"), senders=2)
        a = ZenohEndpoint("a", zenoh_settings=ZenohSettings(team="bench-p", connect=[f"tcp/127.0.0.1:{port}"],
                                                             scouting=False), identity=identity("a"), senders=2)
    arrivals = Arrivals()

    def on_b(msg: Message) -> None:
        if msg.kind == "status":
            arrivals.hit()

    acked: dict[str, threading.Event] = {}
    b.on_message = on_b
    a.on_delivered = lambda addr, mid: acked[mid].set() if mid in acked else None
    b.start()
    a.start()
    to = b.address if kind == "udp" else address_of("b")

    def send_task() -> Callable[[float], bool]:
        done = threading.Event()
        mid = a.send(to, "task", POSE, reliable=True, to="b")
        acked[mid] = done
        return done.wait

    try:
        return measure(lambda: a.send(to, "status", POSE, reliable=False, to="b") and None, send_task, arrivals,
                       pings, burst)
    finally:
        a.stop()
        b.stop()


def raw_round(kind: str, pings: int, burst: int, router: str) -> Result:
    """Raw Zenoh sessions, through the router or peer to peer."""
    if kind == "zenoh router":
        site = ZenohSettings(mode="client", connect=[router])
        sa, sb = open_session(site), open_session(site)
    else:
        port = free_port()
        sb = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], scouting=False))
        sa = open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], scouting=False))
    arrivals = Arrivals()
    entities: list[Any] = [
        sb.declare_subscriber("raw/b/d", lambda sample: arrivals.hit()),
        sb.declare_queryable("raw/b/r", lambda query: query.reply(query.key_expr, b"ack")),
    ]
    pub = sa.declare_publisher("raw/b/d", congestion_control=zenoh.CongestionControl.DROP)

    def send_task() -> Callable[[float], bool]:
        replies = [r for r in sa.get("raw/b/r", payload=PAYLOAD, timeout=2.0) if r.ok is not None]
        return lambda timeout: bool(replies)

    try:
        return measure(lambda: pub.put(PAYLOAD), send_task, arrivals, pings, burst)
    finally:
        pub.undeclare()
        for entity in entities:
            entity.undeclare()
        sa.close()
        sb.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pings", type=int, default=300)
    parser.add_argument("--burst", type=int, default=5000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    router = f"tcp/127.0.0.1:{free_port()}"
    session = open_router([router])
    rows: dict[str, list[Result]] = {}
    try:
        for _ in range(args.rounds):  # rounds interleaved: a noisy moment hits every row alike
            for kind in ("udp", "zenoh router", "zenoh peer"):
                rows.setdefault(f"erni {kind}", []).append(erni_round(kind, args.pings, args.burst, router))
            for kind in ("zenoh router", "zenoh peer"):
                rows.setdefault(f"raw {kind}", []).append(raw_round(kind, args.pings, args.burst, router))
    finally:
        session.close()
    med = statistics.median
    summary: dict[str, tuple[float, float, float, float, float]] = {}
    print(f"loopback, {args.rounds} rounds of {args.pings} pings and a burst of {args.burst}; medians of rounds")
    print(f"{'':<20} {'one-way p50':>12} {'p99':>9} {'ack p50':>9} {'p99':>9} {'status/s':>10}")
    for name, results in rows.items():
        row = (med([pct(r.one_way, 0.5) for r in results]) * 1e6, med([pct(r.one_way, 0.99) for r in results]) * 1e6,
               med([pct(r.ack, 0.5) for r in results]) * 1e6, med([pct(r.ack, 0.99) for r in results]) * 1e6,
               med([r.rate for r in results]))
        summary[name] = row
        print(f"{name:<20} {row[0]:>10.0f}us {row[1]:>7.0f}us {row[2]:>7.0f}us {row[3]:>7.0f}us {row[4]:>10.0f}")
    for where in ("router", "peer"):
        ours, udp, raw = summary[f"erni zenoh {where}"], summary["erni udp"], summary[f"raw zenoh {where}"]
        print(f"erni zenoh {where}: one-way p50 {ours[0] / udp[0]:.2f}x erni udp, {ours[0] / raw[0]:.2f}x raw; "
              f"ack p50 {ours[2] / udp[2]:.2f}x erni udp, {ours[2] / raw[2]:.2f}x raw; "
              f"throughput {ours[4] / udp[4]:.2f}x erni udp, {ours[4] / raw[4]:.2f}x raw")
    return 0


if __name__ == "__main__":
    sys.exit(main())
