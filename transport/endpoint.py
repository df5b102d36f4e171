"""An agent's network endpoint: the sending side, the frame path, and the parts it is made of.

An endpoint is these parts, each a module a reader can take alone:

- `receiver.py`: the sockets and the receive loop (a thread blocked in the UDP socket's recvfrom,
  a selector thread for TCP connections, the discovery port and the sweeps) and every bound on
  what comes in before it is authenticated;
- `session_table.py`: the session table, handshakes, hints and revocation (`session.py`: one
  session's cryptography); the endpoint is its `SessionHost`, the seam another wire would fill;
- `outbox.py`: the sender pool, a record per destination (`Dest`) and the threads that serve them;
- `batching.py`: fast messages (statuses) from the caller's thread, gathered per datagram in a burst;
- `reliable.py`: reliable delivery over TCP, acknowledged, retried, in order;
- `discovery.py`: signed beacons to and from agents not in session yet;
- `inbound.py`: the frame path (`FramePath`: one handler per kind of frame: data, hint,
  handshake, answer, refusal, beacon), frames in, messages out;
- `codec.py` and `wire.py`: frames, envelopes and typed bodies;
- here: construction and life cycle, `send`, the acknowledgement of reliable messages and what the
  parts above need of the endpoint. The endpoint holds each sending part (`fast`, `reliable`,
  `beacons`, `pool`) and hands each, in its constructor, what it uses: the queues they share
  (`outbox.SendQueues`), the wire, the clocks, settings, and itself as the narrow `Protocol` each
  part declares for what it needs back (its counters, frames, reports).

Every message to a peer travels in a session with that peer's current instance: the first
message to an address starts a handshake, which the sender pool drives without blocking (the
handshake frames are retransmitted on a timer; the answer wakes the destination up again).
Reliable messages travel over TCP, one connection per destination, each acknowledged by message
id, retried with exponential backoff until their time to live runs out, and sent in order per
destination (one sender thread serves a destination at a time). Fast messages travel as UDP
datagrams from a bounded queue that drops the oldest. Beacons for unknown receivers are signed
instead (`announce`). Nothing here ever runs inside a blackboard transaction, and no caller ever
waits on a socket: when a session is up and nothing is queued for the destination, the caller's
thread seals a status and hands it to the UDP socket itself (MSG_DONTWAIT), and writes a reliable
message on an idle connection without waiting (a sender thread then waits for its
acknowledgement); whatever the socket does not take at once is queued for the sender pool,
which keeps the order.
"""

from __future__ import annotations

import base64
import errno
import functools
import logging
import os
import random
import socket
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic_core import to_json

from erni.blackboard.clock import SYSTEM
from erni.blackboard.errors import ConfigError, NetworkError
from erni.logs import RateLimitedLog
from erni.transport.batching import FastMessages, item_of
from erni.transport.discovery import Beacons
from erni.transport.identity import Identity
from erni.transport.inbound import INTERNAL, Accepted, FramePath
from erni.transport.limits import Limits, TokenBucket
from erni.transport.outbox import Dest, MessageIds, Outgoing, SenderPool, SendQueues
from erni.transport.receiver import Receiver, close
from erni.transport.reliable import ReliableDelivery
from erni.transport.session import Auth, IdentityAuth, Initiation, Session, TeamKeyAuth
from erni.transport.session_table import SessionTable
from erni.transport.wire import (
    DEFAULT_MAX_FRAME,
    HEADER,
    KIND,
    PLAIN,
    UDP_MAX_FRAME,
    FrameError,
    Message,
    SeenIds,
    encode_body,
    envelope_bytes,
    head_bytes,
    join_envelope,
)
from erni.transport.wires import UdpTcpWire, Wire

Address = tuple[str, int]

CLIENT_ROLE = "cli"
"""The role of a command-line client's endpoint (`erni task`, `erni watch` ...): never a peer."""

InboundFilter = Callable[[str, str], bool]
"""`(sender, role) -> bool`: whether a verified frame may be delivered (False: dropped and counted)."""


