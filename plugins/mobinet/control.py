"""MobiNetControl: answers NetWatch tasks with NetInfo objects and writes the robot's pose.

For each NetWatch task (addressed to this agent or to nobody) the plugin publishes one
`NetInfo` (uid `netinfo:<task uid>`, changed in place at the task's `rate_hz`) and keeps
the task's result RUNNING with a summary in `values`. Removing the task stops the watch
and removes its NetInfo. This robot's `Pose` is written to the network subsystem
(paper 004, Figure 6 step 6) when a write community is configured: when it moved more than
`write_deadband` or turned a degree, at most once per `write_interval` (the newest is written). All SNMP I/O happens on
MobiNetResource's thread; results come back through `later()`, so `execute()` only decides
and publishes. Each NetInfo's `provenance` names the source and table of every field it
fills; when the source does not provide what a watch needs (an agent without NHDP-MIB asked
for neighbours), the NetInfo is degraded and its message says what is missing. A reading whose
source dropped implausible rows of the watched part (`sanity`) is degraded too, with its good
rows; a reading of another part is not. `path_cost` answers a destination no route names
exactly from the route of the longest prefix that covers it.
"""

from __future__ import annotations

import ipaddress
import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import ConfigDict, Field, SecretStr, field_validator, model_validator

from erni.blackboard import NetInfo, Plugin, Pose, Position, Route, Task, TaskState
from erni.blackboard.errors import ConfigError, TransactionError
from erni.blackboard.objects import Model, only_stamp_differs
from erni.blackboard.schemas import Peer
from erni.blackboard.tasks import (
    LinkQualityParams,
    NeighborListParams,
    NodePositionParams,
    PathCostParams,
    TopologyParams,
    WatchParams,
)
from erni.plugins.mobinet.babel import BabelSource
from erni.plugins.mobinet.resource import (
    NEIGHBORS,
    POSITIONS,
    ROUTES,
    TOPOLOGY,
    MobiNetResource,
    NetView,
    NetworkSource,
)
from erni.plugins.mobinet.sanity import MAX_HOPS, WORLD_BOUND, Limits
from erni.plugins.mobinet.snmp import SnmpSource, articulation_points
from erni.plugins.mobinet.usm import UsmUser, read_key

PARTS_OF = {
    "node_position": frozenset({POSITIONS}),
    "network_topology": frozenset({TOPOLOGY}),
    "path_cost": frozenset({ROUTES}),
    "link_quality": frozenset({NEIGHBORS}),
    "neighbor_list": frozenset({NEIGHBORS}),
}
FIELDS_OF = {NEIGHBORS: ("neighbors",), TOPOLOGY: ("links", "articulation_points"),
             ROUTES: ("routes",), POSITIONS: ("positions",)}   # the NetInfo fields a part fills


