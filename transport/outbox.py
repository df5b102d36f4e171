"""The sender pool: a record per destination, the queues the endpoint's parts share, and the
threads that serve destinations in turn.

A destination (`Dest`) has three queues (reliable, fast, announcements), its TCP connection,
its retry and handshake state and the batch of statuses the caller is gathering for it. The
destinations, the ready queue, the delayed heap and the condition that guards them are one
object (`SendQueues`), owned by the endpoint and handed to each part that queues or sends. A
destination with work is put in the ready queue (`make_ready`), or scheduled for a time
(`schedule`: a retry, a handshake's retransmission, a batch's flush); a sender thread takes
one (`take`), and only one thread serves a destination at a time, which keeps its messages in
order (`SenderPool.service`): the gathered batch, then signed announcements, then, in a session
(started here when there is none: `handshake_step`), fast messages (`batching.py`) and reliable
ones (`reliable.py`).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from erni.transport.session import Initiation, patience
from erni.transport.wire import BATCH_BYTES, StreamDecoder

if TYPE_CHECKING:
    from erni.transport.session import Session
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
    written: socket.socket | None = None  # the connection the caller's thread wrote it on (`ReliableDelivery.write_now`)
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


class Counters(Protocol):
    """What every part needs of its endpoint: its counters and its rate-limited warnings."""

    def count(self, name: str, n: int = 1) -> None: ...
    def warn(self, reason: str, text: str) -> None: ...


class MessageIds:
    """The numbering of an endpoint's messages: each message's number (in the order sent) and its
    id (unique per instance, cheap: no uuid)."""

    __slots__ = ("seq", "prefix")

    def __init__(self, prefix: str) -> None:
        self.seq: Iterator[int] = itertools.count(1)
        self.prefix = prefix


class SendQueues:
    """The state the endpoint's parts share: the destinations, the ready queue and the delayed heap
    of the sender pool, guarded by one condition, and whether the pool runs.

    `dests`, `ready` and `delayed` are read and changed under `cond` only (the caller's hot path
    reads `dests` without it: each read is atomic). `started` is true while the sender threads
    run, `stopping` once `stop` has been called.
    """

    __slots__ = ("counters", "queue_limit", "pace", "cond", "dests", "ready", "delayed", "tick", "stopping",
                 "started")

    def __init__(self, counters: Counters, queue_limit: int, pace: Callable[[], float]) -> None:
        self.counters, self.queue_limit, self.pace = counters, queue_limit, pace
        self.cond = threading.Condition()
        self.dests: dict[Address, Dest] = {}
        self.ready: deque[Dest] = deque()
        self.delayed: list[tuple[float, int, int, Dest]] = []
        self.tick = itertools.count()
        self.stopping = False
        self.started = False

    def dest_for(self, addr: Address) -> Dest:
        """The sender pool's state for `addr`, made on first use (under `cond`)."""
        dest = self.dests.get(addr)
        if dest is None:
            dest = self.dests[addr] = Dest(addr)
        return dest

    def make_ready(self, dest: Dest) -> None:
        """Under `cond`: serve this destination now (a delayed wake-up of it becomes stale)."""
        if dest.busy:
            dest.again = True
        elif not dest.ready:
            dest.gen += 1
            dest.ready = True
            self.ready.append(dest)
            self.cond.notify()

    def schedule(self, dest: Dest, when: float) -> None:
        """Under `cond`: serve this destination at `when` (pace's time)."""
        if dest.busy or dest.ready:
            return
        dest.gen += 1
        earliest = not self.delayed or when < self.delayed[0][0]
        heapq.heappush(self.delayed, (when, next(self.tick), dest.gen, dest))
        if earliest:  # else a sender already waits until an earlier time, and then looks again
            self.cond.notify()

    def queue(self, addr: Address, out: Outgoing, lane: str) -> bool:
        """Queue a message for the sender pool; False when it is refused (a reliable queue is full:
        counted and warned of, the caller reports it undeliverable). The fast and announcement
        queues drop their oldest instead. Nothing is queued once stopping."""
        with self.cond:
            if self.stopping:
                return True
            dest = self.dest_for(addr)
            if lane == "reliable":
                if len(dest.reliable) >= self.queue_limit:
                    self.counters.count("dropped.queue_full")
                    self.counters.warn("queue", f"reliable queue to {addr[0]}:{addr[1]} is full "
                                       f"({self.queue_limit}); refusing {out.kind} {out.id}")
                    return False
                dest.reliable.append(out)
            else:
                queue = dest.fast if lane == "fast" else dest.announce
                if len(queue) >= self.queue_limit:
                    queue.popleft()
                    self.counters.count("dropped.fast_oldest")
                queue.append(out)
            self.make_ready(dest)
        return True

    def requeue(self, dest: Dest, outs: list[Outgoing]) -> None:
        """Put fast messages the socket did not take back in front of the queue, in their order."""
        with self.cond:
            room = max(0, self.queue_limit - len(dest.fast))
            dest.fast.extendleft(reversed(outs[:room]))
            if len(outs) > room:
                self.counters.count("dropped.fast_oldest", len(outs) - room)
        self.counters.count("sent.deferred")

    def wake_all(self) -> None:
        """Wake every waiting sender (a test's clock moved: they look again at what has expired)."""
        with self.cond:
            self.cond.notify_all()

    def stop(self) -> None:
        """Tell the sender threads to end, and wake them."""
        with self.cond:
            self.stopping = True
            self.cond.notify_all()

    def take(self) -> Dest | None:
        """Wait for a destination to serve and mark it busy; None once stopping."""
        with self.cond:
            while not self.stopping:
                now = self.pace()
                while self.delayed and self.delayed[0][0] <= now:
                    _, _, gen, d = heapq.heappop(self.delayed)
                    if gen == d.gen:
                        self.make_ready(d)
                if self.ready:
                    dest = self.ready.popleft()
                    dest.ready = False
                    dest.busy = True
                    if self.delayed:  # this thread may have been the one waiting for the earliest
                        self.cond.notify()
                    return dest
                self.cond.wait(self.delayed[0][0] - now if self.delayed else None)
        return None

    def release(self, dest: Dest, when: float | None) -> None:
        """A sender is done with `dest` for now: serve it again at once (new work came meanwhile, or
        it is due), at `when`, or when there is new work (`when` None)."""
        with self.cond:
            dest.busy = False
            again, dest.again = dest.again, False
            if dest.has_work():
                if again or when is None or when <= self.pace():
                    self.make_ready(dest)
                else:
                    self.schedule(dest, when)


