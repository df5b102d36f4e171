"""The real-mesh tier beside the loopback tier, in the same run: round trips by hops, link loss -> stop, discovery.

Both tiers run the same team at the same time (`erni sim`'s `Team`, scenario `mesh-line`: the control node and
robot1..robot3 on a line 5.5 m apart with R = 10 m, so robot k is k radio hops from the control
node; robot4 and robot5 parked out of everyone's range), with the mission plugin network-aware
(policy hold). The loopback tier: agents on 127.0.1.N behind the simulated radio filter, MobiNet
over SNMP. The real-mesh tier (`--netns`, root): agents in namespaces, the radio as nftables
rules, babeld routing, MobiNet reading babeld.

1. Task round trip by hops: a `BotMotion clear` (the robot's motion plugin answers it at once)
   sent by a client to the control node, forwarded to robot k, its final result back to the
   client; samples alternate between the tiers so that both see the same load. Floor: a raw
   UDP echo between the control node's and robot k's addresses (their namespaces in the mesh
   tier), through the same network, in the same run.
2. Link loss -> network-aware stop: robot3 drives a remote goto; the simulator's hand moves it
   11 m sideways, out of every node's range (its links are gone at that instant); the time
   until the robot stands still (|v| < 0.01 m/s and |w| < 0.02 rad/s for 1 s) because its
   mission held it.
3. Discovery of a new robot: robot4 (then robot5) is moved from its parking place to 1 hop
   (beside the control node), then 4 hops (after robot3) away; the time until the control
   node's directory lists it as up.

    sudo python bench/bench_mesh.py [--samples 30] [--losses 5]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from erni.blackboard import Task  # noqa: E402
from erni.blackboard.schemas import ResultUpdate  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.sim.netns import unavailable_reason  # noqa: E402
from erni.sim.scenario import find_scenario, load_scenario  # noqa: E402
from erni.sim.team import CONTROL, Team  # noqa: E402

FAST = {"beacon_period": 0.3, "peer_timeout": 1.5, "task_ttl": 60.0}
PARKED = {"robot4": (-13.75, -11.0), "robot5": (8.25, -11.0)}      # out of everyone's range
JOIN = {"robot4": ((-13.75, -5.5), 1), "robot5": ((8.25, 0.0), 4)}  # where they join: (x, y), hops

ECHO_SERVER = """
    import socket, sys
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind((sys.argv[1], 47998))
    print("ready", flush=True); s.settimeout(30)
    try:
        while True:
            data, peer = s.recvfrom(64); s.sendto(data, peer)
    except socket.timeout:
        pass
"""
ECHO_CLIENT = """
    import socket, sys, time, statistics
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind((sys.argv[1], 0)); s.settimeout(1)
    rtts = []
    for i in range(int(sys.argv[3])):
        t = time.perf_counter(); s.sendto(b"%d" % i, (sys.argv[2], 47998))
        try:
            s.recv(64); rtts.append(time.perf_counter() - t)
        except socket.timeout:
            pass
        time.sleep(0.01)
    print(statistics.median(rtts) * 1000, len(rtts))
