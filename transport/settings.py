"""The settings of the transport plugin (`[plugin.settings]` of `transport`), and the endpoint they describe."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import ConfigDict, Field, SecretStr, model_validator

from erni.blackboard.clock import SYSTEM, Clock
from erni.blackboard.errors import ConfigError
from erni.blackboard.objects import Model
from erni.transport.endpoint import Endpoint, InboundFilter, parse_address, team_key
from erni.transport.identity import Identity, load_identity
from erni.transport.limits import Limits
from erni.transport.zenoh_keys import ZenohSettings


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