class Handshakes(Protocol):
    """What the sender pool needs of the session table (`session_table.SessionTable`)."""

    def current(self, addr: Address) -> Session | None: ...
    def initiate(self, addr: Address, expect: str) -> Initiation: ...
    def abandon(self, init: Initiation) -> None: ...


class FastLane(Protocol):
    """What the sender pool needs of the fast messages (`batching.FastMessages`)."""

    def send_datagram(self, addr: Address, batch: Batch) -> bool: ...
    def send_fast(self, dest: Dest, session: Session | None, outs: list[Outgoing]) -> float | None: ...


class ReliableLane(Protocol):
    """What the sender pool needs of reliable delivery (`reliable.ReliableDelivery`)."""

    def send_reliable(self, dest: Dest, session: Session | None) -> float | None: ...
    def expired(self, dest: Dest, out: Outgoing, now: float) -> bool: ...


class Announcer(Protocol):
    """What the sender pool needs of discovery (`discovery.Beacons`)."""

    def send_beacon(self, dest: Dest, out: Outgoing) -> None: ...


class SenderPool:
    """The sender threads of an endpoint: each takes a destination from the queues, serves it
    (`service`) and hands it back."""

    def __init__(self, queues: SendQueues, carrier: Wire, sessions: Handshakes, counters: Counters,
                 fast: FastLane, reliable: ReliableLane, beacons: Announcer, *, secure: bool,
                 clock: Callable[[], float], pace: Callable[[], float], handshake_timeout: float,
                 retry_max: float, log: logging.Logger) -> None:
        self.queues, self.carrier, self.sessions, self.counters = queues, carrier, sessions, counters
        self.fast, self.reliable, self.beacons = fast, reliable, beacons
        self.secure, self.clock, self.pace = secure, clock, pace
        self.handshake_timeout, self.retry_max, self.log = handshake_timeout, retry_max, log

    def start(self, name: str, n: int) -> list[threading.Thread]:
        """Start `n` sender threads (named `name-0` ...) and return them."""
        threads = []
        for i in range(n):
            t = threading.Thread(target=self.run, name=f"{name}-{i}", daemon=True)
            t.start()
            threads.append(t)
        return threads

    def run(self) -> None:
        """A sender thread: serve destinations until the queues stop."""
        queues = self.queues
        while True:
            dest = queues.take()
            if dest is None:
                return
            when: float | None = None
            try:
                when = self.service(dest)
            except Exception:  # never lose a sender thread
                self.log.exception("sender failed on %s:%s", *dest.addr)
                when = self.pace() + self.retry_max
            queues.release(dest, when)

    def service(self, dest: Dest) -> float | None:
        """Send what can go now; return when to come back (None: when there is new work)."""
        cond = self.queues.cond
        with cond:
            batch, dest.batch = dest.batch, None
            if batch is not None and len(batch.outs) == 1:
                now = self.pace()
                if now - dest.full_at > SOLO_FOR:  # a "burst" of one, and no datagram filled lately
                    dest.solo_until = now + SOLO_FOR
        if batch is not None and not self.fast.send_datagram(dest.addr, batch):
            self.queues.requeue(dest, batch.outs)
            return self.pace() + 0.005
        while True:  # signed announcements first: they need no session
            with cond:
                out = dest.announce.popleft() if dest.announce else None
            if out is None:
                break
            self.beacons.send_beacon(dest, out)
        session: Session | None = None
        if self.secure:
            session = self.sessions.current(dest.addr)
            if session is None:
                return self.handshake_step(dest)
        while True:  # fast messages: they are cheap and never wait
            with cond:
                outs = [dest.fast.popleft() for _ in range(min(len(dest.fast), 64))]
            if not outs:
                break
            retry = self.fast.send_fast(dest, session, outs)
            if retry is not None:
                return retry
        return self.reliable.send_reliable(dest, session)

    def handshake_step(self, dest: Dest) -> float | None:
        """Start, retransmit or give up a handshake with `dest`; return when to look again."""
        assert self.secure
        cond = self.queues.cond
        # what expires (a message's deadline, the handshake's timeout) is timed by the endpoint's clock;
        # when to send again, by real time (the same clock unless a test gave its own)
        now, real = self.clock(), self.pace()
        while True:
            with cond:
                out = dest.reliable[0] if dest.reliable else None
            if out is None or not self.reliable.expired(dest, out, now):
                break
        if not dest.has_work():
            return None
        init = dest.handshake
        wait = patience(self.handshake_timeout, dest.hs_failures)  # for its answer, after those given up
        if init is None:
            if real < dest.hs_not_before:
                return dest.hs_not_before
            with cond:
                first = dest.reliable[0] if dest.reliable else dest.fast[0] if dest.fast else None
            expect = first.to if first is not None else ""
            init = dest.handshake = self.sessions.initiate(dest.addr, expect)
        elif now - init.started > wait:
            self.sessions.abandon(init)
            dest.handshake = None
            dest.hs_failures += 1
            dest.hs_backoff = min(5.0, max(0.5, dest.hs_backoff * 2))
            dest.hs_not_before = real + dest.hs_backoff
            with cond:
                dropped = len(dest.fast)
                dest.fast.clear()
            self.counters.count("handshakes.failed")
            if dropped:
                self.counters.count("dropped.no_session", dropped)
            self.counters.warn("handshake", f"no answer to a handshake with {dest.addr[0]}:{dest.addr[1]}"
                               f"{' (' + init.expect + ')' if init.expect else ''} within "
                               f"{wait:g} s; {dropped} status message(s) dropped")
            return dest.hs_not_before if dest.reliable else None
        if real >= init.next_try:
            try:
                self.carrier.sendto(init.frame, dest.addr)
                self.counters.count("handshakes.sent")
            except OSError as err:
                self.counters.warn("udp", f"handshake to {dest.addr[0]}:{dest.addr[1]} failed: {err}")
            init.attempts += 1
            init.next_try = real + 0.1 * 2 ** min(init.attempts, 3)
        return min(init.next_try, real + init.started + wait - now + 0.001)

    # -- what the session table tells (`SessionHost`, through the endpoint) -------------------

    def session_up(self, session: Session) -> None:
        """A session with `session.addr` is confirmed: its destination's handshake state is reset
        and what waited for it is served."""
        with self.queues.cond:
            dest = self.queues.dests.get(session.addr)
            if dest is not None:
                dest.hs_backoff = dest.hs_not_before = 0.0
                dest.hs_failures = 0
                if dest.has_work():
                    self.queues.make_ready(dest)

    def session_lost(self, addr: Address) -> None:
        """The session with `addr` is gone: what waits for it starts a new handshake."""
        with self.queues.cond:
            dest = self.queues.dests.get(addr)
            if dest is not None and dest.has_work():
                self.queues.make_ready(dest)

    def handshake_done(self, init: Initiation) -> None:
        """A handshake ended (answered or refused): its destination no longer drives it."""
        with self.queues.cond:
            dest = self.queues.dests.get(init.addr)
            if dest is not None and dest.handshake is init:
                dest.handshake = None
