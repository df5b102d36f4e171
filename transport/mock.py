"""An in-memory network for plugin tests: seedable loss, delay, duplication, reordering, partitions.

`MockNetwork.endpoint(name)` returns an object with the interface of `transport.Endpoint`
(`start`, `stop`, `send`, `on_message`, `on_undeliverable`, `address`, `counters`), so a
`TransportPlugin` runs on it unchanged. Bodies are encoded and decoded exactly as on the wire.
Reliable messages are retried until delivered or their time to live ends (a partition makes
them wait), and are de-duplicated by id at the receiver; fast messages may be lost,
duplicated and reordered.
"""

from __future__ import annotations

import heapq
import itertools
import os
import random
import threading
from collections.abc import Callable, Iterable
from typing import Any

from pydantic import BaseModel

from erni.blackboard import new_uid
from erni.blackboard.clock import SYSTEM
from erni.blackboard.errors import UsageError
from erni.transport.endpoint import Address, InboundFilter
from erni.transport.wire import Envelope, Message, SeenIds, body_of, decode_plain, encode_plain


class MockNetwork:
    """A deterministic (given `seed`) lossy network between in-memory endpoints."""

    def __init__(self, seed: int = 0, *, loss: float = 0.0, delay: float = 0.0, jitter: float = 0.0,
                 duplicate: float = 0.0, retry: float = 0.02, clock: Callable[[], float] = SYSTEM):
        for name, p in (("loss", loss), ("duplicate", duplicate)):
            if not 0.0 <= p <= 1.0:
                raise UsageError(f"{name}: expected a probability in 0..1, got {p}")
        self.rng = random.Random(seed)
        self.loss, self.delay, self.jitter, self.duplicate, self.retry = loss, delay, jitter, duplicate, retry
        self.clock = clock  # real time: the network's latencies and retries
        self._endpoints: dict[Address, MockEndpoint] = {}
        self._groups: list[set[str]] | None = None
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._users = 0
        self.counters: dict[str, int] = {"delivered": 0, "lost": 0, "duplicated": 0, "held": 0}

    def endpoint(self, name: str) -> MockEndpoint:
        """Return a new endpoint attached to this network."""
        ep = MockEndpoint(self, name, ("mock", len(self._endpoints) + 1))
        self._endpoints[ep.address] = ep
        return ep

    def partition(self, *groups: Iterable[str]) -> None:
        """Split the network: agents in different groups cannot reach each other."""
        self._groups = [set(g) for g in groups]

    def heal(self) -> None:
        """Remove every partition."""
        self._groups = None

    def connected(self, a: str, b: str) -> bool:
        """Return True when `a` can reach `b` now."""
        if self._groups is None:
            return True
        return any(a in g and b in g for g in self._groups)

    # -- internals ------------------------------------------------------------------------

    def _attach(self) -> None:
        with self._cond:
            self._users += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="erni-mock-network", daemon=True)
                self._thread.start()

    def _detach(self) -> None:
        with self._cond:
            self._users -= 1
            thread = self._thread if self._users == 0 else None
            if thread:
                self._thread = None
                self._cond.notify_all()
        if thread:
            thread.join(2)

    def _later(self, delay: float, fn: Callable[[], None]) -> None:
        with self._cond:
            heapq.heappush(self._heap, (self.clock() + delay, next(self._seq), fn))
            self._cond.notify()

    def _latency(self) -> float:
        return self.delay + (self.rng.random() * self.jitter if self.jitter else 0.0)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while True:
                    if self._thread is None:
                        return
                    now = self.clock()
                    if self._heap and self._heap[0][0] <= now:
                        _, _, fn = heapq.heappop(self._heap)
                        break
                    self._cond.wait(self._heap[0][0] - now if self._heap else None)
            fn()

    def _transmit(self, src: MockEndpoint, addr: Address, frame: bytes, reliable: bool,
                  deadline: float, msg_id: str, kind: str, body: Any, hint: bool = False) -> None:
        found = self._endpoints.get(addr)
        with self._cond:
            if found is None or not found.running or not self.connected(src.name, found.name):
                lost = True
                self.counters["held" if reliable else "lost"] += 1
            else:
                lost = self.rng.random() < self.loss
                if lost:
                    self.counters["lost"] += 1
            dup = not lost and self.rng.random() < self.duplicate
            latency = self._latency()
        if lost:
            if reliable:
                if self.clock() > deadline:
                    src.on_undeliverable(addr, msg_id, kind, body)
                else:
                    self._later(self.retry, lambda: self._transmit(src, addr, frame, True, deadline,
                                                                    msg_id, kind, body))
            return
        dest = found
        assert dest is not None  # not lost: it was found
        self._later(latency, lambda: dest._receive(frame, reliable, hint))
        if dup:
            self.counters["duplicated"] += 1
            self._later(self._latency(), lambda: dest._receive(frame, reliable, hint))


