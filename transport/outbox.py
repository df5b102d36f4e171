"""The sender pool: a record per destination, and the threads that serve destinations in turn.

A destination (`Dest`) has three queues (reliable, fast, announcements), its TCP connection,
its retry and handshake state and the batch of statuses the caller is gathering for it. A
destination with work is put in the ready queue (`_make_ready`), or scheduled for a time
(`_schedule`: a retry, a handshake's retransmission, a batch's flush); a sender thread takes
one, and only one thread serves a destination at a time, which keeps its messages in order
(`_service`): the gathered batch, then signed announcements, then, in a session (started here
when there is none: `_handshake_step`), fast messages (`batching.py`) and reliable ones
(`reliable.py`).
"""

from __future__ import annotations

import heapq
import logging
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from erni.transport.session import Initiation, patience
from erni.transport.wire import BATCH_BYTES, StreamDecoder

if TYPE_CHECKING:
    from erni.transport.session import Auth, Session
    from erni.transport.session_table import SessionTable
    from erni.transport.wires import Wire

Address = tuple[str, int]

SOLO_FOR = 0.01
"""How long (s) the caller sends each status to a destination on its own after a batch it gathered
there went out with one status, when it has filled no datagram there within this time either:
its statuses follow each other closely but it waits between them (each one's delivery in its own
process, a reply), so gathering only held each back by `batching.FLUSH_AFTER`. The end of a real
burst (its last datagram may hold one status) does not count: that caller filled datagrams."""


@dataclass(slots=True)
class Outgoing:
    """A message queued (or being sent) to one destination."""

    id: str
    kind: str
    type: str | None
    body: Any  # as given to send(): what on_undeliverable hands back
    data: bytes  # the body's JSON, serialised when queued
    seq: int  # numbered when queued: a receiver orders a sender's messages as they were sent
    deadline: float
    to: str = ""
    attempts: int = 0
    written: socket.socket | None = None  # the connection the caller's thread wrote it on (`tcp_write_now`)
    rest: bytes = b""  # what the socket did not take then


@dataclass
class Dest:
    """The sender pool's record of one destination address: its queues, its connection, its turn
    in the pool, its retry and handshake state, and the batch the caller is gathering for it."""

    addr: Address
    reliable: deque[Outgoing] = field(default_factory=deque)
    fast: deque[Outgoing] = field(default_factory=deque)
    announce: deque[Outgoing] = field(default_factory=deque)
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
    hs_failures: int = 0  # handshakes with it given up in a row: each waits longer (`patience`)
    batch: Batch | None = None  # statuses of a burst the caller gathers into one datagram
    solo_until: float = 0.0  # until then (monotonic) the caller sends each status on its own (SOLO_FOR)
    full_at: float = 0.0  # when the caller last filled a datagram with gathered statuses (monotonic)

    def has_work(self) -> bool:
        return bool(self.fast or self.reliable or self.announce or self.batch)


@dataclass
class Batch:
    """Fast messages gathered for one datagram: in a session, their items sealed together under
    one head (up to `BATCH_BYTES`); without one (insecure), a single plain frame."""

    session: Session | None
    head: bytes = b""  # the envelope head the datagram's messages share
    outs: list[Outgoing] = field(default_factory=list)
    items: list[bytes] = field(default_factory=list)
    size: int = 0
    limit: int = BATCH_BYTES  # a wire without an MTU to keep under (Zenoh) gathers more

    def fits(self, item: bytes) -> bool:
        """Whether a message with this item may join the datagram (`[head,[item,...]]`)."""
        return not self.outs or self.session is not None and len(self.head) + 4 + self.size + len(item) + 1 <= self.limit

    def add(self, out: Outgoing, item: bytes) -> None:
        self.outs.append(out)
        self.items.append(item)
        self.size += len(item) + 1


