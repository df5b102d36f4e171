"""Paper 004, Table 1: resident memory of a robot's agent and of all of a robot's processes.

Measured the way the paper did: the VmRSS field of /proc/<pid>/status. A team runs as agent
processes (each robot: transport, motion over ARCOS, MobiNet over SNMP, mission), every robot
on a random walk given by the control node, and each process's VmRSS is sampled once a second
once the team has run `settle` seconds; the table gives the largest sample. Beside it, for
reference in the same run: a bare Python interpreter (the floor every Python process pays),
and the SNMP agent a real robot's network subsystem would run, net-snmp's `snmpd` (the
successor of the paper's "UCD SNMP agent"), started with a minimal read-only configuration.
PSS (the process's share of pages it shares with others, from /proc/<pid>/smaps_rollup) is
given too: several agents on one machine share the interpreter's and libraries' pages.

What a robot runs: its agent process (the paper: JVM + CougaarME, plus the NetMgmt agent whose
role MobiNet plays inside our agent, plus Player, whose role the motion plugin plays: the
robot's controller speaks ARCOS to it directly) and the SNMP agent of its network subsystem.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.scenario import Scenario, ScenarioError

PAPER_MB = {"Java (JVM + CougaarME + system)": 7.5, "Player": 1.0, "NetMgmt (PSF agent)": 1.7,
            "UCD SNMP agent": 1.5}
PAPER_TOTAL_MB = 12.0  # "our final implementation runs in about 12MB of RAM"


def status_kb(pid: int, field: str = "VmRSS") -> float:
    """A /proc/<pid>/status field in kB (NaN when the process is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return float("nan")


def pss_kb(pid: int) -> float:
    """Pss of a process from /proc/<pid>/smaps_rollup in kB (NaN when unreadable)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return float(line.split()[1])
    except OSError:
        pass
    return float("nan")


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, **_: Any) -> Result:
    """Measure the team's processes, the interpreter floor and snmpd; return figure and table."""
    from erni.sim.experiments.agents import TeamRun

    s = scenario.strategy
    settle = float(s.get("settle", 20.0))
    window = float(s.get("window", 10.0))
    peaks: dict[str, tuple[float, float]] = {}  # process -> (max VmRSS kB, max Pss kB)
    samples: dict[str, tuple[list[float], list[float]]] = {}  # process -> (t, VmRSS MB)
    with TeamRun(scenario, progress, mission={"network_aware": True}) as team:
        team.start()
        assert team.team is not None
        for name in team.team.names:
            team.send(name, "RemoteBotMotion", "randomwalk", speed=0.3)
        team.wait("settling", settle)
        pids = {name: a.proc.pid for name, a in team.team.agents.items() if a.proc is not None}
        end = team.now + window
        while team.now < end:
            for name, pid in pids.items():
                rss, pss = status_kb(pid), pss_kb(pid)
                old = peaks.get(name, (0.0, 0.0))
                peaks[name] = (max(old[0], rss), max(old[1], pss))
                ts, vs = samples.setdefault(name, ([], []))
                ts.append(round(team.now, 2))
                vs.append(rss / 1024.0)
            team.wait("sampling VmRSS", 1.0)
        sim_rss = status_kb(os.getpid())
    floor = _floor()
    snmpd = _snmpd(progress)
    robots = [n for n in peaks if n != "control"]
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = (f"{len(robots)} robot agent processes on a random walk and a control node; VmRSS from "
                     "/proc/<pid>/status, largest of one sample a second")
    mb = 1024.0
    robot_rss = max(peaks[n][0] for n in robots) / mb
    robot_pss = max(peaks[n][1] for n in robots) / mb
    for name, (rss, pss) in peaks.items():
        res.robots[name] = {"VmRSS_MB": round(rss / mb, 1), "Pss_MB": round(pss / mb, 1)}
        res.series[f"{name}/vmrss"] = (*samples[name], "MB")
    res.metrics["robot agent (transport, motion, MobiNet, mission): VmRSS, largest"] = (robot_rss, "MB")
    res.metrics["robot agent: Pss, largest"] = (robot_pss, "MB")
    res.metrics["control node agent: VmRSS"] = (peaks["control"][0] / mb, "MB")
    res.metrics["bare Python interpreter: VmRSS (floor)"] = (floor / mb, "MB")
    res.metrics["simulator process (world, radio, SNMP of every node): VmRSS"] = (sim_rss / mb, "MB")
    if snmpd is not None:
        res.metrics["net-snmp snmpd (the robot's network subsystem agent): VmRSS"] = (snmpd / mb, "MB")
    whole = robot_rss + (snmpd / mb if snmpd is not None else 0.0)
    res.metrics["whole robot: agent + snmpd"] = (whole, "MB")
    res.compare("method", "VmRSS in /proc/<pid>/status", "VmRSS in /proc/<pid>/status", "", "the paper's", "input")
    res.compare("robot agent process", "7.5 (JVM + CougaarME + system)", round(robot_rss, 1), "MB",
                "largest VmRSS of a robot agent process while its robot random-walks")
    res.compare("  of which the Python interpreter alone", "-", round(floor / mb, 1), "MB",
                "a bare `python -c` process, the floor of any Python agent")
    res.compare("network management agent", "1.7 (NetMgmt, PSF agent)", "inside the agent", "",
                "MobiNet is a plugin of the robot agent, counted above")
    res.compare("robot driver", "1.0 (Player)", "inside the agent", "", "the motion plugin speaks ARCOS itself")
    res.compare("SNMP agent", "1.5 (UCD SNMP agent)", round(snmpd / mb, 1) if snmpd is not None else "not run",
                "MB", "net-snmp snmpd 5.9 (Debian), minimal read-only config" if snmpd is not None
                else "snmpd is not installed here")
    res.compare("whole robot", f"about {PAPER_TOTAL_MB:g} (sum {sum(PAPER_MB.values()):g})", round(whole, 1), "MB",
                "robot agent + snmpd")
    res.notes.append(f"Pss of a robot agent {robot_pss:.1f} MB: pages shared with the other agents on this "
                     "machine are split among them")
    res.draw = lambda fig: _draw(fig, peaks, floor, snmpd)
    return res


def _floor() -> float:
    """VmRSS (kB) of a bare interpreter of the same Python."""
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(3)"])
    try:
        time.sleep(1.0)
        return status_kb(p.pid)
    finally:
        p.terminate()
        p.wait(5)


def _snmpd(progress: Progress) -> float | None:
    """VmRSS (kB) of net-snmp's snmpd on a free loopback port, or None when it is not installed."""
    exe = shutil.which("snmpd") or ("/usr/sbin/snmpd" if Path("/usr/sbin/snmpd").exists() else None)
    if exe is None:
        return None
    progress("snmpd", 0, 1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    run_dir = Path(tempfile.mkdtemp(prefix="erni-snmpd-"))
    conf = run_dir / "snmpd.conf"
    conf.write_text("rocommunity public 127.0.0.1\nsysLocation robot\n", encoding="utf-8")
    p = subprocess.Popen([exe, "-f", "-Lf", str(run_dir / "snmpd.log"), "-C", "-c", str(conf),
                          "-p", str(run_dir / "snmpd.pid"), f"udp:127.0.0.1:{port}"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(2.0)
        if p.poll() is not None:
            raise ScenarioError(f"snmpd exited at once (code {p.returncode}); see {run_dir / 'snmpd.log'}")
        get = shutil.which("snmpget")
        if get:  # a real query, so the agent has done its work once
            subprocess.run([get, "-v2c", "-c", "public", f"127.0.0.1:{port}", "1.3.6.1.2.1.1.1.0"],
                           capture_output=True, timeout=10)
        rss = status_kb(p.pid)
    finally:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(5)
        except subprocess.TimeoutExpired:
            p.kill()
        progress("snmpd", 1, 1)
    shutil.rmtree(run_dir, ignore_errors=True)  # kept when snmpd failed: its error names the log
    return rss


def _draw(fig: Any, peaks: dict[str, tuple[float, float]], floor: float, snmpd: float | None) -> None:
    gs = fig.add_gridspec(1, 2, width_ratios=[1.2, 1])
    ax = fig.add_subplot(gs[0, 0])
    names = list(peaks)
    xs = range(len(names))
    ax.bar([x - 0.2 for x in xs], [peaks[n][0] / 1024 for n in names], width=0.4, color=color(0), label="VmRSS")
    ax.bar([x + 0.2 for x in xs], [peaks[n][1] / 1024 for n in names], width=0.4, color=color(2), label="Pss")
    ax.axhline(floor / 1024, color="#555555", ls=":", lw=1, label=f"bare interpreter {floor / 1024:.1f} MB")
    ax.set_xticks(list(xs), names)
    ax.set_ylabel("MB")
    ax.set_title("Our agent processes (largest sample)")
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    ax.legend(fontsize=8)
    ax = fig.add_subplot(gs[0, 1])
    robot = max(peaks[n][0] for n in names if n != "control") / 1024
    ours = [("agent", robot), ("snmpd", (snmpd or 0.0) / 1024)]
    bottom = 0.0
    for k, (label, value) in enumerate(ours):
        ax.bar([1], [value], bottom=bottom, color=color(k), label=f"ours: {label} {value:.1f} MB")
        bottom += value
    bottom = 0.0
    for k, (label, value) in enumerate(PAPER_MB.items()):
        ax.bar([0], [value], bottom=bottom, color="#bbbbbb" if k % 2 else "#888888", edgecolor="white",
               label=f"paper: {label} {value:g} MB")
        bottom += value
    ax.set_xticks([0, 1], ["CougaarME robot\n(paper 004, Table 1)", "ERNI robot\n(this run)"])
    ax.set_ylabel("resident memory (MB)")
    ax.set_title("A whole robot's processes")
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    ax.legend(fontsize=7.5, loc="upper left")
    fig.suptitle("Paper 004, Table 1: memory usage (VmRSS) of a robot's processes (agents mode)", fontsize=13)
