"""An agent's network endpoint: one receive thread, a pool of sender threads, TCP and UDP.

Reliable messages travel over TCP, one connection per destination, each acknowledged by
message id, retried with exponential backoff until their time to live runs out, and sent in
order per destination (one sender thread serves a destination at a time). Fast messages
travel as UDP datagrams from a bounded queue that drops the oldest. Nothing here ever runs
inside a blackboard transaction: callers enqueue and return at once.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import os
import random
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel

from erni.blackboard import new_uid
from erni.blackboard.errors import ConfigError, NetworkError
from erni.transport.wire import (
    DEFAULT_MAX_FRAME,
    UDP_MAX_FRAME,
    Envelope,
    FrameError,
    Message,
    ReplayWindow,
    SeenIds,
    StreamDecoder,
    body_of,
    decode,
    encode,
)

Address = tuple[str, int]

CLIENT_ROLE = "cli"
"""The role of a command-line client's endpoint (`erni task`, `erni watch` ...): never a peer."""

InboundFilter = Callable[[str, str], bool]
"""`(sender, role) -> bool`: whether a verified frame may be delivered (False: dropped and counted)."""


def parse_address(text: str, default_port: int = 0) -> Address:
    """Parse `host:port` (or `host`, with a default port); raise ValueError naming the problem."""
    host, sep, port = text.strip().rpartition(":")
    if not sep:
        host, port = text.strip(), str(default_port)
    if not host:
        raise ConfigError(f"address {text!r}: expected HOST:PORT")
    try:
        number = int(port)
    except ValueError:
        raise ConfigError(f"address {text!r}: port {port!r} is not a number") from None
    if not 0 <= number <= 65535:
        raise ConfigError(f"address {text!r}: port {number} is outside 0..65535")
    return host, number


@dataclass
class _Outgoing:
    id: str
    kind: str
    type: str | None
    body: Any
    deadline: float
    attempts: int = 0


