"""ERNI's frames over Zenoh: the same sessions, acknowledgements and checks, another wire under them.

`ZenohEndpoint` is an `Endpoint` whose sockets are a Zenoh session (`wire = "zenoh"` in the
transport's settings). Nothing above the frame changes: every frame is sealed in an ERNI session
(AEAD, replay window) before it leaves, so a Zenoh router forwards ciphertext it can neither read,
forge nor replay; every frame that arrives goes through the endpoint's one frame path
(`accept_frame`), and every message through the transport plugin's authorization. What this
module replaces is only how bytes move (key expressions in `zenoh_keys.py`):

- a datagram (`ZenohWire.sendto`: a status, a handshake, its answer, a hint) is a put to the receiver's
  `d` key, best effort and dropped rather than queued when the link is congested (statuses: the
  newest wins, and the receiver orders them by number anyway);
- a reliable message (`ZenohWire.deliver`) is a query to the receiver's `r` key: its reply carries the
  acknowledgement sealed in the session (or a hint that the session is unknown), as ERNI's TCP
  stream does (a task's when the receiver's journal holds it: the query is kept until then); the sender pool retries, de-duplication and order per destination are the
  endpoint's, unchanged;
- discovery is Zenoh's liveliness: each agent holds a token `erni/<team>/<name>/alive/<role>/<inst>/<router>`;
  a token that appears is a hint of presence (as a broadcast beacon is: the session decides), one
  that goes marks its agent gone (`on_gone`) at once instead of after its silence limit; a hint
  that leads to no session is forgotten and given again a bounded number of times (`HINT_WAITS`:
  tokens are unsigned, anyone the router admits may declare one); the
  router in it (declared again when the agent's router changes) says where the agent is reached.

Datagrams wait in a bounded ring channel (the oldest dropped when it is full) for one receive
thread blocked on it, as the UDP wire's thread is on its socket; queries and liveliness changes
are handled on Zenoh's own threads, where the reply has to be made. Either way a frame is checked
and handed on there, never processed under a blackboard transaction.
"""

from __future__ import annotations

import base64
import json
import threading
from dataclasses import dataclass
from typing import Any

import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from erni.blackboard.errors import ConfigError, NetworkError
from erni.blackboard.schemas import Beacon
from erni.transport.endpoint import CLIENT_ROLE, Endpoint
from erni.transport.identity import Identity
from erni.transport.outbox import Dest, Outgoing
from erni.transport.receiver import HEADER_KIND
from erni.transport.session import Session
from erni.transport.wire import DATA, KIND, FrameError, Message
from erni.transport.wires import Wire
from erni.transport.zenoh_keys import ALIVE, DATAGRAM, RELIABLE, Keys, ZenohSettings, address_of, name_at

Address = tuple[str, int]

RECONNECT = 1.0
"""Seconds between attempts to open the session of an agent whose routers were not reachable at start."""

DATAGRAM_QUEUE = 8192
BATCH_BYTES = 16_000  # statuses gathered in one frame in a burst (ERNI's UDP wire: 1400, one datagram)
"""Datagrams waiting for the receive thread; when more arrive the oldest go first (newest wins),
as statuses are meant to (a UDP socket's buffer drops the newest instead)."""

HINT_STAND = 3.0
"""A token's hint stands for this many handshake timeouts: an agent whose token is held but whose
handshake has not completed by then is forgotten (`on_gone`) until its next hint."""

HINT_WAITS = (5.0, 15.0, 45.0)
"""Seconds (agent clock) from one forgotten hint to the next of a token that never led to a session:
a token is hinted 1 + len(HINT_WAITS) times at most while it is held, then no more until it goes.
Anyone the router admits may declare a token in any agent's name; this bounds the handshakes one
such token costs each agent (a real agent reaches this one by its own handshake meanwhile)."""

HINTS_KEPT = 4096
"""Names whose tokens are waited on for a session at once; a newer one is not hinted past this."""

PUBLISHERS = 4096
"""Publishers kept declared (one per receiver); past this many they are all declared again on use."""

