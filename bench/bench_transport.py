"""Transport benchmark on loopback: ERNI endpoints beside raw Python sockets, in the same run.

- UDP status one-way latency: `send(..., reliable=False)` -> `on_message` at the receiver,
  beside a raw `sendto` -> `recvfrom` one-way floor.
- TCP task send -> ack: `send(..., reliable=True)` -> acknowledgement, beside a raw TCP
  request/response ping-pong floor.
- Status throughput (messages/s received), beside a raw UDP burst floor.
Every ERNI frame is JSON-encoded and sealed with ChaCha20-Poly1305 in a session between the two
endpoints (per-agent identities from a team authority made for the run), then opened,
replay-checked and validated; the floors do none of that. The session's handshake (once per
pair: X25519 and two Ed25519 signatures) is timed on its own: the first message to a new peer.

- A task to an agent with a journal: `task.add` from a command-line client's endpoint to an agent
  (the transport plugin, a SQLite journal in a temporary directory) -> acknowledgement, one task at
  a time (p50, p99), and tasks acknowledged a second with `--senders` clients sending at once. An
  agent acknowledges a task once its journal holds it (it would survive a kill -9), so these
  include the blackboard, the plugin's run and the journal's commit (one fsync a batch: the tasks of
  several senders that arrive together share it); the floor is the endpoint's own send -> ack above.

Zenoh's Python binding (`eclipse-zenoh`, `pip install -e .[bench]`) runs in the same rounds with
the same payload: two sessions in peer mode over TCP on loopback, `put` -> subscriber callback
(one-way), `get` -> queryable reply (a request/response, beside ERNI's task -> acknowledgement)
and a `put` burst. Without it installed those rows are left out.

    python bench/bench_transport.py [--rounds 5] [--pings 500] [--burst 5000] [--senders 8] [--cpu N]

Where the scheduler puts the receiving thread decides a one-way figure more than either
transport does: on a quiet 2-vCPU virtual machine, a receiver woken on the other, idle vCPU
costs about 20 us more than one woken on the sender's (the raw socket itself measures 6 or 28
us from one round to the next). `--cpu N` keeps every thread of the run (ERNI's, the raw
sockets', Zenoh's) on CPU N, so each one-way figure is a wake-up on the same CPU and the ratios
compare the transports' own work; without it the kernel places them, as it would two agents.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from erni.blackboard import Pose  # noqa: E402
from erni.transport import Endpoint  # noqa: E402
from erni.transport.identity import Authority, Identity, load_identity  # noqa: E402

_KEYS = tempfile.TemporaryDirectory(prefix="erni-bench-keys-")
_AUTHORITY = Authority.create(_KEYS.name, team="bench")


def identity(name: str) -> Identity:
    return load_identity(_AUTHORITY.issue(name, "robot"))


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def _settle(count: list[int], quiet: float = 0.3) -> None:
    """Wait until the counter stops moving for `quiet` seconds."""
    seen = -1
    while seen != count[0]:
        seen = count[0]
        time.sleep(quiet)


def erni_round(pings: int, burst: int) -> tuple[list[float], list[float], float, float]:
    a, b = Endpoint("a", identity=identity("a"), senders=2), Endpoint("b", identity=identity("b"), senders=2)
    sent: dict[str, float] = {}
    udp_lat: list[float] = []
    got = threading.Event()
    count = [0]
    target = [0]

    def on_b(msg):
        now = time.perf_counter()
        if msg.kind == "status":
            udp_lat.append(now - sent[msg.id])
            got.set()
        else:
            count[0] += 1
            last[0] = now
            if count[0] >= target[0]:
                got.set()

    last = [0.0]
    acked = threading.Event()
    ack_at: dict[str, float] = {}

    def on_delivered(addr, mid):
        ack_at[mid] = time.perf_counter()
        acked.set()

    b.on_message = on_b
    a.on_delivered = on_delivered
    a.start()
    b.start()
    pose = Pose(robot="r1", x=1.0, y=2.0, theta=0.5, v=0.3, battery=12.5)
    try:
        got.clear()  # the first message to a new peer: handshake, then the status
        sent["first"] = time.perf_counter()
        a.send(b.address, "status", pose, reliable=False, msg_id="first")
        got.wait(2)
        first = udp_lat.pop()
        for i in range(pings):
            got.clear()
            mid = f"s{i}"
            sent[mid] = time.perf_counter()
            a.send(b.address, "status", pose, reliable=False, msg_id=mid)
            got.wait(1)
        tcp_lat = []
        for i in range(pings):
            acked.clear()
            mid = f"t{i}"
            t0 = time.perf_counter()
            a.send(b.address, "task", pose, reliable=True, msg_id=mid)
            acked.wait(2)
            tcp_lat.append(ack_at[mid] - t0)
        got.clear()
        target[0] = burst
        t0 = time.perf_counter()
        for i in range(burst):
            a.send(b.address, "bulk", pose, reliable=False)
            if i % 500 == 499:
                time.sleep(0.001)  # let the receiver keep up, as a status stream would
        _settle(count)
        rate = count[0] / (last[0] - t0)  # received per second, until the last arrival
        return udp_lat, tcp_lat, rate, first
    finally:
        a.stop()
        b.stop()


def agent_round(pings: int, senders: int) -> tuple[list[float], float]:
    """Tasks from command-line clients' endpoints to an agent with a journal: each task's send -> ack
    one at a time, and the rate at which `senders` clients sending at once are acknowledged."""
    from erni.blackboard import Agent, Task
    from erni.transport.endpoint import CLIENT_ROLE

    with tempfile.TemporaryDirectory(prefix="erni-bench-journal-") as tmp:
        agent = Agent("control", workers=2, journal=Path(tmp) / "journal.db")
        ident = _AUTHORITY.issue("control", "control")
        agent.add_plugin("transport", settings={"identity": str(ident), "discovery_port": 0}, name="transport")
        agent.start()
        clients = [Endpoint(f"cli{i}", identity=load_identity(_AUTHORITY.issue(f"cli{i}", CLIENT_ROLE)), senders=1,
                            role=CLIENT_ROLE) for i in range(senders)]
        acked: dict[str, float] = {}
        lock = threading.Condition()

        def on_delivered(addr, mid):
            with lock:
                acked[mid] = time.perf_counter()
                lock.notify_all()

        try:
            target = agent.plugin("transport").address  # type: ignore[attr-defined]
            for c in clients:
                c.on_delivered = on_delivered
                c.start()

            def task(i: int, who: int) -> Task:
                return Task(uid=f"bench-{who}-{i}", verb="BotMotion", preposition="stop", source=f"cli{who}",
                            destination="control")

            def wait(mids: list[str], timeout: float = 10.0) -> None:
                deadline = time.monotonic() + timeout
                with lock:
                    while not all(m in acked for m in mids) and time.monotonic() < deadline:
                        lock.wait(0.1)

            lat: list[float] = []
            for i in range(pings + 1):  # the first: the session's handshake, left out
                t0 = time.perf_counter()
                mid = clients[0].send(target, "task.add", task(i, 0), reliable=True, msg_id=f"one-{i}")
                wait([mid])
                if i and mid in acked:
                    lat.append(acked[mid] - t0)
            for j, c in enumerate(clients[1:], 1):  # every client's session up before the clock starts
                wait([c.send(target, "task.add", task(0, j), reliable=True, msg_id=f"warm-{j}")])
            each = max(1, pings // senders)
            t0 = time.perf_counter()
            mids = [c.send(target, "task.add", task(i, j), reliable=True, msg_id=f"many-{j}-{i}")
                    for i in range(1, each + 1) for j, c in enumerate(clients)]
            wait(mids, timeout=60.0)
            done = [acked[m] for m in mids if m in acked]
            rate = len(done) / (max(done) - t0) if done else 0.0
            return lat, rate
        finally:
            for c in clients:
                c.stop()
            agent.stop()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def zenoh_round(pings: int, burst: int) -> tuple[list[float], list[float], float] | None:
    """Zenoh put -> subscriber one-way, get -> queryable round trip, put burst (None: not installed)."""
    try:
        import zenoh  # type: ignore[import-not-found]  # a benchmark-only extra
    except ImportError:
        return None

    def config(listen: int, connect: int | None) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{listen}"]')
        if connect is not None:
            conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{connect}"]')
        return conf

    payload = Pose(robot="r1", x=1.0, y=2.0, theta=0.5, v=0.3, battery=12.5).model_dump_json().encode()
    port = _free_port()
    s1 = zenoh.open(config(port, None))
    s2 = zenoh.open(config(_free_port(), port))
    got = threading.Event()
    arrived = [0.0]
    count = [0]
    last = [0.0]
    target = [0]

    def on_sample(sample: object) -> None:
        now = time.perf_counter()
        arrived[0] = now
        count[0] += 1
        last[0] = now
        if count[0] >= target[0]:
            got.set()

    sub = s2.declare_subscriber("erni/bench/status", on_sample)
    queryable = s2.declare_queryable("erni/bench/task", lambda query: query.reply(query.key_expr, b"ack"))
    pub = s1.declare_publisher("erni/bench/status")
    try:
        deadline = time.monotonic() + 5  # until the two sessions have met and declared
        while time.monotonic() < deadline:
            got.clear()
            target[0] = count[0] + 1
            pub.put(payload)
            if got.wait(0.1):
                break
        one_way = []
        for _ in range(pings):
            got.clear()
            target[0] = count[0] + 1
            t0 = time.perf_counter()
            pub.put(payload)
            if got.wait(1):
                one_way.append(arrived[0] - t0)
        rtt = []
        for _ in range(pings):
            t0 = time.perf_counter()
            replies = [r for r in s1.get("erni/bench/task", payload=payload) if r.ok is not None]
            if replies:
                rtt.append(time.perf_counter() - t0)
        count[0] = 0
        target[0] = burst
        got.clear()
        t0 = time.perf_counter()
        for i in range(burst):
            pub.put(payload)
            if i % 500 == 499:
                time.sleep(0.001)
        _settle(count)
        rate = count[0] / (last[0] - t0)
        return one_way, rtt, rate
    finally:
        sub.undeclare()
        queryable.undeclare()
        pub.undeclare()
        s1.close()
        s2.close()


def floor_round(pings: int, burst: int) -> tuple[list[float], list[float], float]:
    payload = Pose(robot="r1", x=1.0, y=2.0, theta=0.5, v=0.3, battery=12.5).model_dump_json().encode()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    lat: list[float] = []
    count = [0]
    stop = threading.Event()
    got = threading.Event()

    def receive():
        rx.settimeout(0.2)
        while not stop.is_set():
            try:
                rx.recvfrom(65536)
            except TimeoutError:
                continue
            now = time.perf_counter()
            lat.append(now)
            count[0] += 1
            got.set()

    t = threading.Thread(target=receive, daemon=True)
    t.start()
    udp_lat = []
    for _ in range(pings):
        got.clear()
        t0 = time.perf_counter()
        tx.sendto(payload, rx.getsockname())
        got.wait(1)
        udp_lat.append(lat[-1] - t0)
    # TCP request/response
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)

    def echo():
        conn, _ = srv.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        while True:
            data = conn.recv(65536)
            if not data:
                break
            conn.sendall(b"ack")
        conn.close()

    et = threading.Thread(target=echo, daemon=True)
    et.start()
    cli = socket.create_connection(srv.getsockname())
    cli.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    tcp_lat = []
    for _ in range(pings):
        t0 = time.perf_counter()
        cli.sendall(payload)
        cli.recv(16)
        tcp_lat.append(time.perf_counter() - t0)
    cli.close()
    et.join(2)
    srv.close()
    # UDP burst
    count[0] = 0
    t0 = time.perf_counter()
    for i in range(burst):
        tx.sendto(payload, rx.getsockname())
        if i % 500 == 499:
            time.sleep(0.001)
    _settle(count)
    rate = count[0] / (lat[-1] - t0)
    stop.set()
    t.join(1)
    rx.close()
    tx.close()
    return udp_lat, tcp_lat, rate


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--pings", type=int, default=500)
    parser.add_argument("--burst", type=int, default=5000)
    parser.add_argument("--senders", type=int, default=8,
                        help="clients sending tasks at once to the agent with a journal")
    parser.add_argument("--cpu", type=int, default=None,
                        help="keep every thread of the run on this CPU (default: where the kernel puts them)")
    results.add_argument(parser)
    args = parser.parse_args()
    if args.cpu is not None:
        try:
            os.sched_setaffinity(0, {args.cpu})  # threads started after this inherit it
        except (OSError, ValueError) as err:
            parser.error(f"--cpu {args.cpu}: cannot run on that CPU ({err}); expected one of "
                         f"{sorted(os.sched_getaffinity(0))}")
    load_before = os.getloadavg()
    rows, zrows, firsts, arows = [], [], [], []
    for _ in range(args.rounds):  # the three systems take turns in every round
        eu, et, er, first = erni_round(args.pings, args.burst)
        firsts.append(first)
        fu, ft, fr = floor_round(args.pings, args.burst)
        al, ar = agent_round(min(args.pings, 200), args.senders)
        arows.append((pct(al, .5), pct(al, .99), ar))
        rows.append((pct(eu, .5), pct(fu, .5), pct(eu, .99), pct(fu, .99), pct(et, .5), pct(ft, .5),
                     pct(et, .99), pct(ft, .99), er, fr))
        z = zenoh_round(args.pings, args.burst)
        if z is not None:
            zu, zt, zr = z
            zrows.append((pct(zu, .5), pct(zu, .99), pct(zt, .5), pct(zt, .99), zr))
    m = [statistics.median(col) for col in zip(*rows)]
    zm = [statistics.median(col) for col in zip(*zrows)] if zrows else None
    print(f"transport benchmark on loopback: {args.rounds} rounds x {args.pings} pings, burst "
          f"{args.burst}; medians of rounds; floor = raw Python sockets, same run; Zenoh = eclipse-zenoh "
          f"peer mode over TCP, same run ({'not installed' if zm is None else 'put/subscribe, get/queryable'}); "
          f"threads on {'CPU ' + str(args.cpu) if args.cpu is not None else 'the CPUs the kernel chose'}")
    print(f"{'measure':<28} {'ERNI':>10} {'floor':>10} {'ratio':>7} {'Zenoh':>10} {'Zenoh/ERNI':>11}")
    for label, ours, floor, zi in (
        ("UDP status one-way p50", m[0], m[1], 0), ("UDP status one-way p99", m[2], m[3], 1),
        ("TCP task send->ack p50", m[4], m[5], 2), ("TCP task send->ack p99", m[6], m[7], 3),
    ):
        zen = f"{zm[zi] * 1e6:>8.0f}us {zm[zi] / ours:>11.2f}" if zm is not None else ""
        print(f"{label:<28} {ours * 1e6:>8.0f}us {floor * 1e6:>8.0f}us {ours / floor:>7.2f} {zen}")
    zen = f"{zm[4]:>8.0f}/s {m[8] / zm[4]:>11.2f}" if zm is not None else ""
    print(f"{'status throughput':<28} {m[8]:>8.0f}/s {m[9]:>8.0f}/s {m[8] / m[9]:>7.2f} {zen}")
    print("(Zenoh rows: put -> subscriber one-way; get -> queryable reply for send->ack; Zenoh/ERNI > 1: "
          "ERNI ahead; for throughput ERNI/Zenoh)")
    print(f"{'handshake + first status':<28} {statistics.median(firsts) * 1e6:>8.0f}us   (once per pair of "
          "endpoints; no floor)")
    am = [statistics.median(col) for col in zip(*arows)]
    print(f"{'task to a journaled agent p50':<28} {am[0] * 1e6:>8.0f}us {m[4] * 1e6:>8.0f}us {am[0] / m[4]:>7.2f}"
          "   (send -> ack once the journal holds it; floor: ERNI's endpoint send->ack)")
    print(f"{'task to a journaled agent p99':<28} {am[1] * 1e6:>8.0f}us {m[6] * 1e6:>8.0f}us {am[1] / m[6]:>7.2f}")
    print(f"{'tasks acknowledged, ' + str(args.senders) + ' senders':<28} {am[2]:>8.0f}/s   (each sender one task "
          "in flight; a journal batch's tasks share one commit)")
    print(f"load average (1, 5, 15 min) before {' '.join(f'{x:.2f}' for x in load_before)}, after "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}: the floors move with it, so compare ratios of one run")
    targets = [
        results.target("UDP status one-way p50", "≤ 2x a raw socket", f"raw UDP ping-pong, {m[1] * 1e6:.0f} µs",
                       f"{m[0] / m[1]:.2f}x ({m[0] * 1e6:.0f} µs)", m[0] / m[1] <= 2),
        results.target("UDP status one-way p99", "≤ 3x a raw socket", f"raw UDP ping-pong, {m[3] * 1e6:.0f} µs",
                       f"{m[2] / m[3]:.2f}x ({m[2] * 1e6:.0f} µs)", m[2] / m[3] <= 3),
        results.target("status throughput", "≥ 0.8x a raw socket", f"raw UDP burst, {m[9]:.0f}/s",
                       f"{m[8] / m[9]:.2f}x ({m[8]:.0f} statuses/s)", m[8] / m[9] >= 0.8),
        results.target("TCP task → acknowledgement p99", "≤ 1 ms on loopback", f"raw TCP, {m[7] * 1e3:.2f} ms",
                       f"{m[6] * 1e3:.2f} ms", m[6] <= 1e-3),
    ]
    targets += [
        results.target("task to an agent with a journal → acknowledgement p50", "acknowledged once durable",
                       f"ERNI's endpoint send → ack, {m[4] * 1e3:.2f} ms",
                       f"{am[0] * 1e3:.2f} ms (p99 {am[1] * 1e3:.2f} ms)", None),
        results.target(f"tasks acknowledged a second, {args.senders} senders at once", "reported",
                       "one task in flight per sender", f"{am[2]:.0f}/s", None),
    ]
    if zm is not None:
        targets.append(results.target("throughput beside Zenoh's Python binding", "≥ 2x ahead",
                                      f"Zenoh, same run, {zm[4]:.0f}/s", f"{m[8] / zm[4]:.2f}x", m[8] / zm[4] >= 2))
    results.write("bench_transport", targets, path=args.results,
                  about="ERNI endpoints beside raw Python sockets and Zenoh's Python binding on loopback")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
