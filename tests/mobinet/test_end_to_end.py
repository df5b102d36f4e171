"""Done-when check: the example agent, pointed at one node of `erni net-sim`, answers every
NetWatch preposition from live SNMP data and writes its pose into the network."""

from __future__ import annotations

import math
import re
import signal
import subprocess
import sys
from pathlib import Path

from erni.blackboard import Agent, NetInfo, Pose, Task, TaskState
from erni.blackboard.testing import wait_until

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
ADDR_RE = re.compile(r"^\s+(\S+)\s+\S+\s+snmp udp:([\d.]+):(\d+)$")


def test_example_agent_against_net_sim(tmp_path):
    sim = subprocess.Popen([sys.executable, "-m", "erni", "net-sim", str(EXAMPLES / "net-line.toml"),
                            "--base-port", "0"], stdout=subprocess.PIPE, text=True)
    agent = None
    try:
        ports = {}
        for line in sim.stdout:
            if m := ADDR_RE.match(line.rstrip("\n")):
                ports[m.group(1)] = int(m.group(3))
            if "serving;" in line:
                break
        config = (EXAMPLES / "robot-mobinet.toml").read_text()
        config = config.replace("port = 1162", f"port = {ports['robot2']}")
        assert f"port = {ports['robot2']}" in config
        (tmp_path / "robot2.toml").write_text(config)
        agent = Agent.from_config(tmp_path / "robot2.toml")
        agent.start()
        kinds = ["node_position", "network_topology", "path_cost", "link_quality", "neighbor_list"]
        with agent.transaction() as tx:
            for kind in kinds:
                tx.add(Task(verb="NetWatch", preposition=kind, params={"rate_hz": 10}, source="e2e"))
            tx.add(Pose(robot="robot2", x=65.0, y=-5.0, theta=math.pi))

        def answered():
            infos = {i.kind: i for i in agent.query(NetInfo)
                     if not i.degraded and not i.message and i.stamp}
            return infos if set(infos) == set(kinds) else None
        infos = wait_until(answered, timeout=10)
        assert [n.name for n in infos["neighbor_list"].neighbors] == ["robot1", "robot3"]
        assert infos["network_topology"].articulation_points == ["robot2", "robot3", "robot4"]
        assert {r.destination for r in infos["path_cost"].routes} == {"robot1", "robot3", "robot4",
                                                                       "robot5"}
        assert {n.name: n.quality for n in infos["link_quality"].neighbors} == {"robot1": 0.8,
                                                                               "robot3": 0.8}
        # the pose written by SET comes back in what the network knows about robot2
        pos = wait_until(lambda: (p := next(i for i in agent.query(NetInfo)
                                            if i.kind == "node_position").positions.get("robot2"))
                         and p.x == 65.0 and p, timeout=10)
        assert (pos.y, pos.heading) == (-5.0, -180.0)
        tasks = agent.query(Task)
        assert len(tasks) == 5 and all(t.result.state == TaskState.RUNNING for t in tasks)
    finally:
        if agent is not None:
            agent.stop()
        sim.send_signal(signal.SIGINT)
        sim.communicate(timeout=10)
    assert sim.returncode == 0
