"""Sockets and the receive loop of an endpoint: what comes in, and the bounds on it before authentication.

Two threads read: one blocked in the UDP socket's recvfrom (statuses, handshakes, hints: one system
call a datagram), and one on a selector for the TCP listener, the accepted connections, the
discovery port and the periodic sweeps. Each frame goes to the endpoint's frame path
(`ReceiverHost.accept_frame`); a reliable message on a stream is acknowledged on that stream
before it is delivered, once per id, unless its acknowledgement waits until what it asks for is
durable (`ReceiverHost.receive_reliable`): then the stream thread writes it when it is handed back
(`queue_ack`), on the stream of the message's latest copy.

Before a frame is authenticated nothing is spent without a bound (`limits.py`): connections per host
and in total (the oldest stranger makes room), bytes of incomplete frames, idle and partial-frame
timeouts; a stream whose first bytes name no session of ours is closed at once.
"""

from __future__ import annotations

import errno
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from erni.transport.limits import Limits
from erni.transport.session import Auth, Session
from erni.transport.wire import DATA, KIND, KINDS, PLAIN, SESSION_END, FrameError, Message, StreamDecoder

if TYPE_CHECKING:
    from erni.transport.session_table import SessionTable

Address = tuple[str, int]
HEADER_KIND = 4  # offset of the kind byte in a frame
SWEEP_PERIOD = 1.0
"""How often (s) the stream thread sweeps its connections' timeouts (frame_timeout, idle_timeout: seconds
and a minute), the expired handshakes and idle sessions and a changed revocation list; between sweeps it
sleeps until a socket is ready (it woke four times a second, every agent at rest)."""


class ReceiverHost(Protocol):
    """What the receive loop needs from its endpoint."""

    limits: Limits
    max_frame: int
    auth: Auth | None
    sessions: SessionTable

    def clock(self) -> float:
        """Seconds on the endpoint's monotonic clock: connection timeouts and the sweeps use it."""

    def pace(self) -> float:
        """Seconds on the real monotonic clock: the receive loop's own pace."""

    @property
    def stopping(self) -> bool: ...

    def count(self, name: str, n: int = 1) -> None: ...

    def warn(self, reason: str, text: str) -> None: ...

    def accept_frame(self, raw: bytes, channel: str, src: Address) -> tuple[list[Message], Session | None] | None:
        """The frame path: check, open and decode a frame; None when it carries nothing to deliver."""

    def receive_datagram(self, raw: bytes, src: Address) -> None:
        """The whole path of one datagram: check, open, decode, and hand on what it carries."""

    def deliver(self, msg: Message) -> None:
        """Hand a received message on (the endpoint's own kinds excepted)."""

    def deliver_once(self, msg: Message) -> None:
        """Hand a reliable message on unless it was delivered already (a retry)."""

    def receive_reliable(self, msg: Message, session: Session | None, reply: Callable[[bytes], None],
                         reply_later: Callable[[bytes], None]) -> None:
        """Acknowledge a reliable message (now by `reply`, or later by `reply_later`) and hand it on once."""


@dataclass
class Conn:
    """An accepted TCP connection."""

    sock: socket.socket
    peer: Address
    decoder: StreamDecoder
    opened: float
    last_frame: float
    partial_since: float | None = None
    authed: bool = False


