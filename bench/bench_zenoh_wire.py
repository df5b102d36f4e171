"""ERNI's frames over Zenoh beside ERNI's own wire and raw Zenoh, on loopback, in the same run.

Rows (a sender in this process, its receiver in a second process, a Pose as the payload):

- `erni udp`: two endpoints on ERNI's UDP/TCP wire (the floor this wire is measured against);
- `erni zenoh router`: two `ZenohEndpoint`s in client mode through a Zenoh router (in this process);
- `erni zenoh peer`: the same in peer mode, the sender connected to the receiver, no router;
- `raw zenoh router` / `raw zenoh peer`: a Zenoh `put` -> subscriber and `get` -> queryable with
  the same bytes and nothing of ERNI's (no session, no sealing, no validation).

Sender and receiver are two processes, as a robot and a control node are: in one process they
would share one interpreter lock, and what a row measured would be how the two Python threads
and the wire's own threads take turns with it rather than the wire (`--one-process` measures
that setting, for comparison). Arrivals are counted and time-stamped in the receiver
(`time.perf_counter`, the system's monotonic clock, so the two processes' times compare) and
shared with the sender through shared memory; a pipe wakes the sender when what it waits for
has arrived.

Measured per row: status one-way (send -> the receiver's callback, p50 and p99), task -> ack
(a reliable send -> its acknowledgement; raw: `get` -> reply) and status throughput (messages
received per second in a burst; a round's figure is the median of `--bursts` bursts, since on a
loaded machine one burst's rate varies by a factor of two with what else ran in those 50 ms).
Every ERNI frame is sealed in a session with per-agent identities. The last lines give
ERNI-on-Zenoh's ratios to ERNI's UDP and to raw Zenoh.

    python bench/bench_zenoh_wire.py [--pings 300] [--burst 5000] [--bursts 3] [--rounds 3] [--one-process]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh  # noqa: E402

from erni.blackboard import Pose  # noqa: E402
from erni.sim.team import free_port  # noqa: E402
from erni.transport import Endpoint  # noqa: E402
from erni.transport.identity import Authority, load_identity  # noqa: E402
from erni.transport.wire import Message  # noqa: E402
from erni.transport.zenoh_keys import ZenohSettings, address_of  # noqa: E402
from erni.transport.zenoh_wire import ZenohEndpoint, open_router, open_session  # noqa: E402

POSE = Pose(robot="r1", x=1.0, y=2.0, theta=0.5, v=0.3, battery=12.5)
PAYLOAD = POSE.model_dump_json().encode()
ERNI_ROWS = ("udp", "zenoh router", "zenoh peer")
RAW_ROWS = ("zenoh router", "zenoh peer")


@dataclass
class Result:
    one_way: list[float]
    ack: list[float]
    rate: float


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


class Shared:
    """What the receiver counts, in shared memory: arrivals, the newest one's time, and the count
    the sender waits for (reaching it writes to `wake`)."""

    def __init__(self, ctx: Any) -> None:
        self.count = ctx.RawValue("q", 0)
        self.last = ctx.RawValue("d", 0.0)
        self.target = ctx.RawValue("q", 1)
        self.wait_end, self.wake = ctx.Pipe(duplex=False)

    def hit(self) -> None:
        """One arrival (in the receiver)."""
        self.last.value = time.perf_counter()
        n = self.count.value + 1
        self.count.value = n
        if n == self.target.value:
            self.wake.send_bytes(b"")


class Arrivals:
    """The sender's view of the receiver's arrivals: wait for the next n, or for them to settle."""

    def __init__(self, shared: Shared) -> None:
        self.shared = shared

    @property
    def count(self) -> int:
        return int(self.shared.count.value)

    @property
    def last(self) -> float:
        return float(self.shared.last.value)

    def expect(self, n: int) -> None:
        while self.shared.wait_end.poll():
            self.shared.wait_end.recv_bytes()
        self.shared.target.value = self.count + n

    def wait(self, timeout: float) -> bool:
        return bool(self.shared.wait_end.poll(timeout))

    def settle(self, quiet: float = 0.3) -> None:
        seen = -1
        while seen != self.count:
            seen = self.count
            time.sleep(quiet)


def measure(send_status: Callable[[], None], send_task: Callable[[], Callable[[float], bool]],
            arrivals: Arrivals, pings: int, burst: int, bursts: int = 1) -> Result:
    """One round: warm up, one-way pings, request/acknowledgement pings, a burst."""
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:  # until the two have met (handshake, declarations)
        arrivals.expect(1)
        send_status()
        if arrivals.wait(0.2):
            break
    one_way = []
    for _ in range(pings):
        arrivals.expect(1)
        t0 = time.perf_counter()
        send_status()
        if arrivals.wait(1):
            one_way.append(arrivals.last - t0)
    ack = []
    for _ in range(pings):
        t0 = time.perf_counter()
        wait = send_task()
        if wait(2.0):
            ack.append(time.perf_counter() - t0)
    rates = []
    for _ in range(bursts):
        arrivals.settle(0.1)
        start_count = arrivals.count
        t0 = time.perf_counter()
        for i in range(burst):
            send_status()
            if i % 500 == 499:
                time.sleep(0.001)  # a stream, not a flood the receiver cannot read
        arrivals.settle()
        rates.append((arrivals.count - start_count) / max(1e-9, arrivals.last - t0))
    if os.environ.get("BENCH_RATES"):
        print("  rates", [round(r) for r in rates], file=sys.stderr)
    return Result(one_way, ack, statistics.median(rates))


def peer_settings(port: int, *, listen: bool, team: str | None = "bench-p") -> ZenohSettings:
    where = [f"tcp/127.0.0.1:{port}"]
    kw: dict[str, Any] = {"team": team} if team else {}
    return ZenohSettings(listen=where, scouting=False, **kw) if listen else \
        ZenohSettings(connect=where, scouting=False, **kw)


def open_receiver(row: tuple[str, str], keys: str, router: str, port: int, shared: Shared) -> tuple[Any, Callable[[], None]]:
    """Set up the receiving end of a row (in whichever process runs it): its address on the wire
    (ERNI rows) and how to take it down."""
    wire, kind = row
    if wire == "raw":
        sb = open_session(ZenohSettings(mode="client", connect=[router]) if kind == "zenoh router"
                          else peer_settings(port, listen=True, team=None))
        entities: list[Any] = [
            sb.declare_subscriber("raw/b/d", lambda sample: shared.hit()),
            sb.declare_queryable("raw/b/r", lambda query: query.reply(query.key_expr, b"ack")),
        ]

        def close_raw() -> None:
            for entity in entities:
                entity.undeclare()
            sb.close()
        return None, close_raw
    b = erni_endpoint("b", kind, keys, router, port, listen=True)

    def on_b(msg: Message) -> None:
        if msg.kind == "status":
            shared.hit()

    b.on_message = on_b
    b.start()
    return (b.address if kind == "udp" else address_of("b")), b.stop


def serve(commands: Connection, keys: str, shared: Shared) -> None:
    """The receiver process: set up the row it is told, report ready, take it down when told."""
    while True:
        cmd = commands.recv()
        if cmd is None:
            return
        row, router, port = cmd
        address, close = open_receiver(row, keys, router, port, shared)
        commands.send(address)
        commands.recv()
        close()
        commands.send(None)


class Receiver:
    """The receiving ends of the rows: in a second process (`serve`), or in this one."""

    def __init__(self, keys: str, one_process: bool) -> None:
        ctx = multiprocessing.get_context("spawn")  # never fork a process that runs Zenoh's threads
        self.shared = Shared(ctx)
        self.keys = keys
        self.proc = None
        self.close: Callable[[], None] | None = None
        if not one_process:
            self.commands, theirs = ctx.Pipe()
            self.proc = ctx.Process(target=serve, args=(theirs, keys, self.shared), daemon=True)
            self.proc.start()

    def open(self, row: tuple[str, str], router: str, port: int) -> Any:
        if self.proc is None:
            address, self.close = open_receiver(row, self.keys, router, port, self.shared)
            return address
        self.commands.send((row, router, port))
        return self.commands.recv()

    def done(self) -> None:
        if self.proc is None:
            assert self.close is not None
            self.close()
        else:
            self.commands.send("stop")
            self.commands.recv()

    def quit(self) -> None:
        if self.proc is not None:
            self.commands.send(None)
            self.proc.join(5)


def erni_endpoint(name: str, kind: str, keys: str, router: str, port: int, *, listen: bool) -> Endpoint:
    """Endpoint `name` ('a' sends, 'b' receives) of one ERNI row: 'udp', 'zenoh router' or 'zenoh peer'."""
    me = load_identity(Path(keys) / f"{name}.pem")
    if kind == "udp":
        return Endpoint(name, identity=me, senders=2)
    if kind == "zenoh router":
        return ZenohEndpoint(name, zenoh_settings=ZenohSettings(team="bench", mode="client", connect=[router]),
                             identity=me, senders=2)
    return ZenohEndpoint(name, zenoh_settings=peer_settings(port, listen=listen), identity=me, senders=2)


def erni_round(kind: str, rx: Receiver, pings: int, burst: int, bursts: int, router: str) -> Result:
    """ERNI endpoints: 'udp', 'zenoh router' or 'zenoh peer'."""
    port = free_port()
    to = rx.open(("erni", kind), router, port)
    a = erni_endpoint("a", kind, rx.keys, router, port, listen=False)
    acked: dict[str, threading.Event] = {}
    a.on_delivered = lambda addr, mid: acked[mid].set() if mid in acked else None
    a.start()

    def send_task() -> Callable[[float], bool]:
        done = threading.Event()
        mid = a.send(to, "task", POSE, reliable=True, to="b")
        acked[mid] = done
        return done.wait

    try:
        return measure(lambda: a.send(to, "status", POSE, reliable=False, to="b") and None, send_task,
                       Arrivals(rx.shared), pings, burst, bursts)
    finally:
        a.stop()
        rx.done()


def raw_round(kind: str, rx: Receiver, pings: int, burst: int, bursts: int, router: str) -> Result:
    """Raw Zenoh sessions, through the router or peer to peer."""
    port = free_port()
    rx.open(("raw", kind), router, port)
    sa = open_session(ZenohSettings(mode="client", connect=[router]) if kind == "zenoh router"
                      else peer_settings(port, listen=False, team=None))
    pub = sa.declare_publisher("raw/b/d", congestion_control=zenoh.CongestionControl.DROP)

    def send_task() -> Callable[[float], bool]:
        replies = [r for r in sa.get("raw/b/r", payload=PAYLOAD, timeout=2.0) if r.ok is not None]
        return lambda timeout: bool(replies)

    try:
        return measure(lambda: pub.put(PAYLOAD), send_task, Arrivals(rx.shared), pings, burst, bursts)
    finally:
        pub.undeclare()
        sa.close()
        rx.done()


def main() -> int:
    import results as latest  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pings", type=int, default=300)
    parser.add_argument("--burst", type=int, default=5000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--bursts", type=int, default=3, help="bursts a round (its rate: their median)")
    parser.add_argument("--one-process", action="store_true",
                        help="receivers in this process too (one interpreter lock for both ends)")
    latest.add_argument(parser)
    args = parser.parse_args()
    keys = tempfile.TemporaryDirectory(prefix="erni-bench-keys-")
    authority = Authority.create(keys.name, team="bench")
    for name in ("a", "b"):
        authority.issue(name, "robot", Path(keys.name) / f"{name}.pem")
    router = f"tcp/127.0.0.1:{free_port()}"
    session = open_router([router])
    rx = Receiver(keys.name, args.one_process)
    rows: dict[str, list[Result]] = {}
    try:
        for _ in range(args.rounds):  # rounds interleaved: a noisy moment hits every row alike
            for kind in ERNI_ROWS:
                rows.setdefault(f"erni {kind}", []).append(erni_round(kind, rx, args.pings, args.burst, args.bursts, router))
            for kind in RAW_ROWS:
                rows.setdefault(f"raw {kind}", []).append(raw_round(kind, rx, args.pings, args.burst, args.bursts, router))
    finally:
        rx.quit()
        session.close()
        keys.cleanup()
    med = statistics.median
    summary: dict[str, tuple[float, float, float, float, float]] = {}
    where = "one process" if args.one_process else "sender and receiver in two processes"
    print(f"loopback, {where}, {args.rounds} rounds of {args.pings} pings and a burst of {args.burst}; "
          "medians of rounds")
    print(f"{'':<20} {'one-way p50':>12} {'p99':>9} {'ack p50':>9} {'p99':>9} {'status/s':>10}")
    for name, results in rows.items():
        row = (med([pct(r.one_way, 0.5) for r in results]) * 1e6, med([pct(r.one_way, 0.99) for r in results]) * 1e6,
               med([pct(r.ack, 0.5) for r in results]) * 1e6, med([pct(r.ack, 0.99) for r in results]) * 1e6,
               med([r.rate for r in results]))
        summary[name] = row
        print(f"{name:<20} {row[0]:>10.0f}us {row[1]:>7.0f}us {row[2]:>7.0f}us {row[3]:>7.0f}us {row[4]:>10.0f}")
    for site in ("router", "peer"):
        ours, udp, raw = summary[f"erni zenoh {site}"], summary["erni udp"], summary[f"raw zenoh {site}"]
        print(f"erni zenoh {site}: one-way p50 {ours[0] / udp[0]:.2f}x erni udp, {ours[0] / raw[0]:.2f}x raw; "
              f"ack p50 {ours[2] / udp[2]:.2f}x erni udp, {ours[2] / raw[2]:.2f}x raw; "
              f"throughput {ours[4] / udp[4]:.2f}x erni udp, {ours[4] / raw[4]:.2f}x raw")
    targets = []
    for site, label in (("router", "through a router"), ("peer", "peer to peer")):
        ours, udp, raw = summary[f"erni zenoh {site}"], summary["erni udp"], summary[f"raw zenoh {site}"]
        targets.append(latest.target(f"statuses/s over Zenoh {label}", "≥ 1x ERNI's UDP wire",
                                     f"ERNI's UDP wire, {udp[4]:.0f}/s", f"{ours[4] / udp[4]:.2f}x ({ours[4]:.0f}/s)",
                                     ours[4] >= udp[4]))
        targets.append(latest.target(f"one-way p50 {label}", "reported", f"raw Zenoh {label}, {raw[0]:.0f} µs",
                                     f"{ours[0] / raw[0]:.2f}x ({ours[0]:.0f} µs)", None))
    latest.write("bench_zenoh_wire", targets, path=args.results,
                 about="ERNI's frames over Zenoh beside ERNI's UDP wire and raw Zenoh on loopback")
    return 0


if __name__ == "__main__":
    sys.exit(main())