class MockEndpoint:
    """An endpoint of a `MockNetwork`, with the interface of `transport.Endpoint`."""

    def __init__(self, net: MockNetwork, name: str, address: Address, role: str = ""):
        self.net, self.name, self.address, self.role = net, name, address, role
        self.inbound_filter: InboundFilter | None = None
        self.inst = os.urandom(16).hex()
        self._epochs: dict[tuple[str, str], int] = {}
        self._seq = itertools.count(1)
        self._seen = SeenIds()
        self.running = False
        self.counters: dict[str, int] = {}
        self.on_message: Callable[[Message], None] = lambda msg: None
        self.on_undeliverable: Callable[[Address, str, str, Any], None] = lambda a, i, k, b: None

    def start(self) -> None:
        """Join the network."""
        self.running = True
        self.net._attach()

    def receive_buffer(self, size: int) -> int:
        """An in-memory network has no socket buffer to grow: every size is granted."""
        return size

    def stop(self, timeout: float = 1.0) -> None:
        """Leave the network."""
        if self.running:
            self.running = False
            self.net._detach()

    def send(self, addr: Address, kind: str, body: BaseModel | Any = None, *, reliable: bool,
             msg_id: str | None = None, ttl: float | None = None, to: str | None = None) -> str:
        """Queue a message for `addr`; return its id."""
        return self._send(addr, kind, body, reliable, msg_id, ttl, to, hint=False)

    def _send(self, addr: Address, kind: str, body: Any, reliable: bool, msg_id: str | None,
              ttl: float | None, to: str | None, hint: bool) -> str:
        msg_id = msg_id or new_uid()
        env = Envelope(sender=self.name, role=self.role, to=to or "", inst=self.inst, reply=self.address,
                       seq=next(self._seq), id=msg_id, kind=kind,
                       type=type(body).__name__ if isinstance(body, BaseModel) else None,
                       body=body.model_dump(mode="json") if isinstance(body, BaseModel) else body)
        frame = encode_plain(env)
        self.counters["sent"] = self.counters.get("sent", 0) + 1
        self.net._transmit(self, addr, frame, reliable, self.net.clock() + (ttl or 30.0), msg_id, kind, body, hint)
        return msg_id

    def _receive(self, frame: bytes, reliable: bool, hint: bool = False) -> None:
        if not self.running:
            return
        env = decode_plain(frame)
        if env.to and env.to != self.name:
            self.counters["dropped.receiver"] = self.counters.get("dropped.receiver", 0) + 1
            return
        if reliable and not self._seen.first_time(env.sender, env.id):
            self.counters["duplicates"] = self.counters.get("duplicates", 0) + 1
            return
        if self.inbound_filter is not None and not self.inbound_filter(env.sender, env.role):
            self.counters["dropped.unreachable"] = self.counters.get("dropped.unreachable", 0) + 1
            return
        self.net.counters["delivered"] += 1
        key = (env.sender, env.inst)
        if key not in self._epochs:
            self._epochs[key] = 1 + max((e for (name, _), e in self._epochs.items() if name == env.sender), default=0)
        msg = Message(env.sender, env.role, (env.reply[0], env.reply[1]), self._epochs[key], env.seq, env.id,
                      env.kind, body_of(env.type, env.body), hint=hint)
        self.on_message(msg)

    def announce(self, addr: Address, kind: str, body: BaseModel | Any = None) -> str:
        """Send a beacon to a receiver not known yet: it arrives as a hint, as from a real endpoint."""
        return self._send(addr, kind, body, False, None, None, None, hint=True)
