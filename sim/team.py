"""Team: a whole simulated team on one machine, with real agent processes on loopback addresses.

The sim process hosts the world: a robot host in a process of its own (`erni.sim.host_process`,
whose `RobotHost` serves a simulated ARCOS robot per robot over TCP, `socket://127.0.0.1:PORT`,
and shares their poses), one `ManetNetwork` whose robot nodes are served over SNMP
(robot N on `127.0.1.N`), and a feed thread that moves the network's nodes with the robots
and tells every agent's transport which agents its simulated radio can hear whenever the radio's
connectivity changes (through a pipe each agent inherits: see `erni.sim.radio`).

Every robot runs `python -m erni.sim.radio` (the `erni agent` command behind the simulated
radio) with the plugins it would run on a robot
(transport on `127.0.1.N`, motion, mobinet, mission when installed); only the serial URL and
the SNMP address differ. The control node runs the same agent with the transport in role
`control` (and the UI plugin when installed; with `ros2`, the ros2 plugin, which shows every robot
it hears to ROS 2 on a Zenoh session of its own: `team_configs.ros2_settings`). A team authority made for the run (in
`RUN/keys`) gives every agent, and the command-line client, its own identity.

With `netns=True` (`erni sim --netns`, the real-mesh tier) every agent runs as plain
`erni agent` in a network namespace of its own on a shared mesh segment (`erni.sim.netns`):
the radio model's links become packet-filter rules between the namespaces, babeld routes
between nodes that cannot hear each other, agents find each other by broadcast beacons on the
segment and through MobiNet's routes, and MobiNet reads babeld (`mobinet="babel"`, the
default there) or the simulated SNMP nodes. The simulator serves the robots and SNMP nodes on
the service address of the management links, and the GUI through a forwarder on this host.
"""

from __future__ import annotations

import logging
import math
import os
import secrets
import shutil
import socket
import sys
import tempfile
import threading
import time
import urllib.parse
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from erni.blackboard import heap
from erni.blackboard.errors import ErniError
from erni.sim.agent_hosts import Placement, RadioFeed, bundle_dir, spawn_behind_radio, tell_pipe, write_join_file
from erni.sim.host_process import COMMANDED_V, ENERGY, TH, HostProcess, RobotView, V, X, Y
from erni.sim.manet import ManetNetwork, RadioModel
from erni.sim.netns import HELLO_INTERVAL, Mesh, TcpForwarder
from erni.sim.ns3_channel import reach as ns3_reach
from erni.sim.robot import SimRobotConfig
from erni.sim.scenario import MAX_AGENT_ROBOTS, Scenario
from erni.sim.snmp_agent import ManetSnmpAgent
from erni.sim.team_configs import CONTROL as CONTROL
from erni.sim.team_configs import CONTROL_HOST as CONTROL_HOST
from erni.sim.team_configs import AgentConfigs, ros2_settings, stop_processes
from erni.sim.team_configs import AgentProcess as AgentProcess
from erni.sim.team_configs import agent_toml as agent_toml
from erni.sim.team_configs import free_port as free_port
from erni.sim.team_configs import port_free as port_free
from erni.sim.team_configs import private_file as private_file
from erni.sim.team_configs import robot_address as robot_address
from erni.sim.team_configs import toml_value as toml_value
from erni.sim.world import World
from erni.transport.identity import REVOKED, Authority

log = logging.getLogger("erni.sim.team")

CLI = "cli"  # the identity of command-line clients of the run (RUN/keys/cli.pem)
LAUNCH_WAIT = 15.0  # the longest a launch waits for room (a robot that never connects must not stall the start)


class TeamError(ErniError):
    """The team could not be started (a port is busy, an agent died, it did not come up)."""


RUN_SUBDIRS = ("agents", "logs", "journal", "keys")
"""What a run directory holds; a directory with one of them is a run directory (made private when reused)."""


def private_dir(path: Path) -> Path:
    """Make `path` (and missing parents) a directory only this user may enter: 0700, whatever the umask."""
    path.mkdir(parents=True, exist_ok=True)
    os.chmod(path, 0o700)
    return path


def gui_address(url: str) -> str:
    """A GUI URL without its token, for messages that may end up in a log."""
    return url.split("?", 1)[0]