NO_SHARED_MEMORY = "transport/shared_memory/transport_optimization/enabled"
"""Zenoh's setting that copies a message larger than 3 kB into a shared-memory pool (16 MB a session,
touched on first use) when its receiver is on the same host; ERNI's sessions turn it off. Its frames
are at most `BATCH_BYTES`, so the copy it saves is small, while the pool cost every agent of a team
on one host (`erni sim`) 16 MB, and its first use slowed the first burst of statuses between two
agents: a put took 7-10 ms of CPU a burst of 5000 statuses (140 frames) the first time, 2-3 ms after
(1.4-3x less throughput in that burst). Agents on different hosts never use it."""


def tls_config(identity: Identity) -> dict[str, Any]:
    """Zenoh's TLS settings from an ERNI identity: its key and certificate on both sides of a link,
    the team authority as the only root, and the peer's certificate required (mutual TLS). Names
    are not checked against hosts: ERNI's certificates name agents, and who may connect is whoever
    holds a certificate of this team's authority."""
    pem = serialization.Encoding.PEM
    key = base64.b64encode(identity.key.private_bytes(pem, serialization.PrivateFormat.PKCS8,
                                                      serialization.NoEncryption())).decode()
    cert = base64.b64encode(x509.load_der_x509_certificate(identity.cert_der).public_bytes(pem)).decode()
    root = base64.b64encode(identity.trust.authority.public_bytes(pem)).decode()
    return {"root_ca_certificate_base64": root, "enable_mtls": True, "verify_name_on_connect": False,
            "listen_private_key_base64": key, "listen_certificate_base64": cert,
            "connect_private_key_base64": key, "connect_certificate_base64": cert}


def open_session(settings: ZenohSettings, *, listen: list[str] | None = None, mode: str | None = None,
                 identity: Identity | None = None, access: dict[str, Any] | None = None) -> zenoh.Session:
    """Open a Zenoh session as `settings` say (a router with `mode="router"` and `listen`), its
    `tls/` links authenticated with `identity`; raise NetworkError naming the endpoints when Zenoh
    refuses, ConfigError for a `tls/` endpoint without an identity."""
    conf = zenoh.Config()
    values = settings.config()
    if mode is not None:
        values["mode"] = mode
        values["scouting/multicast/enabled"] = mode != "client" and settings.scouting
    if listen:
        values["listen/endpoints"] = list(listen)
    endpoints = values.get("listen/endpoints", []) + values.get("connect/endpoints", [])
    if any(e.startswith("tls/") for e in endpoints):
        if identity is None:
            raise ConfigError(f"zenoh endpoint {next(e for e in endpoints if e.startswith('tls/'))!r}: a tls/ link "
                              "needs an identity from `erni keys issue` (its certificate authenticates the link)")
        values["transport/link/tls"] = tls_config(identity)
    if access is not None:
        values["access_control"] = access
    try:
        conf.insert_json5(NO_SHARED_MEMORY, "false")
    except zenoh.ZError:  # a Zenoh without the setting: nothing to turn off
        pass
    try:
        for key, value in values.items():
            conf.insert_json5(key, json.dumps(value))
        return zenoh.open(conf)
    except zenoh.ZError as err:
        where = ", ".join(values.get("listen/endpoints", []) + values.get("connect/endpoints", [])) or "defaults"
        raise NetworkError(f"cannot open a Zenoh session ({values['mode']}, {where}): {_reason(err)}") from None


def _reason(err: Exception) -> str:
    """Zenoh's error message on one line, without the source location it appends."""
    text = (str(err).splitlines() or [repr(err)])[0].strip("'\" ")
    return text.split(" at /", 1)[0].rstrip(". ") or repr(err)


