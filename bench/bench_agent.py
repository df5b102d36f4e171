"""Robot agent cost: CPU (% of one core) and RSS of one real robot agent, idle and busy.

The agent is the one `erni sim` runs for a robot (`python -m erni.sim.radio CONFIG`: transport
with identities, motion on a simulated ARCOS robot over TCP, mobinet reading its simulated
network node over SNMP, mission), beside a control node that receives its Pose. CPU comes from
/proc/PID/stat over a window; RSS from /proc/PID/statm.

  idle  the robot stands, no task: SIPs arrive every 0.1 s and the agent publishes its Pose
  busy  BotMotion randomwalk (the Pose changes every 0.1 s and is shared with the control
        node) and a NetWatch network_topology task at 1 Hz

Whole-robot memory, beside paper 004 Table 1 (VmRSS on the robot's iPAQ: JVM + CougaarME 7.5 MB,
Player 1 MB, NetMgmt 1.7 MB, UCD SNMP agent 1.5 MB): the robot agent (it is the driver too: the
ARCOS driver runs inside the motion plugin), net-snmp's snmpd as the SNMP agent a real robot
runs (Debian's, when installed), and a bare interpreter; RSS, PSS and private memory.

Floors measured in the same run:
  RSS   a fresh interpreter that imported pydantic, pyserial and pysnmp's asyncio API and waits
  CPU   a bare Python process that reads a simulated robot's pose at 10 Hz with ArcosDriver
        (`erni robot-sim` in another process over TCP)

    python bench/bench_agent.py [--window 60] [--modes idle,busy]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from procstat import cpu_seconds, rss_mb  # noqa: E402  # bench/procstat.py

from erni.sim.scenario import Scenario  # noqa: E402
from erni.sim.team import Team  # noqa: E402

FLOOR_IMPORTS = "import pydantic, serial, pysnmp.hlapi.v3arch.asyncio"

POSE_READER = """
import sys, time
from erni.plugins.motion.driver import ArcosDriver
d = ArcosDriver(sys.argv[1], name="floor")
d.open()
print("ok", flush=True)
last = None
reads = 0
while True:
    time.sleep(0.1)
    s = d.state
    if s is not None and s is not last:
        last = s
        reads += 1