class MobiNetSettings(Model):
    """The `[plugin.settings]` of MobiNetControl."""

    model_config = ConfigDict(extra="forbid")

    source: Literal["snmp", "babel"] = Field("snmp", description="what the network is read from: an SNMP "
                                             "agent (host, port, communities) or babeld's local interface (babel)")
    babel: str = Field("[::1]:33123", description="babeld's local interface, HOST:PORT (`babeld -g PORT`)")
    watch: list[str] = Field(default_factory=list, description="NetWatch prepositions watched from the start, "
                             "without a task (e.g. [\"path_cost\"]: the transport then learns every routed node)")
    watch_rate_hz: float = Field(1.0, gt=0, le=100, description="rate of the watches in `watch` (Hz)")
    netinfo_keepalive: float = Field(1.0, ge=0, le=60, description="a reading that changes nothing but the "
                                     "NetInfo's stamp is published this often (s); 0 = every reading")
    position: tuple[float, float] | None = Field(None, description="where this node stands if it never moves "
                                                 "and nothing else publishes its Pose (a base station): "
                                                 "published as its Pose every second, which the transport "
                                                 "shares, for networks that carry no positions (babeld)")
    host: str = Field("127.0.0.1", description="SNMP agent of this robot's network subsystem")
    port: int = Field(1161, ge=1, le=65535, description="its UDP port")
    community: str = Field("public", description="SNMPv2c read community")
    write_community: str | None = Field(None, min_length=1, description="SNMPv2c write community "
                                        "(SETs the pose); none: the pose is not written")
    v3_user: str | None = Field(None, min_length=1, max_length=32, description="SNMPv3 USM user: every "
                                "request is sent authPriv as this user, who also writes the pose (community "
                                "and write_community are then not used)")
    auth_protocol: Literal["SHA-224", "SHA-256", "SHA-384", "SHA-512"] = Field(
        "SHA-256", description="the v3 user's authentication protocol (HMAC-SHA-2, RFC 7860)")
    auth_key: SecretStr | None = Field(None, description="the v3 user's authentication passphrase; prefer "
                                       "auth_key_file or auth_key_env, which keep it out of the config")
    auth_key_file: str | None = Field(None, description="file whose first line is the authentication "
                                      "passphrase (mode 600)")
    auth_key_env: str | None = Field(None, description="environment variable holding the authentication "
                                     "passphrase")
    priv_protocol: Literal["AES"] = Field("AES", description="the v3 user's privacy protocol: AES-128 (RFC 3826)")
    priv_key: SecretStr | None = Field(None, description="the v3 user's privacy passphrase; prefer "
                                       "priv_key_file or priv_key_env")
    priv_key_file: str | None = Field(None, description="file whose first line is the privacy passphrase "
                                      "(mode 600)")
    priv_key_env: str | None = Field(None, description="environment variable holding the privacy passphrase")
    timeout: float = Field(0.5, gt=0, le=30, description="per-request timeout (s)")
    retries: int = Field(0, ge=0, le=5, description="retries after a timeout")
    max_repetitions: int = Field(100, ge=1, le=500, description="GETBULK rows per request")
    cache_seconds: float = Field(300.0, ge=0, description="reuse a walk while the agent's change "
                                 "counters stand still and it did not restart (sysUpTime), at most "
                                 "this long (s; 0: always walk)")
    robot: str | None = Field(None, description="whose Pose to write (default: this agent)")
    write_pose: bool = Field(True, description="write this robot's Pose to the network subsystem")
    write_deadband: float = Field(0.02, ge=0, description="write a Pose only when the robot moved this far "
                                  "(m) or turned 1 degree since the last one written (0: every Pose)")
    write_interval: float = Field(0.5, ge=0, le=60, description="at most one position write per interval (s); "
                                  "the newest Pose is written when it ends (0: no limit)")
    log_interval: float = Field(10.0, gt=0, description="at most one warning per kind per interval (s)")
    world_bound: float = Field(WORLD_BOUND, gt=0, description="no node is farther than this from the origin "
                               "on either axis (m): a position reported beyond it is dropped as implausible "
                               "(default 10 km)")
    max_hops: int = Field(MAX_HOPS, ge=1, le=255, description="no route is longer (hops): a route reported "
                          "with more hops, or with 0 hops to another node, is dropped as implausible")

    @field_validator("babel")
    @classmethod
    def _babel_address(cls, value: str) -> str:
        babel_address(value)
        return value

    @model_validator(mode="after")
    def _v3(self) -> MobiNetSettings:
        keys = ("auth_key", "auth_key_file", "auth_key_env", "priv_key", "priv_key_file", "priv_key_env")
        if self.v3_user is None:
            given = [k for k in keys if getattr(self, k) is not None]
            if given:
                raise ValueError(f"{given[0]} is given but v3_user is not: keys belong to an SNMPv3 user")
            return self
        if self.write_community is not None:
            raise ValueError("write_community is SNMPv2c's: with v3_user the v3 user writes the pose; "
                             "remove write_community")
        try:   # the keys are there and readable now, not at the first request
            self.usm_user()
        except ConfigError as err:   # a plain ValueError: the message gets the agent and plugin as prefix
            raise ValueError(str(err)) from None
        return self

    def usm_user(self) -> UsmUser | None:
        """The configured SNMPv3 user with its keys read (ConfigError naming the setting), or None."""
        if self.v3_user is None:
            return None
        def secret(value: SecretStr | None) -> str | None:
            return value.get_secret_value() if value is not None else None

        return UsmUser(self.v3_user,
                       read_key("auth_key", secret(self.auth_key), self.auth_key_file, self.auth_key_env),
                       read_key("priv_key", secret(self.priv_key), self.priv_key_file, self.priv_key_env),
                       self.auth_protocol, self.priv_protocol)

    @field_validator("watch")
    @classmethod
    def _watches(cls, value: list[str]) -> list[str]:
        unknown = [w for w in value if w not in PARTS_OF]
        if unknown:
            raise ValueError(f"unknown NetWatch preposition(s) {', '.join(map(repr, unknown))}; expected "
                             f"some of {', '.join(PARTS_OF)}")
        return value