def plugin_available(module: str, cls: str) -> bool:
    """True when `module` defines `cls` (optional plugins are included only once they exist)."""
    import importlib

    try:
        return hasattr(importlib.import_module(module), cls)
    except Exception:  # a half-written plugin must not stop the simulator
        return False


def beacon_port() -> int:
    """A free port for every agent's beacons (bound on all addresses)."""
    return free_port("")


@dataclass
class Sample:
    """The robots at one instant of the feed loop (for experiments and status)."""

    t: float
    x: list[float]
    y: list[float]
    th: list[float]
    v: list[float]
    target_v: list[float]
    energy: list[float]
    components: int
    control_reach: int


@dataclass
class TeamStatus:
    """What the feed loop saw last."""

    components: int = 0
    control_reach: int = 0
    reach: dict[str, list[str]] = field(default_factory=dict)
    writes: int = 0


class Team:
    """Start, watch and stop a simulated team: world, radio, robots, agents and control node."""

    def __init__(self, scenario: Scenario, *, run_dir: str | Path | None = None, headless: bool = False,
                 control_port: int = 47100, log_level: str = "WARNING", physics_hz: float | None = None,
                 feed_hz: float = 10.0, record: bool = False, mission: bool | None = None,
                 ui: bool | None = None, transport: dict[str, Any] | None = None, gui_port: int = 8080,
                 gui_listen: str | None = None, netns: bool = False, mobinet: str | None = None,
                 hello_interval: float = HELLO_INTERVAL, mission_settings: dict[str, Any] | None = None,
                 robot_settings: dict[str, Any] | None = None, keep_run_dir: bool = False,
                 launch_batch: int | None = None, ros2: bool | None = None,
                 channel: str | None = None, listen: str | None = None,
                 agent_hosts: list[str] | None = None, agents_here: int | None = None) -> None:
        if scenario.count > MAX_AGENT_ROBOTS:
            raise TeamError(f"--robots: at most {MAX_AGENT_ROBOTS} robot agents (one loopback "
                            f"address each), got {scenario.count}; use the kinematic mode of "
                            "`erni experiment` for larger teams")
        self.scenario = scenario
        self.run_dir = Path(run_dir) if run_dir else Path(tempfile.mkdtemp(prefix="erni-sim-"))
        # a temporary run directory goes at stop (started or not), unless asked to stay or the start
        # failed (its error names the logs in it); a directory the caller named is never removed
        self._scratch = not run_dir and not keep_run_dir
        self._started_well = False
        self._port_retries = 0  # the control node started again on free ports (`_port_taken_meanwhile`)
        self.headless = headless
        self.log_level = log_level
        # agents starting at once: a few per core keep the cores busy without starving the simulator
        self.launch_batch = _launch_batch(launch_batch)
        self.feed_period = 1.0 / feed_hz
        self._reach_of: object = None  # the truth's components that `_reach` was worked out from
        self._reach: dict[str, list[str]] = {}  # agent -> the agents its radio reaches
        self.record = record
        self.transport = {"peer_timeout": 3.0, **(transport or {})}
        self.gui_port = gui_port
        self.gui_listen = gui_listen  # HOST:PORT of the GUI (default 127.0.0.1:gui_port)
        self.gui_token = secrets.token_urlsafe(16)  # the GUI always asks for it: printed in the URL
        self.mission_extra = dict(mission_settings or {})  # experiments: mission settings for every robot
        self.robot_extra = dict(robot_settings or {})      # experiments: simulated robot settings (inputs)
        self.mission = plugin_available("erni.plugins.mission", "MissionControl") if mission is None else mission
        self.ui = (not headless and plugin_available("erni.plugins.ui", "UIPlugin")) if ui is None else ui
        self.keys_dir = self.run_dir / "keys"
        self.cli_identity = self.keys_dir / f"{CLI}.pem"
        self.discovery_port = beacon_port()
        self.names = scenario.robot_names()
        self.mobinet = _mobinet_source(mobinet, netns)
        # the control node's ros2 plugin, when `ros2` (None: the scenario's `ros2` key) asks for it: the
        # scenario's settings of it over the simulator's (`ros2_settings`); None without the plugin
        asked = scenario.ros2_settings()
        if ros2 is not None:
            asked = (asked or {}) if ros2 else None
        if asked is not None and netns:
            raise TeamError("--ros2 runs on the loopback team only, not with --netns (the control node's "
                            "namespace is not reachable from this host's ROS 2 tools)")
        self.ros2: dict[str, Any] | None = None if asked is None else ros2_settings(asked)
        # robots' agents on other hosts: every agent on its host's address, the world served on `listen`
        self.placement = _placement(self.names, listen, agent_hosts, netns, agents_here)
        self.feed: RadioFeed | None = None
        # the real-mesh tier: namespaces, segment, babeld, radio rules (made in start())
        self.mesh: Mesh | None = Mesh(self.names + [CONTROL], self.run_dir, control=CONTROL,
                                      hello_interval=hello_interval, channel=channel or scenario.radio.channel,
                                      range_m=ns3_reach(scenario.radio.comm_range), seed=scenario.seed) if netns else None
        self._forwarder: TcpForwarder | None = None
        # the control node listens on 127.0.1.250, on the world host's address with agent hosts
        self._control_host = self.placement.world if self.placement is not None else CONTROL_HOST
        self.control_port = _control_port(self._control_host, control_port, netns)
        starts = [s.model_dump() for s in scenario.starts()]  # the scenario's start poses win
        self.world = World.model_validate({**scenario.world.model_dump(), "robot": starts})
        world = self.world
        # big teams step slower: the host's cost grows with the team, and SIPs keep their period at either rate
        # the robots' firmware runs in a process of its own (`erni.sim.host_process`): here it would
        # share one interpreter with the SNMP nodes, the radio feed and the team's client
        self.host = HostProcess(world, physics_hz=physics_hz or (50.0 if scenario.count <= 10 else 20.0),
                                host=self.placement.world if self.placement is not None else "127.0.0.1")
        r = scenario.radio
        self.network = ManetNetwork(RadioModel(r.comm_range, r.lossless_range, r.min_quality),
                                    subnet="127.0.1.0/24")
        self.snmp = ManetSnmpAgent(self.network)
        self.write_communities: dict[str, str] = {}   # robot -> its node's SNMP write community
        self._radio_lock = threading.Lock()
        self.configs = AgentConfigs(scenario, self.run_dir, self.names, world, keys_dir=self.keys_dir,
                                    robot_url=self.host.url, discovery_port=self.discovery_port,
                                    transport=self.transport, mission=self.mission, ui=self.ui, mobinet=self.mobinet,
                                    mission_extra=self.mission_extra, gui_listen=gui_listen,
                                    gui_token=self.gui_token, mesh=self.mesh, ros2=self.ros2,
                                    placement=self.placement)
        self.agents: dict[str, AgentProcess] = self.configs.agents  # filled as the configs are written
        self.samples: list[Sample] = []
        self.status = TeamStatus()
        self.url: str | None = None
        self._stop = threading.Event()
        self._feed: threading.Thread | None = None
        self._sips_seen = {"sips": 0, "skipped": 0}  # the robot host's counters at the last `sips_since()`
        self._fed: dict[str, tuple[float, float]] = {}
        self._t0 = time.monotonic()
        self._started = False
        self._stopped = False
        self._frozen = False
        self._client: Any = None
        self.results: dict[str, Any] = {}  # uid -> final result, of tasks sent with send_task

    # --- addresses ----------------------------------------------------------------------

    @property
    def control_address(self) -> tuple[str, int]:
        """The control node's transport address (for `erni task --via HOST:PORT`)."""
        if self.mesh is not None:
            return self.mesh.node(CONTROL).address, self.control_port
        return self._control_host, self.control_port

    def address_of(self, name: str) -> str:
        """The address agent `name` listens on (its loopback address, or its mesh address)."""
        if self.mesh is not None:
            return self.mesh.node(name).address
        if self.placement is not None:
            return self.placement.address(name)
        return CONTROL_HOST if name == CONTROL else robot_address(self.names.index(name))

    @property
    def robots(self) -> list[RobotView]:
        """The simulated robots, in agent order (their state after the simulator's last step)."""
        return self.host.robots

    def robot(self, name: str) -> RobotView:
        """The simulated robot of agent `name`."""
        return self.host.robots[self.names.index(name)]

    # --- start --------------------------------------------------------------------------

    def start(self, progress: Callable[[str, int, int], None] | None = None, timeout: float = 120.0,
              heard: Iterable[str] | None = None) -> Team:
        """Start world, radio, agents and control node; return when the control node hears the team (of it,
        the robots named in `heard` when given: robots that are never tasked, behind a link too weak for a
        handshake to complete soon, need not hold the start)."""
        say = progress or (lambda what, done, total: None)
        self._started = True
        self._make_private_run_dir()
        authority = Authority(self.keys_dir) if (self.keys_dir / "authority.key").exists() else \
            Authority.create(self.keys_dir, team=f"erni sim {self.scenario.name}")  # a reused run dir keeps its team
        for name in self.names:
            authority.issue(name, "robot")
        authority.issue(CONTROL, "control")
        authority.issue(CLI, "cli")
        n = len(self.names)
        if self.mesh is not None:
            say("network namespaces", 0, n)
            self._make_mesh()
        say("world and robots", 0, n)
        model = self.scenario.robots.model
        for i, name in enumerate(self.names):
            cfg = SimRobotConfig.amigobot(name=name, seed=self.scenario.seed + i, **self.robot_extra) \
                if model == "amigobot" else SimRobotConfig(name=name, seed=self.scenario.seed + i, **self.robot_extra)
            self.host.add_robot(cfg)
        self.host.start(private_file(self.run_dir / "robots.state"), private_file(self.run_dir / "logs" / "robots.log"))
        say("radio network", 0, n)
        for start, robot in zip(self.scenario.starts(), self.host.robots):
            self.network.add_node(start.name, robot.x, robot.y, start.heading)
        c = self.scenario.control
        self.network.add_node(CONTROL, c.x, c.y)
        self.snmp.start()
        # each robot's node gets its own write community: a robot can SET only its own position
        self.write_communities.update({name: secrets.token_hex(8) for name in self.names})
        snmp_ports = {name: self.snmp.serve(name, self._snmp_host(i), 0,
                                            write_community=self.write_communities[name])[1]
                      for i, name in enumerate(self.names)}
        self._update_network(force=True)
        if self.mesh is not None:
            self.mesh.start_babel()
        self._feed = threading.Thread(target=self._feed_loop, name="sim-feed", daemon=True)
        self._feed.start()
        say("agent configs", 0, n)
        self.configs.write(snmp_ports, self.write_communities, self.control_port, self.gui_port)
        self.url, self._forwarder = self.configs.url, self.configs.forwarder
        if self.placement is not None:
            self._write_bundles(authority, say)
        env = self.agent_env()
        # the world, the robots and the network live until stop(): full collections skip them. Done
        # before the agents start, so that this collection stalls nobody's SIPs
        heap.freeze()
        self._frozen = True
        order = [CONTROL] + self.names
        order = [name for name in order if self.placement is None or not self.placement.remote(name)]
        for k, name in enumerate(order):
            self._make_room(order[:k])
            self._spawn(self.agents[name], env)
            say("agents launched", k + 1, len(order))
        self._wait_up(say, timeout, set(self.names if heard is None else heard))
        self._started_well = True
        return self

    def _make_room(self, launched: list[str]) -> None:
        """Wait (at most LAUNCH_WAIT s) until fewer than `launch_batch` of the launched robots' agents
        are still starting, i.e. their simulated robot has no client yet. An agent's start (its
        imports above all) takes about a second of CPU: 40 at once hold a 2-core machine for 20 s,
        the simulator's SIPs stall beyond the drivers' link timeout, and the robots already up
        lose their link and fail their first tasks."""
        deadline = time.monotonic() + LAUNCH_WAIT
        while time.monotonic() < deadline:
            linked = self.host.connected()
            starting = sum(1 for name in launched if name in self.names and self.agents[name].alive
                           and not linked[self.names.index(name)])
            if starting < self.launch_batch:
                return
            time.sleep(0.05)

    def agent_env(self) -> dict[str, str]:
        """The environment agent processes of this team run in."""
        return {**os.environ, "PYTHONUNBUFFERED": "1"}

    def identity(self, name: str) -> dict[str, str]:
        """Transport settings naming agent `name`'s identity and the team's revocation list."""
        return self.configs.identity(name)

    def _make_mesh(self) -> None:
        """Build the namespaces; serve robots and SNMP nodes where the namespaces reach them."""
        assert self.mesh is not None
        self.mesh.create()
        r = self.scenario.radio
        # the radio model's node addresses are the mesh addresses (robots 1..n, then the control node)
        self.network = ManetNetwork(RadioModel(r.comm_range, r.lossless_range, r.min_quality),
                                    subnet=self.mesh.subnet)
        self.snmp = ManetSnmpAgent(self.network)
        self.host.host = self.mesh.service_address

    def _snmp_host(self, index: int) -> str:
        if self.placement is not None:
            return self.placement.world
        return self.mesh.service_address if self.mesh is not None else robot_address(index)

    def _write_bundles(self, authority: Authority, say: Callable[[str, int, int], None]) -> None:
        """Each agent host's bundle (`RUN/hosts/host-K`): its agents' configs and keys, the team's
        revocation list and the join file; then serve the radio feed they join."""
        placement = self.placement
        assert placement is not None
        self.feed = RadioFeed(placement, lambda name: self.status.reach.get(name))
        for k in range(2, 2 + len(placement.hosts)):
            bundle = bundle_dir(self.run_dir, k)
            shutil.copyfile(self.keys_dir / REVOKED, private_file(bundle / "keys" / REVOKED))
            for name in placement.names_of(k):
                authority.issue(name, "robot", out=bundle / "keys" / f"{name}.pem")
            write_join_file(bundle, world=self.feed.address, host=k, secret=self.feed.secrets[k],
                            agents=placement.names_of(k), log_level=self.log_level)
        say("agent hosts joined", 0, len(placement.hosts))

    def _spawn(self, agent: AgentProcess, env: dict[str, str]) -> None:
        if self.mesh is not None:  # the real mesh: plain `erni agent` in the node's namespace, no radio pipe
            agent.proc = self.mesh.popen(agent.name, [sys.executable, "-m", "erni", "agent", str(agent.config),
                                                      "--log-level", self.log_level], agent.log, env=env)
            return
        # the agent's radio: reachability lines from us. The feed thread pushes too: under the lock
        # the agent's first line is the latest
        with self._radio_lock:
            agent.radio = spawn_behind_radio(agent, env, self.log_level)
            self._tell_radio(agent, self.status.reach.get(agent.name))

    def _tell_radio(self, agent: AgentProcess, names: list[str] | None) -> None:
        """Tell `agent` the names it can hear now: into its radio pipe, or its host's radio feed (never blocks)."""
        if self.feed is not None and self.placement is not None and self.placement.remote(agent.name):
            self.feed.tell(agent.name, names)
        else:
            tell_pipe(agent, names)

    def client(self) -> Any:
        """A started transport client of this team, reaching it through the control node."""
        if self._client is None:
            from erni.transport.client import Client

            self._client = Client(self.control_address, identity=self.cli_identity)
            self._client.endpoint.start()
        return self._client

    def sips_since(self) -> tuple[int, int]:
        """SIPs the simulated robots sent, and SIP slots they skipped because the robot host came too
        late for them, since the last call (or the start). A skipped SIP is a Pose its robot lacks:
        the machine is too busy for the team to run in real time."""
        now = self.host.timing()
        last, self._sips_seen = self._sips_seen, now
        return now["sips"] - last["sips"], now["skipped"] - last["skipped"]

    def peers(self, timeout: float = 2.0) -> dict[str, Any]:
        """The control node's directory: agent name -> Peer ({} when it does not answer)."""
        from erni.blackboard.schemas import PeerList
        from erni.transport.client import PeerListParts

        client = self.client()
        client.send(self.control_address, "peers.request", None)
        deadline = time.monotonic() + timeout
        parts = PeerListParts()  # a large directory comes in parts
        while time.monotonic() < deadline:
            msg = client.receive(0.1)
            if msg is not None and msg.kind == "peers.reply" and isinstance(msg.body, PeerList):
                directory = parts.add(msg.body)
                if directory is not None:
                    return {p.name: p for p in directory.peers}
        return {}

    def _make_private_run_dir(self) -> None:
        """The run directory and its folders 0700, what an earlier run left in them 0600: configs,
        logs, journals and keys are this user's only. A directory named that is no run directory
        (no agents/, logs/, ...) keeps its mode; the folders made in it are private."""
        run = self.run_dir
        if not run.exists() or any((run / sub).is_dir() for sub in RUN_SUBDIRS):
            private_dir(run)
        for sub in RUN_SUBDIRS:
            folder = private_dir(run / sub)
            for path in folder.rglob("*"):
                if path.is_symlink() or path.stat().st_uid != os.getuid():
                    continue
                os.chmod(path, 0o700 if path.is_dir() else path.stat().st_mode & 0o600)

    def _wait_up(self, say: Callable[[str, int, int], None], timeout: float, only: set[str]) -> None:
        deadline = time.monotonic() + timeout
        n = len(self.names)
        while True:
            self._check_started()
            connected = sum(self.host.connected())
            joined, hosts = self._hosts_joined()
            missing = hosts - joined
            expected = set(self.status.reach.get(CONTROL, [])) & only
            up = {name for name, p in self.peers(1.0).items() if p.up} if connected == n else set()
            heard = len(up & expected)
            if missing:
                say("agent hosts joined", joined, hosts)
            else:
                say("robots connected", connected, n) if connected < n else say("robots heard by control", heard,
                                                                                  len(expected))
            # the control node is heard before its GUI plugin may listen: the URL printed must open; so
            # must the ROS 2 endpoint printed
            if connected == n and expected <= up and self._gui_answers() and self._ros2_answers():
                return
            if time.monotonic() > deadline:
                late = ""
                if connected == n and expected <= up:
                    late = f"; its GUI at {gui_address(self.url or '')} does not answer" if not self._gui_answers() \
                        else f"; its ROS 2 session at {', '.join(self.ros2_listen)} does not answer"
                if missing:
                    late += (f"; {missing} agent host(s) did not join (erni sim --join on each, with its bundle "
                             f"from {self.run_dir / 'hosts'})")
                raise TeamError(f"the team did not come up within {timeout:.0f} s: {connected}/{n} robots "
                                f"connected, control hears {heard}/{len(expected)} reachable robots{late}; "
                                f"logs in {self.run_dir / 'logs'}")
            time.sleep(0.3)

    def _check_started(self) -> None:
        """Raise TeamError when an agent this process started exited during start-up (a control node
        whose port was taken meanwhile is started again instead)."""
        for agent in self._local_agents():
            if not agent.alive and self._port_taken_meanwhile(agent):
                continue  # started again on other ports
            if not agent.alive:
                tail = _tail(agent.log)
                raise TeamError(f"agent {agent.name} exited with code {agent.proc.returncode if agent.proc else '?'}"
                                f" during start-up; its log ({agent.log}) ends:\n{tail}")

    def _hosts_joined(self) -> tuple[int, int]:
        """How many agent hosts have joined, of how many ((0, 0) without agent hosts)."""
        if self.feed is None or self.placement is None:
            return 0, 0
        return len(self.feed.joined()), len(self.placement.hosts)

    def _local_agents(self) -> list[AgentProcess]:
        """The agents this process starts (not those of agent hosts)."""
        return [a for a in self.agents.values() if self.placement is None or not self.placement.remote(a.name)]

    def _port_taken_meanwhile(self, agent: AgentProcess) -> bool:
        """The loopback control node found its port (or its GUI's) taken after it was checked free
        (another program, or a team started at the same time, bound it first): start it again on
        free ports, at most three times. True when it was started again."""
        if agent.name != CONTROL or self.mesh is not None or self._port_retries >= 3 \
                or "Address already in use" not in _tail(agent.log):
            return False
        self._port_retries += 1
        old = self.control_port
        self.control_port = free_port(self._control_host)
        if not self.gui_listen:
            self.gui_port = free_port("127.0.0.1")
        agent.close_radio()
        agent.log.replace(agent.log.with_suffix(f".log.{self._port_retries}"))  # kept; the next run's log is new
        self.configs.write_control(self.control_port, self.gui_port)
        self.url = self.configs.url
        self._spawn(self.agents[CONTROL], self.agent_env())
        log.warning("control node's port %d was taken meanwhile: started again on %d", old, self.control_port)
        return True

    def _gui_answers(self) -> bool:
        """Whether the GUI (if the team has one) accepts a connection at its URL's address."""
        if self.url is None:
            return True
        where = urllib.parse.urlsplit(self.url)
        try:
            with socket.create_connection((where.hostname or "127.0.0.1", where.port or 80), timeout=0.5):
                return True
        except OSError:
            return False

    @property
    def ros2_listen(self) -> list[str]:
        """The TCP endpoints the control node's ROS 2 session listens on (none without the ros2 plugin)."""
        if self.ros2 is None or self.ros2.get("mode") == "client":
            return []
        return [e for e in self.ros2.get("listen", []) if e.startswith("tcp/")]

    def _ros2_answers(self) -> bool:
        """Whether the control node's ROS 2 session (if the team has one) accepts a connection where it listens."""
        for endpoint in self.ros2_listen:
            host, _, port = endpoint.removeprefix("tcp/").split("#", 1)[0].rpartition(":")
            host = host.strip("[]")
            try:
                with socket.create_connection(("127.0.0.1" if host in ("0.0.0.0", "::", "") else host, int(port)),
                                              timeout=0.5):
                    pass
            except (OSError, ValueError):
                return False
        return True

    # --- running ------------------------------------------------------------------------

    def elapsed(self) -> float:
        """Seconds since the team object was made."""
        return time.monotonic() - self._t0

    def fail(self, name: str) -> None:
        """Make robot `name` fail: its agent is killed at once (its robot stops on the watchdog)."""
        if self.feed is not None and self.placement is not None and self.placement.remote(name):
            self.agents[name].failed = True
            self.feed.fail(name)  # its agent host kills it
        else:
            self.agents[name].kill()

    def teleport(self, name: str, x: float, y: float, heading: float = 0.0) -> None:
        """Move robot `name` in the world (the simulator's hand, not a task)."""
        self.host.teleport(self.names.index(name), x, y, math.radians(heading))

    def cut_serial(self, name: str) -> None:
        """Pull the cable between robot `name` and its agent: the simulated robot drops its client
        (the driver reconnects, as to a robot whose cable is plugged back)."""
        self.host.cut(self.names.index(name))

    def _feed_loop(self) -> None:
        while not self._stop.wait(self.feed_period):
            try:
                self._update_network()
            except Exception:  # the feed must outlive one bad step
                log.exception("sim feed loop error")

    def _update_network(self, force: bool = False) -> None:
        state = self.host.snapshot()  # every robot after one whole physics step
        moved = {}
        for name, row in zip(self.names, state):
            x, y = float(row[X]), float(row[Y])
            old = self._fed.get(name)
            if force or old is None or math.hypot(x - old[0], y - old[1]) > 0.02:
                moved[name] = (x, y)
        if moved:
            self.network.move_many(moved)
            self._fed.update(moved)
        truth = self.network.truth()
        if truth.components is not self._reach_of:  # moves that changed no link keep the components
            self._reach_of, self._reach = truth.components, {
                name: sorted(comp - {name}) for comp in truth.components for name in comp}
        reach = self._reach
        control_reach = len(reach.get(CONTROL, []))
        with self._radio_lock:
            if force or reach != self.status.reach:
                for name, agent in self.agents.items():
                    if force or reach.get(name) != self.status.reach.get(name):
                        self._tell_radio(agent, reach.get(name))
                self.status.writes += 1
            self.status.reach = reach
        self.status.components = len(truth.components)
        self.status.control_reach = control_reach
        if self.mesh is not None:  # the radio as packet-filter rules (rewritten only when they change)
            c = self.scenario.control  # the ns-3 channel moves its nodes instead
            self.mesh.apply(truth.links, {**self._fed, CONTROL: (c.x, c.y)})
        if self.record:
            self.samples.append(Sample(
                self.elapsed(), state[:, X].tolist(), state[:, Y].tolist(), state[:, TH].tolist(),
                state[:, V].tolist(), state[:, COMMANDED_V].tolist(), state[:, ENERGY].tolist(),
                len(truth.components), control_reach))

    def send_task(self, robot: str, verb: str, preposition: str, **params: Any) -> Any:
        """Send a task to agent `robot` through the control node; return the Task sent."""
        from erni.blackboard import Task

        client = self.client()
        task = Task(verb=verb, preposition=preposition, params=params, destination=robot,
                    source=client.endpoint.name)
        client.send(self.control_address, "task.add", task)
        return task

    def wait_result(self, uid: str, timeout: float) -> Any:
        """Return the final AllocationResult of a task sent with `send_task` (TeamError after timeout)."""
        from erni.blackboard.schemas import ResultUpdate

        client = self.client()
        deadline = time.monotonic() + timeout
        while uid not in self.results and time.monotonic() < deadline:
            msg = client.receive(0.1)
            if msg and msg.kind == "task.result" and isinstance(msg.body, ResultUpdate):
                if msg.body.result.state.done:
                    self.results[msg.body.uid] = msg.body.result
        if uid in self.results:
            return self.results[uid]
        raise TeamError(f"task {uid}: no final result within {timeout:g} s")

    # --- stop ---------------------------------------------------------------------------

    def stop(self, timeout: float = 8.0, keep_run_dir: bool = False) -> None:
        """Stop every agent (SIGTERM, then SIGKILL), the feed, the SNMP agent and the robots; remove
        the temporary run directory unless `keep_run_dir` (or the team was made to keep it)."""
        if self._stopped:
            return
        self._stopped = True
        stop_processes([a.proc for a in self.agents.values() if a.proc is not None], timeout)
        self._stop.set()
        if self._feed is not None:
            self._feed.join(5)
        if self.feed is not None:  # every agent host sees its feed end, and stops its agents
            self.feed.close()
        for agent in self.agents.values():
            agent.close_radio()
        if self._client is not None:
            self._client.endpoint.stop()
            self._client = None
        self.snmp.close()
        self.host.stop()
        if self._frozen:  # a process that runs team after team gets each one's memory back
            heap.thaw()
            self._frozen = False
        if self._forwarder is not None:
            self._forwarder.close()
            self._forwarder = None
        if self.mesh is not None:
            self.mesh.destroy()
        if self._scratch and (self._started_well or not self._started) and not keep_run_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)  # a start that failed keeps its logs

    def __enter__(self) -> Team:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc: object) -> None:
        self.stop(keep_run_dir=kind is not None)


