"""Team scale: does `erni sim --headless --robots N` hold real time on this machine?

For each N a whole simulated team is started as `erni sim` starts it (one agent process per
robot with transport, motion, mobinet and mission; the control node; the world and the SNMP
network nodes in this process, the simulated robots in its robot host's). "sim %" is the two
together. "SIPs skipped" is the share of the simulated robots' SIP slots that their host came
too late for (the machine too busy: each is a Pose its robot cannot publish). Every robot random-walks (or stands, with
`--idle`); `erni watch --json` on the control node, in a process of its own as a user runs it,
records every Pose the control node holds for `--window` seconds. Every walk is running when the
window opens (`bench/hall.py`); a walk that ends within it (its robot's link lost) is counted, as
the robot then stands and its Pose goes out on change, not every period. Real time holds when the
interval between consecutive Poses of a robot at the control node has p99 within 2x the 0.1 s
pose period and every robot is heard by the control node. The floor of the interval is the period itself (0.1 s), an input of the
simulation, not a finding. CPU (% of one core) and RSS per agent come from /proc.

    python bench/bench_team.py [--robots 10,20,50] [--window 20] [--idle]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hall import start_hall_team  # noqa: E402  # bench/hall.py
from procstat import cpu_seconds, rss_mb  # noqa: E402  # bench/procstat.py

PERIOD = 0.1


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, max(0, math.ceil(q * len(s)) - 1))] if s else float("nan")


def run(n: int, window: float, idle: bool, *, team_kw: dict[str, Any] | None = None,
        more_pids: Callable[[], dict[str, int]] | None = None) -> dict[str, float]:
    """One team of `n` robots measured for `window` s; `team_kw` goes to `Team`, `more_pids` names the
    processes of agents this process did not start (an agent host's)."""
    team, startup = start_hall_team(f"team{n}", n, walk=not idle, settle=3.0, **(team_kw or {}))
    watcher = None
    with tempfile.TemporaryFile("w+b") as out:
        try:
            # the watcher is a process of its own, as a user's `erni watch` is: in the simulator's
            # process it took the interpreter from the robots' physics and SIPs
            host, port = team.control_address
            watcher = subprocess.Popen([sys.executable, "-m", "erni", "watch", "--via", f"{host}:{port}",
                                        "--identity", str(team.cli_identity), "--json"],
                                       stdout=out, stderr=subprocess.DEVNULL)
            deadline = time.monotonic() + 60
            while os.fstat(out.fileno()).st_size == 0:
                if watcher.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit(f"bench_team: `erni watch` on the control node {host}:{port} printed no "
                                     f"event (exit {watcher.poll()}); expected a stream of Poses")
                time.sleep(0.1)
            pids = {name: a.proc.pid for name, a in team.agents.items() if a.proc}
            pids.update(more_pids() if more_pids is not None else {})
            cpu0 = {name: cpu_seconds(pid) for name, pid in pids.items()}
            sims = [os.getpid()] + ([team.host.pid] if team.host.pid else [])  # the simulator and its robot host
            sim0 = sum(cpu_seconds(pid) for pid in sims)
            watch0 = cpu_seconds(watcher.pid)
            load0 = os.getloadavg()[0]
            team.sips_since()
            first = os.fstat(out.fileno()).st_size
            start = time.monotonic()
            time.sleep(window)
            last = os.fstat(out.fileno()).st_size
            elapsed = time.monotonic() - start
            sips, skipped = team.sips_since()
            cpu = {name: (cpu_seconds(pid) - cpu0[name]) / elapsed * 100 for name, pid in pids.items()}
            sim_cpu = (sum(cpu_seconds(pid) for pid in sims) - sim0) / elapsed * 100
            watch_cpu = (cpu_seconds(watcher.pid) - watch0) / elapsed * 100
            rss = {name: rss_mb(pid) for name, pid in pids.items()}
            heard = sum(1 for p in team.peers().values() if p.name in team.names)
            load1 = os.getloadavg()[0]
        finally:
            if watcher is not None:
                watcher.kill()
                watcher.wait()
            team.stop()
        out.seek(0)
        printed = out.read(last)
    stamps: dict[str, list[float]] = {name: [] for name in team.names}
    stopped: set[str] = set()  # robots whose walk ended in the window: they stand, their Poses go on change
    for line in printed[first:].split(b"\n")[1:-1]:  # whole lines only, within the window
        ev = json.loads(line)
        robot = ev["data"].get("robot")
        if ev["type"] == "Pose" and ev["agent"] == "control" and robot in stamps:
            stamps[robot].append(float(ev["data"]["stamp"]))
        elif (ev["type"] == "Task" and ev["data"].get("preposition") == "randomwalk"
              and (ev["data"].get("result") or {}).get("state") in ("succeeded", "failed", "cancelled")):
            stopped.add(ev["data"].get("destination"))
    intervals: list[float] = []
    for seq in stamps.values():
        seq = sorted(set(seq))
        intervals += [b - a for a, b in zip(seq, seq[1:])]
    poses = sum(len(set(s)) for s in stamps.values())
    robots = list(team.names)
    return {"robots": n, "startup": startup, "p50": pct(intervals, 0.5) * 1000, "p99": pct(intervals, 0.99) * 1000,
            "share": poses / (n * elapsed / PERIOD), "heard_peers": heard,
            "heard_poses": sum(1 for s in stamps.values() if s), "stopped": len(stopped),
            "cpu": statistics.median(cpu[r] for r in robots), "control_cpu": cpu["control"], "sim_cpu": sim_cpu, "watch_cpu": watch_cpu,
            "rss": statistics.median(rss[r] for r in robots), "load": (load0 + load1) / 2,
            "skipped": skipped / max(1, sips + skipped)}


def header(idle: bool, extra: str = "") -> None:
    """What the table's rows say, and its head."""
    print(f"robots {'stand' if idle else 'random-walk'}; Pose period {PERIOD * 1000:.0f} ms (input); "
          f"real time = interval p99 <= {2 * PERIOD * 1000:.0f} ms and every robot heard{extra}")
    print("| robots | start-up s | interval p50 / p99 ms at control | p99 / period | Poses at control / expected "
          "| heard (directory / Poses) | walks ended | SIPs skipped | CPU / robot % | control % | sim % | watcher % | "
          "RSS / robot MB | load | real time |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def report(n: int, r: dict[str, float], what: str = "") -> dict[str, Any]:
    """Print the row of a team of `n` robots measured as `r`; return its target."""
    import results  # bench/results.py

    ok = r["p99"] <= 2 * PERIOD * 1000 and r["heard_peers"] == n and r["heard_poses"] == n and not r["stopped"]
    print(f"| {n} | {r['startup']:.1f} | {r['p50']:.0f} / {r['p99']:.0f} | {r['p99'] / (PERIOD * 1000):.1f} | "
          f"{r['share']:.2f} | {r['heard_peers']} / {r['heard_poses']} of {n} | {r['stopped']} | {r['skipped']:.1%} | "
          f"{r['cpu']:.1f} | {r['control_cpu']:.1f} | {r['sim_cpu']:.1f} | {r['watch_cpu']:.1f} | {r['rss']:.0f} | "
          f"{r['load']:.1f} | {'yes' if ok else 'no'} |", flush=True)
    return results.target(
        f"{n} robots in real time{what}", "Pose interval p99 ≤ 2x the period, every robot heard",
        f"the {PERIOD:g} s Pose period", f"p99 {r['p99'] / (PERIOD * 1000):.1f}x ({r['p99']:.0f} ms), "
        f"{r['share']:.2f} of the Poses, {r['skipped']:.1%} of SIPs skipped", ok)


def arguments(doc: str, robots: str, more: dict[str, dict[str, Any]] | None = None) -> argparse.Namespace:
    """The options of a team benchmark: the team sizes (default `robots`), the window, idle, --results, `more`."""
    import results  # bench/results.py

    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", default=robots)
    ap.add_argument("--window", type=float, default=20.0)
    ap.add_argument("--idle", action="store_true", help="robots stand (default: they random-walk)")
    for flag, kw in (more or {}).items():
        ap.add_argument(flag, **kw)
    results.add_argument(ap)
    return ap.parse_args()


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    args = arguments(__doc__ or "", "10,20,50")
    targets = []
    header(args.idle)
    for n in [int(x) for x in args.robots.split(",") if x]:
        targets.append(report(n, run(n, args.window, args.idle)))
    results.write("bench_team", targets, path=args.results,
                  about="does `erni sim --headless --robots N` hold real time: the Pose interval at the control node")
    return 0


if __name__ == "__main__":
    sys.exit(main())