def loopback(host: str) -> bool:
    """Whether `host` is a loopback address or `localhost` (a name is not resolved: any other is not)."""
    if host.strip("[]").lower() in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def babel_address(text: str) -> tuple[str, int]:
    """`[::1]:33123`, `::1` style or `HOST:PORT` -> (host, port); ConfigError naming the problem."""
    host, sep, port = text.strip().rpartition(":")
    if not sep or not host or (":" in host and not (host.startswith("[") and host.endswith("]"))):
        raise ConfigError(f"babel: {text!r}: expected HOST:PORT, e.g. [::1]:33123")
    try:
        number = int(port)
    except ValueError:
        raise ConfigError(f"babel: {text!r}: port {port!r} is not a number") from None
    if not 1 <= number <= 65535:
        raise ConfigError(f"babel: {text!r}: port {number} is outside 1..65535")
    return host.strip("[]"), number


class MobiNetControl(Plugin[MobiNetSettings]):
    """NetWatch performer: monitors the network subsystem over SNMP and reports on the blackboard."""

    def make_source(self) -> NetworkSource:
        """The source the resource reads through (override to plug in another subsystem)."""
        s = self.settings
        if s.source == "babel":
            host, port = babel_address(s.babel)
            return BabelSource(host, port, node=self.agent_name, timeout=s.timeout, names=lambda: self._names)
        return SnmpSource(s.host, s.port, community=s.community, timeout=s.timeout, retries=s.retries,
                          max_repetitions=s.max_repetitions, cache_seconds=s.cache_seconds,
                          write_community=s.write_community, usm=self._usm,
                          limits=Limits(world_bound=s.world_bound, max_hops=s.max_hops), clock=self.clock)

    def setup(self) -> None:
        me = self.agent_name
        robot = self.settings.robot or me
        self.tasks = self.subscribe(
            Task, where=lambda t: t.verb == "NetWatch" and t.destination in (None, "", me))
        # a standing robot's keep-alive Pose (every second) moves only its stamp: nothing to write
        self.poses = self.subscribe(Pose, where=lambda p: p.robot == robot, ignore=("stamp",))
        # a routing daemon knows addresses; the team directory (the transport's Peers) names them
        self.peers = self.subscribe(Peer, ignore=("last_heard",))   # addresses; a peer heard again is no news
        self._names: dict[str, str] = {}
        self._standing: dict[str, Task] = {}   # watch key -> the in-memory task of a `watch` entry
        self._watching: dict[str, tuple[str, WatchParams]] = {}   # task uid -> (preposition, params)
        self._infos: dict[str, NetInfo] = {}               # task uid -> last published NetInfo
        self._polls: dict[str, int] = {}
        self.resource = MobiNetResource(self.make_source, self._delivered, self.log,
                                        self.settings.log_interval, name=f"mobinet-{me}",
                                        write_interval=self.settings.write_interval, clock=self.clock)
        self._written: Position | None = None   # the last position handed to the resource
        self._unwritten: Pose | None = None     # the newest Pose seen while holding
        self._hold_until = 0.0                  # monotonic: no Pose runs us before (write_interval)
        self._cuts: tuple[tuple[tuple[str, str], ...] | None, list[str]] = (None, [])  # links -> articulation points
        self._cut_rows: list[Any] | None = None  # the links `_cuts` was last looked up for
        snmp = self.settings.source == "snmp"
        self._usm = self.settings.usm_user() if snmp else None
        self.resource.start()
        writer = self.settings.write_community is not None or self._usm is not None
        self._write_pose = snmp and self.settings.write_pose and writer
        if snmp and self.settings.write_pose and not self._write_pose:
            self.log.warning("poses are not written to the network subsystem: no write_community or v3_user")
        if self._write_pose and self._usm is None and not loopback(self.settings.host):
            self.log.warning("the SNMPv2c write community travels in clear to %s:%d, which is not a loopback "
                             "address: anyone on the path can read it and then rewrite this robot's position; "
                             "use an SNMPv3 user (v3_user) there", self.settings.host, self.settings.port)
        for preposition in self.settings.watch:
            task = Task(verb="NetWatch", preposition=preposition, source=me,
                        params={"rate_hz": self.settings.watch_rate_hz})
            key = f"watch:{me}:{preposition}"
            self._standing[key] = task
            self._infos[key] = NetInfo(uid=f"netinfo:{me}:{preposition}", node=me, kind=preposition,
                                       degraded=True, message="waiting for the first reading")
            self._watching[key] = (preposition, task.params_as(WatchParams))
            self._polls[key] = 0
            self.add(self._infos[key])
            self.resource.watch(key, PARTS_OF[preposition], self.settings.watch_rate_hz)
        self._fixed: Pose | None = None
        if self.settings.position is not None:
            x, y = self.settings.position
            self._fixed = Pose(robot=me, x=x, y=y, motors_enabled=False)
            self.add(self._fixed)
            self.wake_every(1.0)

    def teardown(self) -> None:
        self.resource.close()

    # -- the resource's thread calls this; it only hands over ------------------------------

    def _delivered(self, uid: str, view: NetView | None, error: str) -> None:
        self.later(lambda: self._apply(uid, view, error))

    # -- inside transactions ----------------------------------------------------------------

    def execute(self) -> None:
        if self.peers.added or self.peers.changed or self.peers.removed:
            names = {}
            for peer in self.peers:
                host = peer.address.rpartition(":")[0].strip("[]")
                if host:
                    names[host] = peer.name
            self._names = names   # replaced whole: the resource's thread reads it without a lock
        wall = self.clock.wall()
        if self._fixed is not None and wall - self._fixed.stamp >= 0.9:  # a fresh stamp: not stale
            self._fixed = self._fixed.evolve(stamp=wall)
            self.change(self._fixed)
        for task in self.tasks.added:
            self._start(task)
        for task in self.tasks.changed:
            known = self._watching.get(task.uid)
            if known is None:
                self._start(task)
            elif known != (task.preposition, task.params):
                self.resource.unwatch(task.uid)
                self._watching.pop(task.uid, None)
                self._start(task)
        for task in self.tasks.removed:
            self._stop(task.uid)
        if self._write_pose:
            self._write_latest()

    def _write_latest(self) -> None:
        """Hand the newest Pose to the resource if it moved; then, for `write_interval`, Poses
        (ten a second) collect without running this plugin, and the newest is written at its end."""
        latest = self._unwritten
        for pose in list(self.poses.added) + list(self.poses.changed):
            if latest is None or pose.stamp >= latest.stamp:
                latest = pose
        self._unwritten = latest
        now = self.clock()
        if now < self._hold_until:
            return
        self.poses.wakes = True
        self._unwritten = None
        if latest is None:
            return
        position = Position(x=latest.x, y=latest.y, heading=math.degrees(latest.theta))
        if not self._moved(position):
            return
        self._written = position
        self.resource.write_position(position)
        interval = self.settings.write_interval
        if interval > 0:
            self._hold_until = now + interval
            self.poses.wakes = False
            self.wake_in(interval)

    def _moved(self, position: Position) -> bool:
        """True when `position` is worth writing: the first, or beyond the dead-band of the last one."""
        last, band = self._written, self.settings.write_deadband
        if last is None or band == 0:
            return True
        turned = abs((position.heading - last.heading + 180.0) % 360.0 - 180.0)
        return math.hypot(position.x - last.x, position.y - last.y) >= band or turned >= 1.0

    def _start(self, task: Task) -> None:
        if task.done or task.preposition not in PARTS_OF:
            return
        params = task.params_as(WatchParams)
        rate = params.rate_hz
        # no reading yet is no data: degraded until the first answer, so that nobody mistakes
        # the empty lists for "no neighbours"
        info = NetInfo(uid=f"netinfo:{task.uid}", node=self.agent_name, kind=task.preposition,
                       task=task.uid, degraded=True, message="waiting for the first reading")
        try:  # first: a task its requester removed meanwhile is not started, and nothing is staged
            self.change(task.with_result(TaskState.RUNNING, message=f"monitoring at {rate:g} Hz",
                                         values={"netinfo": info.uid}))
        except TransactionError:
            self._stop(task.uid)
            return
        self._watching[task.uid] = (task.preposition, params)
        self._polls[task.uid] = 0
        if task.uid in self._infos:
            self.change(info)
        else:
            self.add(info)
        self._infos[task.uid] = info
        self.resource.watch(task.uid, PARTS_OF[task.preposition], rate)

    def _stop(self, uid: str) -> None:
        if self._watching.pop(uid, None) is not None:
            self.resource.unwatch(uid)
        self._polls.pop(uid, None)
        info = self._infos.pop(uid, None)
        if info is not None:
            self.remove(info)

    def _apply(self, uid: str, view: NetView | None, error: str) -> None:
        if uid in self._standing:
            self._apply_standing(uid, view, error)
            return
        task = self.tasks.get(uid)
        info = self._infos.get(uid)
        if task is None or info is None or uid not in self._watching:
            return  # cancelled while the reading was on its way
        info = self._restored(uid, info)
        self._polls[uid] += 1
        if view is None:
            new_info = info.evolve(degraded=True, message=error, stamp=self.clock.wall())
            values = dict(task.result.values) if task.result else {}
            message = f"degraded: {error}"
        else:
            new_info, values, message = self._answer(task, info, view)
        if self._same(info, new_info):
            return
        self.change(new_info)
        self._infos[uid] = new_info
        values["netinfo"] = new_info.uid
        old = task.result
        if old is None or old.values != values or old.message != message or old.state != TaskState.RUNNING:
            self.change(task.with_result(TaskState.RUNNING, message=message, values=values,
                                         confidence=0.0 if new_info.degraded else 1.0))

    def _restored(self, key: str, info: NetInfo) -> NetInfo:
        """The watch's NetInfo, published afresh if another plugin removed it (seen after a restart)."""
        if self.get(info.uid) is None:
            info = info.evolve(degraded=True, message="waiting for the next reading")
            self.add(info)
            self._infos[key] = info
        return info

    def _apply_standing(self, key: str, view: NetView | None, error: str) -> None:
        info = self._restored(key, self._infos[key])
        self._polls[key] += 1
        if view is None:
            new_info = info.evolve(degraded=True, message=error, stamp=self.clock.wall())
        else:
            new_info = self._answer(self._standing[key], info, view)[0]
        if self._same(info, new_info):
            return
        self.change(new_info)
        self._infos[key] = new_info

    def _same(self, old: NetInfo, new: NetInfo) -> bool:
        """A reading that changes only the stamp, within the keep-alive: not worth a transaction."""
        return new.stamp - old.stamp < self.settings.netinfo_keepalive and only_stamp_differs(old, new)

    def _answer(self, task: Task, info: NetInfo, view: NetView) -> tuple[NetInfo, dict[str, Any], str]:
        parts = PARTS_OF[task.preposition]
        lacking = self._lacking(parts, view)
        fields: dict[str, Any] = {"degraded": bool(lacking), "message": "; ".join(lacking),
                                  "stamp": self.clock.wall(), "node": view.node or self.agent_name,
                                  "provenance": self._provenance(parts, view)}
        values: dict[str, Any] = {}
        message = f"degraded: {fields['message']}" if lacking else ""
        match task.params:
            case NeighborListParams():
                nbrs = [n for n in view.neighbors if n.symmetric]
                fields["neighbors"] = nbrs
                values["neighbors"] = [n.name for n in nbrs]
            case LinkQualityParams() as params:
                message = self._link_quality(view, params, fields, values) or message
            case PathCostParams() as params:
                message = self._path_cost(view, params, fields, values) or message
            case TopologyParams():
                self._topology(view, fields, values)
            case NodePositionParams():
                fields["positions"] = view.positions
                values["positions"] = {n: {"x": p.x, "y": p.y, "heading": p.heading}
                                       for n, p in sorted(view.positions.items())}
        # the fields are this reading's own validated rows: copied in, not validated again (a team's
        # topology of N^2 links is read twice a second)
        return info.model_copy(update=fields), values, message

    @staticmethod
    def _provenance(parts: frozenset[str], view: NetView) -> dict[str, str]:
        """Where each field of the answer came from (`missing: <why>` for a part the source lacks)."""
        provenance = {"node": view.sources.get("node", "")}
        for part in parts:
            for name in FIELDS_OF[part]:
                provenance[name] = (f"missing: {view.missing[part]}" if part in view.missing
                                    else view.sources.get(part, ""))
        if TOPOLOGY in parts and TOPOLOGY not in view.missing:
            provenance["articulation_points"] = "computed from links"
        return provenance

    @staticmethod
    def _lacking(parts: frozenset[str], view: NetView) -> list[str]:
        """What the reading lacks of `parts`: the parts missing, and the rows dropped (said once)."""
        lacking = [view.missing[p] for p in sorted(parts) if p in view.missing]
        dropped = [row for row in view.dropped if row.part in parts]
        if dropped:   # the good rows stand; a reader that trusts only whole readings skips this one
            more = f" and {len(dropped) - 1} more" if len(dropped) > 1 else ""
            lacking.append(f"{dropped[0]}{more}")
        return lacking

    def _topology(self, view: NetView, fields: dict[str, Any], values: dict[str, Any]) -> None:
        cuts = self._articulation_points(view.links)
        nodes = {n for link in view.links for n in (link.a, link.b)} | {view.node}
        fields["links"] = view.links
        fields["articulation_points"] = cuts
        values.update(nodes=len(nodes), links=len(view.links), articulation_points=cuts,
                      articulation_point=view.node in cuts)

    def _articulation_points(self, links: list[Any]) -> list[str]:
        """The cut vertices, found again only when the links changed (a team reporting positions
        reads the same N^2 links every second). A reading whose walk was not redone holds the very
        rows of the last one, which the list comparison tells by identity, without a key of N^2 pairs."""
        if links != self._cut_rows:
            key = tuple((link.a, link.b) for link in links)
            if key != self._cuts[0]:
                self._cuts = (key, articulation_points(links))
            self._cut_rows = list(links)
        return list(self._cuts[1])

    @staticmethod
    def _link_quality(view: NetView, params: LinkQualityParams, fields: dict[str, Any],
                      values: dict[str, Any]) -> str:
        message = ""
        nbrs = list(view.neighbors)
        if params.neighbor is not None:
            nbrs = [n for n in nbrs if params.neighbor in (n.name, n.address)]
            if not nbrs:
                message = f"{params.neighbor} is not a neighbour"
        fields["neighbors"] = nbrs
        values["quality"] = {n.name: round(n.quality, 3) for n in nbrs}
        values["best"] = max((n.quality for n in nbrs), default=0.0)
        return message

    @staticmethod
    def _path_cost(view: NetView, params: PathCostParams, fields: dict[str, Any], values: dict[str, Any]) -> str:
        message = ""
        routes = list(view.routes)
        if params.destination is not None:
            routes = routes_to(routes, params.destination, view.names)
            if not routes:
                message = f"no route to {params.destination}"
        fields["routes"] = routes
        values["routes"] = {r.destination: {"next_hop": r.next_hop, "hops": r.hops,
                                            "cost": round(r.cost, 4)} for r in routes}
        return message


def routes_to(routes: list[Route], destination: str, names: Mapping[str, str]) -> list[Route]:
    """The routes to `destination` (a name or an address): those naming it, else those of the
    longest prefix covering its address(es), as the kernel would forward a packet to it."""
    exact = [r for r in routes if destination in (r.destination,
             next((a for a, n in names.items() if n == r.destination), ""))]
    if exact:
        return exact
    addresses = []
    for text in [destination, *(a for a, n in names.items() if n == destination)]:
        try:
            addresses.append(ipaddress.ip_address(text))
        except ValueError:
            continue
    best: list[Route] = []
    longest = -1
    for route in routes:
        if "/" not in route.destination:
            continue   # a host route: it names its destination, matched above
        try:
            net = ipaddress.ip_network(route.destination, strict=False)
        except ValueError:
            continue
        if net.prefixlen >= longest and any(a.version == net.version and a in net for a in addresses):
            if net.prefixlen > longest:
                best, longest = [], net.prefixlen
            best.append(route)
    return best
