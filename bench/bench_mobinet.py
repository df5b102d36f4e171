"""MobiNet benchmark: SNMP poll round trip and neighbour/topology refresh cost, p50/p99.

The simulated network subsystem is `erni net-sim` in its own process (real UDP on
loopback), read by the same `SnmpSource` MobiNetControl uses. The floor, measured in the
same run: a raw UDP ping-pong between the same asyncio client loop and a bare Python echo
process (same payload size, no SNMP). Ratio = SNMP p50 / floor p50. Refreshes are reported
in milliseconds and as multiples of the floor's round trip, for 10 and 50 nodes; a last
table shows the simulator's CPU cost of rebuilding a node's MIB table after a move.

    python bench/bench_mobinet.py [--samples 400] [--refreshes 60] [--sizes 10,50]
"""

from __future__ import annotations

import argparse
import asyncio
import math
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from erni.plugins.mobinet import snmp as mib
from erni.plugins.mobinet.resource import NEIGHBORS, PARTS, TOPOLOGY
from erni.plugins.mobinet.snmp import SnmpSource
from erni.sim.manet import ManetNetwork, RadioModel
from erni.sim.snmp_agent import ManetSnmpAgent

ROOT = Path(__file__).resolve().parents[1]

ECHO = """
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
print(s.getsockname()[1], flush=True)
while True:
    data, peer = s.recvfrom(65535)
    if data == b"quit":
        break
    s.sendto(data, peer)
"""


