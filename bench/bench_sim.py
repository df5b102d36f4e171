"""Simulator scale: how many robot agents one machine sustains in real time, and the kinematic mode.

Agents mode (`erni sim`: one real agent process per robot). For each team size N: the
team's start-up time; then every robot random-walks while a watcher on the control node
records every Pose for `--window` seconds. A robot agent publishes its Pose every 0.1 s from
its motion loop, so the spread of the intervals between consecutive Pose stamps (made by the
robot's agent) is the jitter of its control loop, and the share of those Poses that reach
the control node says whether the team keeps up. Poses are read from every robot's own
agent (its loop) and from the control node (what the GUI sees). CPU (% of one core) and RSS per agent come
from /proc. In the same run, the import floor: a process that only imports what a robot
agent imports (blackboard, transport, motion, mobinet, mission), and a bare interpreter.

Robot host (`RobotHost`, every simulated robot of `erni sim` in one thread): for 10, 120 and
1000 robots opened through ARCOS and driving with their sonar firing, the milliseconds of one
core that 100 ms of simulated time costs (physics steps, sonar, SIPs), against the 100 ms
real-time budget and against the robot-by-robot path (`vectorised=False`) in the same run.

The radio feed (`Team`'s feed: every robot's true position to the simulated MANET, 10 times a
second): the milliseconds of one core a feed of N nodes costs, each node moved up to 5 cm, against
the 100 ms between feeds. "loss-free": every pair inside the loss-free range (the benchmark hall,
no link changes); "lossy band": every pair between the loss-free range and the range (every
link's quality changes at every feed).

Kinematic mode (`erni experiment spread-*`): 120 and 1000 robots stepped in-process by the
mission's `spread_step`; the real-time factor is simulated seconds per wall-clock second.

    python bench/bench_sim.py [--robots 5,10,20] [--window 10] [--host-robots 10,120,1000]
                              [--physics-hz 20] [--feed-nodes 50,120] [--kinematic-robots 120,1000]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from hall import start_hall_team  # noqa: E402  # bench/hall.py
from procstat import cpu_seconds, rss_mb  # noqa: E402  # bench/procstat.py

from erni.blackboard.schemas import WatchEvent, WatchRequest  # noqa: E402

AGENT_IMPORTS = "import erni.blackboard, erni.transport.plugin, erni.plugins.motion, erni.plugins.mobinet, erni.plugins.mission"


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


def import_floor(code: str) -> float:
    """RSS (MB) of a fresh interpreter that ran `code` and then waits, measured from outside."""
    p = subprocess.Popen([sys.executable, "-c", f"{code}\nimport sys; sys.stdout.write('ok\\n'); "
                          "sys.stdout.flush(); sys.stdin.read()"], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1])
    assert p.stdout is not None and p.stdin is not None
    p.stdout.readline()
    rss = rss_mb(p.pid)
    p.stdin.close()
    p.wait(10)
    return rss


def agents_run(n: int, window: float) -> dict[str, float]:
    """Start an n-robot team, random-walk every robot, watch poses for `window` s; return numbers."""
    team, startup = start_hall_team(f"bench{n}", n, walk=True, settle=2.0)
    try:
        client = team.client()
        pids = {name: a.proc.pid for name, a in team.agents.items() if a.proc}
        cpu0 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        sim0 = cpu_seconds(os.getpid())
        from erni.transport.endpoint import parse_address

        addresses = {p.name: parse_address(p.address) for p in team.peers().values() if p.address}
        stamps: dict[str, list[float]] = {name: [] for name in team.names}  # at each robot's own agent
        relayed: dict[str, list[float]] = {name: [] for name in team.names}  # as the control node has them
        start = time.monotonic()
        next_lease = 0.0
        while time.monotonic() - start < window:
            if time.monotonic() >= next_lease:
                for addr in [team.control_address, *addresses.values()]:
                    client.send(addr, "watch.request", WatchRequest(lease=5.0), reliable=False)
                next_lease = time.monotonic() + 2.0
            msg = client.receive(0.05)
            if msg is None or msg.kind != "watch.event" or not isinstance(msg.body, WatchEvent):
                continue
            ev = msg.body
            robot = ev.data.get("robot")
            if ev.type == "Pose" and robot in stamps:
                (relayed if ev.agent == "control" else stamps)[robot].append(float(ev.data["stamp"]))
        elapsed = time.monotonic() - start
        cpu = {name: (cpu_seconds(pid) - cpu0[name]) / elapsed * 100 for name, pid in pids.items()}
        sim_cpu = (cpu_seconds(os.getpid()) - sim0) / elapsed * 100
        rss = {name: rss_mb(pid) for name, pid in pids.items()}
    finally:
        team.stop()
    intervals = []
    for seq in stamps.values():
        seq = sorted(set(seq))
        intervals += list(np.diff(seq))
    received = sum(len(set(s)) for s in stamps.values())
    at_control = sum(len(set(s)) for s in relayed.values())
    robots = [name for name in team.names]
    return {
        "robots": n, "startup_s": startup,
        "pose_interval_p50_ms": pct(intervals, 0.5) * 1000, "pose_interval_p99_ms": pct(intervals, 0.99) * 1000,
        "poses_delivered_share": received / (n * 10.0 * elapsed),
        "poses_at_control_share": at_control / max(1, received),
        "robot_cpu_pct_median": statistics.median(cpu[r] for r in robots),
        "control_cpu_pct": cpu["control"], "sim_process_cpu_pct": sim_cpu,
        "robot_rss_mb_median": statistics.median(rss[r] for r in robots), "control_rss_mb": rss["control"],
    }


def _arcos(cmd: int, *args: int) -> bytes:
    """A client packet as ARIA sends it (integer arguments only)."""
    from erni.sim.robot import _packet

    body = bytes([cmd]) + b"".join(bytes([0x3B if a >= 0 else 0x1B]) + abs(a).to_bytes(2, "little") for a in args)
    return _packet(body)


def host_tick(n: int, vectorised: bool, ticks: int, physics_hz: float) -> dict[str, float]:
    """Milliseconds per 100 ms of simulated time for n robots in one `RobotHost`, by part.

    Every robot is opened through the real ARCOS bytes (SYNC0-2, OPEN, ENABLE, VEL, RVEL), drives
    and turns with its sonar firing (16 transducers, 2 banks, one per bank every 40 ms), in a
    room with pillars, robots 3 m apart. One simulated 100 ms = physics_hz/10 physics steps, the
    sonar due, and one SIP per robot (`RobotHost.advance`, taken apart to time each part).
    """
    from erni.sim.robot_host import RobotHost
    from erni.sim.swarm import Swarm
    from erni.sim.world import World

    cols = max(1, int(np.ceil(np.sqrt(n))))
    side = cols * 3.0
    pillars = [{"center": [i * 3.0 + 1.5, j * 3.0 + 1.5], "radius": 0.2} for i in range(0, cols, 4) for j in range(0, cols, 4)]
    world = World.from_dict({"bounds": [-2.0, -2.0, side, side], "circle": pillars,
                             "wall": [{"a": [side / 2, -2.0], "b": [side / 2, side / 3]}]})
    host = RobotHost(world, vectorised=vectorised, physics_hz=physics_hz)
    rng = np.random.default_rng(1)
    try:
        for i in range(n):
            robot = host.add_robot(None, port=0)
            robot.x, robot.y = (i % cols) * 3.0, (i // cols) * 3.0
            robot.th = float(rng.uniform(-np.pi, np.pi))
        opening = b"".join([_arcos(0), _arcos(1), _arcos(2), _arcos(1), _arcos(4, 1), _arcos(11, 300),
                            _arcos(21, 10)])
        for ep in host.endpoints:
            ep.firmware.receive(opening, 0.0)
            ep.firmware.take_output()
        dt = 1.0 / physics_hz
        steps_per_tick = max(1, round(0.1 / dt))
        robots, firmwares = host.robots, [ep.firmware for ep in host.endpoints]
        swarm = Swarm(host.world)
        parts = {"physics": 0.0, "sonar": 0.0, "sips": 0.0}
        now = 0.0
        sip_bytes = 0
        for _ in range(ticks):
            for _ in range(steps_per_tick):
                now += dt
                t0 = time.perf_counter()
                if vectorised:  # what RobotHost.advance does
                    swarm.step(robots, dt, now)
                    t1 = time.perf_counter()
                    swarm.fire(firmwares, now)
                else:
                    for r in robots:
                        r.step(dt, now)
                    t1 = time.perf_counter()
                    for fw in firmwares:
                        fw._fire(now)
                t2 = time.perf_counter()
                for fw in firmwares:
                    fw.tick(now, fire=False)
                t3 = time.perf_counter()
                parts["physics"] += t1 - t0
                parts["sonar"] += t2 - t1
                parts["sips"] += t3 - t2
            pulse = _arcos(0)
            for fw in firmwares:  # the client's heartbeat feeds the watchdog (not timed)
                fw.receive(pulse, now)
                sip_bytes += len(fw.take_output())
    finally:
        host.stop()
    out = {k: v / ticks * 1000 for k, v in parts.items()}
    out["total"] = sum(out.values())
    out["sip_bytes"] = sip_bytes / ticks / n
    return out


def feed_cost(n: int, lossy: bool, feeds: int) -> float:
    """CPU ms of one radio feed of `n` nodes on a grid 3 m apart, each moved up to 5 cm."""
    import random

    from erni.sim.manet import ManetNetwork, RadioModel

    side = max(1, int(np.ceil(np.sqrt(n))))
    span = 3.0 * side * 1.5  # the longest distance between two nodes, with room for the moves
    radio = RadioModel(span * 2, span * 1.9) if not lossy else RadioModel(span * 10, 0.0)
    net = ManetNetwork(radio, gps=True)
    pos = {f"r{i}": (3.0 * (i % side), 3.0 * (i // side)) for i in range(n)}
    for name, (x, y) in pos.items():
        net.add_node(name, x, y)
    rng = random.Random(1)
    c0 = time.process_time()
    for _ in range(feeds):
        moved = {k: (x + rng.uniform(-0.05, 0.05), y + rng.uniform(-0.05, 0.05)) for k, (x, y) in pos.items()}
        pos.update(moved)
        net.move_many(moved)
        net.truth()
    return (time.process_time() - c0) / feeds * 1000.0


def kinematic_run(n: int, seconds: float, start: str = "packed") -> list[tuple[str, float, float]]:
    """Time the spread of n robots for `seconds` simulated; return (variant, wall s, real-time factor).

    start "packed": every robot in a 2 m x 2 m square (paper 001's start: everyone within everyone's
    range); "spread": uniform at one robot per 25 m^2, so a robot's 6 m range holds a few neighbours.
    """
    from erni.strategies.potential import SpreadConfig, spread_step

    rng = np.random.default_rng(1)
    half = 1.0 if start == "packed" else 2.5 * np.sqrt(n)
    out = []
    for variant in ("holonomic/physical", "holonomic/delaunay", "nonholonomic/physical", "nonholonomic/delaunay"):
        model, _, hood = variant.partition("/")
        cfg = SpreadConfig(neighbourhood=hood, model=model, range=6.0)
        pos = rng.uniform(-half, half, (n, 2))
        th = rng.uniform(-np.pi, np.pi, n)
        vel, om = np.zeros_like(pos), np.zeros(n)
        t0 = time.perf_counter()
        for _ in range(int(round(seconds / cfg.dt))):
            pos, th, vel, om = spread_step(pos, th, vel, om, cfg)
        wall = time.perf_counter() - t0
        out.append((variant, wall, seconds / wall))
    return out


def main() -> int:
    """Run the benchmark and print a table."""
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", default="5,10,20", help="team sizes for the agents mode (comma-separated)")
    ap.add_argument("--window", type=float, default=10.0, help="seconds of watching per team size")
    ap.add_argument("--host-robots", default="10,120,1000", help="robots in one robot host (comma-separated)")
    ap.add_argument("--host-ticks", type=int, default=20, help="simulated 100 ms rounds timed per size")
    ap.add_argument("--physics-hz", type=float, default=20.0, help="physics rate (erni sim: 20 Hz above 10 robots)")
    ap.add_argument("--feed-nodes", default="50,120", help="nodes of the radio feed (comma-separated)")
    ap.add_argument("--feeds", type=int, default=100, help="radio feeds timed per size")
    ap.add_argument("--kinematic-robots", default="120,1000", help="team sizes for the kinematic mode")
    ap.add_argument("--kinematic-seconds", type=float, default=30.0)
    results.add_argument(ap)
    args = ap.parse_args()
    targets = []
    bare = import_floor("pass")
    floor = import_floor(AGENT_IMPORTS)
    print(f"import floor: bare interpreter {bare:.1f} MB RSS; a robot agent's imports {floor:.1f} MB RSS")
    if args.robots:
        print("\nagents mode (one process per robot agent; robots random-walk; 10 Poses/s per robot expected)")
        head = ("robots", "start s", "pose p50 ms", "pose p99 ms", "poses/10Hz", "at control", "robot CPU %",
                "control CPU %",
                "sim CPU %", "robot RSS MB", "RSS/floor")
        print(" ".join(f"{h:>12}" for h in head), flush=True)
        for n in [int(x) for x in args.robots.split(",") if x]:
            r = agents_run(n, args.window)
            row = (n, r["startup_s"], r["pose_interval_p50_ms"], r["pose_interval_p99_ms"], r["poses_delivered_share"],
                   r["poses_at_control_share"], r["robot_cpu_pct_median"], r["control_cpu_pct"], r["sim_process_cpu_pct"], r["robot_rss_mb_median"],
                   r["robot_rss_mb_median"] / floor)
            print(" ".join(f"{v:>12.3g}" if isinstance(v, float) else f"{v:>12}" for v in row), flush=True)
    print(f"\nthe simulator's robot host alone: ms of one core per 100 ms simulated (budget 100 ms: real time), "
          f"physics at {args.physics_hz:g} Hz, sonar firing, a SIP per robot per 100 ms")
    columns = ("robots", "path", "physics", "sonar", "SIPs", "total", "x budget", "speed-up")
    print(" ".join(f"{h:>10}" for h in columns), flush=True)
    for n in [int(x) for x in args.host_robots.split(",") if x]:
        scalar = host_tick(n, False, max(1, min(args.host_ticks, 2000 // n)), args.physics_hz)
        batch = host_tick(n, True, args.host_ticks, args.physics_hz)
        for name, r in (("by robot", scalar), ("batch", batch)):
            cells = (n, name, r["physics"], r["sonar"], r["sips"], r["total"], r["total"] / 100.0,
                     scalar["total"] / r["total"])
            print(" ".join(f"{v:>10.3g}" if isinstance(v, float) else f"{v:>10}" for v in cells), flush=True)
        targets.append(results.target(f"robot host steps {n} robots with sonar at 10 Hz", "one core, within the "
                                      "100 ms period", "the 100 ms period", f"{batch['total']:.1f} ms per 100 ms "
                                      f"({batch['total'] / 100:.2f}x)", batch["total"] <= 100.0))
    print("\nthe radio feed: ms of one core per feed (10 feeds a second: budget 100 ms)")
    print(" ".join(f"{h:>12}" for h in ("nodes", "radio", "ms / feed", "x budget")), flush=True)
    for n in [int(x) for x in args.feed_nodes.split(",") if x]:
        for name, lossy in (("loss-free", False), ("lossy band", True)):
            ms = feed_cost(n, lossy, max(5, min(args.feeds, 20000 // n)))
            print(" ".join(f"{v:>12.3g}" if isinstance(v, float) else f"{v:>12}" for v in (n, name, ms, ms / 100.0)),
                  flush=True)
    for n in [int(x) for x in args.kinematic_robots.split(",") if x]:
        for start in ("packed", "spread"):
            seconds = args.kinematic_seconds if n <= 200 or start == "spread" else min(args.kinematic_seconds, 2.0)
            print(f"\nkinematic mode: {n} robots, start {start}, {seconds:g} s simulated (dt = 0.2 s)")
            for variant, wall, factor in kinematic_run(n, seconds, start):
                print(f"  {variant:<24} {wall:6.2f} s wall   {factor:6.2f} x real time", flush=True)
                targets.append(results.target(f"kinematic mode, {n} robots {start}, {variant}", "faster than real "
                                              "time", "real time", f"{factor:.2f}x real time", factor >= 1.0))
    results.write("bench_sim", targets, path=args.results,
                  about="the simulator's robot host and kinematic mode at scale")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
