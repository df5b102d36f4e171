"""A simulated team across two hosts, as a user runs it on two machines: two network namespaces on one
segment stand for the hosts, each on a CPU of its own (taskset). Host A runs `erni sim --listen A
--agent-host B` (the world, its robots and SNMP nodes, the control node, two robots' agents); host B
runs `erni sim --join` with a copy of the bundle host A wrote (the other two agents). The team comes up
heard whole by the control node, a robot on host B carries out a task sent to host A's control node,
and when host A's run ends host B's agents stop with it."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from erni.blackboard.testing import wait_until
from erni.sim.netns import Mesh

pytestmark = [pytest.mark.netns, pytest.mark.slow]

ROBOTS = 4  # robot1, robot2 on host A; robot3, robot4 on host B


def erni(mesh: Mesh, node: str, cpu: int, *args: str) -> list[str]:
    """`erni ARGS` in `node`'s namespace, on CPU `cpu` only (when this machine has it)."""
    pin = ["taskset", "-c", str(cpu)] if cpu < (os.cpu_count() or 1) and shutil.which("taskset") else []
    return mesh.exec_argv(node, [*pin, sys.executable, "-m", "erni", *args])


def read_until(proc: subprocess.Popen[str], marker: str, lines: list[str], timeout: float) -> None:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip())
        if line.startswith(marker):
            return
    raise AssertionError(f"no {marker!r} within {timeout:.0f} s:\n" + "\n".join(lines))


def test_a_team_across_two_hosts_comes_up_takes_a_task_and_stops_together(tmp_path: Path):
    mesh = Mesh(["host-a", "host-b"], tmp_path / "mesh")
    procs: list[subprocess.Popen[str]] = []
    try:
        mesh.create()
        mesh.apply({frozenset(("host-a", "host-b")): 1.0})
        a, b = mesh.node("host-a").address, mesh.node("host-b").address
        run = tmp_path / "run"
        world = subprocess.Popen(erni(mesh, "host-a", 0, "sim", "--headless", "--robots", str(ROBOTS), "--listen", a,
                                      "--agent-host", b, "--run-dir", str(run), "--timeout", "120"),
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        procs.append(world)
        out: list[str] = []
        read_until(world, "erni sim: agent host 2", out, 60)
        assert f"agent host 2 ({b}, 2 robot agents)" in out[-1]
        bundle = run / "hosts" / "host-2"
        wait_until(lambda: (bundle / "join.json").exists(), timeout=60, message="host A wrote no bundle")
        copy = tmp_path / "host-b-home" / "host-2"
        shutil.copytree(bundle, copy)  # as scp -r to the other machine would
        joiner = subprocess.Popen(erni(mesh, "host-b", 1, "sim", "--join", str(copy)), stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        procs.append(joiner)
        read_until(world, "Ctrl-C stops the team", out, 120)
        text = "\n".join(out)
        for name, host in (("robot1", a), ("robot2", a), ("robot3", b), ("robot4", b)):
            assert re.search(rf"{name}\s+agent {re.escape(host)}\s", text), text
        control = re.search(r"control\s+agent (\S+):(\d+)", text)
        assert control and control.group(1) == a, text
        via = f"{a}:{control.group(2)}"
        env = {**os.environ, "ERNI_IDENTITY": str(run / "keys" / "cli.pem")}

        peers = subprocess.run(erni(mesh, "host-a", 0, "peers", "--via", via), capture_output=True, text=True,
                               timeout=60, env=env)
        for name, host in (("robot3", b), ("robot4", b)):  # host B's agents, heard on host B's address
            assert re.search(rf"{name}\s+up\s+\w+\s+{re.escape(host)}:\d+", peers.stdout), peers.stdout
        task = subprocess.run(erni(mesh, "host-a", 0, "task", "--via", via, "robot4", "BotMotion", "goto", "x=1.5",
                                   "y=1", "--wait"), capture_output=True, text=True, timeout=90, env=env)
        assert task.returncode == 0 and "robot4" in task.stdout and "succeeded" in task.stdout, task.stdout + task.stderr

        world.send_signal(signal.SIGINT)
        rest, _ = world.communicate(timeout=60)
        assert world.returncode == 0, rest
        said, _ = joiner.communicate(timeout=30)  # host A's run ended: host B's agents stop with it
        assert joiner.returncode == 0, said
        assert "the world host ended the run; the agents of host 2 stopped" in said, said
        logs = (copy / "logs" / "robot4.log").read_text(errors="replace")
        assert "Traceback" not in logs, logs[-2000:]
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        mesh.destroy()
