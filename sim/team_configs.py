"""The configs of a simulated team's agents: what each agent process of a `Team` runs with.

Every robot's agent gets its transport (on its loopback or mesh address), its motion plugin (on
the simulated robot's URL), MobiNet (the simulated SNMP node, or babeld on the real mesh) and the
mission plugin when installed; the control node gets its transport and the GUI. Each config goes
to `RUN/agents/NAME.toml` (private: it holds the node's SNMP write community and the GUI's token)
and is recorded as an `AgentProcess` to be started.
"""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from erni.blackboard.errors import UsageError
from erni.sim.netns import Mesh, TcpForwarder
from erni.sim.scenario import Scenario
from erni.sim.world import World
from erni.transport.identity import REVOKED

if TYPE_CHECKING:
    from erni.sim.agent_hosts import Placement

CONTROL = "control"
CONTROL_HOST = "127.0.1.250"
RMW_ZENOHD = "tcp/127.0.0.1:7447"  # where rmw_zenohd listens by default (ros2 run rmw_zenoh_cpp rmw_zenohd)
ROS2_PORT = 7448  # where the control node's ROS 2 session listens, when free: beside rmw_zenohd's port


def private_file(path: Path) -> Path:
    """Create `path` empty unless it exists, readable and writable by this user only (0600)."""
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600))
    os.chmod(path, 0o600)
    return path


def robot_address(index: int) -> str:
    """Loopback address of robot `index` (0-based): 127.0.1.1, 127.0.1.2, ..."""
    return f"127.0.1.{index + 1}"


def free_port(host: str = "127.0.0.1") -> int:
    """A port free on `host` for both TCP and UDP now (an agent binds one number for both: its
    transport's UDP datagrams and TCP links, a GUI beside its beacons), chosen below the kernel's
    ephemeral range, so that no socket bound to port 0 (by this run or any other program) takes it
    before the agent binds it."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(10_000, max(10_001, low))
        if port_free(host, port):
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # pragma: no cover - every low port taken
        s.bind((host, 0))
        return int(s.getsockname()[1])


def port_free(host: str, port: int) -> bool:
    """True when both TCP and UDP `host:port` can be bound now."""
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as s:
            if kind == socket.SOCK_STREAM:  # as the transport does: TIME_WAIT does not block it
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError:
                return False
    return True


def toml_value(v: Any) -> str:
    """Render a str, number, bool, list or dict as a TOML value."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    raise UsageError(f"cannot write {v!r} as TOML")


def agent_toml(name: str, plugins: list[tuple[str, dict[str, Any]]], *, journal: str | None = None,
               workers: int = 4, comment: str = "") -> str:
    """Return an agent config file with the given `(class, settings)` plugins."""
    lines = [f"# {comment}" if comment else "", "[agent]", f"name = {toml_value(name)}",
             f"workers = {workers}"]
    if journal:
        lines.append(f"journal = {toml_value(journal)}")
    for cls, settings in plugins:
        lines += ["", "[[plugin]]", f"class = {toml_value(cls)}", "[plugin.settings]"]
        lines += [f"{k} = {toml_value(v)}" for k, v in settings.items()]
    return "\n".join(lines).lstrip() + "\n"


def ros2_settings(asked: dict[str, Any]) -> dict[str, Any]:
    """The settings of the control node's ros2 plugin: a Zenoh session of its own (the team's transport
    is not on Zenoh) in peer mode, connected to rmw_zenohd's default port (tried again until a router
    runs there) and listening on 127.0.0.1 (ROS2_PORT when free, else a free port) for ROS 2 clients
    and routers pointed at it; the scenario's `asked` settings win."""
    out: dict[str, Any] = {"session": "own", "mode": "peer", "connect": [RMW_ZENOHD], **asked}
    if "listen" not in asked and out["mode"] == "peer":
        port = ROS2_PORT if port_free("127.0.0.1", ROS2_PORT) else free_port("127.0.0.1")
        out["listen"] = [f"tcp/127.0.0.1:{port}"]
    return out


