"""Team scale across two hosts: does a team split over two machines hold real time?

Two network namespaces on one segment stand for two hosts, each pinned to a CPU of its own
(taskset). Host A runs the world (the simulated robots, their SNMP nodes, the radio model), the
control node, `erni watch` and the first `--world-share` of the robots' agents (`erni sim --listen A
--agent-host B --agents-here N`, as `bench/bench_team.py` starts a team); host B runs the rest
(`erni sim --join` with the bundle host A wrote). The measurement is bench_team.py's: the interval
between a robot's consecutive Poses at the control node, every robot heard. CPU per robot is the
median over both hosts' agents. Needs root (network namespaces).

    sudo python bench/bench_team_hosts.py [--robots 50,150] [--window 20] [--world-share 0.35]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_team import arguments, header, report, run  # noqa: E402  # bench/bench_team.py

from erni.blackboard.errors import ErniError  # noqa: E402

INNER = "ERNI_BENCH_HOSTS"  # set in the re-run inside host A: the hosts' addresses and host B's namespace


def pinned(cpu: int, argv: list[str]) -> list[str]:
    """`argv` on CPU `cpu` only, when this machine has it."""
    # the machine's CPUs, not this process's: host A's process is pinned to CPU 0 and starts host B's
    return ["taskset", "-c", str(cpu), *argv] if cpu < (os.cpu_count() or 1) else argv


def agents_under(pid: int) -> dict[str, int]:
    """The agents a `erni sim --join` (process `pid`) runs: name -> PID, from /proc."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid and b"erni.sim.radio" in argv:
            found[Path(argv[argv.index(b"erni.sim.radio") + 1].decode()).stem] = int(entry.name)
    return found


def join_when_written(bundle: Path, netns: str, log: Path, joiners: list[subprocess.Popen[bytes]]) -> None:
    """Start host B's `erni sim --join` once host A has written its bundle."""
    deadline = time.monotonic() + 120
    while not (bundle / "join.json").exists():
        if time.monotonic() > deadline:
            return
        time.sleep(0.1)
    with open(log, "ab") as out:
        joiners.append(subprocess.Popen(["ip", "netns", "exec", netns, *pinned(1, [sys.executable, "-m", "erni", "sim",
                                                                                  "--join", str(bundle)])],
                                        stdout=out, stderr=subprocess.STDOUT))


def inner(args: argparse.Namespace, hosts: dict[str, str]) -> int:
    """In host A: each team across the two hosts, measured."""
    import results  # bench/results.py

    targets = []
    header(args.idle, f"; host A {hosts['a']} (CPU 0): world, control node, watcher and {args.world_share:.0%} of the "
                      f"agents; host B {hosts['b']} (CPU 1): the rest")
    for n in [int(x) for x in args.robots.split(",") if x]:
        here = round(n * args.world_share)
        what = f" across two hosts (a CPU each; {here} + {n - here} agents)"
        tmp = tempfile.mkdtemp(prefix="bench-hosts-")  # kept when the run fails: its logs say why
        try:
            r = measure(n, args, hosts, here, Path(tmp))
        except (SystemExit, ErniError) as err:  # it did not come up, or its robots would not walk
            print(f"| {n} | did not come up: {str(err).splitlines()[0][:200]} (logs in {tmp}) |", flush=True)
            targets.append(results.target(f"{n} robots in real time{what}", "Pose interval p99 ≤ 2x the period, "
                                          "every robot heard", "the 0.1 s Pose period",
                                          f"did not come up: {str(err).splitlines()[0].split('; logs in ')[0][:160]}",
                                          False))
            continue
        targets.append(report(n, r, what))
        shutil.rmtree(tmp, ignore_errors=True)
    results.write("bench_team_hosts", targets, path=args.results, about=(
        "does a team split over two hosts (network namespaces, a CPU each) hold real time: the Pose interval "
        "at the control node"))
    return 0


def measure(n: int, args: argparse.Namespace, hosts: dict[str, str], here: int, tmp: Path) -> dict[str, float]:
    """One team of `n` robots, `here` of their agents on host A, measured as bench_team measures one."""
    run_dir = tmp / "run"
    joiners: list[subprocess.Popen[bytes]] = []
    threading.Thread(target=join_when_written, daemon=True,
                     args=(run_dir / "hosts" / "host-2", hosts["netns_b"], tmp / "join.log", joiners)).start()
    try:
        return run(n, args.window, args.idle,
                   team_kw={"listen": hosts["a"], "agent_hosts": [hosts["b"]], "agents_here": here, "run_dir": run_dir},
                   more_pids=lambda: agents_under(joiners[0].pid) if joiners else {})
    finally:
        for joiner in joiners:
            try:
                joiner.wait(30)  # the run ended: it stops its agents
            except subprocess.TimeoutExpired:
                joiner.kill()


def main() -> int:
    args = arguments(__doc__ or "", "50,150", {"--world-share": dict(
        type=float, default=0.35, help="the share of the robots whose agents run on host A, beside the simulator, "
        "the control node and the watcher (default 0.35: about what balances the two CPUs)")})
    if os.environ.get(INNER):
        return inner(args, json.loads(os.environ[INNER]))
    from erni.sim.netns import Mesh, NetnsError

    with tempfile.TemporaryDirectory(prefix="bench-hosts-mesh-") as tmp:
        mesh = Mesh(["host-a", "host-b"], tmp)
        try:
            mesh.create()
        except NetnsError as err:
            raise SystemExit(f"bench_team_hosts: {err}") from None
        try:
            mesh.apply({frozenset(("host-a", "host-b")): 1.0})
            hosts = {"a": mesh.node("host-a").address, "b": mesh.node("host-b").address,
                     "netns_b": mesh.node("host-b").netns}
            argv = mesh.exec_argv("host-a", pinned(0, [sys.executable, __file__, *sys.argv[1:]]))
            return subprocess.run(argv, env={**os.environ, INNER: json.dumps(hosts)}).returncode
        finally:
            mesh.destroy()


if __name__ == "__main__":
    sys.exit(main())
