"""The real-mesh tier of `erni sim --netns`: network namespaces, a bridge segment, babeld, nftables.

Every node of the team (each robot and the control node) gets a network namespace of its own
with one address on a shared mesh segment; the simulated radio becomes packet-filter rules
between the nodes' ports on that segment; a real routing daemon (Debian's babeld) runs in every
namespace and routes multi-hop between nodes that cannot hear each other. One run (tag T, four
hex digits; slot K picks its subnets) looks like this::

    erni-T              the segment: bridge `mesh`, one port `pN` per node (N = its network index),
                        and the nftables table `bridge erni` that is the radio
    erni-T-NAME         one per node: `mesh0` 10.231.K.N/24 (a veth into the bridge), `lo`, babeld
                        (local interface on [::1]:33123), and the management link `mgmt0`
                        10.232.K.N (a veth into the root namespace)
    root namespace      `erniTmN`, the far ends of the management links, each holding the service
                        address 10.232.K.254 where the simulator serves the robots' ARCOS ports and
                        SNMP nodes; a host route to the control node's mesh address over its
                        management link, so that `erni task --via` works from this host

The management links are simulator plumbing, not part of the mesh: the radio rules never see
them (they are not bridge ports), babeld does not run on them and announces only `mesh0`'s
address, and nothing routes between them (the root namespace knows only the control node's
mesh address). On a real robot they are the cable between the onboard computer and its base.

The radio: for each ordered pair of ports, frames from a to b pass when the radio model gives the
link a delivery ratio of 1, are dropped with probability 1 - q (`numgen random`, rounded to
5 %) when 0 < q < 1, and are always dropped otherwise (the chain's policy). The rules are
replaced in one nft transaction whenever the model's links change (robots move); broadcasts
and babeld's multicast Hellos are filtered per receiving port like every other frame.

The ns-3 channel (`channel="ns3"`, `erni sim --netns --channel ns3`): no bridge and no rules;
one ns-3 process in the segment's namespace opens each node's `mesh0` as a TAP device inside
that node's namespace and carries the frames through ns-3's 802.11a ad-hoc network, its nodes
moved to the robots' positions (`Mesh.apply(links, positions)`); see `erni.sim.ns3_channel`.
Addresses, babeld, the management links and the clean-up are the same; the process dies with the
launcher and with the segment's namespace, and its TAP devices with it.

Clean-up: everything the run creates lives in its namespaces, and deleting a namespace deletes
its links, addresses, routes and rules (the root ends of the management links die with their
peers). `Mesh.destroy()` stops the daemons and deletes the namespaces. A launcher killed with
SIGKILL leaves them behind: its state file (`/run/erni-netns/T.json`: owner pid and start
time) is written before anything is created, so the next `Mesh.create()` (or
`clean_stale()`) recognises the namespaces of dead owners by name and deletes them. What ran in
them does not outlive the launcher: every process it starts in a namespace (`Mesh.popen`: babeld,
the agents) gets SIGKILL from the kernel when the launcher dies (`die_with_parent`); the clean
stop (SIGTERM, once) is `Mesh.destroy()`'s and the team's, when the launcher stops normally.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import functools
import ipaddress
import json
import logging
import os
import re
import secrets
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from erni.blackboard.errors import ErniError
from erni.sim.ns3_channel import ChannelNode, Ns3Channel, Ns3Error

log = logging.getLogger("erni.sim.netns")

STATE_DIR = Path("/run/erni-netns")
PREFIX = "erni-"
NAMESPACE = re.compile(r"^erni-([0-9a-f]{4})(?:-(.+))?$")
HOST_LINK = re.compile(r"^erni([0-9a-f]{4})m\d+$")
MESH_NET = "10.231.{slot}.0/24"
MGMT_NET = "10.232.{slot}.0/24"
SERVICE_INDEX = 254            # the service address of the root namespace: 10.232.K.254
BABEL_PORT = 33123             # babeld's read-only local interface in every namespace ([::1])
HELLO_INTERVAL = 0.5           # s; babeld's default on wireless links is 4 s
CHANNELS = ("nftables", "ns3")  # what carries the frames between the namespaces (see `Mesh`)
LOSS_STEP = 0.05               # drop probabilities are rounded to this step (fewer rule updates)
INSTALL_HINT = ("run `erni sim` without --netns for the loopback tier (the same agents on "
                "127.0.1.N behind the simulated radio), which needs neither root nor these tools")


class NetnsError(ErniError):
    """The namespaces, links, rules or daemons of the mesh could not be made or removed."""


class NetnsUnavailable(NetnsError):
    """This machine or user cannot run the real-mesh tier; the message says why and what to do."""


# --- running the tools ------------------------------------------------------------------

def _run(argv: list[str], *, input: str | None = None, check: bool = True) -> str:
    """Run a tool; return its stdout; raise NetnsError with its one-line complaint on failure."""
    try:
        done = subprocess.run(argv, input=input, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as err:
        raise NetnsError(f"{' '.join(argv[:4])}: {err}") from None
    if check and done.returncode != 0:
        why = " ".join((done.stderr or done.stdout).split())[:300] or f"exit code {done.returncode}"
        raise NetnsError(f"`{' '.join(argv)[:160]}` failed: {why}")
    return done.stdout


def _ip(*args: str, netns: str | None = None, check: bool = True) -> str:
    return _run(["ip", *(["-n", netns] if netns else []), *args], check=check)


def _in(netns: str, *argv: str, input: str | None = None) -> str:
    return _run(["ip", "netns", "exec", netns, *argv], input=input)


def unavailable_reason() -> str | None:
    """Why the real-mesh tier cannot run here (one line with what to do), or None when it can."""
    if os.geteuid() != 0:
        return ("network namespaces, veth links and packet filters need root: run it with sudo "
                f"(CI runs as root), or {INSTALL_HINT}")
    packages = {"ip": "iproute2", "sysctl": "procps", "nft": "nftables", "babeld": "babeld"}
    missing = [tool for tool in packages if shutil.which(tool) is None]
    if missing:
        return (f"{', '.join(missing)} not found: install {'it' if len(missing) == 1 else 'them'} "
                f"(`apt-get install {' '.join(packages[t] for t in missing)}`), or {INSTALL_HINT}")
    probe = f"{PREFIX}probe-{os.getpid()}"
    try:
        _ip("netns", "add", probe)
    except NetnsError as err:
        return f"cannot create a network namespace ({err}); {INSTALL_HINT}"
    try:
        _ip("link", "add", "probe", "type", "bridge", netns=probe)
        _in(probe, "nft", "add table bridge probe")
    except NetnsError as err:
        return f"this kernel lacks bridges or nftables' bridge family ({err}); {INSTALL_HINT}"
    finally:
        _ip("netns", "delete", probe, check=False)
    return None


def check_available() -> None:
    """Raise NetnsUnavailable (saying why and how to run without) unless the tier can run here."""
    reason = unavailable_reason()
    if reason:
        raise NetnsUnavailable(f"--netns: {reason}")


# --- runs of this machine: which are alive, which left namespaces behind -----------------

def _start_time(pid: int) -> int | None:
    """The kernel's start time of process `pid` (clock ticks since boot), None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])  # field 22; the name may hold spaces


