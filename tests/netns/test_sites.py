"""Two sites on `wire = "zenoh"`, as a fleet across sites runs: real `erni router` and `erni agent`
processes in network namespaces, and the command-line tools run at site A.

One mesh run (netns.Mesh, no babeld) holds four namespaces on one segment, split into three
subnets of its /24, and the radio lets each node hear only its own site::

    site A  10.231.K.0/26     control (.3)  --  router-a (.1)
    link    10.231.K.128/26                     router-a (.129)  --  router-b (.130)
    site B  10.231.K.64/26                                           router-b (.66)  --  robot1 (.68)

No namespace has a route to another subnet than its own and nothing routes IP between them: the
control node reaches robot1 only through the two Zenoh routers, each agent a client of its own
site's router, router-b linked to router-a. Every link is mutual TLS with the team's certificates
and both routers run the access control made from them (`erni router --acl`). robot1 drives the
simulated robot of the motion plugin (simrobot://), so its Pose is the robot's odometry and a
task moves it; its MobiNet reads the network of site B from `erni net-sim` in its own namespace
(robot1 and a relay 40 m away, over SNMP on 127.0.0.1), so its NetInfo is what that network says.
"""

from __future__ import annotations

import ipaddress
import json
import math
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from erni.blackboard.testing import wait_until
from erni.sim import netns
from erni.sim.netns import Mesh
from erni.sim.team import agent_toml

pytest.importorskip("zenoh")

pytestmark = pytest.mark.netns

TEAM = "sites"
PORT = 7447
NAMES = ["router-a", "router-b", "control", "robot1"]
LAN_A, LAN_B, LINK = 0, 64, 128  # offsets of the three /26 subnets in the run's /24
ADDRESSES = {"router-a": [LAN_A, LINK], "router-b": [LAN_B, LINK], "control": [LAN_A], "robot1": [LAN_B]}
HEARS = [("control", "router-a"), ("router-a", "router-b"), ("router-b", "robot1")]
TRANSPORT = {"beacon_period": 0.3, "peer_timeout": 1.5, "task_ttl": 60.0, "link_deadline": 30.0}
SNMP_PORT = 16100  # robot1's network subsystem, in robot1's namespace (its own loopback)
SITE_B_NETWORK = f"""# site B's mesh as robot1's network subsystem reports it (erni net-sim)
comm_range = 100.0
lossless_range = 50.0
host = "127.0.0.1"
base_port = {SNMP_PORT}
read_community = "public"
nodes = [
  {{ name = "robot1", x = 0.0, y = 0.0 }},
  {{ name = "relay-b", x = 40.0, y = 0.0 }},
]
"""


