"""Blackboard benchmark: publish -> subscriber execute() latency and throughput.

Each figure stands beside a floor measured in the same run: a raw thread handoff with
`queue.Queue` (one consumer thread per subscriber) doing the same work. Ratios are ours
divided by the floor (latency: lower is better; throughput: higher is better).

    python bench/bench_blackboard.py [--rounds 7] [--pings 400] [--burst 3000] [--plugins 1,4,16]
"""

from __future__ import annotations

import argparse
import queue
import statistics
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from erni.blackboard import Agent, BBObject, Plugin  # noqa: E402


class Stamp(BBObject):
    """A published object; its publication time is kept in PUBLISHED[n]."""

    n: int = 0


PUBLISHED: dict[int, float] = {}


class Sink(Plugin):
    """Records the latency of every Stamp it is given."""

    def setup(self) -> None:
        self.sub = self.subscribe(Stamp)
        self.latencies: list[float] = []
        self.seen = 0
        self.done = threading.Event()
        self.expect = 0

    def execute(self) -> None:
        now = time.perf_counter()
        for obj in self.sub.added:
            self.latencies.append(now - PUBLISHED[obj.n])
        self.seen += len(self.sub.added)
        if self.seen >= self.expect:
            self.done.set()


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def bench_blackboard(n_plugins: int, pings: int, burst: int, workers: int) -> tuple[list[float], float]:
    agent = Agent("bench", workers=workers)
    sinks = [agent.add_plugin(Sink, name=f"sink{i}") for i in range(n_plugins)]
    agent.start()
    try:
        latencies: list[float] = []
        for n in range(pings):
            for s in sinks:
                s.done.clear()
                s.expect = s.seen + 1
            obj = Stamp(n=n)
            PUBLISHED[n] = time.perf_counter()  # publish = open, add, commit
            with agent.transaction() as tx:
                tx.add(obj)
            for s in sinks:
                s.done.wait(5)
        for s in sinks:
            latencies.extend(s.latencies)
            s.done.clear()
            s.expect = s.seen + burst
        objs = [Stamp(n=pings + n) for n in range(burst)]
        t0 = time.perf_counter()
        for obj in objs:
            PUBLISHED[obj.n] = time.perf_counter()
            with agent.transaction() as tx:
                tx.add(obj)
        for s in sinks:
            s.done.wait(30)
        elapsed = time.perf_counter() - t0
        return latencies, burst / elapsed
    finally:
        agent.stop(timeout=5)


def bench_floor(n_consumers: int, pings: int, burst: int) -> tuple[list[float], float]:
    queues: list[queue.Queue[float | None]] = [queue.Queue() for _ in range(n_consumers)]
    latencies: list[list[float]] = [[] for _ in range(n_consumers)]
    counts = [0] * n_consumers
    events = [threading.Event() for _ in range(n_consumers)]
    expect = [0] * n_consumers

    def consume(i: int) -> None:
        q = queues[i]
        while True:
            t = q.get()
            if t is None:
                return
            latencies[i].append(time.perf_counter() - t)
            counts[i] += 1
            if counts[i] >= expect[i]:
                events[i].set()

    threads = [threading.Thread(target=consume, args=(i,), daemon=True) for i in range(n_consumers)]
    for t in threads:
        t.start()
    for _ in range(pings):
        for i in range(n_consumers):
            events[i].clear()
            expect[i] = counts[i] + 1
        t = time.perf_counter()
        for q in queues:
            q.put(t)
        for e in events:
            e.wait(5)
    ping_lat = [x for lst in latencies for x in lst]
    for i in range(n_consumers):
        events[i].clear()
        expect[i] = counts[i] + burst
    t0 = time.perf_counter()
    for _ in range(burst):
        t = time.perf_counter()
        for q in queues:
            q.put(t)
    for e in events:
        e.wait(30)
    elapsed = time.perf_counter() - t0
    for q in queues:
        q.put(None)
    for t in threads:
        t.join()
    return ping_lat, burst / elapsed


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7, help="repetitions; medians are reported")
    parser.add_argument("--pings", type=int, default=400, help="single publications per round")
    parser.add_argument("--burst", type=int, default=3000, help="publications in the throughput run")
    parser.add_argument("--workers", type=int, default=4, help="agent worker threads")
    parser.add_argument("--plugins", default="1,4,16", help="comma-separated numbers of subscribing plugins")
    results.add_argument(parser)
    args = parser.parse_args()
    targets = []

    print(f"blackboard benchmark: {args.rounds} rounds x {args.pings} pings, burst {args.burst}, "
          f"{args.workers} workers; medians of rounds; floor = queue.Queue thread handoff")
    header = (f"{'plugins':>7} | {'p50 us':>8} {'floor':>7} {'ratio':>6} | {'p99 us':>8} {'floor':>7} "
              f"{'ratio':>6} | {'objects/s':>10} {'floor':>10} {'ratio':>6}")
    print(header)
    print("-" * len(header))
    for n in (int(x) for x in args.plugins.split(",")):
        rows = []
        for _ in range(args.rounds):
            lat, thr = bench_blackboard(n, args.pings, args.burst, args.workers)
            flat, fthr = bench_floor(n, args.pings, args.burst)
            rows.append((percentile(lat, 0.5), percentile(lat, 0.99), thr,
                         percentile(flat, 0.5), percentile(flat, 0.99), fthr))
        p50, p99, thr, f50, f99, fthr = (statistics.median(col) for col in zip(*rows))
        print(f"{n:>7} | {p50 * 1e6:>8.1f} {f50 * 1e6:>7.1f} {p50 / f50:>6.2f} | {p99 * 1e6:>8.1f} "
              f"{f99 * 1e6:>7.1f} {p99 / f99:>6.2f} | {thr:>10.0f} {fthr:>10.0f} {thr / fthr:>6.2f}")
        targets.append(results.target(
            f"{n} plugin(s), publish → execute p50", "≤ 1.2x the hand-off" if n == 1 else "reported",
            f"queue.Queue hand-off, {f50 * 1e6:.1f} µs", f"{p50 / f50:.2f}x ({p50 * 1e6:.1f} µs)",
            p50 / f50 <= 1.2 if n == 1 else None))
    results.write("bench_blackboard", targets, path=args.results,
                  about="publish → a subscribing plugin's execute(), beside a queue.Queue thread hand-off in the same run")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