@dataclass
class RunRecord:
    """What a run writes before it creates anything: its owner and its slot."""

    tag: str
    slot: int
    pid: int
    start: int | None
    created: float = 0.0

    @property
    def alive(self) -> bool:
        """True while the launcher that owns this run is running."""
        return self.start is not None and _start_time(self.pid) == self.start


def _records() -> dict[str, RunRecord | None]:
    """Every run's record by tag; None for a record that cannot be read (its run is not known to be dead)."""
    out: dict[str, RunRecord | None] = {}
    if not STATE_DIR.is_dir():
        return out
    for path in STATE_DIR.glob("*.json"):
        try:
            data = json.loads(path.read_text())
            out[path.stem] = RunRecord(str(data["tag"]), int(data["slot"]), int(data["pid"]),
                                       data.get("start"), float(data.get("created", 0.0)))
        except (OSError, ValueError, KeyError, TypeError):
            log.warning("keeping run %s: its record %s cannot be read, so its owner is not known to be dead",
                        path.stem, path)
            out[path.stem] = None
    return out


def _namespaces() -> list[str]:
    out = _ip("netns", "list", check=False)
    return [line.split()[0] for line in out.splitlines() if line.strip()]


@contextlib.contextmanager
def _registry_lock() -> Iterator[None]:
    STATE_DIR.mkdir(mode=0o755, parents=True, exist_ok=True)
    with open(STATE_DIR / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _delete_namespace(name: str) -> None:
    """Kill what still runs inside namespace `name` (a dead run's daemons), then delete it."""
    pids = _ip("netns", "pids", name, check=False).split()
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(pid), signal.SIGKILL)
    _ip("netns", "delete", name, check=False)


def clean_stale() -> list[str]:
    """Delete the namespaces, links and records of runs whose launcher is gone; return their tags."""
    with _registry_lock():
        return _clean_stale_locked()


