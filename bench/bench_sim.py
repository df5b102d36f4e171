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

Kinematic mode (`erni experiment spread-*`): 120 robots stepped in-process by the mission's
`spread_step`; the real-time factor is simulated seconds per wall-clock second.

    python bench/bench_sim.py [--robots 5,10,20] [--window 10] [--kinematic-robots 120]
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

from erni.sim.scenario import Scenario  # noqa: E402
from erni.sim.team import Team  # noqa: E402
from erni.transport.bridge import WatchEvent, WatchRequest  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")
AGENT_IMPORTS = "import erni.blackboard, erni.transport.bridge, erni.plugins.motion, erni.plugins.mobinet, erni.plugins.mission"


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (s)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def rss_mb(pid: int) -> float:
    """Resident set size of a process (MB)."""
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * PAGE / 1e6


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
    cols = max(1, int(np.ceil(np.sqrt(n))))
    side = cols * 3.0
    scenario = Scenario(name=f"bench{n}", robots={"count": n, "layout": "grid", "spacing": 3.0,
                                                  "origin": [0.0, 0.0], "heading": "random"},
                        radio={"comm_range": 1000.0, "lossless_range": 1000.0},
                        world={"name": "hall", "bounds": [-side / 2 - 3, -3.0, side / 2 + 3, side + 3]})
    team = Team(scenario, headless=True, control_port=0, ui=False)  # robots run what a robot runs
    t0 = time.monotonic()
    try:
        team.start(timeout=60 + 3 * n)
        startup = time.monotonic() - t0
        for name in team.names:
            team.send_task(name, "BotMotion", "randomwalk", speed=0.3, seed=1)
        time.sleep(2.0)
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


def host_cost(n: int, steps: int = 25) -> tuple[float, float]:
    """Milliseconds of one physics step and of one SIP round (sonar cast) for n moving robots in one host."""
    from erni.sim.robot import SimRobotConfig
    from erni.sim.robot_host import RobotHost
    from erni.sim.world import World

    cols = max(1, int(np.ceil(np.sqrt(n))))
    host = RobotHost(World(bounds=(-2.0, -2.0, cols * 3.0, cols * 3.0)))
    try:
        for i in range(n):
            host.add_robot(SimRobotConfig(name=f"r{i}"), port=0)
        for i, ep in enumerate(host.endpoints):
            ep.robot.x, ep.robot.y = (i % cols) * 3.0, (i // cols) * 3.0
            ep.robot.motors_enabled = True
            ep.robot.set_velocity(0.3)
        t0 = time.perf_counter()
        for k in range(steps):
            host.advance(0.02, k * 0.02)
        step = (time.perf_counter() - t0) / steps
        t0 = time.perf_counter()
        for ep in host.endpoints:
            ep.firmware.sip()
        sip = time.perf_counter() - t0
    finally:
        host.stop()
    return step * 1000, sip * 1000


def kinematic_run(n: int, seconds: float) -> list[tuple[str, float, float]]:
    """Time the spread of n robots for `seconds` simulated; return (variant, wall s, real-time factor)."""
    from erni.strategies.potential import SpreadConfig, spread_step

    rng = np.random.default_rng(1)
    out = []
    for variant in ("holonomic/physical", "holonomic/delaunay", "nonholonomic/physical", "nonholonomic/delaunay"):
        model, _, hood = variant.partition("/")
        cfg = SpreadConfig(neighbourhood=hood, model=model, range=6.0)
        pos = rng.uniform(-1, 1, (n, 2))
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
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", default="5,10,20", help="team sizes for the agents mode (comma-separated)")
    ap.add_argument("--window", type=float, default=10.0, help="seconds of watching per team size")
    ap.add_argument("--kinematic-robots", type=int, default=120)
    ap.add_argument("--kinematic-seconds", type=float, default=30.0)
    args = ap.parse_args()
    bare = import_floor("pass")
    floor = import_floor(AGENT_IMPORTS)
    print(f"import floor: bare interpreter {bare:.1f} MB RSS; a robot agent's imports {floor:.1f} MB RSS")
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
    print("\nthe simulator's robot host alone (all simulated robots in the erni sim process)")
    for n in (10, 30, 120):
        step, sip = host_cost(n)
        print(f"  {n:>4} robots: physics step {step:7.1f} ms (x 50/s = {step * 5:5.0f}% of a core), "
              f"SIP round {sip:7.1f} ms (x 10/s = {sip:5.0f}% of a core)", flush=True)
    print(f"\nkinematic mode: {args.kinematic_robots} robots, {args.kinematic_seconds:g} s simulated (dt = 0.2 s)")
    for variant, wall, factor in kinematic_run(args.kinematic_robots, args.kinematic_seconds):
        print(f"  {variant:<24} {wall:6.2f} s wall   {factor:5.2f} x real time", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
