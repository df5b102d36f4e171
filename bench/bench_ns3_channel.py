"""The ns-3 channel of the real-mesh tier, checked against ns-3 itself: delivery by distance, contention, real time.

1. Delivery ratio against distance: two namespaces on the ns-3 channel (`Mesh(channel="ns3")`,
   range 10 m), a static line at several distances; N UDP datagrams at a fixed rate from one
   namespace's socket to the other's (Linux's UDP/IP over the TAPs, ns-3's 802.11a below).
   Beside it, the same channel configuration in a pure ns-3 run (the same program's `pure` mode:
   no namespaces, ns-3's own internet stack, a UdpClient -> UdpServer flow, the same payload size,
   rate and count, in simulated time) over several seeds. They agree at a distance when the
   difference of the two ratios lies within its 95 % confidence interval (normal approximation
   of two binomial proportions; the fading is drawn per frame, so frames are independent trials).
2. Contention: two saturating flows between four namespaces all within range of each other, each
   alone and then both at once: each gets less than alone (one medium, CSMA/CA shares it).
3. Real time: N namespaces within range, each broadcasting a team's traffic (babeld-sized Hellos
   and an agent's beacons and status, 40 datagrams a second of 700 bytes, measured on a 5-robot team), for
   N = 6, 12, 18, 24, 32, 40; the channel's own lag probe (every 100 ms: how far ns-3's real-time
   simulator is behind the wall clock) gives its largest lag and the probes later than 50 ms.
   The largest N with no late probe is `erni.sim.ns3_channel.MAX_NODES`.

    sudo python bench/bench_ns3_channel.py [--count 400] [--seeds 5]
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import results  # noqa: E402

from erni.sim import ns3_channel  # noqa: E402
from erni.sim.netns import Mesh, die_with_parent, unavailable_reason  # noqa: E402

RANGE = 10.0
DISTANCES = [6.0, 10.0, 11.0, 12.0, 13.0, 14.0]
SIZE = 500                # UDP payload bytes
INTERVAL = 0.01           # s between datagrams: 100 a second
LOAD = """
import socket, sys, time
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
end = time.monotonic() + float(sys.argv[2]); t = time.monotonic()
while time.monotonic() < end:
    s.sendto(bytes(700), (sys.argv[1], 47980)); t += 1 / 40; time.sleep(max(0.0, t - time.monotonic()))