def _clean_stale_locked() -> list[str]:
    records = _records()
    # a run is dead only when its record proves it: the owner's pid is gone or started at another time;
    # a run whose record cannot be read is kept (with a warning), and a namespace with no record at all
    # is dead, since a run writes its record (under this lock) before it creates anything
    live = {tag for tag, rec in records.items() if rec is None or rec.alive}
    stale: set[str] = set()
    for name in _namespaces():
        m = NAMESPACE.match(name)
        if m and m.group(1) not in live:
            stale.add(m.group(1))
            _delete_namespace(name)
    for line in _ip("-o", "link", "show", check=False).splitlines():
        parts = line.split(":")
        if len(parts) > 1:
            link = parts[1].strip().split("@")[0]
            m = HOST_LINK.match(link)
            if m and m.group(1) not in live:
                stale.add(m.group(1))
                _ip("link", "delete", link, check=False)
    for tag in set(records) - live:
        stale.add(tag)
        with contextlib.suppress(OSError):
            (STATE_DIR / f"{tag}.json").unlink()
    for tag in sorted(stale):
        log.warning("removed what a dead run (tag %s) left behind", tag)
    return sorted(stale)


def _slot_taken_by_host(slot: int) -> bool:
    """True when this host already has addresses or routes in either subnet of `slot`."""
    nets = [ipaddress.ip_network(MESH_NET.format(slot=slot)), ipaddress.ip_network(MGMT_NET.format(slot=slot))]
    text = _ip("-o", "-4", "addr", "show", check=False) + _ip("-4", "route", "show", "table", "all", check=False)
    for word in re.findall(r"\b\d+\.\d+\.\d+\.\d+(?:/\d+)?\b", text):
        try:
            net = ipaddress.ip_network(word, strict=False)
        except ValueError:
            continue
        if net.prefixlen > 0 and any(net.overlaps(n) for n in nets):
            return True
    return False


# --- one run -----------------------------------------------------------------------------

@dataclass
class MeshNode:
    """One node of the mesh: its namespace, mesh address and management link."""

    name: str
    index: int                 # network index N: mesh address 10.231.K.N, bridge port pN
    netns: str
    address: str
    mgmt: str
    host_link: str             # the root-namespace end of the management link
    babeld: subprocess.Popen[bytes] | None = None

    @property
    def port(self) -> str:
        """The node's port on the segment's bridge."""
        return f"p{self.index}"


@dataclass
class Radio:
    """Fault injection on top of the radio model: links cut by hand and a loss added everywhere."""

    cut: set[frozenset[str]] = field(default_factory=set)
    extra_loss: float = 0.0