"""


def wakeups(pid: int) -> int:
    """Context switches of all threads of a process so far."""
    total = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/status") as f:
                total += sum(int(line.split()[1]) for line in f if "ctxt_switches" in line)
        except FileNotFoundError:
            pass
    return total


def memory(pid: int) -> tuple[float, float, float]:
    """RSS, PSS and private (unshared) memory of a process (MB), from smaps_rollup."""
    fields: dict[str, int] = {}
    with open(f"/proc/{pid}/smaps_rollup") as f:
        for line in f:
            parts = line.split()
            if len(parts) == 3 and parts[2] == "kB":
                fields[parts[0].rstrip(":")] = int(parts[1])
    private = fields.get("Private_Clean", 0) + fields.get("Private_Dirty", 0)
    return fields.get("Rss", 0) / 1024, fields.get("Pss", 0) / 1024, private / 1024


def start_snmpd(workdir: str) -> subprocess.Popen[str] | None:
    """Debian's net-snmp snmpd on a loopback port (read-only community), or None when not installed."""
    snmpd = shutil.which("snmpd") or ("/usr/sbin/snmpd" if os.path.exists("/usr/sbin/snmpd") else None)
    if snmpd is None:
        return None
    conf = Path(workdir) / "snmpd.conf"
    conf.write_text("rocommunity public 127.0.0.1\n")
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return subprocess.Popen([snmpd, "-f", "-Lo", "-C", "-c", str(conf), "-r", f"udp:127.0.0.1:{port}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True)


def import_floor() -> subprocess.Popen[str]:
    """A fresh interpreter that imported the floor's modules and waits on stdin."""
    p = subprocess.Popen([sys.executable, "-c", f"{FLOOR_IMPORTS}\nimport sys; print('ok', flush=True); "
                          "sys.stdin.read()"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert p.stdout is not None
    p.stdout.readline()
    return p


def pose_floor() -> tuple[subprocess.Popen[str], subprocess.Popen[str]]:
    """`erni robot-sim` and a bare 10 Hz ArcosDriver pose reader on it."""
    sim = subprocess.Popen([sys.executable, "-m", "erni", "robot-sim", "--port", "0", "--log-level", "WARNING"],
                           stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert sim.stdout is not None
    url = sim.stdout.readline().split()[1]
    reader = subprocess.Popen([sys.executable, "-c", POSE_READER, url], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert reader.stdout is not None
    reader.stdout.readline()
    return sim, reader


def measure(pids: dict[str, int], window: float) -> dict[str, tuple[float, float, float]]:
    """CPU % of one core, wake-ups/s and RSS (MB) of each process over `window` s."""
    c0 = {k: cpu_seconds(p) for k, p in pids.items()}
    w0 = {k: wakeups(p) for k, p in pids.items()}
    t0 = time.monotonic()
    time.sleep(window)
    dt = time.monotonic() - t0
    return {k: ((cpu_seconds(p) - c0[k]) / dt * 100, (wakeups(p) - w0[k]) / dt, rss_mb(p)) for k, p in pids.items()}


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--window", type=float, default=60.0, help="measuring window per mode (s)")
    ap.add_argument("--modes", default="idle,busy")
    ap.add_argument("--settle", type=float, default=5.0, help="wait after start / after tasking (s)")
    results.add_argument(ap)
    args = ap.parse_args()
    targets = []
    modes = [m for m in args.modes.split(",") if m]

    floor = import_floor()
    bare = subprocess.Popen([sys.executable, "-c", "import sys; print('ok', flush=True); sys.stdin.read()"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert bare.stdout is not None
    bare.stdout.readline()
    workdir = tempfile.mkdtemp(prefix="bench-agent-")
    snmpd = start_snmpd(workdir)
    sim, reader = pose_floor()
    scenario = Scenario(name="bench-agent", robots={"count": 1})
    team = Team(scenario, headless=True, control_port=0, ui=False)
    try:
        team.start(timeout=60)
        robot = team.names[0]
        pids = {"robot agent": team.agents[robot].proc.pid, "control node": team.agents["control"].proc.pid,
                "pose floor": reader.pid, "import floor": floor.pid}
        time.sleep(args.settle)
        print(f"load average at start: {os.getloadavg()[0]:.2f}; window {args.window:.0f} s per mode")
        for mode in modes:
            if mode == "busy":
                team.send_task(robot, "BotMotion", "randomwalk", speed=0.3, seed=1)
                team.send_task(robot, "NetWatch", "network_topology", rate_hz=1.0)
                time.sleep(args.settle)
            load = os.getloadavg()[0]
            m = measure(pids, args.window)
            cpu_floor = m["pose floor"][0]
            rss_floor = m["import floor"][2]
            print(f"\n{mode} (load average {load:.2f} -> {os.getloadavg()[0]:.2f})")
            print("| process | CPU % of a core | wake-ups/s | RSS MB | CPU / pose floor | RSS / import floor |")
            print("|---|---|---|---|---|---|")
            for name, (cpu, wk, rss) in m.items():
                print(f"| {name} | {cpu:.2f} | {wk:.0f} | {rss:.1f} | {cpu / max(cpu_floor, 1e-9):.1f} | "
                      f"{rss / rss_floor:.2f} |")
            cpu, wk, _ = m["robot agent"]
            targets.append(results.target(f"{mode} robot agent CPU", "≤ 1 % of a core",
                                          f"the Pose stream alone, {cpu_floor:.2f} %",
                                          f"{cpu:.2f} % ({wk:.0f} wake-ups/s)", cpu <= 1.0))
        print("\nwhole robot (memory at the end of the run), beside paper 004 Table 1")
        print("| process | RSS MB | PSS MB | private MB | paper 004 (VmRSS) |")
        print("|---|---|---|---|---|")
        rows = [("robot agent (agent + ARCOS driver + SNMP client)", pids["robot agent"],
                 "7.5 MB JVM + CougaarME, 1 MB Player, 1.7 MB NetMgmt")]
        if snmpd is not None and snmpd.poll() is None:
            rows.append(("net-snmp snmpd (Debian)", snmpd.pid, "1.5 MB UCD SNMP agent"))
        rows += [("bare python3 interpreter", bare.pid, ""), ("import floor (pydantic, pyserial, pysnmp)", floor.pid, "")]
        for label, pid, paper in rows:
            rss, pss, private = memory(pid)
            print(f"| {label} | {rss:.1f} | {pss:.1f} | {private:.1f} | {paper} |")
    finally:
        team.stop()
        for p in (reader, sim):
            p.terminate()
            p.wait(10)
        if snmpd is not None:
            snmpd.terminate()
            snmpd.wait(10)
        for p in (floor, bare):
            assert p.stdin is not None
            p.stdin.close()
            p.wait(10)
        shutil.rmtree(workdir, ignore_errors=True)
    results.write("bench_agent", targets, path=args.results, about="CPU of one real robot agent, idle and busy")
    return 0


if __name__ == "__main__":
    sys.exit(main())