"""


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))] if s else float("nan")


def scenario() -> Any:
    base = load_scenario(find_scenario("mesh-line")).with_robots(5)
    starts = [r if r.name not in PARKED else r.model_copy(update={"x": PARKED[r.name][0], "y": PARKED[r.name][1]})
              for r in base.starts()]
    return base.model_copy(update={"robot": starts})


class Bench:
    """One tier's team and what was measured on it."""

    def __init__(self, netns: bool) -> None:
        self.tier = "netns" if netns else "loopback"
        self.team = Team(scenario(), headless=True, netns=netns, mission=True, transport=FAST)
        self.out: dict[str, Any] = {"rtt": {1: [], 2: [], 3: []}, "loss_to_stop": []}

    def start(self) -> None:
        t0 = time.monotonic()
        self.team.start(timeout=120)
        self.out["up"] = time.monotonic() - t0
        wait_until(lambda: self.up() >= {"robot1", "robot2", "robot3"}, timeout=60)

    def up(self) -> set[str]:
        return {n for n, p in self.team.peers(1.0).items() if p.up}

    def final(self, uid: str, timeout: float = 30.0) -> Any:
        client = self.team.client()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            msg = client.receive(0.05)
            if (msg and msg.kind == "task.result" and isinstance(msg.body, ResultUpdate) and msg.body.uid == uid
                    and msg.body.result.state.done):
                return msg.body.result
        raise RuntimeError(f"{self.tier}: task {uid} had no final result within {timeout} s")

    def round_trip(self, hops: int) -> None:
        client = self.team.client()
        task = Task(verb="BotMotion", preposition="clear", destination=f"robot{hops}", source=client.endpoint.name)
        t = time.perf_counter()
        client.send(self.team.control_address, "task.add", task)
        self.final(task.uid)
        self.out["rtt"][hops].append(time.perf_counter() - t)

    def echo_floor(self) -> None:
        team, floors = self.team, {}
        for hops in (1, 2, 3):
            robot = f"robot{hops}"
            server_argv = [sys.executable, "-c", textwrap.dedent(ECHO_SERVER), team.address_of(robot)]
            client_argv = [sys.executable, "-c", textwrap.dedent(ECHO_CLIENT), team.address_of(CONTROL),
                           team.address_of(robot), "200"]
            if team.mesh is not None:
                server_argv, client_argv = team.mesh.exec_argv(robot, server_argv), team.mesh.exec_argv(CONTROL, client_argv)
            server = subprocess.Popen(server_argv, stdout=subprocess.PIPE, text=True)
            try:
                assert server.stdout is not None and server.stdout.readline().strip() == "ready"
                median, got = subprocess.run(client_argv, capture_output=True, text=True, check=True,
                                             timeout=60).stdout.split()
                floors[hops] = (float(median) / 1000, int(got))
            finally:
                server.kill()
                server.wait()
        self.out["echo"] = floors

    def link_loss(self) -> None:
        team = self.team
        robot = team.robot("robot3")
        home = self.out.setdefault("home", (robot.x, robot.y))
        team.teleport("robot3", *home)
        wait_until(lambda: "robot3" in self.up(), timeout=60)
        time.sleep(3.0)  # links and MobiNet's readings settle at home
        goal = (home[0] - 2.75, home[1])  # toward robot2: every link stays loss-free on the way
        task = team.send_task("robot3", "RemoteBotMotion", "goto", x=goal[0], y=goal[1], speed=0.3)
        wait_until(lambda: abs(robot.v) > 0.25, timeout=20)
        time.sleep(1.0)
        t_loss = time.monotonic()
        team.teleport("robot3", robot.x, robot.y + 11.0)  # out of everyone's range at once (and the parked robots')
        self.out["loss_to_stop"].append(self._stopped_after(robot, t_loss) - t_loss)
        team.teleport("robot3", *home)
        cancel = team.send_task("robot3", "RemoteBotMotion", "cancel", task=task.uid)
        self.final(cancel.uid, 60)

    @staticmethod
    def _stopped_after(robot: Any, since: float, hold: float = 1.0, timeout: float = 60.0) -> float:
        """When the robot came to rest for `hold` seconds after `since` (polled at 200 Hz)."""
        still_since: float | None = None
        time.sleep(0.2)  # the teleport's own emergency stop, before the goto drives again
        while time.monotonic() - since < timeout:
            now = time.monotonic()
            if abs(robot.v) < 0.01 and abs(robot.w) < 0.02:
                still_since = still_since or now
                if now - still_since >= hold:
                    return still_since
            else:
                still_since = None
            time.sleep(0.005)
        raise RuntimeError("the robot did not stop")

    def discovery(self) -> None:
        found: dict[str, tuple[float, int]] = {}
        for name, ((x, y), hops) in JOIN.items():
            known = self.team.peers(1.0)
            assert name not in known, f"{self.tier}: {name} was heard before it joined: {known[name]}"
            t = time.monotonic()
            self.team.teleport(name, x, y)
            while name not in self.up():
                if time.monotonic() - t > 90:
                    raise RuntimeError(f"{self.tier}: {name} not discovered within 90 s")
                time.sleep(0.05)
            found[name] = (time.monotonic() - t, hops)
        self.out["discovery"] = found