class Mesh:
    """The namespaces, segment, management links, babeld daemons and radio rules of one run."""

    def __init__(self, names: list[str], run_dir: str | Path, *, control: str | None = None,
                 hello_interval: float = HELLO_INTERVAL, babel_port: int = BABEL_PORT,
                 channel: str = "nftables", range_m: float = 10.0, seed: int = 1) -> None:
        if channel not in CHANNELS:
            raise NetnsError(f"channel: expected one of {', '.join(CHANNELS)}, got {channel!r}")
        if len(names) > SERVICE_INDEX - 1:
            raise NetnsError(f"at most {SERVICE_INDEX - 1} nodes fit one mesh segment, got {len(names)}")
        if not hello_interval > 0:
            raise NetnsError(f"hello_interval: expected a positive number of seconds, got {hello_interval}")
        self.names = list(names)
        self.control = control
        self.run_dir = Path(run_dir)
        self.hello_interval = hello_interval
        self.babel_port = babel_port
        self.tag = ""
        self.slot = -1
        self.nodes: dict[str, MeshNode] = {}
        self.radio = Radio()
        self.rule_updates = 0
        self._rules: str | None = None
        self._links: dict[frozenset[str], float] = {}
        self._lock = threading.Lock()
        self._created = False
        self.channel = channel          # "nftables": the radio model as rules; "ns3": ns-3's 802.11 (erni.sim.ns3_channel)
        self.range_m = range_m          # the ns-3 channel's reach (`ns3_channel.reach` of the comm_range)
        self.seed = seed
        self.ns3: Ns3Channel | None = None
        self._positions: dict[str, tuple[float, float]] = {}

    # -- addresses ---------------------------------------------------------------------

    @property
    def hub(self) -> str:
        """The segment's namespace."""
        return f"{PREFIX}{self.tag}"

    @property
    def subnet(self) -> str:
        """The mesh segment's IPv4 subnet (known once created)."""
        return MESH_NET.format(slot=self.slot)

    @property
    def broadcast(self) -> str:
        """The mesh segment's broadcast address: where agents send their beacons."""
        return str(ipaddress.ip_network(self.subnet).broadcast_address)

    @property
    def service_address(self) -> str:
        """The root namespace's address on every management link (robots' ARCOS ports, SNMP nodes)."""
        return str(ipaddress.ip_network(MGMT_NET.format(slot=self.slot)).network_address + SERVICE_INDEX)

    def node(self, name: str) -> MeshNode:
        """The node called `name`."""
        try:
            return self.nodes[name]
        except KeyError:
            raise NetnsError(f"no mesh node {name!r}; expected one of {', '.join(self.nodes)}") from None

    def exec_argv(self, name: str, argv: list[str]) -> list[str]:
        """`argv` run inside node `name`'s namespace."""
        return ["ip", "netns", "exec", self.node(name).netns, *argv]

    # -- creating ----------------------------------------------------------------------

    def create(self) -> Mesh:
        """Clean what dead runs left, reserve a slot, then build namespaces, segment and links."""
        check_available()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with _registry_lock():
            _clean_stale_locked()
            records = _records()
            used = {rec.slot for rec in records.values() if rec is not None}
            tags = set(records)
            self.slot = next((k for k in range(256) if k not in used and not _slot_taken_by_host(k)), -1)
            if self.slot < 0:
                raise NetnsError("no free subnet slot (10.231.K.0/24 and 10.232.K.0/24 are all in use)")
            self.tag = next(t for t in iter(lambda: secrets.token_hex(2), None) if t not in tags)
            record = {"tag": self.tag, "slot": self.slot, "pid": os.getpid(),
                      "start": _start_time(os.getpid()), "created": time.time(), "run_dir": str(self.run_dir)}
            (STATE_DIR / f"{self.tag}.json").write_text(json.dumps(record) + "\n")
        self._created = True
        try:
            self._build()
        except BaseException:
            self.destroy()
            raise
        return self

    def _build(self) -> None:
        mesh = ipaddress.ip_network(self.subnet)
        mgmt = ipaddress.ip_network(MGMT_NET.format(slot=self.slot))
        service = self.service_address
        _ip("netns", "add", self.hub)
        if self.channel == "nftables":
            _ip("link", "add", "mesh", "type", "bridge", "mcast_snooping", "0", netns=self.hub)
            _ip("link", "set", "mesh", "up", netns=self.hub)
            self._write_rules({})  # the radio exists before any port: nothing passes until told
        for i, name in enumerate(self.names, start=1):
            node = MeshNode(name, i, f"{PREFIX}{self.tag}-{name}", str(mesh.network_address + i),
                            str(mgmt.network_address + i), f"erni{self.tag}m{i}")
            self.nodes[name] = node
            ns = node.netns
            _ip("netns", "add", ns)
            # before the links exist, so that they are born with these settings: no duplicate address
            # detection (babeld needs its link-local address at once), forwarding on (a relay), no
            # ICMP redirects (a relay must forward, not tell the sender to go direct: on a radio
            # segment the direct path may not exist), no reverse-path filter (routes change)
            _in(ns, "sysctl", "-q", "-w", "net.ipv6.conf.default.accept_dad=0", "net.ipv6.conf.all.accept_dad=0",
                "net.ipv4.ip_forward=1", "net.ipv4.conf.all.send_redirects=0",
                "net.ipv4.conf.default.send_redirects=0", "net.ipv4.conf.all.accept_redirects=0",
                "net.ipv4.conf.default.accept_redirects=0", "net.ipv4.conf.all.rp_filter=0",
                "net.ipv4.conf.default.rp_filter=0")
            _ip("link", "set", "lo", "up", netns=ns)
            if self.channel == "nftables":
                _ip("link", "add", node.port, "type", "veth", "peer", "name", "mesh0", "netns", ns, netns=self.hub)
                _ip("link", "set", node.port, "master", "mesh", "up", netns=self.hub)
                self._address_mesh0(node)
            _ip("link", "add", node.host_link, "type", "veth", "peer", "name", "mgmt0", "netns", ns)
            _ip("addr", "add", f"{service}/32", "peer", f"{node.mgmt}/32", "dev", node.host_link)
            _ip("link", "set", node.host_link, "up")
            _ip("addr", "add", f"{node.mgmt}/32", "peer", f"{service}/32", "dev", "mgmt0", netns=ns)
            _ip("link", "set", "mgmt0", "up", netns=ns)
            if name == self.control:  # tasks from this host reach the control node over its link
                _ip("route", "add", f"{node.address}/32", "dev", node.host_link, "src", service)
        if self.channel == "ns3":
            self._start_ns3()

    def _address_mesh0(self, node: MeshNode) -> None:
        prefix = ipaddress.ip_network(self.subnet).prefixlen
        _ip("addr", "add", f"{node.address}/{prefix}", "brd", self.broadcast, "dev", "mesh0", netns=node.netns)
        _ip("link", "set", "mesh0", "up", netns=node.netns)

    def _start_ns3(self) -> None:
        """Start the ns-3 channel in the segment's namespace: it makes every node's `mesh0` (a TAP)."""
        channel = Ns3Channel([ChannelNode(n.name, n.netns, *self._positions.get(n.name, (0.0, 0.0)))
                              for n in self.nodes.values()], self.range_m, self.run_dir / "logs" / "ns3-channel.log",
                             seed=self.seed)
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        try:
            channel.start(wrap=["ip", "netns", "exec", self.hub], preexec_fn=die_with_parent())
        except Ns3Error as err:
            raise NetnsError(str(err)) from None
        self.ns3 = channel
        for node in self.nodes.values():
            self._address_mesh0(node)

    def babeld_config(self, node: MeshNode) -> str:
        """The babeld configuration of `node`."""
        return "\n".join([
            f"# babeld of {node.name} ({node.address}) in namespace {node.netns}, written by erni sim --netns",
            f"local-port {self.babel_port}",   # read-only local interface on [::1]: MobiNet reads it
            "random-id true",                  # the veth has no stable hardware address to derive one from
            f"interface mesh0 type wireless hello-interval {self.hello_interval:g} channel interfering",
            "redistribute local if mesh0 allow",   # announce the mesh address only, never mgmt0's
            "redistribute local deny",
            "",
        ])

    def popen(self, name: str, argv: list[str], log: Path, *,
              env: Mapping[str, str] | None = None) -> subprocess.Popen[bytes]:
        """Start `argv` in node `name`'s namespace, output appended to `log`, killed when this process dies."""
        with open(log, "ab") as out:
            return subprocess.Popen(self.exec_argv(name, argv), stdin=subprocess.DEVNULL, stdout=out,
                                    stderr=subprocess.STDOUT, env=env, start_new_session=True,
                                    preexec_fn=die_with_parent())

    def start_babel(self) -> None:
        """Start babeld in every namespace (foreground children that die with this process)."""
        (self.run_dir / "babel").mkdir(parents=True, exist_ok=True)
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        for node in self.nodes.values():
            base = self.run_dir / "babel" / node.name
            config = base.with_suffix(".conf")
            config.write_text(self.babeld_config(node))
            node.babeld = self.popen(node.name, ["babeld", "-c", str(config), "-I", str(base.with_suffix(".pid")),
                                                 "-S", str(base.with_suffix(".state"))],
                                     self.run_dir / "logs" / f"babeld-{node.name}.log")

    def daemons_alive(self) -> list[str]:
        """Names of the nodes whose babeld runs."""
        return [n.name for n in self.nodes.values() if n.babeld is not None and n.babeld.poll() is None]

    # -- the radio -----------------------------------------------------------------------

    def apply(self, links: Mapping[frozenset[str], float] | None = None,
              positions: Mapping[str, tuple[float, float]] | None = None) -> bool:
        """Make the radio follow the model: on the nftables channel the rules match the links' delivery
        ratios, on the ns-3 channel the nodes move to `positions` (m); True when something changed."""
        if positions is not None and self.channel == "ns3":
            with self._lock:
                moved = {k: v for k, v in positions.items() if self._positions.get(k) != v}
                self._positions.update(moved)
                channel = self.ns3
            if channel is not None and moved:
                channel.move(moved)  # a line each to the channel's input, outside the lock
            return bool(moved)
        with self._lock:
            if links is not None:
                self._links = dict(links)
            if not self._created or not self.nodes or self.channel != "nftables":
                return False
            rules = self.rules(self._links)
            if rules == self._rules:
                return False
            self._write_rules_locked(rules)
            return True

    def _nftables_only(self, what: str) -> None:
        if self.channel != "nftables":
            raise NetnsError(f"{what} is the nftables radio's: the {self.channel} channel decides loss itself")

    def cut(self, a: str, b: str, cut: bool = True) -> None:
        """Cut (or restore) the link between nodes a and b whatever the radio model says."""
        self._nftables_only("cutting a link")
        key = frozenset((self.node(a).name, self.node(b).name))
        with self._lock:
            (self.radio.cut.add if cut else self.radio.cut.discard)(key)
        self.apply()

    def set_extra_loss(self, loss: float) -> None:
        """Drop this share of the frames of every link on top of the radio model (0 to stop)."""
        self._nftables_only("an extra loss")
        if not 0.0 <= loss <= 1.0:
            raise NetnsError(f"extra loss: expected a probability in 0..1, got {loss}")
        with self._lock:
            self.radio.extra_loss = loss
        self.apply()

    def loss(self, links: Mapping[frozenset[str], float], a: str, b: str) -> float:
        """Drop probability of frames from a to b: 1 - delivery ratio, with the injected faults, rounded."""
        key = frozenset((a, b))
        if key in self.radio.cut:
            return 1.0
        delivery = links.get(key, 0.0) * (1.0 - self.radio.extra_loss)
        return min(1.0, max(0.0, round((1.0 - delivery) / LOSS_STEP) * LOSS_STEP))

    def rules(self, links: Mapping[frozenset[str], float]) -> str:
        """The nft rules (one transaction) of the radio for these link delivery ratios."""
        lines = []
        nodes = list(self.nodes.values())
        for a in nodes:
            for b in nodes:
                if a is b:
                    continue
                p = self.loss(links, a.name, b.name)
                if p >= 1.0:
                    continue  # the chain's policy drops it
                match = f'iifname "{a.port}" oifname "{b.port}"'
                if p > 0.0:
                    lines.append(f'add rule bridge erni radio {match} numgen random mod 1000 < {round(p * 1000)} '
                                 f'counter drop comment "{a.name}>{b.name} loss {p:.2f}"')
                lines.append(f'add rule bridge erni radio {match} counter accept comment "{a.name}>{b.name}"')
        return "\n".join(lines)

    def _write_rules(self, links: Mapping[frozenset[str], float]) -> None:
        with self._lock:
            self._write_rules_locked(self.rules(links))

    def _write_rules_locked(self, rules: str) -> None:
        script = "\n".join([
            "table bridge erni {",
            "  chain radio { type filter hook forward priority 0; policy drop; }",
            "}",
            "flush chain bridge erni radio",
            rules,
            "",
        ])
        _in(self.hub, "nft", "-f", "-", input=script)
        self._rules = rules
        self.rule_updates += 1

    def counters(self) -> dict[tuple[str, str], tuple[int, int]]:
        """Frames (dropped at random, passed) per ordered pair of nodes with a link, from the kernel."""
        self._nftables_only("the radio's counters")
        out: dict[tuple[str, str], tuple[int, int]] = {}
        data = json.loads(_in(self.hub, "nft", "-j", "list", "chain", "bridge", "erni", "radio"))
        for item in data.get("nftables", []):
            rule = item.get("rule")
            if not rule:
                continue
            comment = str(rule.get("comment", ""))
            pair = comment.split(" ")[0].split(">")
            packets = next((e["counter"]["packets"] for e in rule.get("expr", []) if "counter" in e), 0)
            if len(pair) == 2:
                dropped, passed = out.get((pair[0], pair[1]), (0, 0))
                if " loss " in comment:
                    dropped += packets
                else:
                    passed += packets
                out[(pair[0], pair[1])] = (dropped, passed)
        return out

    # -- traffic between the nodes, for tests and benchmarks ------------------------------

    def static_neighbours(self) -> None:
        """Give every node a permanent ARP entry for every other (no ARP on the air from now on):
        benchmarks that compare the channel with a pure ns-3 run, whose neighbours are known too."""
        macs = {}
        for node in self.nodes.values():
            link = json.loads(_ip("-j", "link", "show", "mesh0", netns=node.netns))
            macs[node.name] = link[0]["address"]
        for node in self.nodes.values():
            for other in self.nodes.values():
                if other is not node:
                    _ip("neigh", "replace", other.address, "lladdr", macs[other.name], "dev", "mesh0",
                        "nud", "permanent", netns=node.netns)

    def udp_flows(self, flows: list[tuple[str, str]], count: int, interval: float, size: int,
                  port: int = 47990, settle: float = 1.0) -> list[int]:
        """Send `count` UDP datagrams of `size` bytes every `interval` s over each (sender, receiver)
        flow at once, through the nodes' own sockets; return how many each receiver got (distinct).

        Each flow first sends a few datagrams that are not counted, so that ARP has resolved the
        receiver before the counted ones start (Linux queues only a few behind an unresolved address).
        """
        if not 0 < len(flows) < 100 or count < 1 or not interval > 0 or not 8 <= size <= 65000:
            raise NetnsError("udp_flows: expected 1..99 flows, count >= 1, interval > 0 and size in 8..65000")
        receive = (
            "import socket, sys, time\n"
            "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(('', int(sys.argv[1])))\n"
            "s.settimeout(0.2); got = set(); print('ready', flush=True)\n"
            "end = time.monotonic() + float(sys.argv[2])\n"
            "while time.monotonic() < end:\n"
            "    try:\n"
            "        got.add(int.from_bytes(s.recv(65535)[:4], 'big'))\n"
            "    except socket.timeout:\n"
            "        pass\n"
            "print(len([n for n in got if n < 0x7fffffff]))\n")
        send = (
            "import socket, sys, time\n"
            "host, port, n, gap, size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), "
            "int(sys.argv[5])\n"
            "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
            "for _ in range(5):\n"
            "    s.sendto(b'\\x7f\\xff\\xff\\xff' + bytes(size - 4), (host, port)); time.sleep(0.05)\n"
            "time.sleep(float(sys.argv[6]))\n"
            "t = time.monotonic()\n"
            "for i in range(n):\n"
            "    s.sendto(i.to_bytes(4, 'big') + bytes(size - 4), (host, port))\n"
            "    t += gap; time.sleep(max(0.0, t - time.monotonic()))\n")
        listen = count * interval + settle + 3.0
        receivers: list[subprocess.Popen[str]] = []
        for k, (_, b) in enumerate(flows):
            proc = subprocess.Popen(self.exec_argv(b, [sys.executable, "-c", receive, str(port + k), f"{listen:g}"]),
                                    stdout=subprocess.PIPE, text=True, preexec_fn=die_with_parent())
            receivers.append(proc)
        try:
            for proc in receivers:
                assert proc.stdout is not None
                if proc.stdout.readline().strip() != "ready":
                    raise NetnsError("udp_flows: a receiver did not start")
            senders = [subprocess.Popen(self.exec_argv(a, [sys.executable, "-c", send, self.node(b).address,
                                                           str(port + k), str(count), f"{interval:g}", str(size),
                                                           f"{settle:g}"]),
                                        preexec_fn=die_with_parent())
                       for k, (a, b) in enumerate(flows)]
            for sender in senders:
                sender.wait(listen + 30)
            return [int(proc.communicate(timeout=listen + 30)[0].strip() or 0) for proc in receivers]
        finally:
            for proc in receivers:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait(5)

    # -- babeld's view, for tests and benchmarks ----------------------------------------

    def kernel_routes(self, name: str) -> list[str]:
        """The routes babeld installed in node `name`'s kernel table (`ip route` lines)."""
        return [line.strip() for line in _ip("route", "show", "proto", "babel", netns=self.node(name).netns).splitlines()
                if line.strip()]

    # -- removing ------------------------------------------------------------------------

    def destroy(self) -> None:
        """Stop the daemons, delete every namespace (and with them links, routes and rules), forget the run."""
        if not self._created:
            return
        self._created = False
        if self.ns3 is not None:
            self.ns3.stop()
            self.ns3 = None
        for node in self.nodes.values():
            if node.babeld is not None and node.babeld.poll() is None:
                node.babeld.terminate()
        for node in self.nodes.values():
            if node.babeld is not None:
                try:
                    node.babeld.wait(3)
                except subprocess.TimeoutExpired:
                    node.babeld.kill()
                    node.babeld.wait(3)
        errors = []
        for name in _namespaces():
            m = NAMESPACE.match(name)
            if m and m.group(1) == self.tag:
                try:
                    _delete_namespace(name)
                except NetnsError as err:
                    errors.append(str(err))
        for line in _ip("-o", "link", "show", check=False).splitlines():  # created before its peer moved
            parts = line.split(":")
            if len(parts) > 1 and parts[1].strip().split("@")[0].startswith(f"erni{self.tag}m"):
                _ip("link", "delete", parts[1].strip().split("@")[0], check=False)
        with contextlib.suppress(OSError):
            (STATE_DIR / f"{self.tag}.json").unlink()
        if errors:
            raise NetnsError("; ".join(errors))

    def leftovers(self) -> list[str]:
        """What of this run still exists on the machine (namespaces, root links, record): [] after destroy()."""
        found = [n for n in _namespaces() if (m := NAMESPACE.match(n)) and m.group(1) == self.tag]
        found += [line.split(":")[1].strip().split("@")[0] for line in _ip("-o", "link", "show", check=False).splitlines()
                  if len(line.split(":")) > 1 and line.split(":")[1].strip().startswith(f"erni{self.tag}m")]
        if (STATE_DIR / f"{self.tag}.json").exists():
            found.append(str(STATE_DIR / f"{self.tag}.json"))
        return found


