"""An agent's network endpoint: one receive thread, a pool of sender threads, TCP and UDP, sessions.

Every message to a peer travels in a session with that peer's current instance (`session.py`):
the first message to an address starts a handshake, which the sender pool drives without
blocking (the handshake frames are retransmitted on a timer; the answer wakes the
destination up again). Reliable messages travel over TCP, one connection per destination,
each acknowledged by message id, retried with exponential backoff until their time to live
runs out, and sent in order per destination (one sender thread serves a destination at a
time). Fast messages travel as UDP datagrams from a bounded queue that drops the oldest.
Beacons for unknown receivers are signed instead (`announce`). Nothing here ever runs inside a
blackboard transaction, and no caller ever waits on a socket: when a session is up and nothing
is queued for the destination, the caller's thread seals a status and hands it to the
non-blocking UDP socket itself, and writes a reliable message on an idle connection without
waiting (a sender thread then waits for its acknowledgement); whatever the socket does not take
at once is queued for the sender pool, which keeps the order.

Before a frame is authenticated nothing is spent without a bound (`limits.py`): connections
per host and in total, bytes of incomplete frames, idle and partial-frame timeouts, handshakes
and beacon signatures per second.
"""

from __future__ import annotations

import base64
import errno
import functools
import hashlib
import heapq
import itertools
import json
import logging
import math
import os
import random
import selectors
import socket
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic_core import to_json

from erni.blackboard.errors import ConfigError, NetworkError
from erni.transport.identity import Identity, IdentityError, read_crl, write_public
from erni.transport.limits import HostBuckets, Limits, TokenBucket
from erni.transport.session import (
    Auth,
    CertificateRefused,
    IdentityAuth,
    Initiation,
    Session,
    TeamKeyAuth,
    complete,
    cut_signed,
    initiate,
    parse_hello,
    respond,
)
from erni.transport.wire import (
    BATCH_BYTES,
    BEACON,
    DATA,
    DEFAULT_MAX_FRAME,
    HEADER,
    HELLO,
    HINT,
    KIND,
    KINDS,
    PLAIN,
    REFUSAL,
    REPLY,
    SESSION_END,
    UDP_MAX_FRAME,
    FrameError,
    Message,
    SeenIds,
    StreamDecoder,
    batch_payload,
    body_of,
    check_frame,
    encode_body,
    envelope_bytes,
    head_bytes,
    item_bytes,
    join_envelope,
    parse_batch,
    parse_envelope,
    parse_item,
    parse_typed,
)

Address = tuple[str, int]

CLIENT_ROLE = "cli"
"""The role of a command-line client's endpoint (`erni task`, `erni watch` ...): never a peer."""

COALESCE = 20e-6
"""A status sent to a destination less than this (s) after the caller's previous send to it
returned is part of a burst (the caller waited for nothing in between): it is gathered with the
burst's next ones, and the caller seals and sends each `BATCH_BYTES` of them as one datagram. A
robot's statuses, a request waiting for its reply and a ping-pong are far slower than this: they
go out one to a datagram, at once."""

FLUSH_AFTER = 200e-6
"""How long (s) the last, partly filled datagram of a burst waits for more before the sender
pool sends it."""

InboundFilter = Callable[[str, str], bool]
"""`(sender, role) -> bool`: whether a verified frame may be delivered (False: dropped and counted)."""

INTERNAL = ("ack", "crl")  # kinds the endpoint handles itself

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


@dataclass
class _Outgoing:
    id: str
    kind: str
    type: str | None
    body: Any  # as given to send(): what on_undeliverable hands back
    data: bytes  # the body's JSON, serialised when queued
    seq: int  # numbered when queued: a receiver orders a sender's messages as they were sent
    deadline: float
    to: str = ""
    attempts: int = 0
    written: socket.socket | None = None  # the connection the caller's thread wrote it on (`_write_now`)
    rest: bytes = b""  # what the socket did not take then


@dataclass
class _Dest:
    addr: Address
    reliable: deque[_Outgoing] = field(default_factory=deque)
    fast: deque[_Outgoing] = field(default_factory=deque)
    announce: deque[_Outgoing] = field(default_factory=deque)
    sock: socket.socket | None = None
    sock_used: float = 0.0
    decoder: StreamDecoder | None = None
    busy: bool = False
    ready: bool = False
    again: bool = False
    gen: int = 0
    next_try: float = 0.0
    backoff: float = 0.0
    handshake: Initiation | None = None
    hs_backoff: float = 0.0
    hs_not_before: float = 0.0
    batch: _Batch | None = None  # statuses of a burst the caller gathers into one datagram

    def has_work(self) -> bool:
        return bool(self.fast or self.reliable or self.announce or self.batch)


@dataclass
class _Batch:
    """Fast messages gathered for one datagram: in a session, their items sealed together under
    one head (up to `BATCH_BYTES`); without one (insecure), a single plain frame."""

    session: Session | None
    head: bytes = b""  # the envelope head the datagram's messages share
    outs: list[_Outgoing] = field(default_factory=list)
    items: list[bytes] = field(default_factory=list)
    size: int = 0

    def fits(self, item: bytes) -> bool:
        """Whether a message with this item may join the datagram (`[head,[item,...]]`)."""
        return not self.outs or self.session is not None and len(self.head) + 4 + self.size + len(item) + 1 <= BATCH_BYTES

    def add(self, out: _Outgoing, item: bytes) -> None:
        self.outs.append(out)
        self.items.append(item)
        self.size += len(item) + 1


@dataclass
class _Conn:
    sock: socket.socket
    peer: Address
    decoder: StreamDecoder
    opened: float
    last_frame: float
    partial_since: float | None = None
    authed: bool = False


