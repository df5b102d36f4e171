"""The transport plugin: remote tasking through the blackboard, discovery, peer liveness, watchers.

- A task whose `destination` is another agent is sent (reliably) when it is published and
  cancelled there when it is removed here. If its performer is not heard for `link_deadline`
  seconds the task fails with `link lost: ...` (a performer back in time goes on as if nothing
  happened; one back later is told to cancel the task).
- A task received from a peer appears on this blackboard as a task from that source; its
  result changes travel back to the peer it came from (UDP; a final state once, over TCP).
  An agent that cannot keep tasks (its journal cannot write) refuses new ones with the reason.
- Signed beacons go to the configured broadcast/unicast addresses and to addresses learned
  from MobiNet's `NetInfo` where no peer is up: they only tell that an agent may be there. While every known peer
  is up and nothing new is learned, these announcements back off (doubling up to
  `announce_backoff` beacon periods); a newcomer still announces every period and is answered
  at once. Known peers get beacons inside their session, but only the quiet ones (nothing else
  sent to them for a beacon period: any session frame tells they are alive), and at most
  `beacon_fanout` of them a period: with more, each gets one less often and the beacon says
  how often, so its receiver waits as many periods longer. Only session traffic (fresh by
  construction) marks a peer up (a peer not up shows when its signed beacon was last heard; an
  agent running insecure has no sessions, so there any beacon marks its sender up), and a peer silent for `peer_timeout` (scaled by its announced
  interval, and stretched by the share of its numbered beacons that arrive: `liveness`) is down.
  A beacon that says nothing new (its peer up, at the same address and epoch) costs no run: the
  receive thread marks the peer heard, the liveness pass updates `last_heard`.
- Clients (`erni watch`) may lease a stream of blackboard changes; `erni task --wait` asks
  for a task's state (`task.query`).
- With `wire = "zenoh"` the same messages travel over Zenoh (`zenoh_wire.py`): no broadcast
  beacons; an agent's liveliness token stands for them, and a peer whose token goes is down at
  once (`_gone`).

All network traffic is handed to the endpoint's sender pool; received messages are handed
to `execute()` with `later()`, so nothing here does I/O inside a transaction.
"""

from __future__ import annotations

import ipaddress
import math
import random
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, SecretStr, model_validator

from erni.blackboard import AllocationResult, BBObject, NetInfo, Plugin, Pose, Task, TaskState
from erni.blackboard.clock import SYSTEM, Clock
from erni.blackboard.errors import ConfigError
from erni.blackboard.objects import Model, only_stamp_differs
from erni.blackboard.schemas import (
    Beacon,
    Cancel,
    Fresh,
    Peer,
    PeerList,
    ResultUpdate,
    StatusRemoved,
    StatusResend,
    TaskQuery,
    TaskRescind,
    TaskUnknown,
    WatchEvent,
    WatchRequest,
)
from erni.transport.bounds import SenderBounds
from erni.transport.endpoint import (
    CLIENT_ROLE,
    STREAM_BUFFER,
    Address,
    Endpoint,
    InboundFilter,
    parse_address,
    team_key,
)
from erni.transport.identity import Identity, IdentityError, load_identity
from erni.transport.limits import Limits
from erni.transport.liveness import BeaconCount, silence_stretch
from erni.transport.policy import OPERATORS, STATUS, Refusal, check_relay, check_status, check_task, check_watch
from erni.transport.wire import Message, register_type
from erni.transport.zenoh_keys import ZenohSettings


class Received(BBObject):
    """Durable note of which peer gave this agent a task, so results find their way after a restart."""

    durable: ClassVar[bool] = True

    task: str
    sender: str
    address: str = Field("", description="the sender's reply address, HOST:PORT")
    role: str = Field("", description="the role of the task's originator (the relay's statement for a "
                      "relayed task)")


class Relayed(Model):
    """A task forwarded by a relay (`task.relay`): the relay states the role of its originator
    (`task.source`), and the receiver checks that the relay may relay for that role and that the
    originator may give the task."""

    model_config = ConfigDict(extra="forbid")

    task: Task
    role: str = Field(max_length=32)


for _cls in (Peer, Received, Relayed, Beacon, ResultUpdate, Cancel, TaskRescind, TaskQuery, TaskUnknown, StatusResend,
             StatusRemoved, Fresh, PeerList, WatchRequest, WatchEvent):
    register_type(_cls)

WATCHED = (Task, Pose, NetInfo, Peer)