HELD_LIMIT = 10_000
"""Reliable messages whose acknowledgement is held back at once (`Endpoint.held_kinds`): past this
many the oldest is forgotten unacknowledged (its sender retries, and gives up at its deadline)."""


class _Held:
    """A reliable message acknowledged only when its owner says so: the session to seal the
    acknowledgement in, and where to send it (the channel of the latest copy to arrive)."""

    __slots__ = ("session", "reply")

    def __init__(self, session: Session | None, reply: Callable[[bytes], None]):
        self.session, self.reply = session, reply

STREAM_BUFFER = 8 << 20
"""A UDP receive buffer (bytes, for `Endpoint.receive_buffer`) that holds seconds of a team's
Pose stream, for a receiver that hears every robot (the control node, a watcher): 400-500
datagrams a second from 40-50 robots overflow the kernel's default of about 200 kB (it counts
1-2 kB of overhead a datagram) when the machine holds the receiver back for half a second. In the
40-robot hall a watcher lost 341 datagrams in 20 s, and at 50 robots the control node 32."""


@functools.lru_cache(maxsize=4096)  # a peer's address is parsed for every message sent to it
def parse_address(text: str, default_port: int = 0) -> Address:
    """Parse `host:port` (or `host`, with a default port); raise ConfigError naming the problem."""
    host, sep, port = text.strip().rpartition(":")
    if not sep:
        host, port = text.strip(), str(default_port)
    if not host:
        raise ConfigError(f"address {text[:80]!r}: expected HOST:PORT")
    try:
        number = int(port)
    except ValueError:
        raise ConfigError(f"address {text[:80]!r}: port {port[:20]!r} is not a number") from None
    if not 0 <= number <= 65535:
        raise ConfigError(f"address {text[:80]!r}: port {number} is outside 0..65535")
    return host, number