@dataclass
class _Dest:
    addr: Address
    reliable: deque[_Outgoing] = field(default_factory=deque)
    fast: deque[_Outgoing] = field(default_factory=deque)
    sock: socket.socket | None = None
    decoder: StreamDecoder | None = None
    busy: bool = False
    queued: bool = False
    next_try: float = 0.0
    backoff: float = 0.0


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
    """Sockets and threads of one agent; deliver verified messages to `on_message`."""

    def __init__(self, name: str, *, listen: Address = ("127.0.0.1", 0), key: bytes | None = None,
                 insecure: bool = False, senders: int = 4, queue_limit: int = 1000,
                 max_frame: int = DEFAULT_MAX_FRAME, ack_timeout: float = 1.0,
                 connect_timeout: float = 1.0, retry_base: float = 0.05, retry_max: float = 2.0,
                 ttl: float = 30.0, discovery_port: int | None = None, epoch: int | None = None,
                 udp_loss: float = 0.0, seed: int | None = None, role: str = "",
                 inbound_filter: InboundFilter | None = None):
        if not key and not insecure:
            raise ConfigError("no team key: give a key or run with insecure = true")
        self.name = name
        self._listen = listen
        self._sign_key = key or b""
        self._verify_key = None if insecure else key
        self.insecure = insecure
        self.senders = senders
        self.queue_limit = queue_limit
        self.max_frame = max_frame
        self.ack_timeout = ack_timeout
        self.connect_timeout = connect_timeout
        self.retry_base, self.retry_max, self.ttl = retry_base, retry_max, ttl
        self.discovery_port = discovery_port
        if not 0.0 <= udp_loss <= 1.0:
            raise ConfigError(f"udp_loss: expected a probability in 0..1, got {udp_loss}")
        self.udp_loss = udp_loss  # fault injection: drop this share of outgoing datagrams
        self._rng = random.Random(seed)
        self.role = role
        self.inbound_filter = inbound_filter
        self.epoch = epoch if epoch is not None else time.time_ns()
        self._seq = itertools.count(1)
        self.log = logging.getLogger(f"erni.{name}.transport")
        self._drops = _RateLimitedLog(self.log)
        self.counters: dict[str, int] = {}
        self._counter_lock = threading.Lock()
        self._replay = ReplayWindow()
        self._replay_lock = threading.Lock()
        self._seen = SeenIds()
        self._dests: dict[Address, _Dest] = {}
        self._cond = threading.Condition()
        self._ready: deque[_Dest] = deque()
        self._delayed: list[tuple[float, int, _Dest]] = []
        self._tick = itertools.count()
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self.on_message: Callable[[Message], None] = lambda msg: None
        self.on_undeliverable: Callable[[Address, str, str, Any], None] = lambda addr, id, kind, body: None
        self.on_delivered: Callable[[Address, str], None] = lambda addr, id: None
        self.address: Address = listen

    # -- counters -------------------------------------------------------------------------

    def count(self, name: str, n: int = 1) -> None:
        """Add to a named counter (sent, received, dropped.auth, dropped.queue, ...)."""
        with self._counter_lock:
            self.counters[name] = self.counters.get(name, 0) + n

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Bind the sockets and start the receive thread and the sender pool."""
        self._stopping = False
        self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        self._tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        host, port = self._listen
        try:
            self._tcp.bind((host, port))
            self._udp.bind((host, self._tcp.getsockname()[1]))
        except OSError as err:
            self._udp.close()
            self._tcp.close()
            raise NetworkError(err.errno, f"cannot listen on {host}:{port}: {err.strerror}") from None
        self._tcp.listen(64)
        self._tcp.setblocking(False)
        self._udp.setblocking(False)
        self.address = self._tcp.getsockname()[:2]
        self._disc: socket.socket | None = None
        if self.discovery_port:
            self._disc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._disc.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._disc.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            self._disc.bind(("", self.discovery_port))
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

    # -- sending --------------------------------------------------------------------------

    def send(self, addr: Address, kind: str, body: BaseModel | Any = None, *, reliable: bool,
             msg_id: str | None = None, ttl: float | None = None) -> str:
        """Queue a message for `addr`; return its id. Never blocks on the network."""
        msg_id = msg_id or new_uid()
        type_name = type(body).__name__ if isinstance(body, BaseModel) else None
        payload = body.model_dump(mode="json") if isinstance(body, BaseModel) else body
        out = _Outgoing(msg_id, kind, type_name, payload, time.monotonic() + (ttl or self.ttl))
        with self._cond:
            if self._stopping:
                return msg_id
            dest = self._dests.get(addr)
            if dest is None:
                dest = self._dests[addr] = _Dest(addr)
            if reliable:
                if len(dest.reliable) >= self.queue_limit:
                    self.count("dropped.queue_full")
                    self._drops.warning("queue", f"reliable queue to {addr[0]}:{addr[1]} is full "
                                        f"({self.queue_limit}); refusing {kind} {msg_id}")
                    undeliverable = True
                else:
                    dest.reliable.append(out)
                    undeliverable = False
            else:
                if len(dest.fast) >= self.queue_limit:
                    dest.fast.popleft()
                    self.count("dropped.fast_oldest")
                dest.fast.append(out)
                undeliverable = False
            self._make_ready(dest)
        if undeliverable:
            self.on_undeliverable(addr, msg_id, kind, body)
        return msg_id

    def _make_ready(self, dest: _Dest) -> None:
        # under self._cond
        if not dest.busy and not dest.queued:
            dest.queued = True
            self._ready.append(dest)
            self._cond.notify()

    def _frame(self, out: _Outgoing, max_frame: int | None = None) -> bytes:
        env = Envelope.model_construct(v=1, sender=self.name, role=self.role, reply=self.address, epoch=self.epoch,
                                       seq=next(self._seq), id=out.id, kind=out.kind, type=out.type,
                                       body=out.body)  # our own fields: no need to validate
        return encode(env, self._sign_key, max_frame or self.max_frame)

    def _send_loop(self) -> None:
        while True:
            with self._cond:
                dest: _Dest | None = None
                while not self._stopping:
                    now = time.monotonic()
                    while self._delayed and self._delayed[0][0] <= now:
                        _, _, d = heapq.heappop(self._delayed)
                        d.queued = False
                        self._make_ready(d)
                    if self._ready:
                        dest = self._ready.popleft()
                        dest.queued = False
                        dest.busy = True
                        break
                    wait = self._delayed[0][0] - now if self._delayed else None
                    self._cond.wait(wait)
                if self._stopping or dest is None:
                    return
            try:
                self._service(dest)
            except Exception:  # never lose a sender thread
                self.log.exception("sender failed on %s:%s", *dest.addr)
            with self._cond:
                dest.busy = False
                if dest.fast or dest.reliable:
                    if dest.reliable and not dest.fast and dest.next_try > time.monotonic():
                        dest.queued = True
                        heapq.heappush(self._delayed, (dest.next_try, next(self._tick), dest))
                        self._cond.notify()
                    else:
                        self._make_ready(dest)

    def _service(self, dest: _Dest) -> None:
        while True:  # fast messages first: they are cheap and never wait
            with self._cond:
                out = dest.fast.popleft() if dest.fast else None
            if out is None:
                break
            try:
                frame = self._frame(out, min(self.max_frame, UDP_MAX_FRAME))
                if self.udp_loss and self._rng.random() < self.udp_loss:
                    self.count("dropped.injected")
                    continue
                self._udp.sendto(frame, dest.addr)
                self.count("sent.fast")
            except FrameError as err:
                self.count("dropped.too_big")
                self._drops.warning("too_big", f"not sent to {dest.addr}: {err}")
            except OSError as err:
                self.count("dropped.fast_error")
                self._drops.warning("udp", f"UDP send to {dest.addr[0]}:{dest.addr[1]} failed: {err}")
        for _ in range(32):  # then a batch of reliable ones, in order
            if time.monotonic() < dest.next_try or self._stopping:
                return
            with self._cond:
                out = dest.reliable[0] if dest.reliable else None
            if out is None:
                return
            if time.monotonic() > out.deadline:
                with self._cond:
                    dest.reliable.popleft()
                self.count("dropped.expired")
                self._drops.warning("expired", f"gave up on {out.kind} {out.id} to "
                                    f"{dest.addr[0]}:{dest.addr[1]} after {out.attempts} attempt(s)")
                self.on_undeliverable(dest.addr, out.id, out.kind, out.body)
                continue
            out.attempts += 1
            if self._deliver(dest, out):
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
                return

    def _deliver(self, dest: _Dest, out: _Outgoing) -> bool:
        try:
            frame = self._frame(out)
        except FrameError as err:
            with self._cond:
                dest.reliable.popleft()
            self.count("dropped.too_big")
            self._drops.warning("too_big", f"not sent: {err}")
            return True
        try:
            if dest.sock is None:
                dest.sock = socket.create_connection(dest.addr, timeout=self.connect_timeout)
                dest.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                dest.decoder = StreamDecoder(self.max_frame)
            dest.sock.settimeout(self.ack_timeout)
            dest.sock.sendall(frame)
            deadline = time.monotonic() + self.ack_timeout
            while time.monotonic() < deadline:
                data = dest.sock.recv(65536)
                if not data:
                    return False
                assert dest.decoder is not None
                for raw in dest.decoder.feed(data):
                    msg = self._verify(raw, "tcp")
                    if msg is not None and msg.kind == "ack" and msg.body == out.id:
                        return True
            return False
        except (OSError, FrameError) as err:
            self._drops.warning("link", f"link to {dest.addr[0]}:{dest.addr[1]} failed: {err}")
            return False

    # -- receiving ------------------------------------------------------------------------

    def _verify(self, raw: bytes, channel: str) -> Message | None:
        """Check a frame; count and log what fails; return the message or None."""
        try:
            env = decode(raw, self._verify_key, self.max_frame)
            if env.sender == self.name and env.epoch == self.epoch:
                return None  # our own beacon, heard back
            if self.inbound_filter is not None and not self.inbound_filter(env.sender, env.role):
                self.count("dropped.unreachable")
                return None  # e.g. a simulated radio that cannot carry this frame
            with self._replay_lock:
                self._replay.check(env.sender, env.epoch, env.seq)
            body = body_of(env.type, env.body)
        except FrameError as err:
            self.count(f"dropped.{err.reason}")
            self._drops.warning(err.reason, f"dropped a {channel} frame: {err}")
            return None
        self.count("received")
        return Message(env.sender, env.role, (env.reply[0], env.reply[1]), env.epoch, env.seq, env.id, env.kind, body)

    def _receive_loop(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._udp, selectors.EVENT_READ, "udp")
        sel.register(self._tcp, selectors.EVENT_READ, "listen")
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        if self._disc is not None:
            sel.register(self._disc, selectors.EVENT_READ, "udp")
        conns: dict[socket.socket, StreamDecoder] = {}
        try:
            while not self._stopping:
                for key, _ in sel.select(timeout=0.5):
                    sock, role = key.fileobj, key.data
                    if role == "wake":
                        return
                    if role == "listen":
                        try:
                            conn, _ = self._tcp.accept()
                        except OSError:
                            continue
                        conn.setblocking(False)
                        conns[conn] = StreamDecoder(self.max_frame)
                        sel.register(conn, selectors.EVENT_READ, "conn")
                    elif role == "udp":
                        self._read_datagrams(sock)  # type: ignore[arg-type]
                    else:
                        if not self._read_stream(sock, conns[sock]):  # type: ignore[index,arg-type]
                            sel.unregister(sock)
                            conns.pop(sock, None)  # type: ignore[call-overload]
                            _close(sock)  # type: ignore[arg-type]
        finally:
            for conn in conns:
                _close(conn)
            sel.close()

    def _read_datagrams(self, sock: socket.socket) -> None:
        for _ in range(256):
            try:
                data, _ = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            msg = self._verify(data, "udp")
            if msg is not None:
                self._dispatch(msg)

    def _read_stream(self, conn: socket.socket, decoder: StreamDecoder) -> bool:
        try:
            data = conn.recv(65536)
        except (BlockingIOError, InterruptedError):
            return True
        except OSError:
            return False
        if not data:
            return False
        try:
            frames = decoder.feed(data)
        except FrameError as err:
            self.count(f"dropped.{err.reason}")
            self._drops.warning(err.reason, f"closed a TCP stream: {err}")
            return False
        for raw in frames:
            msg = self._verify(raw, "tcp")
            if msg is None:
                continue
            ack = _Outgoing(new_uid(), "ack", None, msg.id, 0.0)
            try:
                conn.sendall(self._frame(ack))
            except OSError:
                return False
            if self._seen.first_time(msg.sender, msg.id):
                self._dispatch(msg)
            else:
                self.count("duplicates")
        return True

    def _dispatch(self, msg: Message) -> None:
        try:
            self.on_message(msg)
        except Exception:
            self.log.exception("handling %s from %s failed", msg.kind, msg.sender)


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