class TransportSettings(Model):
    """The `[plugin.settings]` of the transport plugin."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    wire: Literal["udp", "zenoh"] = Field("udp", description="udp: ERNI's own wire (UDP statuses, TCP tasks, "
                                          "broadcast beacons); zenoh: the same frames over Zenoh (`zenoh` below, "
                                          "docs/tutorials/two-sites-zenoh.md), for a team across sites and routers")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="with wire = \"zenoh\": the team's "
                                 "key chunk, peer or client mode, the routers to connect to")
    listen: str = Field("127.0.0.1:0", description="HOST:PORT for TCP and UDP (0 = any free port)")
    identity: str | None = Field(None, description="this agent's identity bundle from `erni keys issue` "
                                 "(PEM: key, certificate, authority certificate)")
    revocations: str | None = Field(None, description="the team's revocation list (CRL) from `erni keys "
                                    "revoke`; a newer one learned from a peer is written here")
    key: SecretStr | None = Field(None, description="shared team key instead of identities (prefer key_env)")
    key_env: str = Field("ERNI_TEAM_KEY", description="environment variable holding the team key")
    insecure: bool = Field(False, description="run without authentication or encryption (warned about)")
    role: str = Field("robot", description="this agent's role (what it may do: policy.py); with an identity, "
                      "its certificate's role unless set")
    capabilities: list[str] = Field(default_factory=list, description="announced in beacons and shown by `erni peers`")
    discovery_port: int = Field(47000, ge=0, le=65535, description="shared beacon port; 0 disables")
    beacon_to: list[str] = Field(default_factory=lambda: ["127.255.255.255"],
                                 description="broadcast or unicast hosts that get beacons")
    beacon_period: float = Field(1.0, ge=0.05, le=60.0, description="time between beacons (s)")
    beacon_fanout: int = Field(16, ge=1, le=100_000, description="in-session beacons a beacon_period at most: "
                               "with more quiet peers each gets one less often (liveness grows slower "
                               "instead of the traffic growing with the team)")
    announce_backoff: int = Field(8, ge=1, le=1000, description="while every known peer is up, broadcast "
                                  "beacons back off to at most this many beacon periods apart")
    peer_timeout: float = Field(4.0, gt=0, le=3600.0, description="silence after which a peer is down (s); stretched on "
                                "a lossy link, where fewer of its numbered beacons arrive")
    link_deadline: float = Field(30.0, gt=0, le=86400.0, description="a task whose performer is not heard "
                                 "this long fails with 'link lost' (s)")
    peers: list[str] = Field(default_factory=list, description="static peers, NAME@HOST:PORT")
    senders: int = Field(4, ge=1, le=64, description="sender threads")
    queue_limit: int = Field(1000, ge=1, le=1_000_000, description="messages queued per destination: reliable ones "
                             "beyond it are refused (the task fails), fast ones drop the oldest")
    max_frame: int = Field(256 * 1024, ge=1024, le=16 * 1024 * 1024, description="largest frame accepted (bytes)")
    receive_buffer: int | None = Field(None, ge=0, le=256 * 1024 * 1024, description="UDP receive buffer to "
                                       "ask the kernel for (bytes; 0 = the kernel's default); unset: "
                                       "8 MB for role control, which hears every robot's Poses, else 0")
    task_ttl: float = Field(30.0, gt=0, le=86400.0, description="give up delivering a task after this long (s)")
    ack_timeout: float = Field(1.0, gt=0, le=60.0, description="wait this long for an acknowledgement before a retry (s)")
    connect_timeout: float = Field(1.0, gt=0, le=60.0, description="a session's handshake waits this long (s); after each "
                                   "one given up with a peer the next waits twice as long, up to 8x")
    max_connections: int = Field(256, ge=1, le=65536, description="TCP connections accepted at once")
    max_connections_per_host: int = Field(32, ge=1, le=65536, description="... from one address")
    idle_timeout: float = Field(60.0, gt=0, le=86400.0, description="close a connection idle this long (s)")
    frame_timeout: float = Field(10.0, gt=0, le=3600.0, description="a frame (and a new connection's first "
                                 "authenticated frame) must arrive within this time (s)")
    share: list[str] = Field(default_factory=lambda: ["Pose", "NetInfo"],
                             description="object types sent as status to the peers below")
    status_refresh: float = Field(30.0, gt=0, le=3600.0, description="a shared object whose only change is "
                                  "its `stamp` goes to peers that hold it as a freshness note (its uid and "
                                  "stamp); the whole object goes again at least this often (s)")
    share_with_roles: list[str] = Field(default_factory=lambda: ["control"],
                                        description="peers of these roles receive shared status")
    share_with: dict[str, list[str]] = Field(default_factory=dict,
                                             description="per type, the roles that receive it, e.g. "
                                             "{Territory = [\"control\", \"robot\"]}")
    status_objects: int = Field(256, ge=1, le=1_000_000, description="status objects held per sender and "
                                "type, of the types whose uid is the sender's to choose (NetInfo: a robot "
                                "shares one per watched NetWatch preposition and one per NetWatch task it "
                                "answers); a new one beyond is refused and counted (refused.status_bound)")
    status_bytes: int = Field(4 * 1024 * 1024, ge=1024, le=1 << 34, description="bytes (their JSON) of the "
                              "status objects of those types held per sender and type (bytes); one that "
                              "would go beyond is refused and counted (refused.status_bound)")
    tasks_per_requester: int = Field(1000, ge=1, le=1_000_000, description="tasks held for one requester (the "
                                     "peer or client they came from), finished ones included until retention "
                                     "takes them: at the bound its oldest finished task leaves early, and with "
                                     "none finished a new one is refused (its requester is told; "
                                     "refused.task_bound)")
    hinted_peers: int = Field(512, ge=1, le=1_000_000, description="peers known only from hints (broadcast "
                              "beacons, Zenoh liveliness tokens) held at most, and as many addresses learned "
                              "from routing tables (NetInfo); a new one beyond is dropped and counted "
                              "(dropped.hint_bound)")
    hinted_per_source: int = Field(128, ge=1, le=1_000_000, description="... of those from one source: the "
                                   "host a beacon came from, the router a Zenoh token names ('direct' for a "
                                   "peer), the node whose routing table named an address")
    forward_tasks: bool = Field(True, description="false: never send tasks to other agents "
                                "(a replaying control node)")
    udp_loss: float = Field(0.0, ge=0.0, le=1.0, description="fault injection: drop this share of "
                            "outgoing datagrams")

    @model_validator(mode="after")
    def _check(self) -> TransportSettings:
        parse_address(self.listen)
        if self.wire == "zenoh":
            if "discovery_port" in self.model_fields_set and self.discovery_port:
                raise ValueError(f"discovery_port = {self.discovery_port} with wire = \"zenoh\": peers are found by "
                                 "Zenoh liveliness, not broadcast beacons (leave it unset or 0)")
            if "listen" in self.model_fields_set:
                raise ValueError(f"listen = {self.listen!r} is for wire = \"udp\": with wire = \"zenoh\" set "
                                 "zenoh.listen = [\"tcp/HOST:PORT\"] (peer mode) or zenoh.connect")
            self.discovery_port = 0
            tls = [e for e in self.zenoh.connect + self.zenoh.listen if e.startswith("tls/")]
            if tls and self.identity is None:
                raise ValueError(f"zenoh endpoint {tls[0]!r}: a tls/ link needs identity = \"KEYS/NAME.pem\" (from "
                                 "`erni keys issue`): its certificate authenticates the link")
        elif "zenoh" in self.model_fields_set:
            raise ValueError("zenoh settings given but wire = \"udp\": set wire = \"zenoh\" to use them")
        for peer in self.peers:
            name, sep, addr = peer.partition("@")
            if not sep or not name:
                raise ValueError(f"peers: {peer[:80]!r}: expected NAME@HOST:PORT")
            parse_address(addr)
        if self.peer_timeout <= self.beacon_period:
            raise ValueError(f"peer_timeout ({self.peer_timeout:g} s) must be longer than beacon_period "
                             f"({self.beacon_period:g} s)")
        if self.identity is not None:
            if self.insecure:
                raise ValueError("identity and insecure = true: choose one")
            ident = self.load_identity()
            if ident is not None and "role" not in self.model_fields_set:
                self.role = ident.role  # the certificate says what this agent is
        elif not self.insecure and not self.team_key():
            raise ValueError(f"no identity: set identity = \"KEYS/NAME.pem\" (made by `erni keys issue`), "
                             f"a team key (key, or the {self.key_env} environment variable), or insecure = true")
        return self

    def team_key(self) -> bytes | None:
        """The shared team key, if one is configured."""
        return team_key(self.key.get_secret_value() if self.key else None, self.key_env)

    def load_identity(self) -> Identity | None:
        """This agent's identity (IdentityError naming the file), or None without one."""
        if self.identity is None:
            return None
        return load_identity(self.identity, self.revocations)

    def make_endpoint(self, name: str, inbound_filter: InboundFilter | None = None,
                      clock: Clock | Callable[[], float] = SYSTEM) -> Endpoint:
        """Build the endpoint these settings describe (ConfigError if the identity does not fit);
        `clock` times what expires in it (the agent's)."""
        identity = self.load_identity()
        limits = Limits(max_connections=self.max_connections, max_connections_per_host=self.max_connections_per_host,
                        idle_timeout=self.idle_timeout, frame_timeout=self.frame_timeout)
        common: dict[str, Any] = dict(
            identity=identity, key=None if identity else self.team_key(), insecure=self.insecure,
            senders=self.senders, queue_limit=self.queue_limit, max_frame=self.max_frame,
            ack_timeout=self.ack_timeout, connect_timeout=self.connect_timeout, ttl=self.task_ttl,
            udp_loss=self.udp_loss, role=self.role, inbound_filter=inbound_filter, limits=limits,
            revocations=Path(self.revocations) if self.revocations else None, clock=clock)
        if self.wire == "zenoh":
            try:
                from erni.transport.zenoh_wire import ZenohEndpoint
            except ImportError:
                raise ConfigError("wire = \"zenoh\" needs the eclipse-zenoh package, which is not installed: "
                                  "pip install 'erni[zenoh]'") from None
            return ZenohEndpoint(name, zenoh_settings=self.zenoh, **common)
        return Endpoint(name, listen=parse_address(self.listen), discovery_port=self.discovery_port or None, **common)