"""


def ci95(p1: float, n1: int, p2: float, n2: int) -> float:
    """Half-width of the 95 % confidence interval of p1 - p2 (two binomial proportions)."""
    p = (p1 * n1 + p2 * n2) / (n1 + n2)
    return 1.96 * math.sqrt(max(p * (1 - p), 1e-12) * (1 / n1 + 1 / n2))


def delivery(run_dir: Path, count: int, seeds: int) -> list[dict[str, Any]]:
    program = ns3_channel.binary()
    rows = []
    for d in DISTANCES:  # a new channel at each distance: Minstrel starts afresh, as in each pure run
        mesh = Mesh(["a", "b"], run_dir / "delivery", channel="ns3", range_m=RANGE)
        mesh.apply({}, {"a": (0.0, 0.0), "b": (d, 0.0)})
        mesh.create()
        try:
            mesh.static_neighbours()  # as in the pure run: only the channel decides
            (got,) = mesh.udp_flows([("a", "b")], count=count, interval=INTERVAL, size=SIZE)
        finally:
            mesh.destroy()
        pure = [ns3_channel.pure_run(program, d, count, INTERVAL, SIZE, range_m=RANGE, run=k)[1]
                for k in range(1, seeds + 1)]
        p_emu, p_pure = got / count, sum(pure) / (count * seeds)
        half = ci95(p_emu, count, p_pure, count * seeds)
        rows.append({"distance_m": d, "sockets": round(p_emu, 4), "pure_ns3": round(p_pure, 4),
                     "ci95": round(half, 4), "agree": abs(p_emu - p_pure) <= half})
        print(f"  {d:5.1f} m  sockets {p_emu:.3f}  pure ns-3 {p_pure:.3f} (+-{half:.3f})", flush=True)
    return rows


def contention(run_dir: Path) -> dict[str, Any]:
    count, interval, size = 8000, 0.00025, 1400   # 45 Mb/s offered per flow for 2 s: more than the medium carries
    mesh = Mesh(["a", "b", "c", "d"], run_dir / "contention", channel="ns3", range_m=RANGE).create()
    try:
        mesh.apply({}, {"a": (0.0, 0.0), "b": (3.0, 0.0), "c": (0.0, 3.0), "d": (3.0, 3.0)})
        (alone_ab,) = mesh.udp_flows([("a", "b")], count=count, interval=interval, size=size)
        (alone_cd,) = mesh.udp_flows([("c", "d")], count=count, interval=interval, size=size)
        both_ab, both_cd = mesh.udp_flows([("a", "b"), ("c", "d")], count=count, interval=interval, size=size)
        lag = mesh.ns3.lag if mesh.ns3 else None
    finally:
        mesh.destroy()
    out = {"offered": count, "alone": [alone_ab, alone_cd], "together": [both_ab, both_cd],
           "max_lag_ms": lag.max_ms if lag else None}
    print(f"  contention: alone {alone_ab}, {alone_cd}; together {both_ab}, {both_cd} of {count}", flush=True)
    return out


def real_time(run_dir: Path, sizes: list[int], seconds: float) -> list[dict[str, Any]]:
    rows = []
    limit, ns3_channel.MAX_NODES = ns3_channel.MAX_NODES, max(sizes)  # measuring the limit: past it too
    try:
        return _real_time(run_dir, sizes, seconds, rows)
    finally:
        ns3_channel.MAX_NODES = limit


def _real_time(run_dir: Path, sizes: list[int], seconds: float, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    for n in sizes:
        names = [f"n{k}" for k in range(n)]
        mesh = Mesh(names, run_dir / f"rt{n}", channel="ns3", range_m=RANGE).create()
        try:  # a grid 1 m apart: every node hears every other
            side = math.ceil(math.sqrt(n))
            mesh.apply({}, {name: (1.0 * (k % side), 1.0 * (k // side)) for k, name in enumerate(names)})
            time.sleep(1.5)
            assert mesh.ns3 is not None
            before = mesh.ns3.lag
            procs = [subprocess.Popen(mesh.exec_argv(name, [sys.executable, "-c", LOAD, mesh.broadcast, str(seconds)]),
                                      preexec_fn=die_with_parent()) for name in names]
            for p in procs:
                p.wait(seconds + 30)
            time.sleep(1.2)
            lag, mac = mesh.ns3.lag, mesh.ns3.mac
        finally:
            mesh.destroy()
        late = lag.late - before.late
        rows.append({"nodes": n, "max_lag_ms": round(lag.max_ms, 1), "late_probes": late,
                     "probes": lag.probes - before.probes, "frames": mac.sent})
        print(f"  {n:3d} nodes: max lag {lag.max_ms:.1f} ms, late probes {late} of {lag.probes - before.probes}",
              flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=400, help="datagrams per distance")
    ap.add_argument("--seeds", type=int, default=5, help="pure ns-3 runs per distance")
    ap.add_argument("--seconds", type=float, default=8.0, help="load per real-time step")
    ap.add_argument("--nodes", default="6,12,18,24,32,40", help="node counts of the real-time steps")
    results.add_argument(ap)
    ap.add_argument("--run-dir", default="/tmp/erni-bench-ns3")
    args = ap.parse_args()
    for reason in (unavailable_reason(), ns3_channel.unavailable_reason()):
        if reason:
            print(f"bench_ns3_channel: {reason}", file=sys.stderr)
            return 2
    run_dir = Path(args.run_dir)
    print("delivery ratio by distance (range 10 m):", flush=True)
    curve = delivery(run_dir, args.count, args.seeds)
    print("contention:", flush=True)
    shared = contention(run_dir)
    print("real time:", flush=True)
    rt = real_time(run_dir, [int(x) for x in args.nodes.split(",")], args.seconds)
    keep = [r["nodes"] for r in rt if r["late_probes"] == 0]
    agree = sum(r["agree"] for r in curve)
    table = ["| distance (m) | through the sockets | pure ns-3 | 95 % CI of the difference | agree |",
             "|---|---|---|---|---|"]
    table += [f"| {r['distance_m']:g} | {r['sockets']:.3f} | {r['pure_ns3']:.3f} | ±{r['ci95']:.3f} | "
              f"{'yes' if r['agree'] else '**no**'} |" for r in curve]
    rt_table = ["| nodes | largest lag (ms) | probes later than 50 ms | probes |", "|---|---|---|---|"]
    rt_table += [f"| {r['nodes']} | {r['max_lag_ms']} | {r['late_probes']} | {r['probes']} |" for r in rt]
    alone, together = shared["alone"], shared["together"]
    about = ("the ns-3 channel of the real-mesh tier (802.11a ad hoc, LogDistance + Nakagami, Minstrel; "
             f"range {RANGE:g} m) against a pure ns-3 run of the same configuration; "
             f"{args.count} datagrams of {SIZE} bytes at {1 / INTERVAL:g}/s per distance, {args.seeds} pure ns-3 seeds")
    results.write("bench_ns3_channel", [
        results.target("delivery ratio by distance: ERNI's sockets vs pure ns-3", "within the 95 % CI",
                       "pure ns-3, same configuration", f"{agree} of {len(curve)} distances agree",
                       agree == len(curve)),
        results.target("contention: two flows share the medium", "each gets less than alone",
                       f"alone {alone[0]} and {alone[1]} of {shared['offered']}",
                       f"together {together[0]} and {together[1]}",
                       together[0] < alone[0] and together[1] < alone[1]),
        results.target("real time: nodes with team traffic and no probe 50 ms late", "reported",
                       f"MAX_NODES = {ns3_channel.MAX_NODES}", f"up to {max(keep) if keep else 0} nodes", None),
    ], about=about, path=args.results, tables=[
        {"title": "Delivery ratio against distance", "markdown": "\n".join(table)},
        {"title": "Lag of the real-time simulator", "markdown": "\n".join(rt_table)}])
    return 0


if __name__ == "__main__":
    sys.exit(main())
