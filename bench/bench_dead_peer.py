"""Dead peer: transaction -> plugin latency on an agent whose sender waits on a dead peer, beside one that does not.

Two agents in one process, each with the transport (the test team's fast timings and identities)
and a Sink plugin that subscribes to a Stamp. Both list a "ghost" peer that answers handshakes
over UDP and then takes TCP connections and never reads nor acknowledges (a black hole). The
"stalled" agent has 50 tasks queued for the ghost, so its sender waits on it for the
acknowledgement timeout; the "normal" one sends it nothing. Transactions publishing one Stamp are
then sampled alternately on the two, from the commit to the Sink's run that got it: a plugin held
up by the sender's wait would show the acknowledgement timeout (2 s here) in the stalled agent's
figures, a busier agent a higher median.

The ratio of the medians (stalled / normal) is the figure; tests/transport/test_remote_tasking.py
held it to 1.2 (plus 100 us) and every sample to 0.5 s, which a loaded machine broke. That test now
only requires every transaction through while the sender waits 60 s on the ghost.

    python bench/bench_dead_peer.py [--rounds 5] [--samples 400]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from erni.blackboard import Task, TaskState  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from tests.transport.helpers import make_agent  # noqa: E402
from tests.transport.test_remote_tasking import Ghost, Sink, _latency, task_to  # noqa: E402


def one_round(samples: int) -> dict[str, list[float]]:
    """Latencies (s) of `samples` transactions on each agent, taken alternately."""
    ghost = Ghost()
    agents = []
    try:
        dead_peer = [f"ghost@127.0.0.1:{ghost.hole.getsockname()[1]}"]
        normal = make_agent("normal", 0, echo=False, peers=dead_peer, ack_timeout=2.0)
        agents.append(normal)
        stalled = make_agent("stalled", 0, echo=False, peers=dead_peer, ack_timeout=2.0)
        agents.append(stalled)
        sinks = {a.name: a.add_plugin(Sink) for a in agents}
        with stalled.transaction() as tx:
            for i in range(50):
                tx.add(task_to("ghost", distance=float(i + 1)))
        ghost.hole.settimeout(5)
        conn, _ = ghost.hole.accept()  # the stalled agent's sender now waits on the dead peer
        wait_until(lambda: all(t.result is not None and t.result.state is TaskState.PENDING
                               for t in stalled.query(Task)), timeout=30)
        out: dict[str, list[float]] = {"normal": [], "stalled": []}
        for i in range(samples):
            for agent in (normal, stalled) if i % 2 else (stalled, normal):
                out[agent.name].append(_latency(agent, sinks[agent.name], i))
        conn.close()
        return out
    finally:
        for agent in agents:
            agent.stop()
        ghost.close()


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--samples", type=int, default=400, help="transactions per agent and round")
    results.add_argument(ap)
    args = ap.parse_args()
    logging.getLogger("erni").setLevel(logging.ERROR)  # the ghost's connection reset at each round's end
    print(f"dead peer: {args.rounds} rounds x {args.samples} transactions per agent (latency in us)")
    print(f"{'round':>5} | {'normal p50':>10} {'p99':>8} {'max':>8} | {'stalled p50':>11} {'p99':>8} {'max':>8} | ratio")
    ratios, normal, stalled = [], [], []
    for r in range(args.rounds):
        got = one_round(args.samples)
        n, s = got["normal"], got["stalled"]
        normal += n
        stalled += s
        ratio = statistics.median(s) / statistics.median(n)
        ratios.append(ratio)
        print(f"{r + 1:>5} | {statistics.median(n) * 1e6:>10.0f} {pct(n, 0.99) * 1e6:>8.0f} {max(n) * 1e6:>8.0f} | "
              f"{statistics.median(s) * 1e6:>11.0f} {pct(s, 0.99) * 1e6:>8.0f} {max(s) * 1e6:>8.0f} | {ratio:.2f}")
    ratio = statistics.median(ratios)
    print(f"median ratio of the rounds (stalled / normal p50): {ratio:.2f}")
    results.write("bench_dead_peer", [
        results.target("transaction → plugin, beside a sender waiting on a dead peer (p50)", "at most 1.2x the floor",
                       f"the same agent without the dead peer, {statistics.median(normal) * 1e6:.0f} us",
                       f"{ratio:.2f}x ({statistics.median(stalled) * 1e6:.0f} us)", ratio <= 1.2),
        results.target("slowest transaction beside the waiting sender", "far below the 2 s acknowledgement timeout",
                       f"slowest without the dead peer, {max(normal) * 1e3:.1f} ms", f"{max(stalled) * 1e3:.1f} ms",
                       max(stalled) < 1.0)],
        path=args.results, about="a plugin's transaction latency while the transport's sender waits on a black hole")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