class Endpoint:
    """Sockets and threads of one agent; deliver verified messages to `on_message`.

    Give an `identity` (per-agent certificate), or a shared team `key`, or `insecure=True`.
    """

    def __init__(self, name: str, *, listen: Address = ("127.0.0.1", 0), identity: Identity | None = None,
                 key: bytes | None = None, insecure: bool = False, senders: int = 4, queue_limit: int = 1000,
                 max_frame: int = DEFAULT_MAX_FRAME, ack_timeout: float = 1.0, connect_timeout: float = 1.0,
                 retry_base: float = 0.05, retry_max: float = 2.0, ttl: float = 30.0,
                 discovery_port: int | None = None, udp_loss: float = 0.0, seed: int | None = None,
                 role: str = "", inbound_filter: InboundFilter | None = None, limits: Limits | None = None,
                 revocations: str | Path | None = None, handshake_timeout: float | None = None,
                 clock: Callable[[], float] = SYSTEM, pace: Callable[[], float] = SYSTEM):
        self.auth: Auth | None
        if identity is not None:
            if identity.name != name:
                raise ConfigError(f"the identity is issued to {identity.name!r}, not to agent {name!r}")
            if role and identity.role != role:
                raise ConfigError(f"the identity of {name} is issued for role {identity.role!r}, not {role!r}")
            role = identity.role
            self.auth = IdentityAuth(identity)
        elif key:
            self.auth = TeamKeyAuth(name, role, key)
        elif insecure:
            self.auth = None
        else:
            raise ConfigError("no identity and no team key: give one, or run with insecure = true")
        self.name = name
        # what expires is timed by `clock`: a message's deadline, a handshake, an idle session or
        # connection; the threads' own pace (retries, batches, waits, rate limits) by `pace`, real time.
        # A test gives its own clock (erni.testing.ManualClock, usually the agent's) to move time at once
        self.clock, self.pace = clock, pace
        self.identity = identity
        self.revocations = Path(revocations) if revocations else None
        self._listen = listen
        self.insecure = self.auth is None
        self.senders = senders
        self.queue_limit = queue_limit
        self.max_frame = max_frame
        self._udp_frame = min(max_frame, UDP_MAX_FRAME)
        self.ack_timeout = ack_timeout
        self.connect_timeout = connect_timeout
        self.handshake_timeout = handshake_timeout or max(1.0, connect_timeout)
        self.retry_base, self.retry_max, self.ttl = retry_base, retry_max, ttl
        self.discovery_port = discovery_port
        if not 0.0 <= udp_loss <= 1.0:
            raise ConfigError(f"udp_loss: expected a probability in 0..1, got {udp_loss}")
        self.udp_loss = udp_loss  # fault injection: drop this share of outgoing datagrams
        self._rng = random.Random(seed)
        self.role = role
        self.inbound_filter = inbound_filter
        self.limits = limits or Limits()
        self.inst = os.urandom(16).hex()
        self.ids = MessageIds(os.urandom(6).hex() + ".")  # message ids: unique per instance, cheap (no uuid)
        self.log = logging.getLogger(f"erni.{name}.transport")
        self._drops = RateLimitedLog(self.log)
        self.counters: dict[str, int] = {}
        self._counter_lock = threading.Lock()
        self._seen = SeenIds()
        self.address: Address = listen
        self.sessions = SessionTable(self, self.auth, name, self.inst, self.limits, max_frame, self.handshake_timeout,
                                 identity, self.revocations, self.log)
        self._beacon_bucket = TokenBucket(self.limits.beacons_total, clock=self.pace)
        self._clients: OrderedDict[Address, None] = OrderedDict()  # reply addresses of command-line clients heard
        self._heads: dict[str, bytes] = {}  # peer -> the envelope head of messages to it (`head`)
        self._head_opens: dict[str, bytes] = {}  # peer -> that head, open for one message's fields (`head_open`)
        self.queues = SendQueues(self, queue_limit, pace)  # what the sending parts share (outbox.py)
        self._threads: list[threading.Thread] = []
        self.on_message: Callable[[Message], None] = lambda msg: None
        self.on_undeliverable: Callable[[Address, str, str, Any], None] = lambda addr, id, kind, body: None
        self.on_delivered: Callable[[Address, str], None] = lambda addr, id: None
        # the agent at an address refused our certificate (another authority's, revoked): the reason
        self.on_refused: Callable[[Address, str], None] = lambda addr, reason: None
        # would a broadcast beacon from this sender tell the owner anything? (None: always check it)
        self.hint_wanted: Callable[[str], bool] | None = None
        # the agent of this name has left (a wire that tells, as Zenoh's liveliness does; UDP never calls it)
        self.on_gone: Callable[[str], None] = lambda name: None
        self.carrier: Wire = self._make_wire()  # the wire the frames travel on (zenoh_wire.ZenohWire on Zenoh)
        self.wire = self.carrier.name
        secure = self.auth is not None
        self.fast = FastMessages(self.queues, self.ids, self.carrier, self.sessions, self, secure=secure,
                                 udp_frame=self._udp_frame, pace=pace)  # batching.py
        self.reliable = ReliableDelivery(self.queues, self.carrier, self.sessions, self, self._clients, secure=secure,
                                         clock=clock, pace=pace, limits=self.limits, max_frame=max_frame,
                                         ack_timeout=ack_timeout, connect_timeout=connect_timeout,
                                         retry_base=retry_base, retry_max=retry_max, log=self.log)  # reliable.py
        self.beacons = Beacons(self.carrier, self, self.auth, self._beacon_bucket, name=name, inst=self.inst,
                               max_frame=max_frame)  # discovery.py
        self.pool = SenderPool(self.queues, self.carrier, self.sessions, self, self.fast, self.reliable, self.beacons,
                               secure=secure, clock=clock, pace=pace, handshake_timeout=self.handshake_timeout,
                               retry_max=retry_max, log=self.log)  # outbox.py
        self.inbound = FramePath(self, self.beacons.on_beacon)  # inbound.py: frames in, messages out
        # reliable kinds acknowledged only when the owner calls the message's `ack` (a task: once the
        # agent's journal holds it); any other is acknowledged as it arrives
        self.held_kinds: frozenset[str] = frozenset()
        self._held: OrderedDict[tuple[str, str], _Held] = OrderedDict()
        self._held_lock = threading.Lock()
        watch = getattr(clock, "on_advance", None)
        if callable(watch):  # a test's clock moved: the senders look again at what has expired
            watch(self.queues.wake_all)

    def _make_wire(self) -> Wire:
        """The wire this endpoint's frames travel on (a subclass for another wire makes its own)."""
        return UdpTcpWire(self)

    # -- the state the parts share, by its former names (tests read them) ------------------------

    @property
    def _cond(self) -> threading.Condition:
        return self.queues.cond

    @property
    def _dests(self) -> dict[Address, Dest]:
        return self.queues.dests

    @property
    def _seq(self) -> Iterator[int]:
        return self.ids.seq

    @_seq.setter
    def _seq(self, seq: Iterator[int]) -> None:  # a test numbers its messages from elsewhere
        self.ids.seq = seq

    # -- counters -------------------------------------------------------------------------

    def count(self, name: str, n: int = 1) -> None:
        """Add to a named counter (thread-safe)."""
        with self._counter_lock:
            self.counters[name] = self.counters.get(name, 0) + n

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Bind the sockets and start the receive thread and the sender pool (NetworkError if it cannot)."""
        self.queues.stopping = False
        self._tcp, self._udp = self._bind_pair()
        self._tcp.listen(128)
        self._tcp.setblocking(False)
        self._udp.setblocking(True)  # read by a thread blocked in recvfrom; every send on it is MSG_DONTWAIT
        self.address = self._tcp.getsockname()[:2]
        self._disc: socket.socket | None = None
        if self.discovery_port:
            self._disc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._disc.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._disc.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            try:
                self._disc.bind(("", self.discovery_port))
            except OSError as err:
                for s in (self._disc, self._tcp, self._udp):
                    s.close()
                raise NetworkError(f"cannot listen for beacons on UDP port {self.discovery_port}: "
                                   f"{err.strerror or err}") from None
            self._disc.setblocking(False)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)  # a held acknowledgement's wake-up never waits (`Receiver.queue_ack`)
        receiver = Receiver(self, self._tcp, self._udp, self._disc, self._wake_r, self._wake_w)
        rx = threading.Thread(target=receiver.run_streams, name=f"erni-{self.name}-net-rx", daemon=True)
        udp = threading.Thread(target=receiver.run_datagrams, name=f"erni-{self.name}-net-udp", daemon=True)
        rx.start()
        udp.start()
        self._threads = [rx, udp] + self.pool.start(f"erni-{self.name}-net-tx", self.senders)
        self.queues.started = True

    def receive_buffer(self, size: int) -> int:
        """Ask the kernel for a UDP receive buffer of `size` bytes (beyond `net.core.rmem_max` where
        the process may, else up to it) for a receiver that may fall behind a burst, such as a
        watcher sharing its process with other work; return the size granted (the kernel counts
        its own overhead, so this is about twice what it keeps for data)."""
        udp: socket.socket | None = getattr(self, "_udp", None)
        if udp is None:
            raise NetworkError("receive_buffer: the endpoint is not started")
        try:
            udp.setsockopt(socket.SOL_SOCKET, getattr(socket, "SO_RCVBUFFORCE", 33), size)
        except OSError:  # not allowed (no CAP_NET_ADMIN): the kernel caps this one at rmem_max
            udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        return int(udp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))

    def _bind_pair(self) -> tuple[socket.socket, socket.socket]:
        """TCP and UDP sockets on one port; with port 0, retry until both get the same free number."""
        host, port = self._listen
        attempts = 1 if port else 32
        for attempt in range(attempts):
            tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            udp.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            which, number = "TCP", port
            try:
                tcp.bind((host, port))
                which, number = "UDP", tcp.getsockname()[1]
                udp.bind((host, number))
            except OSError as err:
                tcp.close()
                udp.close()
                if port == 0 and which == "UDP" and err.errno == errno.EADDRINUSE and attempt < attempts - 1:
                    continue  # the free TCP port is taken for UDP: draw another
                raise NetworkError(f"cannot listen on {host}:{number} ({which}): {err.strerror or err}") from None
            if tcp.getsockname()[1] != udp.getsockname()[1]:  # never expected; checked, not assumed
                tcp.close()
                udp.close()
                raise NetworkError(f"cannot listen on {host}:{port}: TCP and UDP ports differ")
            return tcp, udp
        raise NetworkError(f"cannot listen on {host}:0: no port free for both TCP and UDP")  # pragma: no cover

    def stop(self, timeout: float = 1.0) -> None:
        """Stop every thread and close every socket."""
        if not self._threads:
            return
        self.queues.stop()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._wake_udp()
        deadline = self.pace() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - self.pace()))
        self._threads = []
        self.queues.started = False
        for dest in self.queues.dests.values():
            close(dest.sock)
            dest.sock = None
        for s in (self._udp, self._tcp, self._disc, self._wake_r, self._wake_w):
            close(s)

    def _wake_udp(self) -> None:
        """Wake the thread blocked in the UDP socket's recvfrom, so that it sees `stopping`: shut
        the socket for reading (Linux wakes its readers even for an unconnected datagram socket) and,
        in case that does not, send it an empty datagram."""
        try:
            self._udp.shutdown(socket.SHUT_RD)
        except OSError:
            pass
        host, port = self._udp.getsockname()[:2]
        try:
            self._udp.sendto(b"", socket.MSG_DONTWAIT, ("127.0.0.1" if host in ("0.0.0.0", "") else host, port))
        except OSError:
            pass

    # -- sessions (session_table.py), and what they need of this endpoint (`SessionHost`) -----------

    def session_with(self, addr: Address) -> Session | None:
        """The confirmed session used to send to `addr` now (None: the next send starts one)."""
        return self.sessions.current(addr)

    def warn(self, reason: str, text: str) -> None:
        self._drops.warning(reason, text)

    def send_datagram(self, frame: bytes, addr: Address) -> None:
        self.carrier.sendto(frame, addr)

    def admit(self, sender: str, role: str) -> None:
        self._filter(sender, role)

    def session_up(self, session: Session) -> None:
        self.pool.session_up(session)

    def session_lost(self, addr: Address) -> None:
        self.pool.session_lost(addr)

    def handshake_done(self, init: Initiation) -> None:
        self.pool.handshake_done(init)

    def send_crl(self, session: Session, der: bytes) -> None:
        self.send(session.addr, "crl", base64.b64encode(der).decode(), reliable=True, to=session.peer)

    # -- sending --------------------------------------------------------------------------

    def send(self, addr: Address, kind: str, body: BaseModel | Any = None, *, reliable: bool,
             msg_id: str | None = None, ttl: float | None = None, to: str | None = None) -> str:
        """Queue a message for `addr` (the agent `to`, when known); return its id. Never blocks."""
        if reliable:
            return self._enqueue(addr, kind, body, "reliable", msg_id, ttl, to)
        return self.fast.send_status(addr, kind, body, msg_id, ttl, to)  # batching.py

    def send_fanout(self, targets: Sequence[tuple[Address, str]], kind: str, body: Any) -> str:
        """Send one status to each `(address, agent)` of `targets`, as one message: sealed for each
        peer in session at once (`FastMessages.fanout`), through `send` for the others; its id."""
        msg_id, later = self.fast.fanout(targets, kind, body)
        for addr, to in later:
            self.send(addr, kind, body, reliable=False, msg_id=msg_id, to=to)
        return msg_id

    def announce(self, addr: Address, kind: str, body: BaseModel | Any = None) -> str:
        """Queue a signed, sessionless datagram for receivers not known yet (beacons, discovery.py)."""
        return self._enqueue(addr, kind, body, "announce", None, None, None)

    def _enqueue(self, addr: Address, kind: str, body: Any, lane: str, msg_id: str | None,
                 ttl: float | None, to: str | None) -> str:
        seq = next(self.ids.seq)
        msg_id = msg_id or f"{self.ids.prefix}{seq:x}"
        type_name, data = encode_body(body)
        out = self.outgoing(msg_id, kind, type_name, body, data, seq, ttl, to)
        if lane == "fast":
            if not self.fast.send_now(addr, out):  # it also notes when (`fast_at`): a burst is told by the time
                self._queue(addr, out, lane)  # until the next
        elif lane != "reliable" or not self.carrier.write_now(addr, out):
            self._queue(addr, out, lane)
        return out.id

    def _queue(self, addr: Address, out: Outgoing, lane: str) -> None:
        """Queue a message for the sender pool (`SendQueues.queue`); a reliable one refused (its
        queue is full) is reported undeliverable."""
        if not self.queues.queue(addr, out, lane):
            self.on_undeliverable(addr, out.id, out.kind, out.body)

    # -- what the parts need of this endpoint (`FrameMaker`, `Deliveries`, `BeaconHost`) ------

    def outgoing(self, msg_id: str, kind: str, type_name: str | None, body: Any, data: bytes, seq: int,
                 ttl: float | None, to: str | None) -> Outgoing:
        """A message to queue or send: it expires `ttl` (the endpoint's own by default) from now."""
        return Outgoing(msg_id, kind, type_name, body, data, seq, self.clock() + (ttl or self.ttl), to or "")

    def envelope(self, out: Outgoing, to: str) -> bytes:
        return envelope_bytes(self.name, self.role, to, self.inst, self.address, out.seq, out.id, out.kind,
                              out.type, out.data)  # our own fields: no need to validate

    def frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes:
        if session is None:
            payload = self.envelope(out, out.to)
            length = 1 + len(payload)
            if HEADER.size + length > max_frame:
                raise FrameError("size", f"frame of {HEADER.size + length} bytes exceeds the limit of {max_frame}")
            return KIND.pack(length, PLAIN) + payload
        return session.seal(join_envelope(self.head(session.peer), item_of(out)), max_frame)

    def head(self, peer: str) -> bytes:
        """The envelope head of every message to `peer` (our own fields, made once per peer)."""
        head = self._heads.get(peer)
        if head is None:
            if len(self._heads) >= 4096:
                self._heads.clear()
            head = self._heads[peer] = head_bytes(self.name, self.role, peer, self.inst, self.address)
        return head

    def head_open(self, peer: str) -> bytes:
        """`head` without its closing brace, and a comma: the start of one message's envelope."""
        head = self._head_opens.get(peer)
        if head is None:
            if len(self._head_opens) >= 4096:
                self._head_opens.clear()
            head = self._head_opens[peer] = self.head(peer)[:-1] + b","
        return head

    def report_delivered(self, addr: Address, msg_id: str) -> None:
        self.on_delivered(addr, msg_id)

    def report_undeliverable(self, addr: Address, msg_id: str, kind: str, body: Any) -> None:
        self.on_undeliverable(addr, msg_id, kind, body)

    def tcp_write_now(self, addr: Address, out: Outgoing) -> bool:
        """Write a reliable message on its idle connection from the caller's thread (`ReliableDelivery.write_now`)."""
        return self.reliable.write_now(addr, out)

    def tcp_deliver(self, dest: Dest, out: Outgoing, session: Session | None) -> bool:
        """Deliver a reliable message over TCP on a sender thread (`ReliableDelivery.tcp_deliver`)."""
        return self.reliable.tcp_deliver(dest, out, session)

    def send_udp(self, frame: bytes, addr: Address) -> None:
        """A datagram on this endpoint's UDP socket (`UdpTcpWire.sendto`), never waiting."""
        if self.udp_loss and self._rng.random() < self.udp_loss:
            self.count("dropped.injected")
            return
        self._udp.sendto(frame, socket.MSG_DONTWAIT, addr)

    _sendto = send_udp  # the former name (a test sends a crafted datagram with it)

    # -- receiving (inbound.py) -----------------------------------------------------------

    def accept_frame(self, raw: bytes, channel: str, src: Address) -> Accepted:
        """Check a frame; count and log what fails; return its messages and their session, or None
        (`FramePath.accept_frame`)."""
        return self.inbound.accept_frame(raw, channel, src)

    def receive_datagram(self, raw: bytes, src: Address) -> None:
        """The UDP receive thread's whole path for one datagram (`FramePath.receive_datagram`)."""
        self.inbound.receive_datagram(raw, src)

    def _filter(self, sender: str, role: str) -> None:
        if self.inbound_filter is not None and not self.inbound_filter(sender, role):
            raise FrameError("unreachable", f"{sender} cannot reach {self.name} now")

    @property
    def refusals(self) -> dict[Address, str]:
        """Address -> why the agent there refused our certificate (another authority's, revoked)."""
        return self.sessions.refusals

    # -- what the receive loop needs of this endpoint (`ReceiverHost`) ----------------------

    @property
    def stopping(self) -> bool:
        return self.queues.stopping

    def deliver(self, msg: Message) -> None:
        if msg.kind not in INTERNAL:
            self.dispatch(msg)

    def deliver_once(self, msg: Message) -> None:
        if msg.kind in INTERNAL:
            return
        if self._seen.first_time(msg.sender, msg.id):
            self.dispatch(msg)
        else:
            self.count("duplicates")

    def receive_reliable(self, msg: Message, session: Session | None, reply: Callable[[bytes], None],
                         reply_later: Callable[[bytes], None]) -> None:
        """A reliable message arrived on a stream: acknowledge it (`reply`, on the receiving thread)
        and hand it on once per id. A kind of `held_kinds` is handed on with an `ack` to call when it
        is durable: the acknowledgement then goes by `reply_later` (from any thread) to the stream
        of its latest copy; a retry that arrives meanwhile is not handed on again, and one that
        arrives after it is acknowledged at once."""
        if msg.kind not in self.held_kinds:
            reply(self.ack_frame(msg, session))
            self.deliver_once(msg)
            return
        key = (msg.sender, msg.id)
        with self._held_lock:
            held = self._held.get(key)
            if held is not None:  # a retry while the first is not durable yet: acknowledged with it
                held.reply = reply_later
                first = False
            else:
                first = self._seen.first_time(msg.sender, msg.id)
                if first:
                    self._held[key] = _Held(session, reply_later)
                    if len(self._held) > HELD_LIMIT:
                        self._held.popitem(last=False)
                        self.count("dropped.held")
        if not first:
            self.count("duplicates")
            if held is None:  # acknowledged before: its acknowledgement was lost
                reply(self.ack_frame(msg, session))
            return
        msg.ack = functools.partial(self._acknowledge, key, msg)
        self.dispatch(msg)

    def _acknowledge(self, key: tuple[str, str], msg: Message) -> None:
        """Send the held acknowledgement of `msg` (once; from any thread)."""
        with self._held_lock:
            held = self._held.pop(key, None)
        if held is None:
            return
        try:
            held.reply(self.ack_frame(msg, held.session))
        except (OSError, FrameError, NetworkError):
            pass  # its stream is gone: the sender's retry is acknowledged at once
        self.count("acks.held")

    def ack_frame(self, msg: Message, session: Session | None) -> bytes:
        seq = next(self.ids.seq)
        ack = Outgoing(f"{self.ids.prefix}{seq:x}", "ack", None, msg.id, to_json(msg.id), seq, 0.0, msg.sender)
        return self.frame(ack, session, self.max_frame)

    def dispatch(self, msg: Message) -> None:
        if msg.role == CLIENT_ROLE and msg.reply not in self._clients:
            self._clients[msg.reply] = None
            if len(self._clients) > 1024:
                self._clients.popitem(last=False)
        try:
            self.on_message(msg)
        except Exception:
            self.log.exception("handling %s from %s failed", msg.kind, msg.sender)


def team_key(config_key: str | None, env_var: str = "ERNI_TEAM_KEY") -> bytes | None:
    """Return the team key from the config, else from the environment, else None."""
    value = config_key or os.environ.get(env_var)
    return value.encode() if value else None