class _RateLimitedLog:
    """Log each reason at most once per `period` seconds, with the count since last time."""

    def __init__(self, log: logging.Logger, period: float = 5.0):
        self.log, self.period = log, period
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, reason: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) >= self.period:
            more = self._suppressed.pop(reason, 0)
            self._last[reason] = now
            self.log.warning("%s%s", text, f" (+{more} more since last report)" if more else "")
        else:
            self._suppressed[reason] = self._suppressed.get(reason, 0) + 1


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
                 revocations: str | Path | None = None, handshake_timeout: float | None = None):
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
        self.identity = identity
        self.revocations = Path(revocations) if revocations else None
        self._crl_mtime = 0.0
        self._listen = listen
        self.insecure = self.auth is None
        self.senders = senders
        self.queue_limit = queue_limit
        self.max_frame = max_frame
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
        self._drops = _RateLimitedLog(self.log)
        self._last_fault = -1e9  # when a fault of the frame path was last logged (monotonic)
        self.counters: dict[str, int] = {}
        self._counter_lock = threading.Lock()
        self._seen = SeenIds()
        # sessions (guarded by _sess_lock)
        self._sess_lock = threading.RLock()
        self._by_sid: OrderedDict[bytes, Session] = OrderedDict()
        self._by_addr: dict[Address, Session] = {}
        self._answers: dict[str, tuple[bytes, Session, float]] = {}  # digest of an 'H' -> our 'R'
        self._initiations: dict[str, tuple[Initiation, _Dest]] = {}
        self._completed: OrderedDict[str, None] = OrderedDict()
        self._instances: OrderedDict[tuple[str, str], int] = OrderedDict()
        self._last_epoch: dict[str, int] = {}
        self._hs_hosts = HostBuckets(self.limits.handshakes_per_host)
        self._hs_total = TokenBucket(self.limits.handshakes_total)
        self._beacon_bucket = TokenBucket(self.limits.beacons_total)
        self._hint_hosts = HostBuckets(2.0)
        self._refusal_hosts = HostBuckets(2.0)
        self.refusals: dict[Address, str] = {}  # address -> why the agent there refused our certificate
        self._clients: OrderedDict[Address, None] = OrderedDict()  # reply addresses of command-line clients heard
        # sender pool
        self._dests: dict[Address, _Dest] = {}
        self._fast_at: dict[Address, float] = {}  # destination -> when the caller's last status to it was handled
        self._heads: dict[str, bytes] = {}  # peer -> the envelope head of messages to it (`_head`)
        self._cond = threading.Condition()
        self._ready: deque[_Dest] = deque()
        self._delayed: list[tuple[float, int, int, _Dest]] = []
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
        self.address: Address = listen

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
        self._udp.setblocking(False)
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
        rx = threading.Thread(target=self._receive_loop, name=f"erni-{self.name}-net-rx", daemon=True)
        rx.start()
        self._threads = [rx]
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
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        self._threads = []
        for dest in self._dests.values():
            _close(dest.sock)
            dest.sock = None
        for s in (self._udp, self._tcp, self._disc, self._wake_r, self._wake_w):
            _close(s)

    # -- sessions -------------------------------------------------------------------------

    def session_with(self, addr: Address) -> Session | None:
        """The confirmed session used to send to `addr` now (None: the next send starts one)."""
        with self._sess_lock:
            session = self._by_addr.get(addr)
            if session is None or session.stale or session.sid not in self._by_sid:
                return None
            return session

    def _epoch(self, name: str, inst: str) -> int:
        """This receiver's count of `name`'s instances: 1, 2 ... in the order they were confirmed."""
        key = (name, inst)
        epoch = self._instances.get(key)
        if epoch is None:
            epoch = self._instances[key] = self._last_epoch.get(name, 0) + 1
            self._last_epoch[name] = epoch
            if len(self._instances) > 8192:
                self._instances.popitem(last=False)
        return epoch

    def _confirm(self, session: Session) -> None:
        """A session is trusted: send on it from now on; forget older instances of that peer there."""
        with self._sess_lock:
            session.confirmed = True
            session.epoch = self._epoch(session.peer, session.inst)
            self._by_sid[session.sid] = session
            for sid, other in list(self._by_sid.items()):
                if other is not session and other.addr == session.addr and other.inst != session.inst:
                    del self._by_sid[sid]
            self._by_addr[session.addr] = session
            if len(self._by_sid) > self.limits.max_sessions:  # the least recently used go first
                idle = sorted(self._by_sid.values(), key=lambda s: max(s.last_rx, s.last_tx))
                for old in idle[:len(self._by_sid) - self.limits.max_sessions]:
                    del self._by_sid[old.sid]
        if self.identity is not None and session.crl < self.identity.trust.crl_number:
            self._push_crl(session)
        with self._cond:
            dest = self._dests.get(session.addr)
            if dest is not None:
                dest.hs_backoff = dest.hs_not_before = 0.0
                if dest.has_work():
                    self._make_ready(dest)

    def _forget(self, keep: Callable[[Session], bool]) -> int:
        with self._sess_lock:
            gone = [sid for sid, s in self._by_sid.items() if not keep(s)]
            for sid in gone:
                session = self._by_sid.pop(sid)
                if self._by_addr.get(session.addr) is session:
                    del self._by_addr[session.addr]
        return len(gone)

    # -- revocation -----------------------------------------------------------------------

    def _push_crl(self, session: Session) -> None:
        assert self.identity is not None
        der = self.identity.trust.crl_der
        if der:
            self.send(session.addr, "crl", base64.b64encode(der).decode(), reliable=True, to=session.peer)

    def _adopt_crl(self, der: bytes, source: str) -> None:
        """Take a newer revocation list: drop revoked peers, keep it, pass it on."""
        if self.identity is None or not self.identity.trust.adopt(der):
            return
        trust = self.identity.trust
        self.log.warning("revocation list %d from %s: %d certificate(s) revoked", trust.crl_number, source,
                         len(trust.revoked))
        if self.revocations is not None and source != str(self.revocations):
            try:  # kept before it is acted on: a restart never forgets a revocation it applied
                write_public(self.revocations, der)
                self._crl_mtime = self.revocations.stat().st_mtime
            except OSError as err:
                self.log.warning("cannot keep the revocation list in %s: %s", self.revocations, err)
        dropped = self._forget(lambda s: s.serial is None or s.serial not in trust.revoked)
        if dropped:
            self.count("sessions.revoked", dropped)
        with self._sess_lock:
            behind = [s for s in self._by_sid.values() if s.confirmed and s.crl < trust.crl_number]
        for session in behind:
            session.crl = trust.crl_number
            self._push_crl(session)

    def _reload_crl(self) -> None:
        if self.revocations is None or self.identity is None:
            return
        try:
            mtime = self.revocations.stat().st_mtime
        except OSError:
            return
        if mtime == self._crl_mtime:
            return
        self._crl_mtime = mtime
        try:
            from cryptography.hazmat.primitives.serialization import Encoding

            der = read_crl(self.revocations).public_bytes(Encoding.DER)
        except IdentityError as err:
            self.log.warning("%s", err)
            return
        self._adopt_crl(der, str(self.revocations))

    # -- sending --------------------------------------------------------------------------

    def send(self, addr: Address, kind: str, body: BaseModel | Any = None, *, reliable: bool,
             msg_id: str | None = None, ttl: float | None = None, to: str | None = None) -> str:
        """Queue a message for `addr` (the agent `to`, when known); return its id. Never blocks."""
        return self._enqueue(addr, kind, body, "reliable" if reliable else "fast", msg_id, ttl, to)

    def announce(self, addr: Address, kind: str, body: BaseModel | Any = None) -> str:
        """Queue a signed, sessionless datagram for receivers not known yet (beacons)."""
        return self._enqueue(addr, kind, body, "announce", None, None, None)

    def _enqueue(self, addr: Address, kind: str, body: Any, lane: str, msg_id: str | None,
                 ttl: float | None, to: str | None) -> str:
        seq = next(self._seq)
        msg_id = msg_id or f"{self._id_prefix}{seq:x}"
        type_name, data = encode_body(body)
        out = _Outgoing(msg_id, kind, type_name, body, data, seq, time.monotonic() + (ttl or self.ttl), to or "")
        if lane == "fast":
            sent = self._send_now(addr, out)
            self._fast_at[addr] = time.monotonic()  # a burst is told by the time until the next
            if sent:
                return msg_id
        if lane == "reliable" and self._write_now(addr, out):
            return msg_id
        undeliverable = False
        with self._cond:
            if self._stopping:
                return msg_id
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
            self.on_undeliverable(addr, msg_id, kind, body)
        return msg_id

    def _caller_session(self, addr: Address, out: _Outgoing) -> tuple[bool, Session | None]:
        """Whether the caller's thread may send `out` to `addr` itself, and the session to seal it in.

        Not while starting or stopping, and only in a confirmed session with the intended peer: a
        handshake to drive, or a wrong peer to report, is the sender pool's work.
        """
        if not self._threads or self._stopping:
            return False, None
        if self.auth is None:
            return True, None
        session = self.session_with(addr)
        return session is not None and not (out.to and out.to != session.peer), session

    def _send_now(self, addr: Address, out: _Outgoing) -> bool:
        """Send a fast message from the caller's thread when that cannot wait: True when it is done.

        Only in a confirmed session (no handshake to drive), with nothing queued before it for
        that destination, and only what the socket takes at once: the UDP socket never blocks
        (a full send buffer raises at once), and then the message is queued for the sender pool.
        A status of a burst (`COALESCE`) is gathered into the destination's batch instead.
        """
        usable, session = self._caller_session(addr, out)
        if not usable:
            return False
        dest = self._dests.get(addr)
        if dest is not None and (dest.fast or dest.announce):
            return False  # keep the order of what is queued already
        if session is not None and (dest is not None and dest.batch is not None
                                    or time.monotonic() - self._fast_at.get(addr, -math.inf) < COALESCE):
            return self._gather(addr, out, session)  # a burst: several statuses to a datagram
        single = self._batch(session)
        single.add(out, self._item(out) if session is not None else b"")
        if not self._send_datagram(addr, single):
            self.count("sent.deferred")
            return False  # the socket's buffer is full: the pool sends it when it drains
        return True

    def _gather(self, addr: Address, out: _Outgoing, session: Session) -> bool:
        """Add a status of a burst to its destination's open batch; send the batch from the
        caller's thread once the next would not fit, and leave what is left at the burst's end
        to the sender pool (`FLUSH_AFTER`)."""
        item = self._item(out)
        full: _Batch | None = None
        with self._cond:
            if self._stopping:
                return True
            dest = self._dest_for(addr)
            if dest.fast or dest.announce:
                return False  # queued meanwhile: it goes after them, in order
            batch = dest.batch
            if batch is not None and (batch.session is not session or not batch.fits(item)):
                full, batch = batch, None
            if batch is None:
                batch = dest.batch = self._batch(session)
                self._schedule(dest, time.monotonic() + FLUSH_AFTER)
            batch.add(out, item)
        if full is not None and not self._send_datagram(addr, full):
            self._requeue(dest, full.outs)
            with self._cond:
                self._make_ready(dest)
        return True

    def _dest_for(self, addr: Address) -> _Dest:
        """The sender pool's state for `addr`, made on first use (under self._cond)."""
        dest = self._dests.get(addr)
        if dest is None:
            dest = self._dests[addr] = _Dest(addr)
        return dest

    def _send_datagram(self, addr: Address, batch: _Batch) -> bool:
        """Send a batch of fast messages as one datagram. False when the socket's buffer is full
        (nothing was sent)."""
        max_frame = min(self.max_frame, UDP_MAX_FRAME)
        outs = batch.outs
        try:
            if batch.session is None:
                frame = self._frame(outs[0], None, max_frame)
            else:
                frame = batch.session.seal(batch_payload(batch.head, batch.items), max_frame)
            self._sendto(frame, addr)
        except (BlockingIOError, InterruptedError):
            return False
        except FrameError as err:
            self.count("dropped.too_big")
            self._drops.warning("too_big", f"not sent to {addr}: {err}")
        except OSError as err:
            self.count("dropped.fast_error")
            self._drops.warning("udp", f"UDP send to {addr[0]}:{addr[1]} failed: {err}")
        else:
            self.count("sent.fast", len(outs))
            if len(outs) > 1:
                self.count("sent.batched", len(outs))
        return True

    def _write_now(self, addr: Address, out: _Outgoing) -> bool:
        """Write a reliable message on its destination's open connection from the caller's thread.

        Only when that destination is idle (nothing queued, no sender serving it, no backoff) in a
        confirmed session; the write never blocks (what the socket does not take at once is left
        to the sender), and a sender thread then waits for the acknowledgement, retries and
        reports as for any reliable message. True when the message is queued that way.
        """
        usable, session = self._caller_session(addr, out)
        if not usable:
            return False
        now = time.monotonic()
        with self._cond:
            dest = self._dests.get(addr)
            if (dest is None or dest.busy or dest.ready or dest.has_work() or dest.sock is None
                    or now < dest.next_try or now - dest.sock_used > self.limits.idle_timeout / 2):
                return False
            dest.busy = True  # no sender touches this connection while the caller writes on it
            sock = dest.sock
        written, frame = 0, b""
        try:
            frame = self._frame(out, session, self.max_frame)
            written = os.write(sock.fileno(), frame)  # the socket is non-blocking (it has a timeout)
        except (BlockingIOError, InterruptedError):
            self.count("sent.deferred")
        except (OSError, FrameError):
            frame = b""  # a broken connection or a frame too big: the sender finds out and reports
        with self._cond:
            if frame:
                out.written, out.rest = sock, frame[written:]
                dest.sock_used = now
                if out.rest:
                    self.count("sent.partial")
            dest.reliable.append(out)
            dest.busy = dest.again = False
            self._make_ready(dest)
        return True

    def _make_ready(self, dest: _Dest) -> None:
        # under self._cond: serve this destination now (a delayed wake-up of it becomes stale)
        if dest.busy:
            dest.again = True
        elif not dest.ready:
            dest.gen += 1
            dest.ready = True
            self._ready.append(dest)
            self._cond.notify()

    def _schedule(self, dest: _Dest, when: float) -> None:
        # under self._cond: serve this destination at `when`
        if dest.busy or dest.ready:
            return
        dest.gen += 1
        earliest = not self._delayed or when < self._delayed[0][0]
        heapq.heappush(self._delayed, (when, next(self._tick), dest.gen, dest))
        if earliest:  # else a sender already waits until an earlier time, and then looks again
            self._cond.notify()

    def _head(self, peer: str) -> bytes:
        """The envelope head of every message to `peer` (our own fields, made once per peer)."""
        head = self._heads.get(peer)
        if head is None:
            if len(self._heads) >= 4096:
                self._heads.clear()
            head = self._heads[peer] = head_bytes(self.name, self.role, peer, self.inst, self.address)
        return head

    def _batch(self, session: Session | None) -> _Batch:
        """An empty datagram for messages to `session`'s peer, with the head they will share."""
        if session is None:
            return _Batch(None)
        return _Batch(session, self._head(session.peer))

    def _item(self, out: _Outgoing) -> bytes:
        return item_bytes(out.seq, out.id, out.kind, out.type, out.data)

    def _envelope(self, out: _Outgoing, to: str) -> bytes:
        return envelope_bytes(self.name, self.role, to, self.inst, self.address, out.seq, out.id, out.kind,
                              out.type, out.data)  # our own fields: no need to validate

    def _frame(self, out: _Outgoing, session: Session | None, max_frame: int) -> bytes:
        if session is None:
            payload = self._envelope(out, out.to)
            length = 1 + len(payload)
            if HEADER.size + length > max_frame:
                raise FrameError("size", f"frame of {HEADER.size + length} bytes exceeds the limit of {max_frame}")
            return KIND.pack(length, PLAIN) + payload
        return session.seal(join_envelope(self._head(session.peer), self._item(out)), max_frame)

    def _sendto(self, frame: bytes, addr: Address) -> None:
        if self.udp_loss and self._rng.random() < self.udp_loss:
            self.count("dropped.injected")
            return
        self._udp.sendto(frame, addr)

    def _send_loop(self) -> None:
        while True:
            with self._cond:
                dest: _Dest | None = None
                while not self._stopping:
                    now = time.monotonic()
                    while self._delayed and self._delayed[0][0] <= now:
                        _, _, gen, d = heapq.heappop(self._delayed)
                        if gen == d.gen:
                            self._make_ready(d)
                    if self._ready:
                        dest = self._ready.popleft()
                        dest.ready = False
                        dest.busy = True
                        if self._delayed:  # this thread may have been the one waiting for the earliest
                            self._cond.notify()
                        break
                    self._cond.wait(self._delayed[0][0] - now if self._delayed else None)
                if self._stopping or dest is None:
                    return
            when: float | None = None
            try:
                when = self._service(dest)
            except Exception:  # never lose a sender thread
                self.log.exception("sender failed on %s:%s", *dest.addr)
                when = time.monotonic() + self.retry_max
            with self._cond:
                dest.busy = False
                again, dest.again = dest.again, False
                if dest.has_work():
                    if again or when is None or when <= time.monotonic():
                        self._make_ready(dest)
                    else:
                        self._schedule(dest, when)

    def _service(self, dest: _Dest) -> float | None:
        """Send what can go now; return when to come back (None: when there is new work)."""
        with self._cond:
            batch, dest.batch = dest.batch, None
        if batch is not None and not self._send_datagram(dest.addr, batch):
            self._requeue(dest, batch.outs)
            return time.monotonic() + 0.005
        while True:  # signed announcements first: they need no session
            with self._cond:
                out = dest.announce.popleft() if dest.announce else None
            if out is None:
                break
            self._announce(dest, out)
        session: Session | None = None
        if self.auth is not None:
            session = self.session_with(dest.addr)
            if session is None:
                return self._handshake_step(dest)
        while True:  # fast messages: they are cheap and never wait
            with self._cond:
                outs = [dest.fast.popleft() for _ in range(min(len(dest.fast), 64))]
            if not outs:
                break
            retry = self._send_fast(dest, session, outs)
            if retry is not None:
                return retry
        for _ in range(32):  # then a batch of reliable ones, in order
            now = time.monotonic()
            if now < dest.next_try:
                return dest.next_try
            if self._stopping or dest.fast:
                return None  # status queued meanwhile goes first (and in the order it was queued)
            with self._cond:
                out = dest.reliable[0] if dest.reliable else None
            if out is None:
                return None
            if self._expired(dest, out, now):
                continue
            if session is not None and out.to and out.to != session.peer:
                with self._cond:
                    dest.reliable.popleft()
                self.count("dropped.wrong_peer")
                self._drops.warning("wrong_peer", f"{out.kind} {out.id} not delivered: {dest.addr[0]}:"
                                    f"{dest.addr[1]} is {session.peer}, not {out.to}")
                self.on_undeliverable(dest.addr, out.id, out.kind, out.body)
                continue
            out.attempts += 1
            if self._deliver(dest, out, session):
                with self._cond:
                    if dest.reliable and dest.reliable[0] is out:
                        dest.reliable.popleft()
                dest.backoff = 0.0
                self.count("sent.reliable")
                self.on_delivered(dest.addr, out.id)
            else:
                _close(dest.sock)
                dest.sock = None
                dest.backoff = min(self.retry_max, max(self.retry_base, dest.backoff * 2))
                dest.next_try = time.monotonic() + dest.backoff
                self.count("retries")
                if session is not None and self.session_with(dest.addr) is None:
                    return None  # the peer does not know the session: a new handshake, at once
                return dest.next_try
        return None

    def _send_fast(self, dest: _Dest, session: Session | None, outs: list[_Outgoing]) -> float | None:
        """Send queued fast messages, in a session as many to a datagram as fit in `BATCH_BYTES`;
        return when to try again if the socket's buffer is full (what is left goes back in front)."""
        batch = self._batch(session)
        for k, out in enumerate(outs):
            if session is not None and out.to and out.to != session.peer:
                self.count("dropped.wrong_peer")
                self._drops.warning("wrong_peer", f"not sent: {dest.addr[0]}:{dest.addr[1]} is "
                                    f"{session.peer}, not {out.to}")
                continue
            item = self._item(out) if session is not None else b""
            if not batch.fits(item):
                if not self._send_datagram(dest.addr, batch):
                    self._requeue(dest, batch.outs + outs[k:])
                    return time.monotonic() + 0.005
                batch = self._batch(session)
            batch.add(out, item)
        if batch.outs and not self._send_datagram(dest.addr, batch):
            self._requeue(dest, batch.outs)
            return time.monotonic() + 0.005
        return None

    def _requeue(self, dest: _Dest, outs: list[_Outgoing]) -> None:
        """Put fast messages the socket did not take back in front of the queue, in their order."""
        with self._cond:
            room = max(0, self.queue_limit - len(dest.fast))
            dest.fast.extendleft(reversed(outs[:room]))
            if len(outs) > room:
                self.count("dropped.fast_oldest", len(outs) - room)
        self.count("sent.deferred")

    def _expired(self, dest: _Dest, out: _Outgoing, now: float) -> bool:
        if now <= out.deadline:
            return False
        with self._cond:
            if dest.reliable and dest.reliable[0] is out:
                dest.reliable.popleft()
        self.count("dropped.expired")
        self._drops.warning("expired", f"gave up on {out.kind} {out.id} to "
                            f"{dest.addr[0]}:{dest.addr[1]} after {out.attempts} attempt(s)")
        self.on_undeliverable(dest.addr, out.id, out.kind, out.body)
        return True

    def _handshake_step(self, dest: _Dest) -> float | None:
        """Start, retransmit or give up a handshake with `dest`; return when to look again."""
        assert self.auth is not None
        now = time.monotonic()
        while True:
            with self._cond:
                out = dest.reliable[0] if dest.reliable else None
            if out is None or not self._expired(dest, out, now):
                break
        if not dest.has_work():
            return None
        init = dest.handshake
        if init is None:
            if now < dest.hs_not_before:
                return dest.hs_not_before
            with self._cond:
                first = dest.reliable[0] if dest.reliable else dest.fast[0] if dest.fast else None
            expect = first.to if first is not None else ""
            init = initiate(self.auth, self.inst, self.address, dest.addr, expect)
            dest.handshake = init
            with self._sess_lock:
                self._initiations[init.digest] = (init, dest)
        elif now - init.started > self.handshake_timeout:
            with self._sess_lock:
                self._initiations.pop(init.digest, None)
            dest.handshake = None
            dest.hs_backoff = min(5.0, max(0.5, dest.hs_backoff * 2))
            dest.hs_not_before = now + dest.hs_backoff
            with self._cond:
                dropped = len(dest.fast)
                dest.fast.clear()
            self.count("handshakes.failed")
            if dropped:
                self.count("dropped.no_session", dropped)
            self._drops.warning("handshake", f"no answer to a handshake with {dest.addr[0]}:{dest.addr[1]}"
                                f"{' (' + init.expect + ')' if init.expect else ''} within "
                                f"{self.handshake_timeout:g} s; {dropped} status message(s) dropped")
            return dest.hs_not_before if dest.reliable else None
        if now >= init.next_try:
            try:
                self._sendto(init.frame, dest.addr)
                self.count("handshakes.sent")
            except OSError as err:
                self._drops.warning("udp", f"handshake to {dest.addr[0]}:{dest.addr[1]} failed: {err}")
            init.attempts += 1
            init.next_try = now + 0.1 * 2 ** min(init.attempts, 3)
        return min(init.next_try, init.started + self.handshake_timeout + 0.001)

    def _announce(self, dest: _Dest, out: _Outgoing) -> None:
        try:
            frame = self._frame(replace(out, to=""), None, UDP_MAX_FRAME) if self.auth is None else \
                self.auth.sign(BEACON, self._envelope(out, ""))
            self._sendto(frame, dest.addr)
            self.count("sent.announce")
        except (OSError, FrameError) as err:
            self.count("dropped.fast_error")
            self._drops.warning("udp", f"beacon to {dest.addr[0]}:{dest.addr[1]} failed: {err}")

    def _deliver(self, dest: _Dest, out: _Outgoing, session: Session | None) -> bool:
        written, out.written = out.written, None
        try:
            if written is not None and written is dest.sock:
                frame = out.rest  # written by the caller's thread (`_write_now`): the rest, then the ack
            else:
                frame = self._frame(out, session, self.max_frame)
        except FrameError as err:
            with self._cond:
                dest.reliable.popleft()
            self.count("dropped.too_big")
            self._drops.warning("too_big", f"not sent: {err}")
            return True
        try:
            now = time.monotonic()
            if dest.sock is not None and now - dest.sock_used > self.limits.idle_timeout / 2:
                _close(dest.sock)  # the receiver closes idle connections: never send into one
                dest.sock = None
            if dest.sock is None:
                dest.sock = socket.create_connection(dest.addr, timeout=self.connect_timeout)
                dest.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                dest.decoder = StreamDecoder(self.max_frame)
            dest.sock_used = now
            dest.sock.settimeout(self.ack_timeout)
            if frame:
                dest.sock.sendall(frame)
            deadline = time.monotonic() + self.ack_timeout
            while time.monotonic() < deadline:
                data = dest.sock.recv(65536)
                if not data:
                    return False
                assert dest.decoder is not None
                for raw in dest.decoder.feed(data):
                    got = self._accept(raw, "tcp", dest.addr)
                    if got is not None and any(m.kind == "ack" and m.body == out.id for m in got[0]):
                        return True
                if session is not None and session.stale:
                    return False  # the peer does not know this session any more
            return False
        except (OSError, FrameError) as err:
            if dest.addr in self._clients and isinstance(err, ConnectionRefusedError):
                self._client_gone(dest)
                return False
            if dest.addr in self._clients and isinstance(err, ConnectionResetError | BrokenPipeError):
                return False  # a client exiting closes its streams: the next try finds out (quietly)
            self._drops.warning("link", f"link to {dest.addr[0]}:{dest.addr[1]} failed: {err}")
            return False

    def _client_gone(self, dest: _Dest) -> None:
        """A command-line client's port refuses connections: it exited (as `erni task` does once its
        task runs). What was queued for it is dropped at once, quietly: no retries, no warnings."""
        with self._cond:
            reliable, fast = list(dest.reliable), len(dest.fast)
            dest.reliable.clear()
            dest.fast.clear()
        self.count("dropped.client_gone", len(reliable) + fast)
        self.log.debug("client at %s:%d has gone: %d message(s) for it dropped", *dest.addr, len(reliable) + fast)
        for out in reliable:
            self.on_undeliverable(dest.addr, out.id, out.kind, out.body)

    # -- receiving ------------------------------------------------------------------------

    def _dropped(self, channel: str, err: FrameError) -> None:
        self.count(f"dropped.{err.reason}")
        self._drops.warning(err.reason, f"dropped a {channel} frame: {err}")

    def _accept(self, raw: bytes, channel: str, src: Address) -> tuple[list[Message], Session | None] | None:
        """Check a frame; count and log what fails; return its messages (several in a batch of
        statuses) and their session, or None. A fault of the frame path itself (any exception
        other than a FrameError) drops the frame and is logged with its traceback, rate-limited:
        one frame must never end the receive thread."""
        try:
            return self._accept_frame(raw, channel, src)
        except Exception:
            self.count("dropped.fault")
            now = time.monotonic()
            if now - self._last_fault >= 5.0:
                self._last_fault = now
                self.log.exception("dropped a %s frame of %d bytes from %s: the frame path failed on it",
                                   channel, len(raw), src[0] if src else "?")
            return None

    def _accept_frame(self, raw: bytes, channel: str, src: Address) -> tuple[list[Message], Session | None] | None:
        try:
            kind = check_frame(raw, self.max_frame)
            if self.auth is None:
                if kind != PLAIN:
                    raise FrameError("auth", f"a {KINDS[kind]} frame at an agent running insecure")
                msg = self._plain(raw)
                return ([msg], None) if msg is not None else None
            if kind == DATA:
                return self._data(raw, channel, src)
            if kind == HINT:  # on UDP, or on the TCP stream a sender is waiting for its ack on
                self._on_hint(raw, src)
                return None
            if channel == "tcp":
                raise FrameError("parse", f"a {KINDS[kind]} frame on a TCP stream")
            if kind == HELLO:
                try:
                    self._on_hello(raw, src)
                except CertificateRefused as err:
                    self._refuse(raw, src, err)
                    raise
            elif kind == REFUSAL:
                self._on_refusal(raw, src)
            elif kind == REPLY:
                self._on_reply(raw)
            elif kind == BEACON:
                msg = self._on_beacon(raw)
                return ([msg], None) if msg is not None else None
            else:
                raise FrameError("auth", "an unauthenticated frame (is the sender running insecure?)")
        except FrameError as err:
            self._dropped(channel, err)
        return None

    def _plain(self, raw: bytes) -> Message | None:
        env = parse_envelope(raw[KIND.size:])
        if env.sender == self.name and env.inst == self.inst:
            return None  # our own beacon, heard back
        if env.to and env.to != self.name:
            raise FrameError("receiver", f"frame for {env.to} arrived at {self.name}")
        self._filter(env.sender, env.role)
        body = body_of(env.type, env.body)
        self.count("received")
        # no hint: without authentication a beacon is as good a sign of life as any other frame
        return Message(env.sender, env.role, (env.reply[0], env.reply[1]), self._epoch(env.sender, env.inst),
                       env.seq, env.id, env.kind, body)

    def _filter(self, sender: str, role: str) -> None:
        if self.inbound_filter is not None and not self.inbound_filter(sender, role):
            raise FrameError("unreachable", f"{sender} cannot reach {self.name} now")

    def _data(self, raw: bytes, channel: str, src: Address) -> tuple[list[Message], Session | None]:
        """Open a data frame of a session: one envelope, or a batch of statuses (`[head, [message,
        ...]]`). A batch's message or body that does not validate is dropped alone; a head or an
        envelope that does not validate, or that names another sender or receiver, drops the
        whole frame."""
        sid = raw[KIND.size:KIND.size + 8]
        session = self._by_sid.get(sid)
        if session is None:
            self._hint(sid, src)
            raise FrameError("session", f"unknown session {sid.hex()} (its sender or this agent restarted)")
        plain = session.open(raw)
        batch = plain[:1] == b"["
        typed = parse_typed(plain)  # head, messages and bodies in one step, or None: the two steps below
        if typed is not None:
            head, items = typed
        elif batch:  # a message of the batch that does not validate is dropped alone
            head, values = parse_batch(plain)
            items = []
            for value in values:
                try:
                    items.append(parse_item(value))
                except FrameError as err:
                    self._dropped(channel, err)
        else:
            head = parse_envelope(plain)
            items = [head]
        if head.sender != session.peer or head.role != session.role or head.inst != session.inst:
            raise FrameError("auth", f"envelope names {head.sender[:64]} but the session is with {session.peer}")
        if head.to != self.name:
            raise FrameError("receiver", f"frame for {head.to} arrived at {self.name}")
        if not session.confirmed:
            self._confirm(session)
        self._filter(session.peer, session.role)
        msgs = []
        for item in items:
            try:
                if item.kind == "crl" and isinstance(item.body, str):
                    try:
                        self._adopt_crl(base64.b64decode(item.body, validate=True), session.peer)
                    except ValueError:
                        raise FrameError("parse", "revocation list is not base64") from None
                body = item.body if typed else body_of(item.type, item.body)
            except FrameError as err:
                if not batch:
                    raise
                self._dropped(channel, err)
                continue
            msgs.append(Message(session.peer, session.role, session.addr, session.epoch, item.seq, item.id,
                                item.kind, body))
        self.count("received", len(msgs))
        return msgs, session

    def _hint(self, sid: bytes, src: Address, conn: socket.socket | None = None) -> None:
        """Tell a sender we do not know its session (at most twice a second per host)."""
        if not self._hint_hosts.take(src[0]):
            return
        frame = KIND.pack(1 + 8, HINT) + sid
        try:
            if conn is not None:
                conn.send(frame)
            else:
                self._udp.sendto(frame, src)
            self.count("hints.sent")
        except OSError:
            pass

    def _refuse(self, hello: bytes, src: Address, err: FrameError) -> None:
        """Tell the sender of a handshake why its certificate is not trusted here (at most twice a
        second per host). Unsigned, but it names the handshake's digest: only who saw the handshake
        can forge it, and the sender takes it only as the reason its handshake goes unanswered."""
        trusted = getattr(self.auth, "trusted", None)
        if not callable(trusted) or not self._refusal_hosts.take(src[0]):
            return
        note = {"answers": hashlib.sha256(hello).hexdigest(), "agent": self.name,
                "reason": f"{str(err).partition(': ')[2]}; {self.name} trusts {trusted()}"[:400]}
        body = json.dumps(note).encode()
        try:
            self._udp.sendto(KIND.pack(1 + len(body), REFUSAL) + body, src)
            self.count("refusals.sent")
        except OSError:
            pass

    def _on_refusal(self, raw: bytes, src: Address) -> None:
        """A refusal of our handshake: record its reason for the address (and tell `on_refused`)."""
        if len(raw) > KIND.size + 1024:
            raise FrameError("size", f"a refusal of {len(raw)} bytes (at most {KIND.size + 1024})")
        try:
            note = json.loads(raw[KIND.size:])
            answers, agent, reason = str(note["answers"]), str(note["agent"]), str(note["reason"])
        except (ValueError, TypeError, KeyError):
            raise FrameError("parse", "a refusal that is not the expected JSON object") from None
        with self._sess_lock:
            found = self._initiations.get(answers)
        if found is None or found[0].addr != src:
            raise FrameError("session", "a refusal of no handshake of ours")
        why = f"{agent[:64]} at {src[0]}:{src[1]} refused this agent's certificate: {' '.join(reason[:400].split())}"
        self.count("refusals.received")
        if self.refusals.get(src) != why:
            self.refusals[src] = why
            self.log.warning("%s", why)
        self.on_refused(src, why)

    def _on_hint(self, raw: bytes, src: Address) -> None:
        if len(raw) != KIND.size + 8:
            raise FrameError("size", "a hint frame is 13 bytes")
        with self._sess_lock:
            session = self._by_sid.get(raw[KIND.size:])
            if session is None or session.addr[0] != src[0]:
                return
            now = time.monotonic()
            if now - session.stale < 1.0:
                return  # at most one new handshake a second for hints, which anyone can forge
            session.stale = now
            if self._by_addr.get(session.addr) is session:
                del self._by_addr[session.addr]
        self.count("hints.received")
        with self._cond:
            dest = self._dests.get(session.addr)
            if dest is not None and dest.has_work():
                self._make_ready(dest)

    def _on_hello(self, raw: bytes, src: Address) -> None:
        assert self.auth is not None
        digest = hashlib.sha256(raw).hexdigest()
        with self._sess_lock:
            known = self._answers.get(digest)
        if known is not None:  # a retransmission: the same answer again, no new keys
            self._answer(known[0], src)
            return
        now = time.monotonic()
        if not self._hs_hosts.take(src[0], now) or not self._hs_total.take(now):
            raise FrameError("rate", f"too many handshakes from {src[0]}")
        if len(self._answers) >= 4 * self.limits.max_connections:
            raise FrameError("rate", "too many handshakes waiting for their first frame")
        signed = cut_signed(raw, self.max_frame)
        hello = parse_hello(signed.body)
        if hello.sender == self.name and hello.inst == self.inst:
            return
        if hello.to and hello.to != self.name:
            raise FrameError("receiver", f"handshake for {hello.to} arrived at {self.name}")
        serial = self.auth.verify(signed, hello.sender, hello.role)
        self._filter(hello.sender, hello.role)
        frame, session = respond(self.auth, hello, raw, serial, self.inst, self.address)
        with self._sess_lock:
            self._answers[digest] = (frame, session, now)
            self._by_sid[session.sid] = session
        self.count("handshakes.answered")
        self._answer(frame, src)

    def _answer(self, frame: bytes, src: Address) -> None:
        """Answer a handshake from the receive thread: a send error (no route to the sender yet, as
        on a mesh whose routes are still forming) is counted and reported, never raised, so the
        receive thread goes on; the sender retransmits its handshake."""
        try:
            self._sendto(frame, src)
        except OSError as err:
            self.count("dropped.answer")
            self._drops.warning("udp", f"handshake answer to {src[0]}:{src[1]} failed: {err}")

    def _on_reply(self, raw: bytes) -> None:
        assert self.auth is not None
        signed = cut_signed(raw, self.max_frame)
        answer = parse_hello(signed.body)
        with self._sess_lock:
            found = self._initiations.get(answer.answers)
            if found is None and answer.answers in self._completed:
                return  # a second answer to a retransmitted handshake: the first one made the session
        if found is None:
            raise FrameError("session", "an answer to no handshake of ours")
        init, dest = found
        if answer.to != self.name:
            raise FrameError("receiver", f"handshake answer for {answer.to} arrived at {self.name}")
        serial = self.auth.verify(signed, answer.sender, answer.role)
        if init.expect and answer.sender != init.expect:
            raise FrameError("wrong_peer", f"{init.addr[0]}:{init.addr[1]} answered as {answer.sender}, "
                             f"expected {init.expect}")
        self._filter(answer.sender, answer.role)
        session = complete(self.auth, init, answer, raw, serial)
        with self._sess_lock:
            if self._initiations.pop(answer.answers, None) is None:
                return  # answered twice: the first answer made the session
            self._completed[answer.answers] = None
            if len(self._completed) > 256:
                self._completed.popitem(last=False)
            if init.addr != session.addr:
                self._by_addr[init.addr] = session
        with self._cond:
            if dest.handshake is init:
                dest.handshake = None
        self.count("handshakes.completed")
        self._confirm(session)

    def _on_beacon(self, raw: bytes) -> Message | None:
        assert self.auth is not None
        signed = cut_signed(raw, self.max_frame)
        env = parse_envelope(signed.body)
        if env.sender == self.name and env.inst == self.inst:
            return None  # our own beacon, heard back
        if env.kind != "beacon":
            raise FrameError("parse", f"a signed broadcast frame of kind {env.kind[:64]!r}: beacons only")
        if self.hint_wanted is not None and not self.hint_wanted(env.sender):
            self.count("received.beacons.known")  # a peer in session already: its hint is not worth a signature check
            return None
        if not self._beacon_bucket.take():
            raise FrameError("rate", "too many beacons to check")
        self.auth.verify(signed, env.sender, env.role)
        self._filter(env.sender, env.role)
        body = body_of(env.type, env.body)
        self.count("received.beacons")
        return Message(env.sender, env.role, (env.reply[0], env.reply[1]), 0, env.seq, env.id, env.kind,
                       body, hint=True)

    def _receive_loop(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._udp, selectors.EVENT_READ, "udp")
        sel.register(self._tcp, selectors.EVENT_READ, "listen")
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        if self._disc is not None:
            sel.register(self._disc, selectors.EVENT_READ, "udp")
        conns: dict[socket.socket, _Conn] = {}
        per_host: dict[str, int] = {}
        cap = self.limits.connection_cap()
        listening = True
        paused_until = 0.0
        next_sweep = 0.0
        try:
            while not self._stopping:
                now = time.monotonic()
                if now >= next_sweep:
                    next_sweep = now + 0.25
                    for conn in self._sweep(conns, now):
                        self._drop_conn(sel, conns, per_host, conn)
                    if not listening and now >= paused_until:
                        sel.register(self._tcp, selectors.EVENT_READ, "listen")
                        listening = True
                for key, _ in sel.select(timeout=0.25):
                    sock, what = key.fileobj, key.data
                    if what == "wake":
                        return
                    if what == "listen":
                        if not self._accept_all(sel, conns, per_host, cap):
                            sel.unregister(self._tcp)  # out of file descriptors: pause, do not spin
                            listening, paused_until = False, time.monotonic() + 0.5
                    elif what == "udp":
                        self._read_datagrams(sock)  # type: ignore[arg-type]  # a registered socket
                    else:
                        conn = conns.get(sock)  # type: ignore[call-overload]  # a registered socket
                        if conn is not None and not self._read_stream(conn, conns):
                            self._drop_conn(sel, conns, per_host, conn)
        finally:
            for conn in conns.values():
                _close(conn.sock)
            sel.close()

    def _accept_all(self, sel: selectors.BaseSelector, conns: dict[socket.socket, _Conn],
                    per_host: dict[str, int], cap: int) -> bool:
        """Accept waiting connections within the caps; False when out of file descriptors."""
        for _ in range(64):
            try:
                sock, peer = self._tcp.accept()
            except (BlockingIOError, InterruptedError):
                return True
            except OSError as err:
                if err.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                    self.count("refused.no_files")
                    self._drops.warning("accept", f"cannot accept a connection: {err.strerror} "
                                        f"({len(conns)} open); pausing for 0.5 s")
                    return False
                return True
            host = peer[0]
            # full, in total or for this host: the oldest connection (of this host, when its cap is
            # what is full) that never authenticated makes room, so idle strangers never lock out
            # an agent or a client that authenticates at once
            full_host = per_host.get(host, 0) >= self.limits.max_connections_per_host
            if len(conns) >= cap or full_host:
                stranger = min((c for c in conns.values() if not c.authed and (not full_host or c.peer[0] == host)),
                               key=lambda c: c.opened, default=None)
                if stranger is not None:
                    self._drop_conn(sel, conns, per_host, stranger)
                    self.count("closed.evicted")
            if len(conns) >= cap or per_host.get(host, 0) >= self.limits.max_connections_per_host:
                _close(sock)
                self.count("refused.connections")
                self._drops.warning("conn_cap", f"refused a connection from {host}: {len(conns)} open "
                                    f"(cap {cap}), {per_host.get(host, 0)} from that host "
                                    f"(cap {self.limits.max_connections_per_host})")
                continue
            sock.setblocking(False)
            now = time.monotonic()
            conns[sock] = _Conn(sock, (host, peer[1]), StreamDecoder(self.max_frame), now, now)
            per_host[host] = per_host.get(host, 0) + 1
            sel.register(sock, selectors.EVENT_READ, "conn")
        return True

    def _drop_conn(self, sel: selectors.BaseSelector, conns: dict[socket.socket, _Conn],
                   per_host: dict[str, int], conn: _Conn) -> None:
        if conns.pop(conn.sock, None) is None:
            return
        try:
            sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        _close(conn.sock)
        left = per_host.get(conn.peer[0], 1) - 1
        if left > 0:
            per_host[conn.peer[0]] = left
        else:
            per_host.pop(conn.peer[0], None)

    def _sweep(self, conns: dict[socket.socket, _Conn], now: float) -> list[_Conn]:
        """Connections past a timeout or over the byte budget; expired handshakes and sessions."""
        limits = self.limits
        late: list[_Conn] = []
        buffered = 0
        for conn in conns.values():
            reason = ""
            if conn.partial_since is not None and now - conn.partial_since > limits.frame_timeout:
                reason = f"a frame incomplete for {limits.frame_timeout:g} s"
            elif not conn.authed and now - conn.opened > limits.frame_timeout:
                reason = f"no authenticated frame within {limits.frame_timeout:g} s"
            elif now - conn.last_frame > limits.idle_timeout:
                reason = f"idle for {limits.idle_timeout:g} s"
            if reason:
                late.append(conn)
                self.count("closed.timeout")
                self._drops.warning("timeout", f"closed a connection from {conn.peer[0]}: {reason}")
            else:
                buffered += conn.decoder.buffered
        while buffered > limits.buffer_budget:
            biggest = max((c for c in conns.values() if c not in late), key=lambda c: c.decoder.buffered)
            late.append(biggest)
            buffered -= biggest.decoder.buffered
            self.count("closed.budget")
            self._drops.warning("budget", f"closed a connection from {biggest.peer[0]}: incomplete frames "
                                f"hold more than {limits.buffer_budget} bytes")
        with self._sess_lock:
            for digest, (_, session, made) in list(self._answers.items()):
                if session.confirmed or now - made > 5 * self.handshake_timeout:
                    del self._answers[digest]
                    if not session.confirmed:
                        self._by_sid.pop(session.sid, None)
            for digest, (init, _) in list(self._initiations.items()):
                if now - init.started > 3 * self.handshake_timeout:
                    del self._initiations[digest]
        self._forget(lambda s: now - max(s.last_rx, s.last_tx) < limits.session_idle)
        self._reload_crl()
        return late

    def _read_datagrams(self, sock: socket.socket) -> None:
        for _ in range(256):
            try:
                data, src = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            got = self._accept(data, "udp", src)
            for msg in got[0] if got is not None else ():
                if msg.kind not in INTERNAL:
                    self._dispatch(msg)

    def _read_stream(self, conn: _Conn, conns: dict[socket.socket, _Conn]) -> bool:
        try:
            data = conn.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return True
        except OSError:
            return False
        if not data:
            return False
        try:
            frames = conn.decoder.feed(data)
        except FrameError as err:
            self.count(f"dropped.{err.reason}")
            self._drops.warning(err.reason, f"closed a TCP stream from {conn.peer[0]}: {err}")
            return False
        now = time.monotonic()
        for raw in frames:
            conn.last_frame = now
            if not self._head_ok(raw, conn):
                return False
            got = self._accept(raw, "tcp", conn.peer)
            if got is None:
                continue
            msgs, session = got
            conn.authed = True
            for msg in msgs:
                if msg.kind == "ack":
                    continue
                seq = next(self._seq)
                ack = _Outgoing(f"{self._id_prefix}{seq:x}", "ack", None, msg.id, to_json(msg.id), seq, 0.0,
                                msg.sender)
                try:
                    conn.sock.sendall(self._frame(ack, session, self.max_frame))
                except (OSError, FrameError):
                    return False
                if msg.kind in INTERNAL:
                    continue
                if self._seen.first_time(msg.sender, msg.id):
                    self._dispatch(msg)
                else:
                    self.count("duplicates")
        if conn.decoder.buffered:
            if conn.partial_since is None:
                conn.partial_since = now
            head = conn.decoder.head(SESSION_END)
            if head is not None and not self._head_ok(head, conn):
                return False  # a frame of no session of ours: not worth waiting for
        else:
            conn.partial_since = None
        return True

    def _head_ok(self, head: bytes, conn: _Conn) -> bool:
        """Whether the start of a TCP frame belongs to one of our sessions (or insecure plain frames)."""
        kind = head[HEADER_KIND]
        if self.auth is None:
            if kind != PLAIN:
                self.count("dropped.auth")
                return False
            return True
        if kind != DATA:
            self.count("dropped.parse")
            self._drops.warning("parse", f"closed a TCP stream from {conn.peer[0]}: a "
                                f"{KINDS.get(kind, hex(kind))} frame where data frames belong")
            return False
        sid = head[KIND.size:KIND.size + 8]
        if sid not in self._by_sid:
            self._hint(sid, conn.peer, conn.sock)
            self.count("dropped.session")
            self._drops.warning("session", f"closed a TCP stream from {conn.peer[0]}: unknown session "
                                f"{sid.hex()} (its sender or this agent restarted)")
            return False
        return True

    def _dispatch(self, msg: Message) -> None:
        if msg.role == CLIENT_ROLE and msg.reply not in self._clients:
            self._clients[msg.reply] = None
            if len(self._clients) > 1024:
                self._clients.popitem(last=False)
        try:
            self.on_message(msg)
        except Exception:
            self.log.exception("handling %s from %s failed", msg.kind, msg.sender)


HEADER_KIND = 4  # offset of the kind byte in a frame


def _close(sock: socket.socket | None) -> None:
    if sock is not None:
        try:
            sock.close()
        except OSError:
            pass


def team_key(config_key: str | None, env_var: str = "ERNI_TEAM_KEY") -> bytes | None:
    """Return the team key from the config, else from the environment, else None."""
    value = config_key or os.environ.get(env_var)
    return value.encode() if value else None
