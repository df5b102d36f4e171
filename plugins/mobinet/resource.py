"""`MobiNetResource` and the one interface (`NetworkSource`) it reads the network through.

The resource is the thread that polls the network subsystem and writes the robot's pose.
It owns one asyncio loop (thread `mobinet-<agent>`) and one `NetworkSource` created inside
it. Watches (one per NetWatch task) are polled at their own rates; watches due at about
the same time share one read, and a watch whose period is a multiple of another's falls into
that one's pace after its first read (a watch added later shares reads too). Results and failures go to a callback that must not block
(MobiNetControl hands them to the blackboard with `later()`). Pose writes keep only the
latest pose. Nothing here ever touches the blackboard, and no call made from another
thread waits for SNMP.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from erni.blackboard import Link, Neighbor, Position, Route
from erni.blackboard.clock import monotonic
from erni.blackboard.errors import ErniError
from erni.plugins.mobinet.sanity import Absurd

# what a read may ask for
NEIGHBORS = "neighbors"
TOPOLOGY = "topology"
ROUTES = "routes"
POSITIONS = "positions"
PARTS = frozenset({NEIGHBORS, TOPOLOGY, ROUTES, POSITIONS})


class SourceError(ErniError):
    """The network subsystem could not be read or written; the message says why, in one line."""


@dataclass
class NetView:
    """One reading of the network subsystem (only the requested parts are filled).

    `sources` maps "node" and each filled part (a PARTS name) to where it came from, e.g.
    "snmp 127.0.0.1:1162 NHDP-MIB nhdpDiscIfSetTable"; `missing` maps each requested part
    the subsystem does not provide to the reason, e.g. "NHDP-MIB not served by ...";
    `dropped` lists the rows left out as implausible or mistyped (their part is degraded).
    """

    node: str
    address: str
    names: dict[str, str] = field(default_factory=dict)   # address -> node name
    neighbors: list[Neighbor] = field(default_factory=list)
    links: list[Link] = field(default_factory=list)
    routes: list[Route] = field(default_factory=list)
    positions: dict[str, Position] = field(default_factory=dict)
    sources: dict[str, str] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)
    dropped: list[Absurd] = field(default_factory=list)


@runtime_checkable
class NetworkSource(Protocol):
    """Reads and writes the network subsystem; methods run on MobiNet's asyncio thread.

    Implementations raise `SourceError` (one clear line) for timeouts, error answers and
    malformed or mistyped data, and list the parts they cannot provide in `NetView.missing`
    instead of failing. The SNMP implementation is `SnmpSource`; another (for example a
    babeld or olsrd2 reader) only has to provide these three coroutines.
    """

    async def read(self, parts: frozenset[str]) -> NetView:
        """Return a view with the requested parts (a subset of PARTS), each either filled
        (named in `sources`) or named in `missing`."""
        ...

    async def write_position(self, position: Position) -> None:
        """Tell the network subsystem where this node is (x, y in m, heading in deg)."""
        ...

    async def aclose(self) -> None:
        """Release sockets and engines."""
        ...


Delivery = Callable[[str, "NetView | None", str], None]   # (watch key, view or None, error)


class RateLimitedLog:
    """Log a warning per key at most once per `interval` seconds, counting what was held back."""

    def __init__(self, log: logging.Logger, interval: float,
                 clock: Callable[[], float] = monotonic) -> None:
        self.log = log
        self.interval = interval
        self.clock = clock
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def warning(self, key: str, message: str) -> bool:
        """Emit `message` unless the same key was logged within the interval; True if logged."""
        now = self.clock()
        if now - self._last.get(key, -1e18) < self.interval:
            self._held[key] = self._held.get(key, 0) + 1
            return False
        held = self._held.pop(key, 0)
        suffix = f" ({held} similar message(s) suppressed)" if held else ""
        self.log.warning("%s%s", message, suffix)
        self._last[key] = now
        return True


@dataclass
class _Watch:
    key: str
    parts: frozenset[str]
    period: float
    due: float


class MobiNetResource:
    """Poll watches at their rates and write poses through a `NetworkSource` on its own thread."""

    def __init__(self, make_source: Callable[[], NetworkSource], deliver: Delivery,
                 log: logging.Logger, log_interval: float = 10.0, name: str = "mobinet",
                 retry_delay: float = 1.0, write_interval: float = 0.0, absurd_interval: float = 60.0,
                 clock: Callable[[], float] = monotonic) -> None:
        self.retry_delay = retry_delay
        self.write_interval = write_interval
        self._make_source = make_source
        self._deliver = deliver
        self.log = log
        self.clock = clock  # when watches are due (a test's ManualClock: they fall due as it advances)
        self.limited = RateLimitedLog(log, log_interval, clock)
        # an implausible row is read again at every poll while the agent keeps saying it: one
        # warning a minute per agent and column, whatever the rate of the watches
        self.absurd = RateLimitedLog(log, absurd_interval, clock)
        self.name = name
        self._watches: dict[str, _Watch] = {}
        self._pose: Position | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._kick: asyncio.Event | None = None
        self._pose_event: asyncio.Event | None = None
        self._stopping = False
        self._tasks: list[asyncio.Future[Any]] = []
        self.source: NetworkSource | None = None
        self.stats = {"reads": 0, "read_errors": 0, "writes": 0, "write_errors": 0, "dropped": 0}
        watch = getattr(clock, "on_advance", None)
        if callable(watch):  # a test's clock says when it moves: the poller looks at the watches again
            watch(lambda: self._call(self._wake))

    # -- called from any thread (never blocks on SNMP) ------------------------------------

    def start(self) -> MobiNetResource:
        """Start the SNMP thread."""
        if self._thread is not None:
            return self
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()
        return self

    def watch(self, key: str, parts: frozenset[str], rate_hz: float) -> None:
        """Poll `parts` every 1/rate_hz seconds and deliver under `key` (replaces an old watch)."""
        period = 1.0 / rate_hz

        def add() -> None:
            self._watches[key] = _Watch(key, parts, period, self.clock())
            self._wake()

        self._call(add)

    def unwatch(self, key: str) -> None:
        """Stop polling for `key`; nothing more is delivered for it."""
        def drop() -> None:
            self._watches.pop(key, None)
        self._call(drop)

    def watching(self) -> list[str]:
        """Keys of the watches currently polled."""
        return list(self._watches)

    def write_position(self, position: Position) -> None:
        """Write this position to the network subsystem soon (a newer one replaces it)."""
        def store() -> None:
            self._pose = position
            if self._pose_event is not None:
                self._pose_event.set()
        self._call(store)

    def close(self, timeout: float = 3.0) -> None:
        """Stop polling, close the source and join the thread."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return

        def stop() -> None:
            self._stopping = True
            for task in self._tasks:  # a read or write in flight is abandoned, not awaited
                task.cancel()
        self._call(stop)
        thread.join(timeout)
        if thread.is_alive():
            self.log.warning("MobiNet SNMP thread did not stop within %.1f s", timeout)
        self._thread = None

    # -- the loop --------------------------------------------------------------------------

    def _call(self, fn: Callable[[], Any]) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(fn)
        except RuntimeError:  # loop closed meanwhile
            pass

    def _wake(self) -> None:
        if self._kick is not None:
            self._kick.set()

    def _run(self) -> None:
        assert self._loop is not None
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._main())
        except Exception:
            self.log.exception("MobiNet SNMP thread failed")
        finally:
            self._loop.run_until_complete(self._loop.shutdown_asyncgens())
            self._loop.run_until_complete(self._loop.shutdown_default_executor())
            self._loop.close()

    async def _main(self) -> None:
        self._kick = asyncio.Event()
        self._pose_event = asyncio.Event()
        if self._pose is not None:
            self._pose_event.set()
        try:
            self.source = self._make_source()
        except Exception as err:
            self.log.error("cannot create the network source: %s", err)
            return
        self._tasks = [asyncio.ensure_future(self._poller()),
                       asyncio.ensure_future(self._pose_writer())]
        if self._stopping:
            for task in self._tasks:
                task.cancel()
        try:
            for outcome in await asyncio.gather(*self._tasks, return_exceptions=True):
                if isinstance(outcome, Exception):
                    self.log.error("MobiNet SNMP task failed: %r", outcome)
        finally:
            try:
                await self.source.aclose()
            except Exception as err:  # closing must not hide the shutdown
                self.log.debug("closing the network source: %s", err)

    async def _poller(self) -> None:
        assert self._kick is not None
        while not self._stopping:
            now = self.clock()
            # a watch due within a fifth of its period joins this read
            due = [w for w in self._watches.values() if w.due - now <= 0.2 * w.period]
            if not due:
                nxt = min((w.due for w in self._watches.values()), default=None)
                self._kick.clear()
                try:  # no watch: sleep until one is added (or the resource closes)
                    await asyncio.wait_for(self._kick.wait(), None if nxt is None else max(0.0, nxt - now))
                except TimeoutError:
                    pass
                continue
            parts = frozenset().union(*(w.parts for w in due))
            view, error = await self._read(parts)
            done = self.clock()
            for w in due:
                if self._watches.get(w.key) is not w:
                    continue  # cancelled or replaced during the read
                w.due = self._aligned(w, w.due + w.period if w.due + w.period > done else done + w.period, done)
                try:
                    self._deliver(w.key, view, error)
                except Exception:
                    self.log.exception("delivering a MobiNet result failed")

    def _aligned(self, w: _Watch, due: float, done: float) -> float:
        """When `w` is read next: `due`, or the latest read of a faster (or as fast) watch whose period
        divides its own in the half period before it, after which it keeps that watch's pace. Watches
        added at different times then share their reads (a 1 Hz watch every other read of a 2 Hz one)
        instead of each waking the source at its own phase."""
        best = due
        for o in self._watches.values():
            if o is w or o.period > w.period:
                continue
            ratio = w.period / o.period
            if abs(ratio - round(ratio)) > 0.01 * ratio:
                continue  # not on a common pace: joining its reads would change this watch's rate
            k = math.floor((due - o.due) / o.period + 1e-9)
            point = o.due + k * o.period
            if done < point < best and point >= due - 0.5 * w.period - 1e-9:
                best = point
        return best

    async def _read(self, parts: frozenset[str]) -> tuple[NetView | None, str]:
        assert self.source is not None
        self.stats["reads"] += 1
        try:
            view = await self.source.read(parts)
            for row in view.dropped:
                self.stats["dropped"] += 1
                self.absurd.warning(f"{row.agent} {row.column}", str(row))
            return view, ""
        except SourceError as err:
            message = str(err)
        except Exception as err:  # a source bug degrades the result, it never stops polling
            message = f"{type(err).__name__}: {err}"
        self.stats["read_errors"] += 1
        self.limited.warning("read", f"network read failed: {message}")
        return None, message

    async def _pose_writer(self) -> None:
        assert self._pose_event is not None and self.source is not None
        while not self._stopping:
            await self._pose_event.wait()
            self._pose_event.clear()
            pose, self._pose = self._pose, None
            if pose is None or self._stopping:
                continue
            self.stats["writes"] += 1
            started = monotonic()  # the pace of real writes, slept in real time
            try:
                await self.source.write_position(pose)
                rest = started + self.write_interval - monotonic()
                if rest > 0 and not self._stopping:  # a newer pose meanwhile waits for the interval's end
                    await asyncio.sleep(rest)
            except Exception as err:
                self.stats["write_errors"] += 1
                self.limited.warning("write", f"writing the position failed: {err}")
                if self._pose is None:  # retry the same pose unless a newer one arrived
                    self._pose = pose
                await asyncio.sleep(self.retry_delay)
                self._pose_event.set()