class TransportPlugin(Plugin[TransportSettings]):
    """Bridges this agent's blackboard to the other agents of the team."""

    essential: ClassVar[bool] = True  # an agent that cannot reach its team must not run deaf
    endpoint_factory: Any = None  # tests may inject a mock network endpoint
    inbound_filter: InboundFilter | None = None
    """Set before the agent starts: `(sender, role) -> bool` decides which verified frames are
    delivered (`erni sim` hands its simulated radio to the transport this way)."""

    def setup(self) -> None:
        s = self.settings
        # peers' silence, task deadlines, watch leases and status refreshes are timed by the agent's
        # clock (`self.clock`), as is what expires in the endpoint (a test's ManualClock moves them all)
        if self.endpoint_factory is not None:
            self.endpoint: Endpoint = self.endpoint_factory(self.agent_name)
            self.endpoint.inbound_filter = self.inbound_filter
            self.endpoint.role = s.role  # its frames carry the agent's role, as a real session's do
        else:
            try:
                self.endpoint = s.make_endpoint(self.agent_name, self.inbound_filter, self.clock)
            except IdentityError as err:
                raise ConfigError(str(err)) from None
        if s.insecure:
            self.log.warning("transport of %s runs WITHOUT authentication (insecure = true): any "
                             "host on the network can task this agent", self.agent_name)
        elif s.identity is None:
            self.log.info("transport of %s authenticates with a shared team key: any holder of the key "
                          "can speak as any agent (give identities on a real team: erni keys)", self.agent_name)
        self.status_in: dict[str, tuple[int, int]] = {}  # uid of a status received -> (epoch, seq) of its owner
        self.status_owner: dict[str, str] = {}  # uid of a status received -> the one sender that holds it
        self._refused_at: dict[tuple[str, str, str], float] = {}  # (sender, kind, rule) -> last logged (monotonic)
        self._refused_more: dict[tuple[str, str, str], int] = {}  # ... refusals since, not logged
        self.status_base: dict[str, float] = {}  # uid of a status received -> stamp of the whole version held
        self.whole_sent: dict[str, _Sent] = {}  # uid of a shared object of ours -> its last whole version sent
        self._resend_asked: dict[str, float] = {}  # uid of a status received -> when we last asked for it whole
        self._count: Callable[[str], None] = getattr(self.endpoint, "count", None) or (lambda name: None)  # (a test's
        self.bounds = SenderBounds(s, self._count, self.log, self.clock)  # in-memory endpoint counts nothing)  # per sender: what it may make us hold
        self.tasks = self.subscribe(Task)
        self.receipts = self.subscribe(Received)
        self.watched = self.subscribe(lambda o: isinstance(o, WATCHED))
        self.watched.wakes = False  # only while a client watches: else every Pose or Peer change ran us again
        self.netinfo = self.subscribe(NetInfo)
        shared = set(s.share) | set(s.share_with)
        # our own shared objects: a status received from a peer (status_in) is committed by us and
        # must not run us again (a control node receives ten Poses a second from every robot)
        self.shared = self.subscribe(lambda o: type(o).__name__ in shared and o.uid not in self.status_in)
        self.directory = _Directory()
        self._targets: dict[str, tuple[int, list[_Target], frozenset[tuple[str, int]]]] = {}  # `_status_targets`
        self.tasks_out: dict[str, _TaskOut] = {}  # task uid -> what we know of a task we sent to its performer
        self.tasks_in: dict[str, _TaskIn] = {}  # task uid -> what we know of a task given to us (or relayed)
        self._waiting = 0  # records of tasks_out whose performer is not discovered yet (`_retry_pending`)
        self.peers: dict[str, _PeerRecord] = {}  # peer -> when we heard it, beaconed it, its limit and counts
        self._peer_lock = threading.Lock()  # a record made on the receive thread and in a run at once: one
        self.watchers: dict[tuple[str, Address], float] = {}  # (client, its address) -> lease end
        self.learned: set[str] = set()
        self.addresses: dict[str, Address] = {}  # reply address of every sender, clients included
        self._next_beacon = 0.0
        self._next_liveness = 0.0  # beacons and silences are looked at a few times a period
        self._next_silences = 0.0  # when the peers' silences are looked at next (monotonic)
        self._next_link_check = 0.0  # performers' silences are looked at a few times a period
        self._announce_every = s.beacon_period  # backs off while the directory stands
        self._announce_seen: tuple[int, int] = (-1, -1)  # peers and learned addresses at the last announcement
        self._beacon_said: Beacon | None = None  # what the last in-session beacons said (but the interval)
        for spec in s.peers:
            name, _, addr = spec.partition("@")
            host, port = parse_address(addr)
            self.directory[name] = Peer(uid=f"peer:{name}", name=name, address=f"{host}:{port}")
            self.add(self.directory[name])
        self._kinds = self._kind_table()
        # a task is acknowledged once this agent's journal holds it (it survives a kill -9): the
        # acknowledgement of a task.add or task.relay waits for the journal's next write (`_keep`)
        self.endpoint.held_kinds = frozenset({"task.add", "task.relay"})
        self.endpoint.on_message = self._received
        self.endpoint.hint_wanted = self._hint_wanted
        self.endpoint.on_gone = lambda name: self.later(lambda: self._gone(name))
        self.endpoint.on_undeliverable = lambda addr, mid, kind, body: self.later(
            lambda: self._undeliverable(addr, kind, body))
        self.endpoint.start()
        self.address = self.endpoint.address
        room = s.receive_buffer if s.receive_buffer is not None else (STREAM_BUFFER if s.role == "control" else 0)
        if room:  # a burst of Poses that arrives while the agent is held back waits here, not lost
            got = self.endpoint.receive_buffer(room)
            if got < room:
                self.log.info("UDP receive buffer: %d bytes granted of %d asked (net.core.rmem_max caps it "
                              "without root)", got, room)
        if s.wire == "zenoh":
            self.log.info("agent %s on Zenoh (%s, team %s%s)", self.agent_name, s.zenoh.mode, s.zenoh.team,
                          f", connect {' '.join(s.zenoh.connect)}" if s.zenoh.connect else "")
        else:
            self.log.info("agent %s listening on %s:%d (TCP+UDP), beacons on port %s", self.agent_name,
                          *self.address, s.discovery_port or "off")
        self.wake_every(s.beacon_period)
        self.wake()

    def teardown(self) -> None:
        self.endpoint.stop()

    def _degraded(self) -> str:
        """Why this agent cannot keep new tasks ('' when it can)."""
        return str(getattr(self._require_agent(), "degraded", "") or "")

    # -- each run -------------------------------------------------------------------------

    def execute(self) -> None:
        me = self.agent_name
        for receipt in self.receipts.added:  # after a restart: who gave us which task, and where
            self.bounds.task(receipt.sender, receipt.task)
            given = self._task_in(receipt.task)
            if given.sender is None:
                given.sender = receipt.sender
            if receipt.role and given.origin_role is None:
                given.origin_role = receipt.role
            if receipt.address:
                try:
                    addr = parse_address(receipt.address)
                except ConfigError:
                    continue
                if given.reply_to is None:
                    given.reply_to = addr
                self.addresses.setdefault(receipt.sender, addr)
        for task in self.tasks.added:
            if self.rehydrated(task):
                self._reconcile(task)
            elif (task.destination not in (None, "", me) and self.settings.forward_tasks
                  and self._requester(task.uid) != task.destination):
                self._send_task(task)
        for task in self.tasks.added + self.tasks.changed:  # added and changed in one window: added
            origin = self._requester(task.uid)
            if origin and task.result is not None:
                self._send_result(origin, task)
        for task in self.tasks.removed:
            self.bounds.task_gone(task.uid)
            sent = self.tasks_out.pop(task.uid, None)
            if sent is not None and sent.pending is not None:
                self._waiting -= 1
            if sent is not None and sent.dest:
                self._send_to_peer(sent.dest, "task.cancel", Cancel(uid=task.uid), reliable=True)
            received = self.tasks_in.pop(task.uid, None)
            if received is not None and received.sender and self.get(f"received:{task.uid}") is not None:
                self.remove(f"received:{task.uid}")
        known = len(self.learned)
        for info in self.netinfo.added + self.netinfo.changed:
            for n in info.neighbors:
                if n.address and n.address not in self.learned:
                    self._learn(n.address, info.node)
            for route in info.routes:  # several hops away: a routing daemon's destination not yet named
                if route.destination not in self.learned and _is_ip(route.destination):
                    self._learn(route.destination, info.node)
        if len(self.learned) != known:  # somewhere new to announce to: at once
            self._next_beacon = 0.0
        self._share_status()
        self._retry_pending()
        self._forward_to_watchers()
        mono = self.clock()
        if mono >= self._next_liveness:  # O(peers): not on every run of a busy agent
            self._next_liveness = mono + self.settings.beacon_period / 4
            self._beacon_and_liveness()
        if mono >= self._next_link_check:  # O(tasks sent): a control node runs for every Pose it receives
            self._next_link_check = mono + min(self.settings.beacon_period, self.settings.link_deadline) / 4
            self._check_links()

    def _learn(self, address: str, node: str) -> None:
        """Announce to `address` from now on (named by `node`'s routing table), within the bounds."""
        why = self.bounds.learned(address, node)
        if why:
            self.bounds.refuse("dropped.hint_bound", node, "learned", why)
        else:
            self.learned.add(address)

    # -- what is known of each task and peer -----------------------------------------------

    def _task_in(self, uid: str) -> _TaskIn:
        """The record of task `uid` given to us, made when first written."""
        given = self.tasks_in.get(uid)
        if given is None:
            given = self.tasks_in[uid] = _TaskIn()
        return given

    def _requester(self, uid: str) -> str | None:
        """The peer task `uid` came from (None: not given to us)."""
        given = self.tasks_in.get(uid)
        return given.sender if given is not None else None

    def _performer(self, uid: str) -> str | None:
        """The peer task `uid` was sent to (None: not sent by us)."""
        sent = self.tasks_out.get(uid)
        return sent.dest if sent is not None else None

    def _stop_waiting(self, record: _TaskOut) -> None:
        record.pending = None
        self._waiting -= 1

    def _peer(self, name: str) -> _PeerRecord:
        """The record of peer `name`, made when first written (in a run or on the receive thread)."""
        peer = self.peers.get(name)
        if peer is None:
            peer = self.peers.setdefault(name, _PeerRecord())
        return peer

    def _sent_peer_at(self, name: str) -> float:
        peer = self.peers.get(name)
        return peer.sent_peer_at if peer is not None else -math.inf

    # -- outgoing -------------------------------------------------------------------------

    def _address_of(self, name: str, uid: str | None = None) -> Address | None:
        peer = self.directory.get(name)
        if peer is not None and peer.address:
            return parse_address(peer.address)
        given = self.tasks_in.get(uid) if uid is not None else None
        if given is not None and given.reply_to is not None:  # a client: the address its task came from
            return given.reply_to
        return self.addresses.get(name)

    def _send_to_peer(self, name: str, kind: str, body: Any, *, reliable: bool, uid: str | None = None) -> bool:
        addr = self._address_of(name, uid)
        if addr is None:
            return False
        self.endpoint.send(addr, kind, body, reliable=reliable, to=name)
        self._peer(name).sent_peer_at = self.clock()
        return True

    def _send_task(self, task: Task) -> None:
        dest = task.destination
        assert dest is not None
        record = self.tasks_out.get(task.uid)
        if record is None:
            record = self.tasks_out[task.uid] = _TaskOut(dest, self.clock())
        else:
            record.dest, record.sent_at = dest, self.clock()
        given = self.tasks_in.get(task.uid)
        if given is not None and given.sender:  # relayed: the receiver checks that we may relay for its originator
            sent = self._send_to_peer(dest, "task.relay", Relayed(task=task, role=given.origin_role or ""),
                                      reliable=True)
        else:
            sent = self._send_to_peer(dest, "task.add", task, reliable=True)
        if not sent:
            if record.pending is None:
                self._waiting += 1
            record.pending = (dest, self.clock() + self.settings.task_ttl)
            self.log.info("task %s waits for agent %s to be discovered", task.uid, dest)
            return
        latest = self._task_now(task.uid)  # this run may have applied its performer's result already
        if latest is not None and not latest.result:
            self.change(latest.with_result(TaskState.PENDING, message=f"sent to {dest}"))

    def _task_now(self, uid: str) -> Task | None:
        """The task as this run leaves it so far: a change is built on it, never on an older version."""
        task = self.current(uid)
        return task if isinstance(task, Task) else None

    def _reconcile(self, task: Task) -> None:
        """After a restart: re-send unfinished tasks we pass on; report on tasks we were given."""
        me = self.agent_name
        if task.destination not in (None, "", me) and self.settings.forward_tasks:
            if not task.done:  # ours or relayed: the receiver de-duplicates by uid
                self.log.info("re-sending task %s to %s after restart", task.uid, task.destination)
                self._send_task(task)
        origin = self._requester(task.uid)
        if origin and task.result is not None and task.destination in (None, "", me):
            self._task_in(task.uid).final_sent = False  # the requester may have missed it while we were away
            self._send_result(origin, task)

    def _retry_pending(self) -> None:
        if not self._waiting:  # O(tasks sent) only while some wait
            return
        mono = self.clock()
        for uid, record in list(self.tasks_out.items()):
            if record.pending is None:
                continue
            dest, deadline = record.pending
            task = self._task_now(uid)
            if task is None or task.done:
                self._stop_waiting(record)
            elif self._address_of(dest) is not None:
                self._stop_waiting(record)
                self._send_task(task)
            elif mono > deadline:
                self._stop_waiting(record)
                self.change(task.with_result(TaskState.FAILED, message=f"unknown agent {dest}: "
                                             "never discovered"))

    def _check_links(self) -> None:
        """Fail tasks whose performer has not been heard for `link_deadline` seconds."""
        deadline = self.settings.link_deadline
        mono = self.clock()
        for uid, record in list(self.tasks_out.items()):
            if record.lost or record.pending is not None:
                continue
            dest = record.dest
            heard = self.peers.get(dest)
            since = max(heard.heard_at if heard is not None else 0.0, record.sent_at)
            if mono - since <= deadline:
                continue
            task = self._task_now(uid)
            if task is None or task.done:
                continue
            record.lost = True
            self.log.warning("task %s: link lost: %s not heard for %.0f s", uid, dest, mono - since)
            self.change(task.with_result(TaskState.FAILED, message=f"link lost: {dest} not heard for "
                                         f"{mono - since:.0f} s (link_deadline {deadline:g} s)"))
            self._send_to_peer(dest, "task.cancel", Cancel(uid=uid), reliable=True)

    def _send_result(self, origin: str, task: Task) -> None:
        if task.result is None:
            return
        update = ResultUpdate(uid=task.uid, result=task.result)
        if not task.done:
            self._send_to_peer(origin, "task.result", update, reliable=False, uid=task.uid)
        elif not (given := self._task_in(task.uid)).final_sent:  # a final state once, and reliably
            given.final_sent = True
            self._send_to_peer(origin, "task.result", update, reliable=True, uid=task.uid)

    def _undeliverable(self, addr: Address, kind: str, body: Any) -> None:
        if kind == "task.relay" and isinstance(body, Relayed):
            kind, body = "task.add", body.task
        if kind == "task.add" and isinstance(body, Task):
            task = self._task_now(body.uid)
            if task is not None and not task.done:
                self.change(task.with_result(
                    TaskState.FAILED, message=f"link lost: could not deliver to {task.destination} "
                    f"at {addr[0]}:{addr[1]}"))

    # -- incoming -------------------------------------------------------------------------

    def _handle(self, msg: Message) -> None:
        try:
            self._handle_message(msg)
        finally:
            ack, msg.ack = msg.ack, None
            if ack is not None:  # a held acknowledgement nothing durable waits for (refused, or no task)
                ack()

    def _keep(self, msg: Message) -> None:
        """Acknowledge `msg` once what this run publishes is durable: after the run's commit, at the
        journal's next write (group commit: the tasks of one write are acknowledged together)."""
        ack, msg.ack = msg.ack, None
        if ack is not None:
            agent = self._require_agent()
            self.after_commit(lambda: agent.when_durable(ack))

    def _handle_message(self, msg: Message) -> None:
        if msg.hint:  # a broadcast beacon: signed but replayable, so only a hint of presence
            if msg.kind == "beacon" and msg.role != CLIENT_ROLE:
                self._hinted(msg)
            return
        self.addresses[msg.sender] = msg.reply
        if msg.role != CLIENT_ROLE:  # a command-line client is not a peer
            self._heard(msg.sender, msg.reply, msg.epoch, msg.body if msg.kind == "beacon" else None, msg.role)
        try:
            self._authorized(msg)
        except Refusal as refusal:
            self._refused(msg, refusal)
            return
        handler = self._kinds.get(msg.kind)
        if handler is not None and isinstance(msg.body, handler[0]):
            handler[1](msg, msg.body)

    def _kind_table(self) -> dict[str, tuple[type | tuple[type, ...], Callable[[Message, Any], None]]]:
        """The handler of each kind of message, with the type its body must have (anything else is
        not acted on: `_authorized` has already let the sender send that kind)."""
        return {
            "task.add": (Task, lambda msg, task: self._task_added(msg, task, msg.sender, msg.role)),
            "task.relay": (Relayed, lambda msg, relayed: self._task_added(msg, relayed.task, relayed.task.source,
                                                                          relayed.role)),
            "task.rescind": (TaskRescind, self._on_rescind),
            "task.cancel": (Cancel, self._on_cancel),
            "task.result": (ResultUpdate, self._apply_result),
            "task.query": (TaskQuery, self._on_query),
            "status": (BBObject, self._apply_status),
            "status.fresh": (Fresh, self._apply_fresh),
            "status.resend": (StatusResend, self._on_resend),
            "status.remove": (StatusRemoved, self._on_status_removed),
            "peers.request": (object, self._on_peers_request),
            "watch.request": (WatchRequest, self._on_watch_request),
        }

    def _on_rescind(self, msg: Message, body: TaskRescind) -> None:
        if self._requester(body.uid) == msg.sender and self._board.contains(body.uid):
            self.log.info("task %s was rescinded by %s (it no longer has it)", body.uid, msg.sender)
            self.remove(body.uid)

    def _on_cancel(self, msg: Message, body: Cancel) -> None:
        requester = self._requester(body.uid)
        if requester is not None and requester != msg.sender:  # an operator's (`_authorized`)
            self._cancelled_by_operator(msg, body.uid, requester)
        elif requester == msg.sender and self._board.contains(body.uid):
            self.remove(body.uid)

    def _on_query(self, msg: Message, body: TaskQuery) -> None:
        known = self._board.get(body.uid)
        if isinstance(known, Task):
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=known.uid, result=known.result
                                                                      or AllocationResult()),
                               reliable=False, to=msg.sender)
        else:
            self.endpoint.send(msg.reply, "task.unknown", TaskUnknown(uid=body.uid), reliable=False, to=msg.sender)

    def _on_resend(self, msg: Message, body: StatusResend) -> None:
        sent = self.whole_sent.get(body.uid)
        if sent is not None:  # its next change goes whole again
            sent.holders = frozenset(h for h in sent.holders if h[0] != msg.sender)

    def _on_status_removed(self, msg: Message, body: StatusRemoved) -> None:
        self.bounds.status_gone(body.uid)
        self.status_base.pop(body.uid, None)
        self._resend_asked.pop(body.uid, None)
        self.status_owner.pop(body.uid, None)
        if self.status_in.pop(body.uid, None) is not None and self.get(body.uid) is not None:
            self.remove(body.uid)

    def _on_peers_request(self, msg: Message, body: object) -> None:
        """The directory, in as many `peers.reply` parts as keep each within half a frame (room for
        the envelope and the seal): a directory of any size reaches the client whole."""
        counted = {name: peer.beacon_count.share() for name, peer in list(self.peers.items())
                   if peer.beacon_count is not None and peer.beacon_count.sent}
        budget = max(1024, self.settings.max_frame // 2)
        parts: list[list[Peer]] = [[]]
        used = 0
        for peer in self.directory.values():
            size = len(peer.model_dump_json()) + 2 * len(peer.name) + 64  # and its rows of beacons, down_after
            if parts[-1] and used + size > budget:
                parts.append([])
                used = 0
            parts[-1].append(peer)
            used += size
        for i, chunk in enumerate(parts):
            names = [p.name for p in chunk]
            reply = PeerList(agent=self.agent_name, peers=chunk, request=msg.id[:128], part=i, parts=len(parts),
                             beacons={n: counted[n] for n in names if n in counted},
                             down_after={n: self._down_after(n) for n in names})
            self.endpoint.send(msg.reply, "peers.reply", reply, reliable=True, to=msg.sender)

    def _on_watch_request(self, msg: Message, body: WatchRequest) -> None:
        key = (msg.sender, msg.reply)
        new = key not in self.watchers
        self.watchers[key] = self.clock() + body.lease
        self.watched.wakes = True
        if new:  # start the stream with the current state
            for obj in self.query(lambda o: isinstance(o, WATCHED)):
                self._watch_event(key, "add", obj)

    # -- authorization (policy.py) ---------------------------------------------------------

    def _authorized(self, msg: Message) -> None:
        """Raise Refusal unless the policy lets `msg`'s sender send it (every kind, default deny)."""
        kind, body, sender, role = msg.kind, msg.body, msg.sender, msg.role
        me = self.endpoint.role
        if kind in ("task.add", "task.relay"):
            task, origin_role = (body, role) if isinstance(body, Task) else (body.task, body.role) \
                if isinstance(body, Relayed) else (None, "")
            if task is None:
                raise Refusal("kind", f"a {kind} without a task")
            if kind == "task.relay":
                if not task.source or task.source == sender:
                    raise Refusal("relay", "a relayed task must name its originator as its source")
                check_relay(role, origin_role)
            dest = task.destination
            if dest in (None, "", self.agent_name):
                check_task(origin_role, me, task.verb, task.preposition)
            else:  # we are asked to relay it on: may we, for its originator, and may it task that agent?
                check_relay(me, origin_role)
                peer = self.directory.get(dest)
                check_task(origin_role, peer.role if peer is not None else "", task.verb, task.preposition)
        elif kind in ("task.cancel", "task.rescind"):
            uid = getattr(body, "uid", "")
            requester = self._requester(uid)
            if requester is not None and requester != sender and (kind == "task.rescind" or role not in OPERATORS):
                raise Refusal("requester", f"task {uid[:64]} was given by {requester}, not {sender}")
        elif kind == "task.result":
            uid = getattr(body, "uid", "")
            performer = self._performer(uid)
            if performer is not None and performer != sender:
                raise Refusal("performer", f"task {uid[:64]} is performed by {performer}, not {sender}")
        elif kind == "task.query":
            uid = getattr(body, "uid", "")
            if role not in OPERATORS and sender not in (self._requester(uid), self._performer(uid)):
                raise Refusal("query", f"role {role or '(none)'} may query only its own tasks")
        elif kind == "status":
            if not isinstance(body, BBObject):
                raise Refusal("status", "a status that is no blackboard object")
            check_status(sender, role, body)
            self._check_holder(sender, body.uid)
        elif kind in ("status.fresh", "status.remove"):
            self._check_holder(sender, getattr(body, "uid", ""))
        elif kind in ("watch.request", "peers.request"):
            check_watch(role)
        elif kind not in ("beacon", "status.resend"):
            raise Refusal("kind", f"no rule lets anyone send {kind[:64]!r}")

    def _cancelled_by_operator(self, msg: Message, uid: str, requester: str) -> None:
        """An operating role cancels a task another agent gave: its requester gets the final state
        (`cancelled by NAME`), then the task leaves, as at its requester's own cancel."""
        task = self._task_now(uid)
        if task is None:
            return
        self.log.info("task %s of %s cancelled by %s (role %s)", uid, requester, msg.sender, msg.role)
        given = self.tasks_in.get(uid)
        if not task.done and not (given is not None and given.final_sent):
            self._task_in(uid).final_sent = True
            update = ResultUpdate(uid=uid, result=AllocationResult(
                state=TaskState.CANCELLED, message=f"cancelled by {msg.sender} ({msg.role})"))
            self._send_to_peer(requester, "task.result", update, reliable=True, uid=uid)
        self.remove(uid)

    def _check_holder(self, sender: str, uid: str) -> None:
        """A status uid is held by one sender (until it removes it): no other may change or remove it."""
        holder = self.status_owner.get(uid)
        if holder is not None and holder != sender:
            raise Refusal("status", f"{uid[:64]} is held by {holder}, not {sender}")

    def _refused(self, msg: Message, refusal: Refusal) -> None:
        """Count a refusal; log it once per sender, kind and rule every 10 s; tell a task's sender."""
        self.endpoint.count(f"refused.{refusal.rule}")
        key = (msg.sender, msg.kind, refusal.rule)
        mono = self.clock()
        if mono - self._refused_at.get(key, -math.inf) >= 10.0:
            more = self._refused_more.pop(key, 0)
            self._refused_at[key] = mono
            if len(self._refused_at) > 4096:  # bounded: forget the oldest
                del self._refused_at[next(iter(self._refused_at))]
            self.log.warning("refused %s from %s (role %s): rule %s: %s%s", msg.kind, msg.sender[:64],
                             msg.role[:32] or "(none)", refusal.rule, refusal,
                             f" (+{more} more since)" if more else "")
        elif len(self._refused_more) < 4096 or key in self._refused_more:
            self._refused_more[key] = self._refused_more.get(key, 0) + 1
        task = msg.body.task if isinstance(msg.body, Relayed) else msg.body
        if msg.kind in ("task.add", "task.relay") and isinstance(task, Task):  # its requester must not wait
            result = AllocationResult(state=TaskState.FAILED,
                                      message=f"refused by {self.agent_name}: not authorized: {refusal}")
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=task.uid, result=result),
                               reliable=True, to=msg.sender)

    def _task_added(self, msg: Message, body: Task, origin: str, role: str) -> None:
        """A task from `msg.sender`, given by `origin` of `role` (the sender itself, or the originator
        a relay named)."""
        if body.source != origin:
            body = body.evolve(source=origin)  # the source is who asked, as authenticated or relayed
        known = self.current(body.uid)
        if known is not None:  # the requester restarted and re-sent it: tell it where we are
            self._keep(msg)  # (its journal write may still be on its way)
            if self._requester(body.uid) in (None, msg.sender) and isinstance(known, Task):
                given = self._task_in(body.uid)
                given.sender, given.reply_to = msg.sender, msg.reply
                if known.result is not None:
                    given.final_sent = False
                    self._send_result(msg.sender, known)
            return
        reason = self._degraded()
        if reason:  # never acknowledge what this agent cannot keep
            self.log.warning("refused task %s from %s: %s", body.uid, msg.sender, reason)
            refusal = AllocationResult(state=TaskState.FAILED, message=f"refused by {self.agent_name}: {reason}")
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=body.uid, result=refusal),
                               reliable=True, to=msg.sender)
            return
        if self.bounds.task_full(msg.sender) and not self._make_room(msg.sender):
            s = self.settings
            why = (f"{msg.sender} has {s.tasks_per_requester} unfinished tasks here (tasks_per_requester = "
                   f"{s.tasks_per_requester})")
            self.bounds.refuse("refused.task_bound", msg.sender, "tasks", f"task {body.uid[:64]} refused: {why}")
            refusal = AllocationResult(state=TaskState.FAILED, message=f"refused by {self.agent_name}: {why}")
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=body.uid, result=refusal),
                               reliable=True, to=msg.sender)
            return
        given = self._task_in(body.uid)
        given.sender, given.reply_to, given.origin_role = msg.sender, msg.reply, role
        self.bounds.task(msg.sender, body.uid)
        self.add(body)
        self.add(Received(uid=f"received:{body.uid}", task=body.uid, sender=msg.sender,
                          address=f"{msg.reply[0]}:{msg.reply[1]}", role=role))
        self._keep(msg)

    def _make_room(self, requester: str) -> bool:
        """At `requester`'s bound of tasks: its oldest finished task leaves now instead of after the
        retention (its performer is told, as at retention); False when none of them is finished."""
        for uid in self.bounds.tasks_of(requester):
            task = self._task_now(uid)
            if task is None or task.done:
                self.bounds.task_gone(uid)
                if task is not None:
                    self.remove(uid)
                    self._count("evicted.task_bound")
                return True
        return False

    def _apply_result(self, msg: Message, update: ResultUpdate) -> None:
        task = self.current(update.uid)
        if task is None:  # a result for a task we no longer have: stale, rescind it there
            self.endpoint.send(msg.reply, "task.rescind", TaskRescind(uid=update.uid), reliable=True, to=msg.sender)
            return
        sent = self.tasks_out.get(update.uid)
        if sent is None or sent.dest != msg.sender:
            return
        if not isinstance(task, Task) or task.done or sent.final_seen:  # a final state is
            if sent.lost and not update.result.state.done:  # never overwritten; back too late:
                self.endpoint.send(msg.reply, "task.cancel", Cancel(uid=update.uid), reliable=True, to=msg.sender)
            return  # stop it there
        stamp = (msg.epoch, msg.seq)
        final = update.result.state.done  # the last word, whatever its number: a status sent before it
        applied = sent.last_result or (0, 0)
        if stamp <= applied and not final:  # may be numbered after it
            return  # an older update never overwrites a newer one
        sent.last_result = max(stamp, applied)
        if final:
            sent.final_seen = True
        self.change(task.evolve(result=update.result), reports=[f"result from {msg.sender}"])

    def _received(self, msg: Message) -> None:
        """Hand a message to a run, unless it is an in-session beacon that tells nothing new: then it
        only marks its peer heard (the liveness pass puts that on the board). Runs on the endpoint's
        receive thread; in a team of N each agent hears up to `beacon_fanout` of these a period."""
        if self._beacon_repeats(msg):
            self._peer(msg.sender).heard_at = self.clock()
            self._count_beacon(msg.sender, msg.body)
            return
        self.later(lambda: self._handle(msg))

    def _beacon_repeats(self, msg: Message) -> bool:
        """Whether `msg` is an in-session beacon from a peer that is up, at the address, epoch and with
        the announced interval it had, saying what it said last: nothing for `_heard` to change."""
        body = msg.body
        if msg.hint or msg.kind != "beacon" or not isinstance(body, Beacon) or msg.role == CLIENT_ROLE:
            return False
        peer = self.directory.get(msg.sender)
        return (peer is not None and peer.up and peer.epoch == msg.epoch
                and peer.address == f"{msg.reply[0]}:{msg.reply[1]}"  # `addresses` is set with it
                and (peer.role, peer.capabilities, peer.degraded) == (body.role, body.capabilities, body.degraded)
                and (known := self.peers.get(msg.sender)) is not None
                and known.limit == self._silence_limit(body))

    def _silence_limit(self, beacon: Beacon) -> float:
        """How long a peer may be silent before it is down: `peer_timeout`, scaled by the interval
        its beacon announced (a peer with many quiet peers beacons each of them less often)."""
        s = self.settings
        return s.peer_timeout * max(1.0, beacon.interval / s.beacon_period)

    def _count_beacon(self, name: str, beacon: Beacon) -> None:
        """Count a numbered beacon of `name` (runs on the receive thread or in a run)."""
        if beacon.seq:
            peer = self._peer(name)
            count = peer.beacon_count
            if count is None:
                with self._peer_lock:
                    if peer.beacon_count is None:
                        peer.beacon_count = BeaconCount()
                    count = peer.beacon_count
            count.heard(beacon.seq)

    def _down_after(self, name: str) -> float:
        """The silence that marks peer `name` down: its limit on a link that loses nothing
        (`_silence_limit`), stretched by the share of its beacons that arrive (`liveness`)."""
        s = self.settings
        peer = self.peers.get(name)
        limit = peer.limit if peer is not None and peer.limit is not None else s.peer_timeout
        count = peer.beacon_count if peer is not None else None
        if count is None:
            return limit
        return limit * silence_stretch(count.delivery(), s.peer_timeout / s.beacon_period)

    def _hint_wanted(self, name: str) -> bool:
        """Whether a broadcast beacon from `name` could change anything: not while its peer is up
        (`_hinted` acts on unknown and down peers only). Runs on the endpoint's receive thread."""
        peer = self.directory.get(name)
        return peer is None or not peer.up

    def _hinted(self, msg: Message) -> None:
        """A signed beacon: learn where an unknown (or silent) agent may be; a session will tell."""
        name = msg.sender
        if not name or name == self.agent_name:
            return
        old = self.directory.get(name)
        address = f"{msg.reply[0]}:{msg.reply[1]}"
        beacon = msg.body if isinstance(msg.body, Beacon) else Beacon(role=msg.role)
        now = self.clock.wall()  # a peer not up shows when its beacon was last heard (up needs a session)
        if old is None:
            source = msg.source or msg.reply[0]
            why = self.bounds.hint(name, source)
            if why:
                self.bounds.refuse("dropped.hint_bound", source, "hint", why)
                return
            peer = Peer(uid=f"peer:{name}", name=name, address=address, role=beacon.role,
                        capabilities=beacon.capabilities, last_heard=now)
            self.directory[name] = peer
            self.add(peer)
            self.log.info("agent %s announces itself at %s", name, address)
        elif not old.up and old.address != address:  # a replayed beacon never moves a peer that is up
            peer = old.evolve(address=address, last_heard=now)
            self.directory[name] = peer
            self.change(peer, reports=["moved"])
        else:
            if not old.up and now - old.last_heard > self.settings.peer_timeout / 4:
                self.directory[name] = old = old.evolve(last_heard=now)
                self.change(old, reports=["heard"])
            return
        self.endpoint.send(msg.reply, "beacon", self._beacon(), reliable=False, to=name)  # starts a session

    def _gone(self, name: str) -> None:
        """The wire tells that agent `name` has left (its Zenoh liveliness token went): down at once,
        not after its silence limit. A session frame from it brings it up again. A peer known only
        from that hint (never heard in a session) is forgotten."""
        peer = self.directory.get(name)
        if peer is not None and not peer.up and self.bounds.is_hinted(name):
            self.bounds.hint_gone(name)
            del self.directory[name]
            self.peers.pop(name, None)
            if self.get(peer.uid) is not None:
                self.remove(peer.uid)
            self._count("forgot.hinted")
            return
        if peer is None or not peer.up:
            return
        self.directory[name] = peer = peer.evolve(up=False)
        self.log.warning("peer %s is down: it left (%s liveliness)", name, self.endpoint.wire)
        self.change(peer, reports=["down"])

    def _heard(self, name: str, reply: tuple[str, int], epoch: int, beacon: Any, role: str = "") -> None:
        if not name or name == self.agent_name:
            return
        if self.bounds.is_hinted(name):  # heard in a session: a peer, no longer a hint
            self.bounds.hint_gone(name)
        now = self.clock.wall()
        self._peer(name).heard_at = self.clock()
        old = self.directory.get(name)
        address = f"{reply[0]}:{reply[1]}"
        if (beacon is None and old is not None and old.up and old.epoch == epoch and old.address == address
                and (old.role or not role) and now - old.last_heard <= self.settings.peer_timeout / 4):
            return  # a peer up, heard again: the common case (a control node hears ten Poses a second from each)
        fields: dict[str, Any] = {"address": address, "epoch": epoch, "last_heard": now, "up": True}
        if role and (old is None or not old.role):
            # a configured peer's role, from its session, before any beacon: two peers that talk
            # send each other no beacons, and its shared status must not wait for one
            fields["role"] = role
        if isinstance(beacon, Beacon):
            self._count_beacon(name, beacon)
            fields.update(role=beacon.role, capabilities=beacon.capabilities, degraded=beacon.degraded)
            self._peer(name).limit = self._silence_limit(beacon)
        if old is None:
            peer = Peer(uid=f"peer:{name}", name=name, **fields)
            self.directory[name] = peer
            self.add(peer)
            self.log.info("peer %s is up at %s", name, address)
            return
        changed = any(getattr(old, k) != v for k, v in fields.items() if k != "last_heard")
        if changed or now - old.last_heard > self.settings.peer_timeout / 4:
            peer = old.evolve(**fields)
            self.directory[name] = peer
            report = "up" if not old.up else ("restarted" if old.epoch and old.epoch != epoch else "heard")
            if report != "heard":
                self.log.info("peer %s is %s at %s", name, report, address)
            reports = [report]
            if peer.degraded != old.degraded:
                reports.append("degraded" if peer.degraded else "recovered")
                if peer.degraded:
                    self.log.warning("peer %s is degraded: %s", name, peer.degraded)
                else:
                    self.log.info("peer %s takes tasks again", name)
            self.change(peer, reports=reports)

    # -- periodic -------------------------------------------------------------------------

    def _beacon(self, interval: float = 0.0) -> Beacon:
        s = self.settings
        return Beacon(role=s.role, capabilities=s.capabilities, degraded=self._degraded(), interval=interval)

    def _beacon_and_liveness(self) -> None:
        s = self.settings
        mono = self.clock()
        if mono >= self._next_beacon:
            seen = (len(self.directory), len(self.learned))
            # a lone agent keeps announcing every period (it is heard by nobody yet, and costs nobody much)
            standing = (seen == self._announce_seen and bool(self.directory)
                        and all(p.up for p in self.directory.values()))
            self._announce_seen = seen
            self._announce_every = (min(self._announce_every * 2, s.beacon_period * s.announce_backoff)
                                    if standing else s.beacon_period)
            self._next_beacon = mono + self._announce_every * 0.9
            announced: set[Address] = set()
            if s.discovery_port:
                announced |= {(host, s.discovery_port) for host in s.beacon_to}
                # a learned address whose agent is already up with us needs no announcement: its
                # session carries beacons (and on one host, as under `erni sim`, a unicast to the
                # shared beacon port lands on whichever agent bound it last, not on that agent)
                up = {p.address for p in self.directory.values() if p.up}
                up_hosts = {a.rpartition(":")[0] for a in up}
                for learned in self.learned:  # HOST (beacon port) or HOST:PORT (data port)
                    if learned in up or learned in up_hosts:
                        continue
                    try:
                        announced.add(parse_address(learned, s.discovery_port))
                    except ConfigError:
                        continue
            if announced:
                beacon = self._beacon()
                for addr in announced:
                    self.endpoint.announce(addr, "beacon", beacon)
        self._beacon_quiet_peers(mono)
        if mono < self._next_silences:
            return
        # O(peers), so every quarter peer timeout, earlier only when a peer's silence may reach its
        # limit then: hearing a peer moves that moment later, a peer that comes up has a limit of at
        # least one peer timeout, and a limit that shrinks (a shorter announced interval, fewer
        # beacons lost) is looked at within the quarter
        self._next_silences = mono + s.peer_timeout / 4
        wall = self.clock.wall()
        for name, peer in list(self.directory.items()):
            if not peer.up:
                continue  # a session frame will bring it up: nothing to look at
            heard = self.peers.get(name)
            silent = mono - (heard.heard_at if heard is not None else 0.0)
            limit = self._down_after(name)
            if silent <= limit:
                self._next_silences = min(self._next_silences, mono - silent + limit)
                if wall - silent - peer.last_heard > s.peer_timeout / 4:  # heard by beacons that said nothing new
                    self.directory[name] = peer = peer.evolve(last_heard=wall - silent)
                    self.change(peer, reports=["heard"])
                continue
            peer = peer.evolve(up=False)
            self.directory[name] = peer
            count = heard.beacon_count if heard is not None else None
            counted = f"; {100.0 * count.share():.0f} % of its beacons arrived" if count and count.sent else ""
            self.log.warning("peer %s is down: not heard for %.1f s (limit %.1f s%s)", name, silent, limit, counted)
            self.change(peer, reports=["down"])
            self._next_beacon = min(self._next_beacon, mono + s.beacon_period)  # announce often again

    def _beacon_quiet_peers(self, mono: float) -> None:
        """In-session beacons to the peers sent nothing else for a period, at most `beacon_fanout` a
        period: with more, each is beaconed less often, a newly quiet one at once, the others spread.
        What a beacon says (role, capabilities, degraded) going stale is news for every peer: when it
        changes, every peer gets a beacon at once, talking or not."""
        s = self.settings
        said = self._beacon()
        news = said != self._beacon_said
        self._beacon_said = said
        quiet = [(name, peer) for name, peer in self.directory.items()
                 if peer.address and mono - self._sent_peer_at(name) >= s.beacon_period]
        interval = s.beacon_period * max(1.0, len(quiet) / s.beacon_fanout)
        if news:
            quiet = [(name, peer) for name, peer in self.directory.items() if peer.address]
        beacon: Beacon | None = None
        for name, peer in quiet:
            due = None if news or (record := self.peers.get(name)) is None else record.beacon_due
            if due is not None and due > mono + interval:  # the interval shrank: no longer than the new one
                due = self._peer(name).beacon_due = mono + random.uniform(0.0, interval)
            if due is not None and mono < due:
                continue
            beacon = beacon or self._beacon(interval)
            record = self._peer(name)
            seq = record.beacons_sent = record.beacons_sent + 1  # the receiver counts what arrives
            self.endpoint.send(parse_address(peer.address), "beacon", beacon.model_copy(update={"seq": seq}),
                               reliable=False, to=name)
            # the next a little early (runs come every period); after a newly quiet peer's first
            # beacon (at once: its last frame is a period old), at a random phase, so that many
            # peers' beacons spread over the interval instead of leaving together
            early = 0.9 if due is not None or interval == s.beacon_period else random.uniform(0.3, 0.9)
            record.beacon_due = mono + early * interval
        for record in list(self.peers.values()):
            if record.beacon_due is not None and mono - record.sent_peer_at < s.beacon_period:
                record.beacon_due = None  # talking again: its frames tell it we are alive

    def _share_status(self) -> None:
        """Send this agent's own shared objects (poses, network info) to the status peers.

        A change of nothing but an object's `stamp` (a keep-alive: a standing robot's Pose, a
        network reading that did not change) goes as a `Fresh` note to peers that were sent the
        whole object, unless `status_refresh` has passed since: a control node hears of every
        robot's network topology each second, and the whole of it only when it changed."""
        objs = self.shared.added + self.shared.changed
        gone = self.shared.removed
        if not objs and not gone:
            return
        s = self.settings
        mono = self.clock()
        for obj in objs:
            targets, holders = self._status_targets(type(obj).__name__)
            if not targets:
                continue
            sent = self.whole_sent.get(obj.uid)
            if sent is not None and holders <= sent.holders and mono - sent.at < s.status_refresh \
                    and only_stamp_differs(sent.obj, obj):
                self._send_status(targets, "status.fresh", Fresh(uid=obj.uid, base=sent.obj.stamp,  # type: ignore[attr-defined]
                                                                 stamp=obj.stamp), False, mono)  # type: ignore[attr-defined]
                continue
            self._send_status(targets, "status", obj, False, mono)
            if isinstance(getattr(obj, "stamp", None), float):
                self.whole_sent[obj.uid] = _Sent(obj, mono, holders)
        for obj in gone:  # removals reliably: a stale object would stay forever
            self.whole_sent.pop(obj.uid, None)
            self._send_status(self._status_targets(type(obj).__name__)[0], "status.remove", StatusRemoved(uid=obj.uid),
                              True, mono)

    def _status_targets(self, type_name: str) -> tuple[list[_Target], frozenset[tuple[str, int]]]:
        """The peers (name, address, epoch) that an object of `type_name` is shared with, and the set
        of their (name, epoch): worked out again only when the directory changed who is up where
        (a robot shares ten Poses a second; its peers' liveness alone changes nothing here)."""
        cached = self._targets.get(type_name)
        if cached is not None and cached[0] == self.directory.gen:
            return cached[1], cached[2]
        s = self.settings
        roles = s.share_with.get(type_name, s.share_with_roles)
        targets = []
        for p in self.directory.values():
            if p.up and p.address and p.role in roles:
                try:
                    targets.append(_Target(p.name, parse_address(p.address), p.epoch))
                except ConfigError:
                    continue
        holders = frozenset((t.name, t.epoch) for t in targets)
        self._targets[type_name] = (self.directory.gen, targets, holders)
        return targets, holders

    def _send_status(self, targets: list[_Target], kind: str, body: BaseModel, reliable: bool, mono: float) -> None:
        """Send a status to its peers: a fast one as one burst (encoded once, sealed per peer, the
        datagrams handed to the socket back to back), a reliable one to each peer's queue."""
        fanout = getattr(self.endpoint, "send_fanout", None)  # a test's in-memory endpoint has none
        if reliable or len(targets) < 2 or fanout is None:
            for t in targets:
                self.endpoint.send(t.address, kind, body, reliable=reliable, to=t.name)
        else:
            fanout([(t.address, t.name) for t in targets], kind, body)
        for t in targets:
            self._peer(t.name).sent_peer_at = mono

    def _apply_status(self, msg: Message, obj: BBObject) -> None:
        stamp = (msg.epoch, msg.seq)
        if stamp <= self.status_in.get(obj.uid, (0, 0)):
            return  # an older status never overwrites a newer one
        first = obj.uid not in self.status_in  # (two statuses of a new object may come in one run)
        if first and self._board.get(obj.uid) is not None:
            return  # never overwrite an object of our own with a peer's
        why = self._hold_status(msg.sender, obj)
        if why:
            self.bounds.refuse("refused.status_bound", msg.sender, f"status {type(obj).__name__}", why)
            return
        self.status_in[obj.uid] = stamp
        self.status_owner[obj.uid] = msg.sender
        base = getattr(obj, "stamp", None)
        if isinstance(base, float):
            self.status_base[obj.uid] = base
        if first:
            self.add(obj)
        else:
            self.change(obj, reports=[f"status from {msg.sender}"])

    def _hold_status(self, sender: str, obj: BBObject) -> str:
        """'' when `sender`'s status `obj` fits its bounds (held from now on), else why not. A type whose
        uid the policy fixes (one per sender: a Pose, a Peer) is not counted: its one object is at most
        a frame."""
        name = type(obj).__name__
        rule = STATUS.get(name)
        if rule is not None and rule.uid:
            return ""
        return self.bounds.status(sender, name, obj.uid, len(obj.model_dump_json()))

    def _apply_fresh(self, msg: Message, note: Fresh) -> None:
        """A peer's shared object is unchanged but for its stamp: if we hold the version it was
        sent whole as, take the new stamp; else (that version was lost) ask for it whole."""
        stamp = (msg.epoch, msg.seq)
        if stamp <= self.status_in.get(note.uid, (0, 0)):
            return
        held = self._board.get(note.uid) if note.uid in self.status_in else None
        if held is None or self.status_base.get(note.uid) != note.base:
            now = self.clock()
            if now - self._resend_asked.get(note.uid, -math.inf) >= 1.0:
                if len(self._resend_asked) >= 4096 and note.uid not in self._resend_asked:
                    del self._resend_asked[next(iter(self._resend_asked))]  # bounded: the oldest asked goes
                self._resend_asked[note.uid] = now
                self.endpoint.send(msg.reply, "status.resend", StatusResend(uid=note.uid), reliable=False, to=msg.sender)
            return
        self.status_in[note.uid] = stamp
        self.change(held.model_copy(update={"stamp": note.stamp}), reports=[f"status from {msg.sender}"])

    def _forward_to_watchers(self) -> None:
        mono = self.clock()
        for key, until in list(self.watchers.items()):
            if until < mono:
                del self.watchers[key]
        if not self.watchers:
            self.watched.wakes = False
            return
        for op, objs in (("add", self.watched.added), ("change", self.watched.changed),
                         ("remove", self.watched.removed)):
            for obj in objs:
                for key in self.watchers:
                    self._watch_event(key, op, obj)

    def _watch_event(self, watcher: tuple[str, Address], op: str, obj: BBObject) -> None:
        event = WatchEvent(agent=self.agent_name, op=op, type=type(obj).__name__,
                           data=obj.model_dump(mode="json"))
        self.endpoint.send(watcher[1], "watch.event", event, reliable=False, to=watcher[0])


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