@dataclass
class AgentProcess:
    """One agent process of the team."""

    name: str
    config: Path
    log: Path
    address: tuple[str, int]
    proc: subprocess.Popen[bytes] | None = None
    failed: bool = False
    radio: int | None = None  # write end of the agent's radio pipe

    @property
    def alive(self) -> bool:
        """True while the process runs."""
        return self.proc is not None and self.proc.poll() is None

    @property
    def pid(self) -> int | None:
        """The process id, once started."""
        return self.proc.pid if self.proc is not None else None

    def kill(self) -> None:
        """Fail it at once (a scenario's failure): marked failed, its process killed and reaped."""
        self.failed = True
        if self.alive:
            assert self.proc is not None
            self.proc.kill()
            self.proc.wait(5)

    def close_radio(self) -> None:
        """Close the write end of its radio pipe, when open."""
        if self.radio is not None:
            os.close(self.radio)
            self.radio = None


def stop_processes(procs: list[subprocess.Popen[bytes]], timeout: float) -> None:
    """Stop `procs` together: SIGTERM to each still running, then SIGKILL to any not gone within `timeout` s."""
    for p in procs:
        if p.poll() is None:
            try:
                p.send_signal(signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


class AgentConfigs:
    """Write the config of every agent of a team and record each as an `AgentProcess` (`agents`);
    the GUI's `url` (and on the real mesh the `forwarder` that reaches it) once written."""

    def __init__(self, scenario: Scenario, run_dir: Path, names: list[str], world: World, *, keys_dir: Path,
                 robot_url: Callable[[int], str], discovery_port: int, transport: dict[str, Any], mission: bool,
                 ui: bool, mobinet: str, mission_extra: dict[str, Any], gui_listen: str | None, gui_token: str,
                 mesh: Mesh | None, ros2: dict[str, Any] | None = None, placement: Placement | None = None) -> None:
        self.scenario, self.run_dir, self.names, self.world = scenario, run_dir, names, world
        self.keys_dir, self.robot_url, self.discovery_port = keys_dir, robot_url, discovery_port
        self.transport, self.mission, self.ui, self.mobinet = transport, mission, ui, mobinet
        self.mission_extra, self.gui_listen, self.gui_token, self.mesh = mission_extra, gui_listen, gui_token, mesh
        self.ros2 = ros2  # the control node's ros2 plugin settings (None: no plugin)
        self.placement = placement  # robots' agents on agent hosts (None: every agent here on loopback)
        self.agents: dict[str, AgentProcess] = {}
        self.url: str | None = None
        self._forwarder: TcpForwarder | None = None
        self._control_common: dict[str, Any] = {}
        self.write_communities: dict[str, str] = {}
        self.control_port = self.gui_port = 0

    @property
    def forwarder(self) -> TcpForwarder | None:
        """On the real mesh, the forwarder from this host to the GUI in the control node's namespace."""
        return self._forwarder

    def identity(self, name: str) -> dict[str, str]:
        """Transport settings naming agent `name`'s identity and the team's revocation list (on an agent
        host, relative to its bundle: the agents run there)."""
        if self.placement is not None and self.placement.remote(name):
            return {"identity": f"keys/{name}.pem", "revocations": f"keys/{REVOKED}"}
        return {"identity": str(self.keys_dir / f"{name}.pem"), "revocations": str(self.keys_dir / REVOKED)}

    def _robot_address(self, index: int) -> str:
        """Where robot `index`'s agent listens: its loopback address, or its host's."""
        return robot_address(index) if self.placement is None else self.placement.address(self.names[index])

    @property
    def _control_host(self) -> str:
        return CONTROL_HOST if self.placement is None else self.placement.world

    def _gui_bind(self) -> tuple[str, int]:
        """The GUI's listening address: `gui_listen`, else 127.0.0.1 on `gui_port` (a free port when it is taken)."""
        gui_host, gui_port = "127.0.0.1", self.gui_port
        if self.gui_listen:
            from erni.transport import parse_address

            gui_host, gui_port = parse_address(self.gui_listen)
        bind = "0.0.0.0" if gui_host in ("", "0.0.0.0") else gui_host
        if not gui_port or not port_free(bind, gui_port):
            gui_port = free_port(bind)
        return bind, gui_port

    def _floorplan(self) -> Path:
        """Write the world's walls and obstacles for the GUI to draw (`RUN/world.toml`)."""
        plan = self.run_dir / "world.toml"
        world = self.world.model_dump(mode="json", exclude={"robot", "name"}, exclude_none=True)
        private_file(plan).write_text("".join(f"{k} = {toml_value(v)}\n" for k, v in world.items() if v),
                                      encoding="utf-8")
        return plan

    def write(self, snmp_ports: dict[str, int], write_communities: dict[str, str], control_port: int,
              gui_port: int) -> None:
        """Write every agent's config: each robot's node serves SNMP on its port of `snmp_ports` with its
        write community; the control node listens on `control_port`, its GUI on `gui_port` (or a free one),
        and runs the ros2 plugin when asked."""
        self.write_communities = write_communities
        self.control_port, self.gui_port = control_port, gui_port
        if self.mesh is not None:
            self._write_mesh_configs(snmp_ports)
            return
        broadcast = "127.255.255.255" if self.placement is None else self.placement.broadcast
        common = dict(discovery_port=self.discovery_port, beacon_to=[broadcast], **self.transport)
        for i, name in enumerate(self.names):
            addr = self._robot_address(i)
            port = 0  # any free port: two simulations side by side never collide
            plugins: list[tuple[str, dict[str, Any]]] = [
                ("transport", dict(listen=f"{addr}:{port}", role="robot", **self.identity(name),
                                   capabilities=["motion", "mobinet"] + (["mission"] if self.mission else []),
                                   # patrol heartbeats travel between robots; poses only to the control node
                                   **({"share_with": {"Territory": ["control", "robot"]}} if self.mission else {}),
                                   **common)),
                ("motion", dict(url=self.robot_url(i), model=self.scenario.robots.model)),
                # one retry: a busy laptop running a whole team must not turn a late answer into
                # a degraded network view that holds every deployment
                ("mobinet", dict(host=addr if self.placement is None else self.placement.world,  # the world's node
                                 port=snmp_ports[name], timeout=1.0, retries=1,
                                 write_community=self.write_communities[name])),
            ]
            if self.mission:
                plugins.append(("mission", self._mission_settings()))
            self._add_agent(name, (addr, port), plugins, f"robot {name} of scenario {self.scenario.name}")
        self._control_common = common
        self._write_control_config()

    def write_control(self, control_port: int, gui_port: int) -> None:
        """Write the loopback control node's config again, on other ports."""
        self.control_port, self.gui_port = control_port, gui_port
        self._write_control_config()

    def _write_control_config(self) -> None:
        """The loopback control node's config: its transport on `control_port`, its GUI."""
        plugins = [("transport", dict(listen=f"{self._control_host}:{self.control_port}", role="control",
                                      **self.identity(CONTROL), **self._control_common))]
        if self.ui:
            bind, gui_port = self._gui_bind()
            plan = self._floorplan()
            plugins.append(("ui", {"listen": f"{bind}:{gui_port}", "floorplan": str(plan), "token": self.gui_token}))
            shown = bind
            if bind in ("0.0.0.0", "::"):
                from erni.plugins.ui.server import public_address

                shown = public_address()
            shown = f"[{shown}]" if ":" in shown else shown
            self.url = f"http://{shown}:{gui_port}/?token={self.gui_token}"
        if self.ros2 is not None:  # it hears every robot's Pose: it serves the whole team's topics
            plugins.append(("ros2", self.ros2))
        self._add_agent(CONTROL, (self._control_host, self.control_port), plugins,
                        f"control node of scenario {self.scenario.name}", workers=2)

    def _write_mesh_configs(self, snmp_ports: dict[str, int]) -> None:
        """Agent configs of the real-mesh tier: mesh addresses, segment broadcast, babel or SNMP MobiNet."""
        mesh = self.mesh
        assert mesh is not None
        common = dict(discovery_port=self.discovery_port, beacon_to=[mesh.broadcast], **self.transport)

        def mobinet(name: str) -> dict[str, Any]:
            # every node watches its routes: the transport beacons each routed node it has not met
            if self.mobinet == "babel":
                return dict(source="babel", babel=f"[::1]:{mesh.babel_port}", watch=["path_cost"], timeout=1.0)
            # SNMP routes name their nodes; neighbour lists carry addresses, shared with the control node
            return dict(host=mesh.service_address, port=snmp_ports[name], timeout=1.0, retries=1,
                        write_community=self.write_communities[name], watch=["neighbor_list"])

        # babeld carries no positions: robots share their poses over the mesh (WiDep, relay need them)
        shared = {"Pose": ["control", "robot"]} if self.mobinet == "babel" else {}
        if self.mission:
            shared["Territory"] = ["control", "robot"]
        for i, name in enumerate(self.names):
            addr = mesh.node(name).address
            plugins: list[tuple[str, dict[str, Any]]] = [
                ("transport", dict(listen=f"{addr}:0", role="robot", **self.identity(name),
                                   capabilities=["motion", "mobinet"] + (["mission"] if self.mission else []),
                                   **({"share_with": shared} if shared else {}), **common)),
                ("motion", dict(url=self.robot_url(i), model=self.scenario.robots.model)),
                ("mobinet", mobinet(name)),
            ]
            if self.mission:
                plugins.append(("mission", self._mission_settings()))
            self._add_agent(name, (addr, 0), plugins,
                            f"robot {name} of scenario {self.scenario.name}, namespace {mesh.node(name).netns}")
        control = mesh.node(CONTROL)
        plugins = [("transport", dict(listen=f"{control.address}:{self.control_port}", role="control",
                                      **self.identity(CONTROL), **common))]
        if self.mobinet == "babel":  # the control node is a mesh node too: its routes name far robots
            c = self.scenario.control  # and the base station's position, which babeld cannot carry
            plugins[0][1]["share_with"] = {"Pose": ["control", "robot"]}
            plugins.append(("mobinet", dict(source="babel", babel=f"[::1]:{mesh.babel_port}",
                                            watch=["path_cost"], timeout=1.0, position=[c.x, c.y])))
        if self.ui:
            bind, gui_port = self._gui_bind()
            plan = self._floorplan()
            shown = bind
            allowed = []
            if bind in ("0.0.0.0", "::"):
                from erni.plugins.ui.server import public_address

                shown = public_address()
                allowed.append(shown)
            # the GUI listens in the control node's namespace; this host's address forwards to it
            plugins.append(("ui", {"listen": f"{control.mgmt}:{gui_port}", "floorplan": str(plan),
                                   "token": self.gui_token, "allowed_hosts": allowed}))
            self._forwarder = TcpForwarder((bind, gui_port), (control.mgmt, gui_port))
            shown = f"[{shown}]" if ":" in shown else shown
            self.url = f"http://{shown}:{gui_port}/?token={self.gui_token}"
        self._add_agent(CONTROL, (control.address, self.control_port), plugins,
                        f"control node of scenario {self.scenario.name}, namespace {control.netns}", workers=2)

    def _mission_settings(self) -> dict[str, Any]:
        """What the mission plugin knows of the world: obstacles (circles) and walls."""
        world = self.scenario.world
        out: dict[str, Any] = {}
        if world.circle:
            out["obstacles"] = [[c.center[0], c.center[1], c.radius] for c in world.circle]
        walls = [[a[0], a[1], b[0], b[1]] for a, b in world.segments()]
        if walls:
            out["walls"] = walls
        if "speed" in self.scenario.strategy:  # the scenario's deployment speed (m/s)
            out["speed"] = float(self.scenario.strategy["speed"])
        return {**out, **self.mission_extra}

    def _add_agent(self, name: str, address: tuple[str, int], plugins: list[tuple[str, dict[str, Any]]],
                   comment: str, workers: int = 4) -> None:
        folder, journal = self.run_dir, str(self.run_dir / "journal" / f"{name}.sqlite")
        if self.placement is not None and self.placement.remote(name):  # its host's bundle, paths within it
            from erni.sim.agent_hosts import bundle_dir, private_bundle

            folder = private_bundle(bundle_dir(self.run_dir, self.placement.share[name]))
            journal = f"journal/{name}.sqlite"
        config = folder / "agents" / f"{name}.toml"
        # it holds the node's SNMP write community, the GUI's token
        private_file(config).write_text(agent_toml(name, plugins, journal=journal, workers=workers, comment=comment),
                                        encoding="utf-8")
        self.agents[name] = AgentProcess(name, config, private_file(folder / "logs" / f"{name}.log"), address)