class SenderPool:
    """The sender threads of an endpoint (a mixin of `Endpoint`; what it uses of the rest is
    declared below)."""

    if TYPE_CHECKING:
        carrier: Wire
        clock: Callable[[], float]
        pace: Callable[[], float]
        _cond: threading.Condition
        _delayed: list[tuple[float, int, int, Dest]]
        _dests: dict[Address, Dest]
        _ready: deque[Dest]
        _stopping: bool
        _tick: Iterator[int]
        auth: Auth | None
        handshake_timeout: float
        log: logging.Logger
        retry_max: float
        sessions: SessionTable
        def _envelope(self, out: Outgoing, to: str) -> bytes: ...
        def _expired(self, dest: Dest, out: Outgoing, now: float) -> bool: ...
        def _frame(self, out: Outgoing, session: Session | None, max_frame: int) -> bytes: ...
        def _announce(self, dest: Dest, out: Outgoing) -> None: ...
        def _requeue(self, dest: Dest, outs: list[Outgoing]) -> None: ...
        def _send_datagram(self, addr: Address, batch: Batch) -> bool: ...
        def _send_fast(self, dest: Dest, session: Session | None, outs: list[Outgoing]) -> float | None: ...
        def _send_reliable(self, dest: Dest, session: Session | None) -> float | None: ...
        def count(self, name: str, n: int = 1) -> None: ...
        def session_with(self, addr: Address) -> Session | None: ...
        def warn(self, reason: str, text: str) -> None: ...

    def _dest_for(self, addr: Address) -> Dest:
        """The sender pool's state for `addr`, made on first use (under self._cond)."""
        dest = self._dests.get(addr)
        if dest is None:
            dest = self._dests[addr] = Dest(addr)
        return dest

    def _make_ready(self, dest: Dest) -> None:
        # under self._cond: serve this destination now (a delayed wake-up of it becomes stale)
        if dest.busy:
            dest.again = True
        elif not dest.ready:
            dest.gen += 1
            dest.ready = True
            self._ready.append(dest)
            self._cond.notify()

    def _schedule(self, dest: Dest, when: float) -> None:
        # under self._cond: serve this destination at `when`
        if dest.busy or dest.ready:
            return
        dest.gen += 1
        earliest = not self._delayed or when < self._delayed[0][0]
        heapq.heappush(self._delayed, (when, next(self._tick), dest.gen, dest))
        if earliest:  # else a sender already waits until an earlier time, and then looks again
            self._cond.notify()

    def _send_loop(self) -> None:
        while True:
            with self._cond:
                dest: Dest | None = None
                while not self._stopping:
                    now = self.pace()
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
                when = self.pace() + self.retry_max
            with self._cond:
                dest.busy = False
                again, dest.again = dest.again, False
                if dest.has_work():
                    if again or when is None or when <= self.pace():
                        self._make_ready(dest)
                    else:
                        self._schedule(dest, when)

    def _service(self, dest: Dest) -> float | None:
        """Send what can go now; return when to come back (None: when there is new work)."""
        with self._cond:
            batch, dest.batch = dest.batch, None
            if batch is not None and len(batch.outs) == 1:
                now = self.pace()
                if now - dest.full_at > SOLO_FOR:  # a "burst" of one, and no datagram filled lately
                    dest.solo_until = now + SOLO_FOR
        if batch is not None and not self._send_datagram(dest.addr, batch):
            self._requeue(dest, batch.outs)
            return self.pace() + 0.005
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
        return self._send_reliable(dest, session)

    def _handshake_step(self, dest: Dest) -> float | None:
        """Start, retransmit or give up a handshake with `dest`; return when to look again."""
        assert self.auth is not None
        # what expires (a message's deadline, the handshake's timeout) is timed by the endpoint's clock;
        # when to send again, by real time (the same clock unless a test gave its own)
        now, real = self.clock(), self.pace()
        while True:
            with self._cond:
                out = dest.reliable[0] if dest.reliable else None
            if out is None or not self._expired(dest, out, now):
                break
        if not dest.has_work():
            return None
        init = dest.handshake
        wait = patience(self.handshake_timeout, dest.hs_failures)  # for its answer, after those given up
        if init is None:
            if real < dest.hs_not_before:
                return dest.hs_not_before
            with self._cond:
                first = dest.reliable[0] if dest.reliable else dest.fast[0] if dest.fast else None
            expect = first.to if first is not None else ""
            init = dest.handshake = self.sessions.initiate(dest.addr, expect)
        elif now - init.started > wait:
            self.sessions.abandon(init)
            dest.handshake = None
            dest.hs_failures += 1
            dest.hs_backoff = min(5.0, max(0.5, dest.hs_backoff * 2))
            dest.hs_not_before = real + dest.hs_backoff
            with self._cond:
                dropped = len(dest.fast)
                dest.fast.clear()
            self.count("handshakes.failed")
            if dropped:
                self.count("dropped.no_session", dropped)
            self.warn("handshake", f"no answer to a handshake with {dest.addr[0]}:{dest.addr[1]}"
                                f"{' (' + init.expect + ')' if init.expect else ''} within "
                                f"{wait:g} s; {dropped} status message(s) dropped")
            return dest.hs_not_before if dest.reliable else None
        if real >= init.next_try:
            try:
                self.carrier.sendto(init.frame, dest.addr)
                self.count("handshakes.sent")
            except OSError as err:
                self.warn("udp", f"handshake to {dest.addr[0]}:{dest.addr[1]} failed: {err}")
            init.attempts += 1
            init.next_try = real + 0.1 * 2 ** min(init.attempts, 3)
        return min(init.next_try, real + init.started + wait - now + 0.001)
