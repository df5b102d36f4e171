"""What an endpoint spends before it knows who is talking: connections, bytes, handshakes, beacons."""

from __future__ import annotations

import resource
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from erni.blackboard.clock import SYSTEM


@dataclass(frozen=True)
class Limits:
    """Caps and timeouts that hold before authentication (and after: nothing is unbounded)."""

    max_connections: int = 256
    """TCP connections accepted at once (also kept below the open-file limit)."""
    max_connections_per_host: int = 32
    """TCP connections accepted at once from one source address."""
    idle_timeout: float = 60.0
    """a TCP connection with no complete frame for this long is closed (s)."""
    frame_timeout: float = 10.0
    """a frame started on TCP must be complete within this time, and a new connection must
    deliver its first authenticated frame within it (s)."""
    buffer_budget: int = 32 * 1024 * 1024
    """bytes of incomplete frames held over all connections; beyond it the largest is closed."""
    handshakes_per_host: float = 20.0
    """handshakes answered per second from one source address (burst: as many)."""
    handshakes_total: float = 200.0
    """handshakes answered per second in total."""
    beacons_total: float = 200.0
    """signed beacons verified per second in total."""
    max_sessions: int = 4096
    """sessions kept at once (the least recently used goes first)."""
    session_idle: float = 600.0
    """a session unused for this long is forgotten; the next frame starts a new one (s)."""

    def connection_cap(self) -> int:
        """`max_connections`, kept 64 below the process's open-file limit."""
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft == resource.RLIM_INFINITY:
            return self.max_connections
        return max(1, min(self.max_connections, soft - 64))


class TokenBucket:
    """`rate` events per second with bursts of up to `burst`."""

    def __init__(self, rate: float, burst: float | None = None, clock: Callable[[], float] = SYSTEM):
        self.rate = rate
        self.burst = burst if burst is not None else max(1.0, rate)
        self._clock = clock  # real time: a bucket holds a flood off
        self._tokens = self.burst
        self._at = clock()

    def take(self, now: float | None = None) -> bool:
        """Spend one token; False when none is left."""
        now = self._clock() if now is None else now
        self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
        self._at = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


class HostBuckets:
    """One token bucket per source host, at most `hosts` of them (the least recently used is forgotten)."""

    def __init__(self, rate: float, hosts: int = 4096, clock: Callable[[], float] = SYSTEM):
        self.rate, self.hosts, self._clock = rate, hosts, clock
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()

    def take(self, host: str, now: float | None = None) -> bool:
        """Spend one token of `host`'s bucket."""
        bucket = self._buckets.get(host)
        if bucket is None:
            bucket = self._buckets[host] = TokenBucket(self.rate, clock=self._clock)
            if len(self._buckets) > self.hosts:
                self._buckets.popitem(last=False)
        else:
            self._buckets.move_to_end(host)
        return bucket.take(now)