PR_SET_PDEATHSIG = 1
DEATH_SIGNAL = signal.SIGKILL
"""What the kernel sends a process the launcher started when the launcher dies.

Not SIGTERM: the kernel sends the death signal each time the thread that is the child's parent
exits, and a dying launcher hands its children from one of its threads to the next, so under
load a child gets it several times within milliseconds. `erni agent`'s SIGTERM handler, run
again while its first run held the lock of its stop event (Event.set), waited for that lock
forever: the agent outlived its launcher. SIGKILL needs no handler and cannot be caught before
exec either. Agents and babeld get their clean stop (one SIGTERM) when the launcher stops
normally (Team.stop, Mesh.destroy); a launcher killed outright leaves nothing to stop cleanly for.
"""


@functools.cache
def _prctl() -> Callable[..., int] | None:
    try:
        return ctypes.CDLL("libc.so.6", use_errno=True).prctl
    except (OSError, AttributeError):
        return None


def die_with_parent(signum: int = DEATH_SIGNAL) -> Callable[[], None]:
    """A `preexec_fn` (make one per Popen, in the process that starts the child): the child gets
    `signum` when its parent dies, and does not start at all if its parent is already gone.

    PR_SET_PDEATHSIG only covers a parent that dies after the call: a launcher killed between
    fork and the child's prctl never signals it (the child's new parent, init, does not die), so
    the child compares its parent with the launcher's pid once the signal is armed, and exits
    before exec when they differ.
    """
    parent = os.getpid()
    prctl = _prctl()  # looked up here: between fork and exec the child only calls it

    def arm() -> None:  # in the child, between fork and exec
        if prctl is not None:
            prctl(PR_SET_PDEATHSIG, int(signum))
        if os.getppid() != parent:
            os.write(2, b"erni: the launcher died before this process started; not starting it\n")
            os._exit(1)

    return arm


