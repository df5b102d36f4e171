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
  parts above need of each other.

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
import itertools
import logging
import os
import random
import socket
import threading
from collections import OrderedDict, deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic_core import to_json

from erni.blackboard.clock import SYSTEM
from erni.blackboard.errors import ConfigError, NetworkError
from erni.logs import RateLimitedLog
from erni.transport.batching import FastMessages
from erni.transport.discovery import Beacons
from erni.transport.identity import Identity
from erni.transport.inbound import INTERNAL, Accepted, FramePath
from erni.transport.limits import Limits, TokenBucket
from erni.transport.outbox import Dest, Outgoing, SenderPool
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


class Endpoint(FastMessages, ReliableDelivery, Beacons, SenderPool):
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
        self._seq = itertools.count(1)
        self._id_prefix = os.urandom(6).hex() + "."  # message ids: unique per instance, cheap (no uuid)
        self.log = logging.getLogger(f"erni.{name}.transport")
        self._drops = RateLimitedLog(self.log)
        self.counters: dict[str, int] = {}
        self._counter_lock = threading.Lock()
        self._seen = SeenIds()
        self.address: Address = listen
        self.sessions = SessionTable(self, self.auth, name, self.inst, self.limits, max_frame, self.handshake_timeout,
                                 identity, self.revocations, self.log)
        self._beacon_bucket = TokenBucket(self.limits.beacons_total, clock=self.pace)
        self.inbound = FramePath(self, self._on_beacon)  # inbound.py: frames in, messages out
        self._clients: OrderedDict[Address, None] = OrderedDict()  # reply addresses of command-line clients heard
        # sender pool
        self._dests: dict[Address, Dest] = {}
        self._fast_at: dict[Address, float] = {}  # destination -> when the caller's last status to it was handled
        self._heads: dict[str, bytes] = {}  # peer -> the envelope head of messages to it (`_head`)
        self._head_opens: dict[str, bytes] = {}  # peer -> that head, open for one message's fields (`_head_open`)
        self._cond = threading.Condition()
        self._ready: deque[Dest] = deque()
        self._delayed: list[tuple[float, int, int, Dest]] = []
        self._tick = itertools.count()
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self.on_message: Callable[[Message], None] = lambda msg: None
        self.on_undeliverable: Callable[[Address, str, str, Any], None] = lambda addr, id, kind, body: None
        self.on_delivered: Callable[[Address, str], None] = lambda addr, id: None
        # the agent at an address refused our certificate (another authority's, revoked): the reason
        self.on_refused: Callable[[Address, str], None] = lambda addr, reason: None
        # would a broadcast beacon from this sender tell the owner anything? (None: always check it)
        self.hint_wanted: Callable[[str], bool] | None = None
        # the agent of this name has left (a wire that tells, as Zenoh's liveliness does; UDP never calls it)
        self.on_gone: Callable[[str], None] = lambda name: None
        self.carrier: Wire = UdpTcpWire(self)  # the wire the frames travel on (zenoh_wire.ZenohWire on Zenoh)
        self.wire = self.carrier.name
        # reliable kinds acknowledged only when the owner calls the message's `ack` (a task: once the
        # agent's journal holds it); any other is acknowledged as it arrives
        self.held_kinds: frozenset[str] = frozenset()
        self._held: OrderedDict[tuple[str, str], _Held] = OrderedDict()
        self._held_lock = threading.Lock()
        watch = getattr(clock, "on_advance", None)
        if callable(watch):  # a test's clock moved: the senders look again at what has expired
            watch(self._clock_moved)

    def _clock_moved(self) -> None:
        with self._cond:
            self._cond.notify_all()

    # -- counters -------------------------------------------------------------------------

    def count(self, name: str, n: int = 1) -> None:
        """Add to a named counter (thread-safe)."""
        with self._counter_lock:
            self.counters[name] = self.counters.get(name, 0) + n

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Bind the sockets and start the receive thread and the sender pool (NetworkError if it cannot)."""
        self._stopping = False
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
        self._threads = [rx, udp]
        for i in range(self.senders):
            t = threading.Thread(target=self._send_loop, name=f"erni-{self.name}-net-tx-{i}", daemon=True)
            t.start()
            self._threads.append(t)

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
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._wake_udp()
        deadline = self.pace() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - self.pace()))
        self._threads = []
        for dest in self._dests.values():
            close(dest.sock)
            dest.sock = None
        for s in (self._udp, self._tcp, self._disc, self._wake_r, self._wake_w):
            close(s)

    def _wake_udp(self) -> None:
        """Wake the thread blocked in the UDP socket's recvfrom, so that it sees `_stopping`: shut
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
        with self._cond:
            dest = self._dests.get(session.addr)
            if dest is not None:
                dest.hs_backoff = dest.hs_not_before = 0.0
                dest.hs_failures = 0
                if dest.has_work():
                    self._make_ready(dest)

    def session_lost(self, addr: Address) -> None:
        with self._cond:
            dest = self._dests.get(addr)
            if dest is not None and dest.has_work():
                self._make_ready(dest)

    def handshake_done(self, init: Initiation) -> None:
        with self._cond:
            dest = self._dests.get(init.addr)
            if dest is not None and dest.handshake is init:
                dest.handshake = None

    def send_crl(self, session: Session, der: bytes) -> None:
        self.send(session.addr, "crl", base64.b64encode(der).decode(), reliable=True, to=session.peer)

    # -- sending --------------------------------------------------------------------------

    def send(self, addr: Address, kind: str, body: BaseModel | Any = None, *, reliable: bool,
             msg_id: str | None = None, ttl: float | None = None, to: str | None = None) -> str:
        """Queue a message for `addr` (the agent `to`, when known); return its id. Never blocks."""
        if reliable:
            return self._enqueue(addr, kind, body, "reliable", msg_id, ttl, to)
        return self._send_status(addr, kind, body, msg_id, ttl, to)  # batching.py

    def _enqueue(self, addr: Address, kind: str, body: Any, lane: str, msg_id: str | None,
                 ttl: float | None, to: str | None) -> str:
        seq = next(self._seq)
        msg_id = msg_id or f"{self._id_prefix}{seq:x}"
        type_name, data = encode_body(body)
        out = self._outgoing(msg_id, kind, type_name, body, data, seq, ttl, to)
        if lane == "fast":
            if not self._send_now(addr, out):  # it also notes when (`_fast_at`): a burst is told by the time
                self._queue(addr, out, lane)  # until the next
        elif lane != "reliable" or not self.carrier.write_now(addr, out):
            self._queue(addr, out, lane)
        return out.id

    def _outgoing(self, msg_id: str, kind: str, type_name: str | None, body: Any, data: bytes, seq: int,
                  ttl: float | None, to: str | None) -> Outgoing:
        """A message to queue or send: it expires `ttl` (the endpoint's own by default) from now."""
        return Outgoing(msg_id, kind, type_name, body, data, seq, self.clock() + (ttl or self.ttl), to or "")

    def _queue(self, addr: Address, out: Outgoing, lane: str) -> None:
        """Queue a message for the sender pool (a reliable one is refused when its queue is full; the
        fast and announcement queues drop their oldest)."""
        msg_id, kind = out.id, out.kind
        undeliverable = False
        with self._cond:
            if self._stopping:
                return
            dest = self._dest_for(addr)
            if lane == "reliable":
                if len(dest.reliable) >= self.queue_limit:
                    self.count("dropped.queue_full")
                    self._drops.warning("queue", f"reliable queue to {addr[0]}:{addr[1]} is full "
                                        f"({self.queue_limit}); refusing {kind} {msg_id}")
                    undeliverable = True
                else:
                    dest.reliable.append(out)
            else:
                queue = dest.fast if lane == "fast" else dest.announce
                if len(queue) >= self.queue_limit:
                    queue.popleft()
                    self.count("dropped.fast_oldest")
                queue.append(out)
            if not undeliverable:
                self._make_ready(dest)
        if undeliverable:
            self.on_undeliverable(addr, msg_id, kind, out.body)

    def _caller_session(self, addr: Address, out: Outgoing) -> tuple[bool, Session | None]:
        """Whether the caller's thread may send `out` to `addr` itself, and the session to seal it in.

        Not while starting or stopping, and only in a confirmed session with the intended peer: a
        handshake to drive, or a wrong peer to report, is the sender pool's work.
        """
        if not self._threads or self._stopping:
            return False, None
        if self.auth is None:
            return True, None
        session = self.sessions.usable(addr)
        if session is None:
            return False, None
        return not (out.to and out.to != session.peer), session

    def _envelope(self, out: Outgoing, to: str) -> bytes:
        return envelope_bytes(self.name, self.role, to, self.inst, self.address, out.seq, out.id, out.kind,
                              out.type, out.data)  # our own fields: no need to validate

    def _frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes:
        if session is None:
            payload = self._envelope(out, out.to)
            length = 1 + len(payload)
            if HEADER.size + length > max_frame:
                raise FrameError("size", f"frame of {HEADER.size + length} bytes exceeds the limit of {max_frame}")
            return KIND.pack(length, PLAIN) + payload
        return session.seal(join_envelope(self._head(session.peer), self._item(out)), max_frame)

    def send_udp(self, frame: bytes, addr: Address) -> None:
        """A datagram on this endpoint's UDP socket (`UdpTcpWire.sendto`), never waiting."""
        if self.udp_loss and self._rng.random() < self.udp_loss:
            self.count("dropped.injected")
            return
        self._udp.sendto(frame, socket.MSG_DONTWAIT, addr)

    _sendto = send_udp  # the former name (a test sends a crafted datagram with it)

    # -- receiving ------------------------------------------------------------------------

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
        return self._stopping

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
        seq = next(self._seq)
        ack = Outgoing(f"{self._id_prefix}{seq:x}", "ack", None, msg.id, to_json(msg.id), seq, 0.0, msg.sender)
        return self._frame(ack, session, self.max_frame)

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