def open_router(listen: list[str], *, connect: list[str] | None = None, scouting: bool = False,
                identity: Identity | None = None, access: dict[str, Any] | None = None,
                team: str | None = None, name: str | None = None) -> zenoh.Session:
    """Run a Zenoh router in this process, listening on `listen` (and linked to the routers in
    `connect`; `tls/` links authenticated with `identity`; `access`: its access control, from
    `zenoh_acl.access_control`), until the returned session is closed. It forwards the team's
    frames unread. With `team` it holds a token of role `router` in its `name` (the identity's by
    default), so the team's agents name the router each peer is reached through."""
    settings = ZenohSettings(connect=list(connect or []), scouting=scouting)
    session = open_session(settings, listen=listen, mode="router", identity=identity, access=access)
    name = name or (identity.name if identity is not None else None)
    if team and name:
        token = Keys(team).token(name, ROUTER_ROLE, str(session.zid()))
        _router_tokens[id(session)] = session.liveliness().declare_token(token)  # held while the session is
    return session


@dataclass(slots=True)
class _Hint:
    """A token's hint that has not led to a session yet: when it was given, how many were, when the
    next is due (None: it stands now) and what it announced."""

    given: float
    role: str
    router: str
    hints: int = 1
    due: float | None = None


ROUTER_ROLE = "router"
_router_tokens: dict[int, Any] = {}  # a router's name token lives as long as the process's router