def pct(values: list[float], q: float) -> float:
    """The q-quantile (0..1) of values, nearest rank."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))]


def grid(n: int, spacing: float = 40.0) -> list[tuple[str, float, float]]:
    """n nodes on a square-ish grid, `spacing` m apart."""
    cols = math.ceil(math.sqrt(n))
    return [(f"n{i + 1}", (i % cols) * spacing, (i // cols) * spacing) for i in range(n)]


def start_net_sim(n: int, workdir: Path) -> tuple[subprocess.Popen[str], dict[str, tuple[str, int]]]:
    """Run `erni net-sim` with an n-node grid on free ports; return it and the node addresses."""
    scenario = workdir / f"grid{n}.toml"
    nodes = ",\n".join(f'  {{ name = "{name}", x = {x}, y = {y} }}' for name, x, y in grid(n))
    scenario.write_text(f"comm_range = 100.0\nlossless_range = 50.0\nbase_port = 0\n"
                        f"nodes = [\n{nodes}\n]\n")
    proc = subprocess.Popen([sys.executable, "-m", "erni", "net-sim", str(scenario)],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None
    addresses: dict[str, tuple[str, int]] = {}
    for line in proc.stdout:
        if "serving;" in line:
            break
        parts = line.split()
        if len(parts) == 4 and parts[3].startswith("udp:"):
            host, port = parts[3][4:].rsplit(":", 1)
            addresses[parts[0]] = (host, int(port))
    return proc, addresses


class _Pong(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.waiter: asyncio.Future[bytes] | None = None

    def datagram_received(self, data: bytes, addr: object) -> None:
        if self.waiter is not None and not self.waiter.done():
            self.waiter.set_result(data)


async def udp_floor(port: int, samples: int, size: int) -> list[float]:
    """Raw UDP ping-pong round trips (s) from this asyncio loop to the echo process."""
    loop = asyncio.get_running_loop()
    transport, proto = await loop.create_datagram_endpoint(_Pong, remote_addr=("127.0.0.1", port))
    payload = b"x" * size
    times = []
    try:
        for i in range(samples + 20):
            proto.waiter = loop.create_future()
            t0 = time.perf_counter()
            transport.sendto(payload)
            await asyncio.wait_for(proto.waiter, 2.0)
            if i >= 20:
                times.append(time.perf_counter() - t0)
    finally:
        transport.close()
    return times


async def snmp_get_times(address: tuple[str, int], samples: int) -> list[float]:
    """One-varbind SNMP GET round trips (s) through SnmpSource."""
    src = SnmpSource(*address, timeout=2.0)
    times = []
    try:
        for i in range(samples + 20):
            t0 = time.perf_counter()
            await src.get([mib.ERNI_NODE_NAME])
            if i >= 20:
                times.append(time.perf_counter() - t0)
    finally:
        await src.aclose()
    return times


async def refresh_times(address: tuple[str, int], parts: frozenset[str], rounds: int,
                        cache_seconds: float) -> tuple[list[float], float, int, int]:
    """Refresh round trips (s), requests per refresh, neighbours and links seen."""
    src = SnmpSource(*address, timeout=2.0, cache_seconds=cache_seconds)
    times = []
    try:
        view = await src.read(parts)  # warm-up: sizes the GETBULK repetitions
        before = src.requests
        for _ in range(rounds):
            t0 = time.perf_counter()
            view = await src.read(parts)
            times.append(time.perf_counter() - t0)
        per = (src.requests - before) / rounds
    finally:
        await src.aclose()
    return times, per, len(view.neighbors), len(view.links)


def rebuild_cost(n: int, rounds: int = 10) -> tuple[list[float], list[float]]:
    """CPU time (s) after a move to rebuild one node's MIB table, and every node's, n-node grid."""
    net = ManetNetwork(RadioModel(100.0, 50.0))
    for name, x, y in grid(n):
        net.add_node(name, x, y)
    agent = ManetSnmpAgent(net)          # not started: only its table building is timed
    one, every = [], []
    for i in range(rounds):
        net.move("n2", 40.0 + (i % 2), 0.0)
        t0 = time.perf_counter()
        agent.table("n1")
        t1 = time.perf_counter()
        for name in net.names():
            agent.table(name)
        one.append(t1 - t0)
        every.append(time.perf_counter() - t0)
    return one, every


def main() -> int:
    """Run the benchmark and print Markdown tables."""
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=400, help="round trips per latency figure")
    ap.add_argument("--refreshes", type=int, default=60, help="refreshes per size and kind")
    ap.add_argument("--sizes", default="10,50", help="network sizes (nodes)")
    results.add_argument(ap)
    args = ap.parse_args()
    targets: list[dict[str, object]] = []
    sizes = [int(s) for s in args.sizes.split(",")]
    echo = subprocess.Popen([sys.executable, "-c", ECHO], stdout=subprocess.PIPE, text=True)
    assert echo.stdout is not None
    echo_port = int(echo.stdout.readline())
    procs = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            sims = {n: start_net_sim(n, Path(tmp)) for n in sizes}
            procs = [p for p, _ in sims.values()]

            async def run() -> None:
                first = sims[sizes[0]][1]["n1"]
                floor = await udp_floor(echo_port, args.samples, 60)
                get = await snmp_get_times(first, args.samples)
                g50 = pct(get, 0.5)
                f50, f99 = pct(floor, 0.5), pct(floor, 0.99)
                print("## SNMP poll round trip (loopback, net-sim in its own process)\n")
                print("| path | p50 (ms) | p99 (ms) | ratio p50 / floor |")
                print("|---|---|---|---|")
                print(f"| raw UDP ping-pong (floor, 60 B) | {f50 * 1e3:.3f} | {f99 * 1e3:.3f} | 1.0 |")
                print(f"| SNMP GET, 1 varbind (SnmpSource) | {pct(get, 0.5) * 1e3:.3f} | "
                      f"{pct(get, 0.99) * 1e3:.3f} | {pct(get, 0.5) / f50:.1f} |")
                print("\n## Refresh cost (all columns of a NetWatch kind, one node's view)\n")
                print("cold = every table walked (the cost after any change); steady = the "
                      "change counters stood still, one GET answers.\n")
                print("| nodes | refresh | neighbours | links | requests | p50 (ms) | p99 (ms) "
                      "| p50 / floor RTT |")
                print("|---|---|---|---|---|---|---|---|")
                for n in sizes:
                    address = sims[n][1]["n1"]
                    for label, parts, cache in (
                            ("neighbours, cold", frozenset({NEIGHBORS}), 0.0),
                            ("topology, cold", frozenset({TOPOLOGY}), 0.0),
                            ("full (all parts), cold", PARTS, 0.0),
                            ("full (all parts), steady", PARTS, 3600.0)):
                        times, per, nb, links = await refresh_times(address, parts,
                                                                    args.refreshes, cache)
                        print(f"| {n} | {label} | {nb} | {links} | {per:.1f} | "
                              f"{pct(times, 0.5) * 1e3:.2f} | {pct(times, 0.99) * 1e3:.2f} | "
                              f"{pct(times, 0.5) / f50:.0f} |")
                        t50 = pct(times, 0.5)
                        if label.endswith("steady"):
                            targets.append(results.target(
                                f"steady refresh, {n} nodes", "≤ 3x one SNMP GET", f"one GET, {g50 * 1e3:.3f} ms",
                                f"{t50 / g50:.1f}x ({t50 * 1e3:.2f} ms)", t50 / g50 <= 3))
                        elif label.startswith("full"):
                            targets.append(results.target(
                                f"cold full refresh, {n} nodes", "≤ 131.5 ms (half of 263 ms) at 50 nodes"
                                if n == 50 else "reported", f"raw UDP ping-pong, {f50 * 1e3:.3f} ms",
                                f"{t50 * 1e3:.1f} ms (p99 {pct(times, 0.99) * 1e3:.1f})",
                                t50 <= 0.1315 if n == 50 else None))

            asyncio.run(run())
    finally:
        for p in procs:
            p.send_signal(2)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        with __import__("socket").socket(2, 2) as s:
            s.sendto(b"quit", ("127.0.0.1", echo_port))
        echo.wait(5)
    print("\n## Simulator: MIB tables rebuilt after a move (CPU, in process, grid 40 m, R 100 m)\n")
    print("| nodes | first node p50 (ms) | first node p99 (ms) | every node p50 (ms) |")
    print("|---|---|---|---|")
    for n in sorted(set(sizes) | {120}):
        one, every = rebuild_cost(n)
        print(f"| {n} | {statistics.median(one) * 1e3:.2f} | {pct(one, 0.99) * 1e3:.2f} | "
              f"{statistics.median(every) * 1e3:.1f} |")
    results.write("bench_mobinet", targets, path=args.results,
                  about="MobiNet's SNMP reads of `erni net-sim` in its own process, beside one SNMP GET")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