def _launch_batch(asked: int | None) -> int:
    """How many agents may start at once: `asked`, else a few per core (they keep the cores busy
    without starving the simulator)."""
    batch = asked if asked is not None else 4 * (os.cpu_count() or 1)
    if batch < 1:
        raise TeamError(f"launch_batch: expected at least 1 agent starting at a time, got {asked}")
    return batch


def _control_port(host: str, asked: int | None, netns: bool) -> int:
    """The control node's port: `asked` when free on `host` (any free one when not); on the real mesh
    `asked` or 47100, as the control node's namespace has every port free."""
    if netns:
        return asked or 47100
    return asked if asked and port_free(host, asked) else free_port(host)


def _placement(names: list[str], listen: str | None, agent_hosts: list[str] | None, netns: bool,
               here: int | None = None) -> Placement | None:
    """Where each robot's agent runs: every one here on loopback (None) unless agent hosts are named."""
    if not agent_hosts:
        if listen or here is not None:
            raise TeamError(f"{'--listen' if listen else '--agents-here'}: for a team across hosts; name the agent "
                            "hosts with --agent-host")
        return None
    if netns:
        raise TeamError("--agent-host runs on the loopback tier only, not with --netns")
    if not listen:
        raise TeamError("--agent-host: name this host's address the agent hosts reach with --listen ADDR")
    return Placement.plan(names, listen, agent_hosts, here)


def _mobinet_source(asked: str | None, netns: bool) -> str:
    """Where MobiNet reads the network: `asked`, else babeld on the real mesh and SNMP on loopback."""
    mobinet = asked or ("babel" if netns else "snmp")
    if mobinet not in ("snmp", "babel"):
        raise TeamError(f"mobinet: expected 'snmp' or 'babel', got {mobinet!r}")
    if mobinet == "babel" and not netns:
        raise TeamError("mobinet 'babel' reads babeld, which runs only in the real-mesh tier: add --netns")
    return mobinet


def _tail(path: Path, lines: int = 8) -> str:
    try:
        return "\n".join(path.read_text(encoding="utf-8", errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"