class Receiver:
    """The receiving sockets of one endpoint and the threads that read them (`run_streams`,
    `run_datagrams`); stop by waking the stream thread (`wake`) and shutting the UDP socket."""

    def __init__(self, host: ReceiverHost, tcp: socket.socket, udp: socket.socket, disc: socket.socket | None,
                 wake: socket.socket, waker: socket.socket | None = None):
        self.host, self.tcp, self.udp, self.disc, self.wake = host, tcp, udp, disc, wake
        self.waker = waker  # the other end of `wake`
        self._acks: deque[tuple[Conn, bytes]] = deque()  # held acknowledgements to write (`queue_ack`)
        self._acks_lock = threading.Lock()

    def queue_ack(self, conn: Conn, frame: bytes) -> None:
        """Have the stream thread write an acknowledgement on `conn` (from any thread; dropped when
        the connection has closed meanwhile: the sender's retry is acknowledged then)."""
        with self._acks_lock:
            self._acks.append((conn, frame))
        if self.waker is not None:
            try:
                self.waker.send(b"a")
            except OSError:  # full of wake-ups already, or stopping
                pass

    def _woken(self, sel: selectors.BaseSelector, conns: dict[socket.socket, Conn], per_host: dict[str, int]) -> bool:
        """The wake-up socket: False to stop, else write the acknowledgements handed back."""
        try:
            self.wake.recv(4096)
        except OSError:
            pass
        if self.host.stopping:
            return False
        for conn in self._write_acks(conns):
            self._drop_conn(sel, conns, per_host, conn)
        return True

    def _write_acks(self, conns: dict[socket.socket, Conn]) -> list[Conn]:
        """Write the queued acknowledgements; return the connections that failed."""
        with self._acks_lock:
            acks, self._acks = self._acks, deque()
        failed = []
        for conn, frame in acks:
            if conns.get(conn.sock) is not conn:
                continue
            try:
                if conn.sock.send(frame) == len(frame):
                    continue
            except OSError:
                pass
            failed.append(conn)  # a part of a frame on the stream: only closing it keeps the framing
        return failed

    def run_streams(self) -> None:
        """The stream thread: accept and read TCP connections, read the discovery port, sweep."""
        sel = selectors.DefaultSelector()
        sel.register(self.tcp, selectors.EVENT_READ, "listen")
        sel.register(self.wake, selectors.EVENT_READ, "wake")
        if self.disc is not None:
            sel.register(self.disc, selectors.EVENT_READ, "udp")
        conns: dict[socket.socket, Conn] = {}
        per_host: dict[str, int] = {}
        cap = self.host.limits.connection_cap()
        listening = True
        paused_until = 0.0
        next_sweep = 0.0
        try:
            while not self.host.stopping:
                real = self.host.pace()  # the loop's own pace is real time; what times out, the endpoint's clock
                if real >= next_sweep:
                    next_sweep = real + SWEEP_PERIOD
                    for conn in self._sweep(conns, self.host.clock()):
                        self._drop_conn(sel, conns, per_host, conn)
                    if not listening and real >= paused_until:
                        sel.register(self.tcp, selectors.EVENT_READ, "listen")
                        listening = True
                for key, _ in sel.select(timeout=max(0.0, next_sweep - real)):  # asleep until the sweep
                    sock, what = key.fileobj, key.data
                    if what == "wake":
                        if not self._woken(sel, conns, per_host):
                            return
                        continue
                    if what == "listen":
                        if not self._accept_all(sel, conns, per_host, cap):
                            sel.unregister(self.tcp)  # out of file descriptors: pause, do not spin
                            listening, paused_until = False, self.host.pace() + 0.5
                    elif what == "udp":
                        self._read_datagrams(sock)  # type: ignore[arg-type]  # a registered socket
                    else:
                        conn = conns.get(sock)  # type: ignore[call-overload]  # a registered socket
                        if conn is not None and not self._read_stream(conn, conns):
                            self._drop_conn(sel, conns, per_host, conn)
        finally:
            for conn in conns.values():
                close(conn.sock)
            sel.close()

    def _accept_all(self, sel: selectors.BaseSelector, conns: dict[socket.socket, Conn],
                    per_host: dict[str, int], cap: int) -> bool:
        """Accept waiting connections within the caps; False when out of file descriptors."""
        for _ in range(64):
            try:
                sock, peer = self.tcp.accept()
            except (BlockingIOError, InterruptedError):
                return True
            except OSError as err:
                if err.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                    self.host.count("refused.no_files")
                    self.host.warn("accept", f"cannot accept a connection: {err.strerror} "
                                   f"({len(conns)} open); pausing for 0.5 s")
                    return False
                return True
            host = peer[0]
            # full, in total or for this host: the oldest connection (of this host, when its cap is
            # what is full) that never authenticated makes room, so idle strangers never lock out
            # an agent or a client that authenticates at once
            full_host = per_host.get(host, 0) >= self.host.limits.max_connections_per_host
            if len(conns) >= cap or full_host:
                stranger = min((c for c in conns.values() if not c.authed and (not full_host or c.peer[0] == host)),
                               key=lambda c: c.opened, default=None)
                if stranger is not None:
                    self._drop_conn(sel, conns, per_host, stranger)
                    self.host.count("closed.evicted")
            if len(conns) >= cap or per_host.get(host, 0) >= self.host.limits.max_connections_per_host:
                close(sock)
                self.host.count("refused.connections")
                self.host.warn("conn_cap", f"refused a connection from {host}: {len(conns)} open "
                               f"(cap {cap}), {per_host.get(host, 0)} from that host "
                               f"(cap {self.host.limits.max_connections_per_host})")
                continue
            sock.setblocking(False)
            now = self.host.clock()
            conns[sock] = Conn(sock, (host, peer[1]), StreamDecoder(self.host.max_frame), now, now)
            per_host[host] = per_host.get(host, 0) + 1
            sel.register(sock, selectors.EVENT_READ, "conn")
        return True

    def _drop_conn(self, sel: selectors.BaseSelector, conns: dict[socket.socket, Conn],
                   per_host: dict[str, int], conn: Conn) -> None:
        if conns.pop(conn.sock, None) is None:
            return
        try:
            sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        close(conn.sock)
        left = per_host.get(conn.peer[0], 1) - 1
        if left > 0:
            per_host[conn.peer[0]] = left
        else:
            per_host.pop(conn.peer[0], None)

    def _sweep(self, conns: dict[socket.socket, Conn], now: float) -> list[Conn]:
        """Connections past a timeout or over the byte budget; expired handshakes and sessions (`SessionTable.sweep`)."""
        limits = self.host.limits
        late: list[Conn] = []
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
                self.host.count("closed.timeout")
                self.host.warn("timeout", f"closed a connection from {conn.peer[0]}: {reason}")
            else:
                buffered += conn.decoder.buffered
        while buffered > limits.buffer_budget:
            biggest = max((c for c in conns.values() if c not in late), key=lambda c: c.decoder.buffered)
            late.append(biggest)
            buffered -= biggest.decoder.buffered
            self.host.count("closed.budget")
            self.host.warn("budget", f"closed a connection from {biggest.peer[0]}: incomplete frames "
                           f"hold more than {limits.buffer_budget} bytes")
        self.host.sessions.sweep(now)
        return late

    def run_datagrams(self) -> None:
        """The datagrams of the endpoint's port (statuses, handshakes, hints), one at a time from a
        blocking recvfrom: one system call a datagram and no wake-up of a selector first; each
        goes whole to `receive_datagram`, which hands what it carries to `on_message`."""
        recvfrom, receive = self.udp.recvfrom, self.host.receive_datagram
        while not self.host.stopping:
            try:
                data, src = recvfrom(65536)
            except OSError as err:
                if self.host.stopping or err.errno in (errno.EBADF, errno.EINVAL, errno.ENOTSOCK):
                    return
                self.host.count("udp.errors")  # an unconnected socket reports no ICMP errors: unexpected,
                time.sleep(0.001)  # and one that repeats (out of memory ...) must not spin this thread
                continue
            if data:  # an empty datagram (or the wake-up of `stop`) is no frame
                receive(data, src)

    def _read_datagrams(self, sock: socket.socket) -> None:
        for _ in range(256):
            try:
                data, src = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            got = self.host.accept_frame(data, "udp", src)
            for msg in got[0] if got is not None else ():
                self.host.deliver(msg)

    def _read_stream(self, conn: Conn, conns: dict[socket.socket, Conn]) -> bool:
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
            self.host.count(f"dropped.{err.reason}")
            self.host.warn(err.reason, f"closed a TCP stream from {conn.peer[0]}: {err}")
            return False
        now = self.host.clock()
        for raw in frames:
            conn.last_frame = now
            if not self._head_ok(raw, conn):
                return False
            got = self.host.accept_frame(raw, "tcp", conn.peer)
            if got is None:
                continue
            msgs, session = got
            conn.authed = True
            for msg in msgs:
                if msg.kind == "ack":
                    continue
                try:
                    self.host.receive_reliable(msg, session, conn.sock.sendall,
                                               lambda frame, conn=conn: self.queue_ack(conn, frame))  # type: ignore[misc]
                except (OSError, FrameError):
                    return False
        if conn.decoder.buffered:
            if conn.partial_since is None:
                conn.partial_since = now
            head = conn.decoder.head(SESSION_END)
            if head is not None and not self._head_ok(head, conn):
                return False  # a frame of no session of ours: not worth waiting for
        else:
            conn.partial_since = None
        return True

    def _head_ok(self, head: bytes, conn: Conn) -> bool:
        """Whether the start of a TCP frame belongs to one of our sessions (or insecure plain frames)."""
        kind = head[HEADER_KIND]
        if self.host.auth is None:
            if kind != PLAIN:
                self.host.count("dropped.auth")
                return False
            return True
        if kind != DATA:
            self.host.count("dropped.parse")
            self.host.warn("parse", f"closed a TCP stream from {conn.peer[0]}: a "
                           f"{KINDS.get(kind, hex(kind))} frame where data frames belong")
            return False
        sid = head[KIND.size:KIND.size + 8]
        if sid not in self.host.sessions.by_sid:
            self.host.sessions.hint(sid, conn.peer, conn.sock.send)
            self.host.count("dropped.session")
            self.host.warn("session", f"closed a TCP stream from {conn.peer[0]}: unknown session "
                           f"{sid.hex()} (its sender or this agent restarted)")
            return False
        return True


def close(sock: socket.socket | None) -> None:
    """Close a socket, if any, ignoring errors."""
    if sock is not None:
        try:
            sock.close()
        except OSError:
            pass