def load_average() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=30, help="round trips per hop count and tier")
    parser.add_argument("--losses", type=int, default=5, help="link losses per tier")
    results.add_argument(parser)
    args = parser.parse_args()
    targets = []
    reason = unavailable_reason()
    if reason:
        print(f"bench_mesh: the real-mesh tier cannot run here: {reason}", file=sys.stderr)
        return 2
    loads = [load_average()]
    benches = [Bench(False), Bench(True)]
    try:
        for bench in benches:  # one after the other: each start-up time on a machine without the other team
            print(f"{bench.tier}: starting...", file=sys.stderr, flush=True)
            bench.start()
        print("round trips...", file=sys.stderr, flush=True)
        for _ in range(args.samples):
            for hops in (1, 2, 3):
                for bench in benches:
                    bench.round_trip(hops)
        loads.append(load_average())
        for bench in benches:
            bench.echo_floor()
        print("link losses...", file=sys.stderr, flush=True)
        for _ in range(args.losses):
            for bench in benches:
                bench.link_loss()
        print("discovery...", file=sys.stderr, flush=True)
        for bench in benches:
            bench.discovery()
        loads.append(load_average())
    finally:
        for bench in benches:
            bench.team.stop()
    loop, mesh = benches[0].out, benches[1].out
    ms = 1000.0
    print(f"\nload average {min(loads):.1f}-{max(loads):.1f}; both teams running; {args.samples} round trips "
          f"per hop count, {args.losses} link losses, per tier\n")
    print(f"team up: loopback {loop['up']:.1f} s, netns {mesh['up']:.1f} s\n")
    print("| hops | loopback p50 | p90 | netns p50 | p90 | ratio netns/loopback p50 | UDP echo loopback | UDP echo netns |")
    print("|---|---|---|---|---|---|---|---|")
    for hops in (1, 2, 3):
        lo, me = loop["rtt"][hops], mesh["rtt"][hops]
        print(f"| {hops} | {statistics.median(lo) * ms:.1f} ms | {pct(lo, 0.9) * ms:.1f} ms | "
              f"{statistics.median(me) * ms:.1f} ms | {pct(me, 0.9) * ms:.1f} ms | "
              f"{statistics.median(me) / statistics.median(lo):.2f} | {loop['echo'][hops][0] * ms:.3f} ms | "
              f"{mesh['echo'][hops][0] * ms:.3f} ms |")
        ratio = statistics.median(me) / statistics.median(lo)
        targets.append(results.target(f"task round trip, {hops} hop(s), mesh / loopback", "equal within the noise",
                                      f"raw UDP echo on the mesh, {mesh['echo'][hops][0] * ms:.3f} ms",
                                      f"{ratio:.2f}x ({statistics.median(me) * ms:.1f} ms)", None))
    print("\n| measure | loopback | netns | ratio |\n|---|---|---|---|")
    lo, me = statistics.median(loop["loss_to_stop"]), statistics.median(mesh["loss_to_stop"])
    print(f"| link loss -> network-aware stop (median of {args.losses}; each: "
          f"{', '.join(f'{t:.2f}' for t in loop['loss_to_stop'])} / {', '.join(f'{t:.2f}' for t in mesh['loss_to_stop'])} s) "
          f"| {lo:.2f} s | {me:.2f} s | {me / lo:.2f} |")
    targets.append(results.target("link loss → network-aware stop", "reported", f"the loopback tier, {lo:.2f} s",
                                  f"{me / lo:.1f}x ({me:.2f} s)", None))
    for name, (t_loop, hops) in loop["discovery"].items():
        t_mesh = mesh["discovery"][name][0]
        print(f"| new robot {hops} hop{'s' if hops > 1 else ''} away -> up at the control node (one sample) "
              f"| {t_loop:.2f} s | {t_mesh:.2f} s | {t_mesh / t_loop:.2f} |")
        targets.append(results.target(f"new robot {hops} hop(s) away → up at the control node", "reported",
                                      f"the loopback tier, {t_loop:.2f} s", f"{t_mesh / t_loop:.1f}x ({t_mesh:.2f} s)",
                                      None))
    results.write("bench_mesh", targets, path=args.results,
                  about="the real-mesh tier beside the loopback tier in the same run (scenario mesh-line)")
    return 0


if __name__ == "__main__":
    threading.current_thread().name = "bench-mesh"
    sys.exit(main())
