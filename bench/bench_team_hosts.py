"""Team scale across two hosts: does a team split over two machines hold real time?

Two network namespaces on one segment stand for two hosts, each pinned to a CPU of its own
(taskset): host A runs the world (the simulated robots, their SNMP nodes, the radio model), the
control node, `erni watch` and the first half of the robots' agents (`erni sim --listen A
--agent-host B`, as `bench/bench_team.py` starts a team); host B runs the other half (`erni sim
--join` with the bundle host A wrote). The measurement is bench_team.py's: the interval between a
robot's consecutive Poses at the control node, every robot heard. CPU per robot is the median over
both hosts' agents. Needs root (network namespaces).

    sudo python bench/bench_team_hosts.py [--robots 50,150] [--window 20]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_team import arguments, header, report, run  # noqa: E402  # bench/bench_team.py

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
    header(args.idle, f"; host A {hosts['a']} (CPU 0): world, control node, half the agents; "
                      f"host B {hosts['b']} (CPU 1): the other half")
    for n in [int(x) for x in args.robots.split(",") if x]:
        with tempfile.TemporaryDirectory(prefix="bench-hosts-") as tmp:
            run_dir = Path(tmp) / "run"
            joiners: list[subprocess.Popen[bytes]] = []
            starter = threading.Thread(target=join_when_written, daemon=True,
                                       args=(run_dir / "hosts" / "host-2", hosts["netns_b"], Path(tmp) / "join.log",
                                             joiners))
            starter.start()
            try:
                r = run(n, args.window, args.idle, team_kw={"listen": hosts["a"], "agent_hosts": [hosts["b"]],
                                                            "run_dir": run_dir},
                        more_pids=lambda joiners=joiners: agents_under(joiners[0].pid) if joiners else {})
            finally:
                for joiner in joiners:
                    try:
                        joiner.wait(30)  # the run ended: it stops its agents
                    except subprocess.TimeoutExpired:
                        joiner.kill()
            targets.append(report(n, r, " across two hosts (a CPU each)"))
    results.write("bench_team_hosts", targets, path=args.results, about=(
        "does a team split over two hosts (network namespaces, a CPU each) hold real time: the Pose interval "
        "at the control node"))
    return 0


def main() -> int:
    args = arguments(__doc__ or "", "50,150")
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
