"""Reliable delivery: each message over the destination's TCP connection, acknowledged by id,
retried with exponential backoff until its time to live runs out, in order per destination.

The caller's thread writes a message itself when its destination is idle (`write_now`: never
waiting; what the socket does not take is finished by a sender thread). A sender thread then
waits for the acknowledgement on that connection (`tcp_deliver`), and reports each message as
delivered (`on_delivered`) or, past its deadline or to the wrong peer, undeliverable
(`on_undeliverable`). A connection idle for half the receiver's idle timeout is never reused.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable, Container
from typing import TYPE_CHECKING, Any, Protocol

from erni.transport.outbox import Counters, Dest, Outgoing, SendQueues
from erni.transport.receiver import close
from erni.transport.wire import FrameError, StreamDecoder

if TYPE_CHECKING:
    from erni.transport.limits import Limits
    from erni.transport.session import Session
    from erni.transport.session_table import SessionTable
    from erni.transport.wire import Message
    from erni.transport.wires import Wire

Address = tuple[str, int]


class Deliveries(Counters, Protocol):
    """What reliable delivery needs of its endpoint: frames sealed and checked, and its reports
    (`on_delivered`, `on_undeliverable`), besides its counters."""

    def frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes: ...
    def accept_frame(self, raw: bytes, channel: str, src: Address) -> tuple[list[Message], Session | None] | None: ...
    def report_delivered(self, addr: Address, msg_id: str) -> None: ...
    def report_undeliverable(self, addr: Address, msg_id: str, kind: str, body: Any) -> None: ...


class ReliableDelivery:
    """Reliable messages: written from the caller's thread (`write_now`), delivered, retried and
    reported by the sender pool (`send_reliable`, `tcp_deliver`)."""

    def __init__(self, queues: SendQueues, carrier: Wire, sessions: SessionTable, host: Deliveries,
                 clients: Container[Address], *, secure: bool, clock: Callable[[], float],
                 pace: Callable[[], float], limits: Limits, max_frame: int, ack_timeout: float,
                 connect_timeout: float, retry_base: float, retry_max: float, log: logging.Logger) -> None:
        self.queues, self.carrier, self.sessions, self.host, self.clients = queues, carrier, sessions, host, clients
        self.secure, self.clock, self.pace, self.limits, self.max_frame = secure, clock, pace, limits, max_frame
        self.ack_timeout, self.connect_timeout = ack_timeout, connect_timeout
        self.retry_base, self.retry_max, self.log = retry_base, retry_max, log

    def caller_session(self, addr: Address, out: Outgoing) -> tuple[bool, Session | None]:
        """Whether the caller's thread may send `out` to `addr` itself, and the session to seal it in.

        Not while starting or stopping, and only in a confirmed session with the intended peer: a
        handshake to drive, or a wrong peer to report, is the sender pool's work.
        """
        if not self.queues.started or self.queues.stopping:
            return False, None
        if not self.secure:
            return True, None
        session = self.sessions.usable(addr)
        if session is None:
            return False, None
        return not (out.to and out.to != session.peer), session

    def write_now(self, addr: Address, out: Outgoing) -> bool:
        """Write a reliable message on its destination's open connection from the caller's thread.

        Only when that destination is idle (nothing queued, no sender serving it, no backoff) in a
        confirmed session; the write never blocks (what the socket does not take at once is left
        to the sender), and a sender thread then waits for the acknowledgement, retries and
        reports as for any reliable message. True when the message is queued that way.
        """
        usable, session = self.caller_session(addr, out)
        if not usable:
            return False
        now = self.pace()
        with self.queues.cond:
            dest = self.queues.dests.get(addr)
            if (dest is None or dest.busy or dest.ready or dest.has_work() or dest.sock is None
                    or now < dest.next_try or now - dest.sock_used > self.limits.idle_timeout / 2):
                return False
            dest.busy = True  # no sender touches this connection while the caller writes on it
            sock = dest.sock
        written, frame = 0, b""
        try:
            frame = self.host.frame(out, session, self.max_frame)
            written = os.write(sock.fileno(), frame)  # the socket is non-blocking (it has a timeout)
        except (BlockingIOError, InterruptedError):
            self.host.count("sent.deferred")
        except (OSError, FrameError):
            frame = b""  # a broken connection or a frame too big: the sender finds out and reports
        with self.queues.cond:
            if frame:
                out.written, out.rest = sock, frame[written:]
                dest.sock_used = now
                if out.rest:
                    self.host.count("sent.partial")
            dest.reliable.append(out)
            dest.busy = dest.again = False
            self.queues.make_ready(dest)
        return True

    def send_reliable(self, dest: Dest, session: Session | None) -> float | None:
        """Send a batch of `dest`'s reliable messages, in order, each waiting for its acknowledgement;
        return when to come back (None: when there is new work)."""
        for _ in range(32):  # then a batch of reliable ones, in order
            now = self.pace()
            if now < dest.next_try:
                return dest.next_try
            if self.queues.stopping or dest.fast:
                return None  # status queued meanwhile goes first (and in the order it was queued)
            with self.queues.cond:
                out = dest.reliable[0] if dest.reliable else None
            if out is None:
                return None
            if self.expired(dest, out, self.clock()):  # a deadline is on the endpoint's clock
                continue
            if session is not None and out.to and out.to != session.peer:
                with self.queues.cond:
                    dest.reliable.popleft()
                self.host.count("dropped.wrong_peer")
                self.host.warn("wrong_peer", f"{out.kind} {out.id} not delivered: {dest.addr[0]}:"
                                    f"{dest.addr[1]} is {session.peer}, not {out.to}")
                self.host.report_undeliverable(dest.addr, out.id, out.kind, out.body)
                continue
            out.attempts += 1
            if self.carrier.deliver(dest, out, session):
                with self.queues.cond:
                    if dest.reliable and dest.reliable[0] is out:
                        dest.reliable.popleft()
                dest.backoff = 0.0
                self.host.count("sent.reliable")
                self.host.report_delivered(dest.addr, out.id)
            else:
                close(dest.sock)
                dest.sock = None
                dest.backoff = min(self.retry_max, max(self.retry_base, dest.backoff * 2))
                dest.next_try = self.pace() + dest.backoff
                self.host.count("retries")
                if session is not None and self.sessions.current(dest.addr) is None:
                    return None  # the peer does not know the session: a new handshake, at once
                return dest.next_try
        return None

    def frame_or_drop(self, dest: Dest, out: Outgoing, session: Session | None) -> bytes | None:
        """The sealed frame of `dest`'s first reliable message `out`; None when it is too big to
        send ever (taken off the queue, counted and warned of)."""
        try:
            return self.host.frame(out, session, self.max_frame)
        except FrameError as err:
            with self.queues.cond:
                dest.reliable.popleft()
            self.host.count("dropped.too_big")
            self.host.warn("too_big", f"not sent: {err}")
            return None

    def tcp_deliver(self, dest: Dest, out: Outgoing, session: Session | None) -> bool:
        written, out.written = out.written, None
        if written is not None and written is dest.sock:
            frame: bytes | None = out.rest  # written by the caller's thread (`write_now`): the rest, then the ack
        else:
            frame = self.frame_or_drop(dest, out, session)
        if frame is None:
            return True
        try:
            now = self.pace()
            if dest.sock is not None and now - dest.sock_used > self.limits.idle_timeout / 2:
                close(dest.sock)  # the receiver closes idle connections: never send into one
                dest.sock = None
            if dest.sock is None:
                dest.sock = socket.create_connection(dest.addr, timeout=self.connect_timeout)
                dest.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                dest.decoder = StreamDecoder(self.max_frame)
            dest.sock_used = now
            dest.sock.settimeout(self.ack_timeout)
            if frame:
                dest.sock.sendall(frame)
            deadline = self.pace() + self.ack_timeout
            while self.pace() < deadline:
                data = dest.sock.recv(65536)
                if not data:
                    return False
                assert dest.decoder is not None
                for raw in dest.decoder.feed(data):
                    got = self.host.accept_frame(raw, "tcp", dest.addr)
                    if got is not None and any(m.kind == "ack" and m.body == out.id for m in got[0]):
                        return True
                if session is not None and session.stale:
                    return False  # the peer does not know this session any more
            return False
        except (OSError, FrameError) as err:
            if dest.addr in self.clients and isinstance(err, ConnectionRefusedError):
                self.client_gone(dest)
                return False
            if dest.addr in self.clients and isinstance(err, ConnectionResetError | BrokenPipeError):
                return False  # a client exiting closes its streams: the next try finds out (quietly)
            self.host.warn("link", f"link to {dest.addr[0]}:{dest.addr[1]} failed: {err}")
            return False

    def client_gone(self, dest: Dest) -> None:
        """A command-line client's port refuses connections: it exited (as `erni task` does once its
        task runs). What was queued for it is dropped at once, quietly: no retries, no warnings."""
        with self.queues.cond:
            reliable, fast = list(dest.reliable), len(dest.fast)
            dest.reliable.clear()
            dest.fast.clear()
        self.host.count("dropped.client_gone", len(reliable) + fast)
        self.log.debug("client at %s:%d has gone: %d message(s) for it dropped", *dest.addr, len(reliable) + fast)
        for out in reliable:
            self.host.report_undeliverable(dest.addr, out.id, out.kind, out.body)

    def expired(self, dest: Dest, out: Outgoing, now: float) -> bool:
        if now <= out.deadline:
            return False
        with self.queues.cond:
            if dest.reliable and dest.reliable[0] is out:
                dest.reliable.popleft()
        self.host.count("dropped.expired")
        self.host.warn("expired", f"gave up on {out.kind} {out.id} to "
                            f"{dest.addr[0]}:{dest.addr[1]} after {out.attempts} attempt(s)")
        self.host.report_undeliverable(dest.addr, out.id, out.kind, out.body)
        return True