class Sites:
    """The mesh, the team's keys, the routers and agents of the two sites, and a watch at site A."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.mesh = Mesh(NAMES, run_dir)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.events: list[dict[str, Any]] = []
        self.watch: subprocess.Popen[str] | None = None
        self.addr: dict[str, list[str]] = {}
        self.started: dict[str, int] = {}  # router: its log's start lines before its latest start
        (run_dir / "logs").mkdir(parents=True, exist_ok=True)

    # -- the network -------------------------------------------------------------------

    def create(self) -> None:
        self.mesh.create()
        base = ipaddress.ip_network(self.mesh.subnet).network_address
        for name, node in self.mesh.nodes.items():  # the segment's /24 gives way to the sites' /26s
            netns._ip("addr", "del", f"{node.address}/24", "dev", "mesh0", netns=node.netns)
            self.addr[name] = [str(base + offset + node.index) for offset in ADDRESSES[name]]
            for address in self.addr[name]:
                netns._ip("addr", "add", f"{address}/26", "dev", "mesh0", netns=node.netns)
        self.mesh.apply({frozenset(pair): 1.0 for pair in HEARS})
        self.site = "b"
        self._keys()

    def move_robot1(self, site: str) -> None:
        """robot1 drives to `site`: it hears that site's router only, has an address of that
        site's LAN, and its link to the router it leaves is torn down (as when its radio loses
        that site's access point; `ss -K` saves waiting out Zenoh's lease)."""
        if site == self.site:
            return
        node = self.mesh.node("robot1")
        base = ipaddress.ip_network(self.mesh.subnet).network_address
        router, left = ("router-a", "router-b") if site == "a" else ("router-b", "router-a")
        pairs = [p for p in HEARS if "robot1" not in p] + [("robot1", router)]
        self.mesh.apply({frozenset(pair): 1.0 for pair in pairs})
        new = str(base + (LAN_A if site == "a" else LAN_B) + node.index)
        netns._ip("addr", "del", f"{self.addr['robot1'][0]}/26", "dev", "mesh0", netns=node.netns)
        netns._ip("addr", "add", f"{new}/26", "dev", "mesh0", netns=node.netns)
        self.addr["robot1"], self.site = [new], site
        netns._in(node.netns, "ss", "-K", "dst", self.addr[left][0])

    def endpoint(self, router: str) -> str:
        """Where the agents of `router`'s site connect."""
        return f"tls/{self.addr[router][0]}:{PORT}"

    def _keys(self) -> None:
        from erni.transport.identity import Authority

        self.keys = self.run_dir / "keys"
        authority = Authority.create(self.keys, team="two sites")
        self.identity = {name: str(authority.issue(name, role)) for name, role in
                         (("control", "control"), ("robot1", "robot"), ("cli", "cli"), ("watcher", "cli"),
                          ("router-a", "router"), ("router-b", "router"))}

    # -- processes -----------------------------------------------------------------------

    def start(self, name: str, argv: list[str], node: str | None = None) -> None:
        self.procs[name] = self.mesh.popen(node or name, argv, self.log(name))

    def start_network_b(self) -> None:
        """Site B's network subsystem: `erni net-sim` in robot1's namespace, read by its MobiNet."""
        scenario = self.run_dir / "site-b-network.toml"
        scenario.write_text(SITE_B_NETWORK)
        self.start("net-b", [sys.executable, "-m", "erni", "net-sim", str(scenario)], node="robot1")

    def log(self, name: str) -> Path:
        return self.run_dir / "logs" / f"{name}.log"

    def start_router(self, name: str) -> None:
        argv = [sys.executable, "-m", "erni", "router", "--listen", f"tls/0.0.0.0:{PORT}",
                "--identity", self.identity[name], "--acl", str(self.keys), "--team", TEAM]
        if name == "router-b":  # site B's router links to site A's over the link subnet
            argv += ["--connect", f"tls/{self.addr['router-a'][1]}:{PORT}"]
        self.started[name] = len(self._router_lines(name))
        self.start(name, argv)

    def _router_lines(self, name: str) -> list[str]:
        if not self.log(name).exists():
            return []
        return [line for line in self.log(name).read_text(errors="replace").splitlines()
                if line.startswith("erni router ") and ": listening on" in line]

    def router_id(self, name: str) -> str:
        """The Zenoh id router `name` printed when it last started (once it has)."""
        def printed() -> str:
            lines = self._router_lines(name)
            return lines[-1].split()[2].rstrip(":") if len(lines) > self.started[name] else ""
        return wait_until(printed, timeout=20, message=f"{name} did not start: {self.tail(name)}")

    def kill(self, name: str) -> None:
        proc = self.procs.pop(name)
        proc.kill()
        proc.wait(10)

    def start_agent(self, name: str, plugins: list[tuple[str, dict[str, Any]]], router: str) -> None:
        config = self.run_dir / f"{name}.toml"
        config.write_text(agent_toml(name, plugins, workers=4, comment=f"{name}, a client of {router}"))
        self.start(name, [sys.executable, "-m", "erni", "agent", str(config)])

    def transport(self, name: str, role: str, routers: list[str]) -> tuple[str, dict[str, Any]]:
        return ("transport", {"role": role, "wire": "zenoh", "identity": self.identity[name], **TRANSPORT,
                              **({"capabilities": ["motion"]} if role == "robot" else {}),
                              "zenoh": {"team": TEAM, "mode": "client",
                                        "connect": [self.endpoint(r) for r in routers]}})

    def cli(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        """An `erni` command at site A (the control node's namespace), through router-a, via control."""
        argv = [sys.executable, "-m", "erni", *args, "--zenoh", self.endpoint("router-a"), "--team", TEAM,
                "--identity", self.identity["cli"], "--via", "control"]
        return subprocess.run(self.mesh.exec_argv("control", argv), capture_output=True, text=True,
                              timeout=timeout)

    def start_watch(self) -> None:
        """`erni watch --json` at site A through the control node, its events gathered in `events`."""
        argv = [sys.executable, "-m", "erni", "watch", "--json", "--zenoh", self.endpoint("router-a"),
                "--team", TEAM, "--identity", self.identity["watcher"], "--via", "control"]
        with open(self.log("watch"), "ab") as err:
            self.watch = subprocess.Popen(self.mesh.exec_argv("control", argv), stdout=subprocess.PIPE, stderr=err,
                                          text=True, preexec_fn=netns.die_with_parent())

        def read() -> None:
            assert self.watch is not None and self.watch.stdout is not None
            for line in self.watch.stdout:
                self.events.append(json.loads(line))

        threading.Thread(target=read, name="sites-watch", daemon=True).start()

    # -- what site A sees ----------------------------------------------------------------

    def poses(self) -> list[dict[str, Any]]:
        return [e["data"] for e in list(self.events) if e["type"] == "Pose" and e["data"]["robot"] == "robot1"]

    def pose(self) -> dict[str, Any]:
        return wait_until(lambda: (p := self.poses()) and p[-1], timeout=10, message="no Pose of robot1 at site A")

    def peers(self) -> dict[str, dict[str, Any]]:
        """`erni peers --json` at site A: the control node's directory, by name."""
        done = self.cli("peers", "--json", timeout=30)
        assert done.returncode == 0, done.stderr
        return {p["name"]: p for p in map(json.loads, done.stdout.splitlines())}

    def reaches(self, src: str, address: str) -> str:
        """From node `src`'s namespace, a TCP connection to a router's port at `address`: 'connected'
        or the error's name."""
        code = (f"import socket\ns = socket.socket(); s.settimeout(2)\n"
                f"try:\n    s.connect(({address!r}, {PORT})); print('connected')\n"
                f"except OSError as err:\n    print(type(err).__name__, err.errno)\n")
        done = subprocess.run(self.mesh.exec_argv(src, [sys.executable, "-c", code]), capture_output=True,
                              text=True, timeout=30)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()

    def tail(self, name: str, lines: int = 15) -> str:
        try:
            return "\n".join(self.log(name).read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def stop(self) -> None:
        procs = list(self.procs.values()) + ([self.watch] if self.watch is not None else [])
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
        self.procs.clear()
        self.mesh.destroy()


def robot1_up(sites: Sites) -> bool:
    return any(e["type"] == "Peer" and e["data"]["name"] == "robot1" for e in sites.events) and \
        [e["data"]["up"] for e in sites.events if e["type"] == "Peer" and e["data"]["name"] == "robot1"][-1]


@pytest.fixture(scope="module")
def sites(tmp_path_factory):
    sites = Sites(tmp_path_factory.mktemp("sites"))
    try:
        sites.create()
        sites.start_router("router-a")
        sites.start_agent("control", [sites.transport("control", "control", ["router-a"])], "router-a")
        sites.start_network_b()
        sites.start_agent("robot1", [sites.transport("robot1", "robot", ["router-b", "router-a"]),
                                     ("motion", {"url": "simrobot://", "pose_keepalive": 0.5}),
                                     ("mobinet", {"host": "127.0.0.1", "port": SNMP_PORT, "timeout": 0.5,
                                                  "retries": 0, "watch": ["neighbor_list"]})],
                           "router-b")
        sites.router_id("router-a")
        sites.start_watch()
        yield sites
    finally:
        sites.stop()
    assert sites.mesh.leftovers() == []


def test_site_a_reaches_site_b_only_through_the_routers(sites):
    """No IP route joins the sites (robot1 lists router-a too, and cannot reach it): the control
    node sees robot1 only once router-b runs and links to router-a, reached through router-b."""
    a, b = sites.addr["router-a"], sites.addr["router-b"]
    assert sites.reaches("control", a[0]) == "connected"  # the probe works: its own site's router
    for src, address in (("control", b[0]), ("control", b[1]), ("robot1", a[0]), ("robot1", a[1])):
        assert sites.reaches(src, address).startswith("OSError 101"), (src, address)  # ENETUNREACH
    if "router-b" in sites.procs:
        sites.kill("router-b")
    wait_until(lambda: "robot1" not in sites.peers() or not sites.peers()["robot1"]["up"], timeout=20)
    time.sleep(1.0)
    assert "robot1" not in sites.peers() or not sites.peers()["robot1"]["up"]  # site B is cut off
    sites.start_router("router-b")
    sites.router_id("router-b")
    # up, and reached through router-b by the name router-b's token holds (the token travels on its own)
    robot1 = wait_until(lambda: (p := sites.peers().get("robot1")) is not None and p["up"]
                        and p["router"] == "router-b" and p, timeout=30,
                        message=f"robot1 not up through router-b at site A: {sites.peers().get('robot1')}\n"
                        f"{sites.tail('robot1')}\n{sites.tail('router-b')}")
    assert robot1["wire"] == "zenoh"
    wait_until(lambda: robot1_up(sites), timeout=10)  # the watch at site A saw it appear


def ensure_linked(sites: Sites) -> None:
    sites.move_robot1("b")
    if "router-b" not in sites.procs:
        sites.start_router("router-b")
    wait_until(lambda: (p := sites.peers().get("robot1")) is not None and p["up"], timeout=30,
               message=f"robot1 not up at site A:\n{sites.tail('robot1')}")


def dist(a: dict[str, Any], b: dict[str, Any]) -> float:
    return math.dist((a["x"], a["y"]), (b["x"], b["y"]))


def final_lines(out: str) -> list[dict[str, Any]]:
    return [r for r in map(json.loads, out.splitlines()) if r.get("state") in ("succeeded", "failed", "cancelled")]


def test_control_at_site_a_tasks_and_cancels_robot1_at_site_b_and_sees_its_pose(sites):
    ensure_linked(sites)
    start = sites.pose()
    done = sites.cli("task", "robot1", "BotMotion", "forward", "distance=0.5", "--wait", "--json")
    assert done.returncode == 0, done.stderr
    assert [r["state"] for r in final_lines(done.stdout)] == ["succeeded"]
    moved = wait_until(lambda: (p := sites.pose()) and dist(p, start) > 0.4 and p, timeout=10)
    assert dist(moved, start) < 0.6  # robot1's odometry, seen at site A
    done = sites.cli("task", "robot1", "BotMotion", "forward", "distance=20", "--wait", "--json", "--timeout", "3")
    assert done.returncode == 1 and "cancelling" in done.stderr, done.stderr
    uid = json.loads(done.stdout.splitlines()[0])["uid"]
    wait_until(lambda: any(e["op"] == "remove" and e["type"] == "Task" and e["data"]["uid"] == uid
                           for e in sites.events), timeout=10, message="the cancelled task stayed at control")
    # robot1 stopped: the task was cancelled there, not only here
    stopped = wait_until(lambda: (p := sites.pose()) and p["v"] == 0 and p, timeout=10,
                         message="robot1 did not stop: its task was not cancelled there")
    time.sleep(1.5)
    assert dist(sites.pose(), stopped) < 0.02
    assert 0.05 < dist(stopped, moved) < 5.0


def test_control_at_site_a_sees_robot1s_network_info_from_site_b(sites):
    """robot1's NetInfo (what its MobiNet reads from site B's network) is shared with the control
    role across the two routers, as its Pose is."""
    ensure_linked(sites)

    def neighbours() -> list[dict[str, Any]] | None:
        infos = [e["data"] for e in list(sites.events) if e["type"] == "NetInfo" and e["data"]["node"] == "robot1"
                 and e["data"]["kind"] == "neighbor_list" and not e["data"]["degraded"]]
        return infos[-1]["neighbors"] if infos and infos[-1]["neighbors"] else None

    seen = wait_until(neighbours, timeout=30, message=f"no NetInfo of robot1 at site A: {sites.tail('robot1')}")
    assert [n["name"] for n in seen] == ["relay-b"]
    assert 0.0 < seen[0]["quality"] <= 1.0  # 40 m of a 50 m lossless range: a full link
    assert seen[0]["quality"] == pytest.approx(1.0)


def test_a_task_across_the_sites_ends_once_when_site_bs_router_restarts_mid_task(sites):
    ensure_linked(sites)
    start = sites.pose()
    argv = [sys.executable, "-m", "erni", "task", "robot1", "BotMotion", "forward", "distance=1.0", "--wait",
            "--json", "--zenoh", sites.endpoint("router-a"), "--team", TEAM, "--identity", sites.identity["cli"],
            "--via", "control"]
    task = subprocess.Popen(sites.mesh.exec_argv("control", argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        assert task.stdout is not None
        uid = ""
        while not uid:  # the task runs at robot1
            line = task.stdout.readline()
            assert line, f"erni task ended early: {task.communicate()[1]}"
            update = json.loads(line)
            uid = update["uid"] if update.get("state") == "running" else ""
        sites.kill("router-b")  # mid-task: robot1 drives on, its results wait for a way back
        wait_until(lambda: not robot1_up(sites), timeout=10, message="site A did not see robot1 go")
        time.sleep(3.0)  # about the rest of the drive: its end waits for the way back
        sites.start_router("router-b")
        out, err = task.communicate(timeout=40)
    finally:
        if task.poll() is None:
            task.kill()
            task.communicate()
    assert task.returncode == 0, err
    assert [r["state"] for r in final_lines(out)] == ["succeeded"]
    wait_until(lambda: robot1_up(sites), timeout=20, message="site A did not see robot1 again")
    ended = [e for e in sites.events if e["type"] == "Task" and e["data"]["uid"] == uid and e["op"] != "remove"
             and (e["data"].get("result") or {}).get("state") in ("succeeded", "failed", "cancelled")]
    assert [e["data"]["result"]["state"] for e in ended] == ["succeeded"]  # once at the control node
    end = wait_until(lambda: (p := sites.pose()) and dist(p, start) > 0.9 and p["v"] == 0 and p, timeout=10,
                     message=f"robot1's poses at site A since the task: {sites.poses()[-3:]}")
    time.sleep(1.0)
    assert dist(sites.pose(), end) < 0.02 and dist(end, start) < 1.1  # driven once, not again after the restart


def test_robot1_driven_to_site_a_reconnects_through_router_a_and_keeps_its_session(sites):
    """robot1 lists both sites' routers; at site A only router-a is in reach. The control node keeps
    it as the same instance (its epoch), tasks it through router-a and sees its Pose."""
    ensure_linked(sites)
    before = sites.peers()["robot1"]
    assert before["router"] == "router-b"
    sites.move_robot1("a")
    try:
        assert sites.reaches("robot1", sites.addr["router-b"][0]).startswith("OSError 101")  # site B is gone
        robot1 = wait_until(lambda: (p := sites.peers().get("robot1")) is not None and p["up"]
                            and p["router"] == "router-a" and p, timeout=30,
                            message=f"robot1 not up through router-a:\n{sites.tail('robot1')}")
        assert robot1["epoch"] == before["epoch"] and robot1["address"] == before["address"]
        start = sites.pose()
        done = sites.cli("task", "robot1", "BotMotion", "forward", "distance=0.3", "--wait", "--json")
        assert done.returncode == 0, done.stderr
        assert [r["state"] for r in final_lines(done.stdout)] == ["succeeded"]
        wait_until(lambda: dist(sites.pose(), start) > 0.2, timeout=10)
        assert sites.procs["robot1"].poll() is None  # the same process all along
    finally:
        sites.move_robot1("b")