class _Directory(dict[str, Peer]):
    """The peers by name. `gen` moves when a peer is added or deleted, or stored with a change of
    what decides which of our statuses it is sent and where: up, address, role or epoch (not its
    `last_heard`). Peers are only stored (`d[name] = peer`) and deleted (`del d[name]`)."""

    gen = 0

    def __setitem__(self, name: str, peer: Peer) -> None:
        old = self.get(name)
        if old is None or (old.up, old.address, old.role, old.epoch) != (peer.up, peer.address, peer.role, peer.epoch):
            self.gen += 1
        super().__setitem__(name, peer)

    def __delitem__(self, name: str) -> None:
        self.gen += 1
        super().__delitem__(name)


class _Target(NamedTuple):
    """A peer a status goes to: its name, its address parsed, and its epoch (the `holders` key)."""

    name: str
    address: Address
    epoch: int


class _Sent:
    """The last whole version of a shared object sent, when, and to which peers (name, epoch)."""

    __slots__ = ("obj", "at", "holders")

    def __init__(self, obj: BBObject, at: float, holders: frozenset[tuple[str, int]]):
        self.obj, self.at, self.holders = obj, at, holders


@dataclass(slots=True)
class _TaskOut:
    """A task this agent sent to its performer (`_send_task`), until the task leaves the board."""

    dest: str  # the peer it was sent to
    sent_at: float  # when it was sent (monotonic)
    pending: tuple[str, float] | None = None  # (destination, deadline) while the destination is not discovered
    lost: bool = False  # failed because its performer was not heard in time
    last_result: tuple[int, int] | None = None  # (epoch, seq) of the performer's result applied
    final_seen: bool = False  # the performer's final result was applied


@dataclass(slots=True)
class _TaskIn:
    """A task given to this agent (to perform or to relay), until the task leaves the board."""

    sender: str | None = None  # the peer it came from
    origin_role: str | None = None  # role of its originator (relayed: as its relay stated)
    reply_to: Address | None = None  # address of the agent or client it came from
    final_sent: bool = False  # its final state went back to its requester


@dataclass(slots=True)
class _PeerRecord:
    """What the transport keeps of a peer: when it was heard and sent to, its beacons and limit."""

    heard_at: float = 0.0  # when a session frame of it last arrived (monotonic)
    sent_peer_at: float = -math.inf  # when a session frame other than a beacon went to it (monotonic)
    beacon_due: float | None = None  # while quiet: when its next in-session beacon is due (monotonic)
    limit: float | None = None  # silence that marks it down, from its announced interval
    beacon_count: BeaconCount | None = None  # how many of its numbered beacons arrive
    beacons_sent: int = 0  # in-session beacons sent it (their numbers)