class TcpForwarder:
    """Accept TCP connections on one address and splice each to a target (the GUI from the host).

    The control node's GUI listens inside its namespace; the operator's browser opens the
    address the loopback tier would use (127.0.0.1:8080, or --gui-listen), and this thread
    carries the bytes both ways. Simulator plumbing, like the management links.
    """

    def __init__(self, listen: tuple[str, int], target: tuple[str, int]) -> None:
        self.target = target
        self._listener = socket.socket(socket.AF_INET6 if ":" in listen[0] else socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind(listen)
        except OSError as err:
            self._listener.close()
            raise NetnsError(f"GUI: cannot listen on {listen[0]}:{listen[1]}: {err.strerror}") from None
        self._listener.listen(16)
        self._listener.setblocking(False)
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self._wake_r, self._wake_w = socket.socketpair()
        self._thread = threading.Thread(target=self._run, name="sim-gui-forward", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the thread and close every connection."""
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(5)
        for s in (self._listener, self._wake_r, self._wake_w):
            s.close()

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._listener, selectors.EVENT_READ, None)
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        pairs: dict[socket.socket, socket.socket] = {}

        def drop(s: socket.socket) -> None:
            other = pairs.pop(s, None)
            for x in (s, other):
                if x is not None:
                    with contextlib.suppress(KeyError, ValueError):
                        sel.unregister(x)
                    pairs.pop(x, None)
                    x.close()

        try:
            while True:
                for key, _ in sel.select():
                    if key.data == "wake":
                        return
                    if key.fileobj is self._listener:
                        try:
                            conn, _ = self._listener.accept()
                        except OSError:
                            continue
                        try:
                            far = socket.create_connection(self.target, timeout=3)
                        except OSError:  # the GUI is not up (yet): the browser sees a closed connection
                            conn.close()
                            continue
                        for s in (conn, far):
                            s.setblocking(True)
                            s.settimeout(5)
                        pairs[conn], pairs[far] = far, conn
                        sel.register(conn, selectors.EVENT_READ, "conn")
                        sel.register(far, selectors.EVENT_READ, "conn")
                        continue
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    try:
                        data = sock.recv(65536)
                        if data:
                            pairs[sock].sendall(data)
                            continue
                    except (OSError, KeyError):
                        pass
                    drop(sock)
        finally:
            for s in list(pairs):
                s.close()
            sel.close()