class ZenohEndpoint(Endpoint):
    """An endpoint whose frames travel over Zenoh (`zenoh_keys.py` names where)."""

    def __init__(self, name: str, *, zenoh_settings: ZenohSettings, **kw: Any):
        kw["listen"] = address_of(name)
        kw["discovery_port"] = None  # liveliness tokens instead of broadcast beacons
        super().__init__(name, **kw)
        self.zenoh_settings = zenoh_settings
        self.keys = Keys(zenoh_settings.team)
        self._zs: zenoh.Session | None = None
        self._alive: dict[str, set[tuple[str, str]]] = {}  # agent -> (instance, router) of its tokens held now
        self._routes: dict[str, str] = {}  # agent -> the router its newest token names ('' direct)
        self._router_names: dict[str, str] = {}  # a router's Zenoh id -> its name, from its token
        self._token: zenoh.LivelinessToken | None = None
        self._token_router = ""
        self._next_route_check = 0.0
        self._alive_lock = threading.Lock()
        self._hints: dict[str, _Hint] = {}  # agent -> its token's hint, until a session with it (`_follow_hints`)
        self._halt = threading.Event()
        self._rx: threading.Thread | None = None  # the datagram thread (`_receive_loop`)
        self._next_open = 0.0  # when to try again to open a session that could not be opened (monotonic)
        self._declared: list[Any] = []  # subscribers, queryable, token: undeclared at stop

    def _make_wire(self) -> Wire:
        """Puts and queries instead of UDP datagrams and TCP streams (made while `Endpoint.__init__`
        builds the parts that send on it)."""
        self.zenoh_wire = ZenohWire(self)
        return self.zenoh_wire

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Open the Zenoh session, declare what this agent receives and its liveliness token, and
        start the sender pool (NetworkError if Zenoh refuses). An agent in client mode whose routers
        are not reachable yet starts all the same and tries again every `RECONNECT` seconds (a
        command-line client fails at once); once connected, Zenoh itself reconnects after a loss."""
        self.queues.stopping = False
        self._halt.clear()
        try:
            self._attach(open_session(self.zenoh_settings, identity=self.identity))
        except NetworkError as err:
            if self.zenoh_settings.mode != "client" or self.role == CLIENT_ROLE:
                raise
            self.log.warning("%s; trying again every %g s", err, RECONNECT)
            self._next_open = self.pace() + RECONNECT
        sweeper = threading.Thread(target=self._sweep_loop, name=f"erni-{self.name}-zenoh-sweep", daemon=True)
        sweeper.start()
        self._threads = [sweeper] + self.pool.start(f"erni-{self.name}-net-tx", self.senders)
        self.queues.started = True

    def _attach(self, zs: zenoh.Session) -> None:
        """Declare this agent's subscriber, queryable, token and token subscriber on a new session."""
        try:
            datagrams = zs.declare_subscriber(self.keys.listen(self.name, DATAGRAM),
                                              zenoh.handlers.RingChannel(DATAGRAM_QUEUE))
            declared: list[Any] = [datagrams, zs.declare_queryable(self.keys.listen(self.name, RELIABLE), self._on_query)]
            if self.role != CLIENT_ROLE:  # a command-line client is no peer: it shows no token
                self._token_router = _router_of(zs)
                self._token = zs.liveliness().declare_token(self.keys.token(self.name, self.role, self.inst,
                                                                            self._token_router))
            declared.append(zs.liveliness().declare_subscriber(self.keys.tokens(), self._on_token, history=True))
        except zenoh.ZError as err:
            zs.close()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs
            raise NetworkError(f"cannot declare {self.keys.root}/{self.name}/... on Zenoh: {err}") from None
        self._declared = declared
        self._zs = zs
        self._rx = threading.Thread(target=self._receive_loop, args=(datagrams.handler,),
                                    name=f"erni-{self.name}-zenoh-rx", daemon=True)
        self._rx.start()

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the sender pool, undeclare the token (peers see this agent go) and close the session."""
        if not self._threads:
            return
        self.queues.stop()
        self._halt.set()
        deadline = self.pace() + timeout
        for t in self._threads[:1]:  # the sweeper: it may be attaching a session
            t.join(max(0.0, deadline - self.pace()))
        token, self._token = self._token, None
        for entity in ([token] if token is not None else []) + list(reversed(self._declared)):
            # the token first (peers see this agent go); the subscriber's end ends the receive thread
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self._declared = []
        for t in self._threads[1:] + ([self._rx] if self._rx is not None else []):
            t.join(max(0.0, deadline - self.pace()))
        self._threads, self._rx = [], None
        self.queues.started = False
        zs, self._zs = self._zs, None
        self.zenoh_wire.forget_publishers()
        if zs is not None:
            zs.close()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs

    def receive_buffer(self, size: int) -> int:
        """Nothing to ask for: Zenoh queues what arrives in its own buffers. Returns `size`."""
        return size

    def _sweep_loop(self) -> None:
        """Forget expired handshakes and idle sessions, as the UDP wire's stream thread does; and
        open the session of a client whose routers were not reachable at start."""
        while not self._halt.wait(0.25):
            now = self.pace()
            try:
                if self._zs is None and now >= self._next_open:
                    self._next_open = now + RECONNECT
                    self._attach(open_session(self.zenoh_settings, identity=self.identity))
                    self.log.info("connected to Zenoh through %s", " ".join(self.zenoh_settings.connect))
                if now >= self._next_route_check:
                    self._next_route_check = now + 1.0
                    self._follow_router()
                self._follow_hints()
                self.sessions.sweep(self.clock())
            except NetworkError:
                self.count("zenoh.unreachable")
            except Exception:  # never lose the sweeper
                self.log.exception("session sweep failed")

    def _follow_router(self) -> None:
        """Declare the token again when the router this agent is connected through changed (a
        reconnection to another router of the site): the new one first, so it is never gone."""
        zs, old = self._zs, self._token
        if zs is None or old is None:
            return
        router = _router_of(zs)
        if router == self._token_router:
            return
        self._token = zs.liveliness().declare_token(self.keys.token(self.name, self.role, self.inst, router))
        self._token_router = router
        old.undeclare()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs

    def _follow_hints(self) -> None:
        """The tokens hinted that have not led to a session: a hint that stood `HINT_STAND` handshake
        timeouts (agent clock) is forgotten (`on_gone`: a peer known only from it leaves the team's
        directory, and nothing is sent to it); one forgotten is hinted again after the next of
        `HINT_WAITS`, and after the last not until its token goes and comes again."""
        now = self.clock()
        stand = HINT_STAND * self.handshake_timeout
        again: list[tuple[str, _Hint]] = []
        forget: list[str] = []
        with self._alive_lock:
            for name, hint in list(self._hints.items()):
                if self._in_session(name):
                    del self._hints[name]  # a peer now: its token's end says when it leaves
                elif hint.due is None and now - hint.given >= stand:
                    forget.append(name)
                    hint.due = now + HINT_WAITS[hint.hints - 1] if hint.hints <= len(HINT_WAITS) else float("inf")
                elif hint.due is not None and now >= hint.due:
                    hint.given, hint.hints, hint.due = now, hint.hints + 1, None
                    again.append((name, hint))
        for name in forget:
            if not self._in_session(name):  # not reached meanwhile
                self.count("zenoh.hints_forgotten")
                self._drop_statuses(name)
                self._gone(name)
        for name, hint in again:
            self._hint(name, hint.role, hint.router)

    def _drop_statuses(self, name: str) -> None:
        """Drop the statuses waiting for a session with agent `name` (a forgotten hint): its handshake
        then stops with nothing left to carry (a reliable message waits out its own deadline)."""
        with self.queues.cond:
            dest = self.queues.dests.get(address_of(name))
            dropped = len(dest.fast) if dest is not None else 0
            if dest is not None:
                dest.fast.clear()
        if dropped:
            self.count("dropped.no_session", dropped)

    def _in_session(self, name: str) -> bool:
        """Whether agent `name` is reached: a confirmed session with it, or its peer up (an agent
        running insecure has no sessions)."""
        return (self.sessions.usable(address_of(name)) is not None
                or (self.hint_wanted is not None and not self.hint_wanted(name)))

    def _hint(self, name: str, role: str, router: str) -> None:
        """Tell the owner an agent may be up there (its token): a session will tell."""
        if not self._beacon_bucket.take():  # unsigned: anyone the router admits may declare one
            self.count("dropped.rate")
            return
        self.count("zenoh.hints")
        self.dispatch(Message(name, role, address_of(name), 0, 0, "", "beacon", Beacon(role=role), hint=True,
                               source=f"router {router}" if router else "direct"))

    def _gone(self, name: str) -> None:
        try:
            self.on_gone(name)
        except Exception:
            self.log.exception("handling the end of %s's liveliness failed", name)

    @property
    def session(self) -> zenoh.Session:
        """The open Zenoh session (NetworkError when the endpoint is not started)."""
        if self._zs is None:
            raise NetworkError("the Zenoh endpoint is not started")
        return self._zs

    # -- sending --------------------------------------------------------------------------

    # -- receiving (on Zenoh's threads) ---------------------------------------------------

    def _receive_loop(self, samples: zenoh.Handler[zenoh.Sample]) -> None:
        """The datagram thread: blocked in the channel's receive while it is empty, as the UDP wire's
        thread is in its socket's; what queued meanwhile is taken without blocking again (a blocking
        receive lets go of the interpreter lock even when a sample waits, and then waits to get it
        back). Ends when the subscriber is undeclared (its channel closes)."""
        sources: dict[str, Address | None] = {}  # key -> the address it names (a team has few senders)
        recv, try_recv = samples.recv, samples.try_recv
        accept, deliver = self.accept_frame, self.deliver
        while True:
            sample: zenoh.Sample | None
            try:
                sample = recv()
            except zenoh.ZError:
                return
            while sample is not None:
                key = str(sample.key_expr)
                if key in sources:
                    src = sources[key]
                else:
                    sender = self.keys.sender_of(key)
                    src = None if sender is None else address_of(sender)
                    if len(sources) >= 4096:
                        sources.clear()
                    sources[key] = src
                if self.queues.stopping:
                    pass
                elif src is None:
                    self.count("dropped.key")
                else:
                    got = accept(sample.payload.to_bytes(), "udp", src)
                    if got is not None:
                        for msg in got[0]:
                            deliver(msg)
                try:
                    sample = try_recv()
                except zenoh.ZError:
                    return

    def _on_query(self, query: zenoh.Query) -> None:
        """A reliable frame: acknowledge each message in the reply, then hand it on once."""
        sender = self.keys.sender_of(str(query.key_expr))
        payload = query.payload
        if self.queues.stopping:
            return
        if sender is None or payload is None:
            self.count("dropped.key")
            return
        raw, src = payload.to_bytes(), address_of(sender)
        key = query.key_expr

        def reply(frame: bytes) -> None:
            query.reply(key, frame)

        if self.auth is not None and len(raw) >= KIND.size + 8 and raw[HEADER_KIND] == DATA:
            sid = raw[KIND.size:KIND.size + 8]
            if sid not in self.sessions.by_sid:  # tell the sender at once, in the reply it waits for
                self.sessions.hint(sid, src, reply)
                self.count("dropped.session")
                return
        got = self.accept_frame(raw, "tcp", src)
        if got is None:
            return
        msgs, session = got

        def reply_later(frame: bytes) -> None:  # a held acknowledgement: the query waits for it (or times out)
            try:
                query.reply(key, frame)
            except zenoh.ZError as err:
                raise NetworkError(f"acknowledgement to {sender} failed: {err}") from None
            finally:
                query.drop()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs

        for msg in msgs:
            if msg.kind == "ack":
                continue
            try:
                self.receive_reliable(msg, session, reply, reply_later)
            except (zenoh.ZError, FrameError) as err:
                self.warn("link", f"acknowledgement to {sender} failed: {err}")
                return

    def _on_token(self, sample: zenoh.Sample) -> None:
        """A liveliness token appeared (a hint: an agent may be up there) or went (it is gone)."""
        parsed = self.keys.parse_token(str(sample.key_expr))
        if parsed is None:
            return
        name, role, inst, router = parsed
        if name == self.name and inst == self.inst:
            return
        if role == ROUTER_ROLE:  # a router's name (its instance is its Zenoh id): no agent to reach
            with self._alive_lock:
                if sample.kind == zenoh.SampleKind.PUT and len(self._router_names) < 4096:
                    self._router_names[inst] = name
                elif sample.kind != zenoh.SampleKind.PUT:
                    self._router_names.pop(inst, None)
            return
        if sample.kind == zenoh.SampleKind.PUT:
            with self._alive_lock:
                self._alive.setdefault(name, set()).add((inst, router))
                self._routes[name] = router
                if len(self._alive) > 65536:  # bounded: tokens are anyone's to declare
                    oldest = next(iter(self._alive))
                    del self._alive[oldest]
                    self._routes.pop(oldest, None)
            self.count("zenoh.tokens")
            if self.hint_wanted is not None and not self.hint_wanted(name):
                return  # a peer in session already: its token tells nothing new
            with self._alive_lock:
                hint = self._hints.get(name)
                if hint is not None:  # hinted already (or waiting to be again): `_follow_hints` paces it
                    hint.role, hint.router = role, router
                    return
                if len(self._hints) >= HINTS_KEPT:
                    self.count("dropped.hints")
                    return
                self._hints[name] = _Hint(self.clock(), role, router)
            self._hint(name, role, router)
            return
        with self._alive_lock:
            held = self._alive.get(name, set())
            held.discard((inst, router))
            gone = not held
            if gone:
                self._alive.pop(name, None)
                self._routes.pop(name, None)
                self._hints.pop(name, None)
        if gone:
            self.count("zenoh.gone")
            self._gone(name)

    def alive(self) -> dict[str, set[str]]:
        """The agents whose liveliness tokens are held now, with their instances."""
        with self._alive_lock:
            return {name: {inst for inst, _ in held} for name, held in self._alive.items()}

    def route_of(self, name: str) -> str | None:
        """The router agent `name` is connected through, by its newest token: the router's name when
        the router holds a name token (`erni router --team`), else its Zenoh id; '' directly (as a
        peer); None when no token of it is held."""
        with self._alive_lock:
            zid = self._routes.get(name)
            return self._router_names.get(zid, zid) if zid else zid


def _router_of(zs: zenoh.Session) -> str:
    """The Zenoh id of the router a session is connected through ('' for none)."""
    routers = zs.info.routers_zid()
    return str(routers[0]) if routers else ""


__all__ = ["ALIVE", "ZenohEndpoint", "open_router", "open_session"]


class ZenohWire:
    """The Zenoh wire: a datagram is a put to the receiver's datagram key (a publisher per receiver,
    declared on first use), a reliable message a query to its reliable key, acknowledged by the reply."""

    name = "zenoh"
    batch_limit: int | None = BATCH_BYTES  # Zenoh keeps no datagram under a link's MTU (its links are
    # streams, and it fragments what is larger): a burst's statuses gather up to this for one put

    def __init__(self, endpoint: ZenohEndpoint) -> None:
        self.endpoint = endpoint
        self._publishers: dict[Address, zenoh.Publisher] = {}  # a receiver's address -> its publisher
        self._pub_lock = threading.Lock()

    def forget_publishers(self) -> None:
        """Drop every publisher (the session closes)."""
        with self._pub_lock:
            self._publishers.clear()

    def sendto(self, frame: bytes, addr: Address) -> None:
        """Put one frame to the agent at `addr`, best effort (NetworkError, an OSError, when it cannot go)."""
        if self.endpoint.udp_loss and self.endpoint._rng.random() < self.endpoint.udp_loss:
            self.endpoint.count("dropped.injected")
            return
        pub = self._publishers.get(addr)  # one dictionary look-up a frame once the publisher is declared
        if pub is None:
            pub = self._publisher(addr)
        try:
            pub.put(frame)
        except zenoh.ZError as err:
            raise NetworkError(f"Zenoh put to {addr[0]} failed: {err}") from None

    def _publisher(self, addr: Address) -> zenoh.Publisher:
        """The publisher of frames to the agent at `addr`, declared on first use (NetworkError for an
        address of no agent, or when Zenoh refuses)."""
        name = name_at(addr)
        if name is None:
            raise NetworkError(f"{addr[0]}:{addr[1]} is no address on the Zenoh wire (expected zenoh/NAME:0)")
        with self._pub_lock:
            pub = self._publishers.get(addr)
            if pub is None:
                if len(self._publishers) >= PUBLISHERS:
                    for old in self._publishers.values():
                        old.undeclare()  # type: ignore[no-untyped-call]  # untyped in Zenoh's stubs
                    self._publishers.clear()
                try:
                    pub = self.endpoint.session.declare_publisher(self.endpoint.keys.inbox(name, DATAGRAM, self.endpoint.name),
                                                         congestion_control=zenoh.CongestionControl.DROP)
                except zenoh.ZError as err:
                    raise NetworkError(f"Zenoh put to {name} failed: {err}") from None
                self._publishers[addr] = pub
        return pub

    def write_now(self, addr: Address, out: Outgoing) -> bool:
        """Reliable messages always go through the sender pool here: it waits for the reply."""
        return False

    def deliver(self, dest: Dest, out: Outgoing, session: Session | None) -> bool:
        """Query the receiver with the sealed frame; True when a reply acknowledges `out`."""
        frame = self.endpoint.reliable.frame_or_drop(dest, out, session)
        if frame is None:
            return True
        name = name_at(dest.addr)
        if name is None:
            self.endpoint.warn("link", f"{dest.addr[0]}:{dest.addr[1]} is no address on the Zenoh wire")
            return False
        try:
            replies = self.endpoint.session.get(self.endpoint.keys.inbox(name, RELIABLE, self.endpoint.name), payload=frame,
                                       timeout=self.endpoint.ack_timeout, target=zenoh.QueryTarget.ALL,
                                       consolidation=zenoh.ConsolidationMode.NONE,
                                       congestion_control=zenoh.CongestionControl.BLOCK)
            answered = False
            for reply in replies:
                answered = True
                sample = reply.ok
                if sample is None:
                    continue
                got = self.endpoint.accept_frame(sample.payload.to_bytes(), "tcp", dest.addr)
                if got is not None and any(m.kind == "ack" and m.body == out.id for m in got[0]):
                    return True
        except (zenoh.ZError, NetworkError) as err:
            self.endpoint.warn("link", f"query to {name} failed: {err}")
            return False
        self.endpoint.count("zenoh.unanswered")
        if not answered and dest.addr in self.endpoint._clients:
            self.endpoint.reliable.client_gone(dest)  # nothing answers for a command-line client: it exited
        return False
