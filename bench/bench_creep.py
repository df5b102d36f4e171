"""Creep benchmark: end robots drive away from their only neighbour; does the guard stop them in range?

Scenario `creep` (see its file and `erni.sim.creep`): four spokes, each an end robot that drives
straight away from its relay at its own speed (0.1, 0.3, 0.5, 1.0 m/s) through the lossy band
(6-10 m) towards the range limit (10 m), in the mission's default policy (`hold`,
`min_link_quality` 0.3). Every round is one trial per speed; a round ends when each end robot
has stood for 12 s (a release on a flicker shows), reached its goal, or left its relay's range.

    python bench/bench_creep.py --rounds 10                 # loopback tier (SNMP, simulated radio)
    sudo python bench/bench_creep.py --rounds 10 --netns    # real-mesh tier (namespaces, babeld)
    ... --loss 0.3                                          # and 30 % background loss
    ... --blind                                             # the same with the guard off
    sudo python bench/bench_creep.py --rounds 3 --netns --channel ns3   # ns-3's 802.11a channel

Printed per speed: partitions (the end robot left its relay's range: the team split), the closest
approach to the range limit (m), the time from crossing the distance where the radio delivers 0.3
to standstill (s, negative: stood before crossing), how far it crept on after it first stood (m);
and the load average. The floor is the radio itself: the distance of quality 0.3 (8.8 m) and the
range (10 m) are the scenario's inputs. `--json FILE` keeps every trial with its track.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from erni.sim import creep  # noqa: E402
from erni.sim.scenario import find_scenario, load_scenario  # noqa: E402
from erni.sim.team import Team  # noqa: E402

FAST = {"beacon_period": 0.3, "peer_timeout": 1.5, "task_ttl": 60.0}


def team_for(netns: bool, loss: float, blind: bool, run_dir: str, channel: str | None = None) -> Team:
    scenario = load_scenario(find_scenario("creep"))
    transport = dict(FAST)
    if loss and not netns:  # the loopback tier has no radio to lose frames on: each agent drops its own
        transport["udp_loss"] = loss
    team = Team(scenario, run_dir=run_dir, headless=True, transport=transport, netns=netns, mission=True,
                mission_settings={"network_aware": not blind}, channel=channel)
    return team


def messages_of(team: Team) -> Callable[[str], list[str]]:
    seen: dict[str, list[str]] = {}

    def pump() -> None:
        client = team.client()
        while (msg := client.receive(0.0)) is not None:
            body = getattr(msg, "body", None)
            if msg.kind == "task.result" and body is not None:
                seen.setdefault(body.uid, []).append(body.result.message)

    def messages(uid: str) -> list[str]:
        pump()
        return seen.get(uid, [])
    return messages


def main(argv: list[str] | None = None) -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3, help="trials per speed (default 3)")
    ap.add_argument("--netns", action="store_true", help="the real-mesh tier (root: namespaces, babeld)")
    ap.add_argument("--channel", choices=["nftables", "ns3"], help="with --netns: the channel between the "
                    "namespaces (default nftables; ns3: ns-3's 802.11a, reaching as far as the radio model)")
    ap.add_argument("--loss", type=float, default=0.0, help="background loss on every link, 0..1 (default 0)")
    ap.add_argument("--blind", action="store_true", help="the mission's network awareness off")
    ap.add_argument("--speeds", type=float, nargs="+", default=list(creep.SPEEDS), help="m/s, one per spoke")
    ap.add_argument("--json", type=Path, help="write every trial (with its track) here")
    ap.add_argument("--plot", type=Path, help="draw the trials of the --json files given with --from as a PNG")
    ap.add_argument("--from", dest="sources", type=Path, nargs="+", default=[],
                    help="with --plot: JSON files of earlier runs (one per tier and loss)")
    results.add_argument(ap)
    args = ap.parse_args(argv)
    if args.plot:
        if not args.sources:
            ap.error("--plot: name the runs to draw with --from FILE.json ...")
        plot(args.sources, args.plot)
        print(f"wrote {args.plot}")
        return 0
    if not 0.0 <= args.loss < 1.0:
        ap.error(f"--loss: expected a share in 0..1, got {args.loss}")
    if args.channel and not args.netns:
        ap.error("--channel chooses the real-mesh tier's channel: add --netns")
    if args.channel == "ns3" and args.loss:
        ap.error("--loss is the nftables channel's: on ns-3 the channel decides loss itself")
    trials: list[creep.Trial] = []
    loads = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory(prefix="erni-creep-") as tmp:
        team = team_for(args.netns, args.loss, args.blind, tmp, args.channel)
        t0 = time.monotonic()
        try:
            team.start(timeout=120)
            messages = messages_of(team)
            if args.netns and args.loss:
                assert team.mesh is not None
                team.mesh.set_extra_loss(args.loss)
            for k in range(args.rounds):
                creep.reset(team, lambda: creep.peers_up(team), rest=8.0 if args.netns else 3.0)
                got = creep.run_round(team, k + 1, args.speeds, messages=messages)
                trials += got
                loads.append(os.getloadavg()[0])
                print(f"round {k + 1}/{args.rounds}: " + "; ".join(
                    f"{t.speed:g} m/s {'PARTITION' if t.partitioned else 'held'} closest {t.closest:.2f} m, "
                    f"stood {_s(t.stop_after_crossing)} after crossing, crept on {t.crept_on:.2f} m, "
                    f"resumed {t.resumed}x, top speed {t.top_speed:.2f} m/s"
                    for t in got), flush=True)
        finally:
            team.stop()
        took = time.monotonic() - t0
    tier = ("netns-ns3 (babeld, ns-3's 802.11a)" if args.channel == "ns3" else "netns (babeld)") if args.netns \
        else "loopback (SNMP)"
    print(f"\ncreep, tier {tier}, loss {args.loss:.0%}, guard {'off' if args.blind else 'on'}, "
          f"{args.rounds} round(s), {took:.0f} s, load average {min(loads):.1f}-{max(loads):.1f}")
    print(f"{'speed':>6} {'partitions':>11} {'closest to limit (m)':>30} {'stood after crossing (s)':>32} "
          f"{'crept on (m)':>13} {'top speed':>10}")
    for v in args.speeds:
        ts = [t for t in trials if t.speed == v]
        part = sum(t.partitioned for t in ts)
        closest = [t.closest for t in ts]
        after = [t.stop_after_crossing for t in ts if t.stop_after_crossing is not None]
        print(f"{v:6g} {part:>5}/{len(ts):<5} {_range(closest):>30} {_range(after):>32} "
              f"{max((t.crept_on for t in ts), default=0):13.2f} {max((t.top_speed for t in ts), default=0):10.2f}")
    if args.json:
        args.json.write_text(json.dumps({"tier": tier, "loss": args.loss, "blind": args.blind,
                                         "trials": [t.row() | {"track": t.track} for t in trials]}, indent=1))
    name = f"{tier.split()[0]}, loss {args.loss:.0%}" + (", guard off" if args.blind else "")
    targets = [results.target(f"partitions, {name}", "none" if not args.blind else "reported",
                              "the radio's range limit", f"{sum(t.partitioned for t in trials)} in {len(trials)} trials",
                              not any(t.partitioned for t in trials) if not args.blind else None)]
    targets += [results.target(f"closest approach to the range limit at {v:g} m/s, {name}", "reported",
                               "the range limit", _range([t.closest for t in trials if t.speed == v]) + " m", None)
                for v in args.speeds]
    results.write("bench_creep", targets, path=args.results, argv=argv,
                  about="end robots driving away from their only neighbour with the guard on")
    return 1 if any(t.partitioned for t in trials) and not args.blind else 0


def plot(sources: list[Path], out: Path) -> None:
    """Per run: each end robot's distance from its relay over time (the radio's 0.3 and its range
    drawn in); then the closest approach to the range limit and the time from crossing to standing,
    per speed and run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [json.loads(p.read_text()) for p in sources]
    speeds = sorted({t["speed"] for r in runs for t in r["trials"]})
    colours = {v: c for v, c in zip(speeds, ("#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e"))}
    fig, axes = plt.subplots(2, max(2, len(runs)), figsize=(4.2 * max(2, len(runs)), 7.5), squeeze=False)
    names = []
    for col, run in enumerate(runs):
        ax = axes[0][col]
        name = f"{run['tier'].split()[0]}, loss {run['loss']:.0%}" + (", guard off" if run.get("blind") else "")
        names.append(name)
        for t in run["trials"]:
            ts, ds = zip(*t["track"]) if t["track"] else ((), ())
            ax.plot(ts, ds, color=colours[t["speed"]], lw=0.8, alpha=0.7)
        ax.axhline(8.8, color="grey", ls="--", lw=0.8)
        ax.axhline(10.0, color="black", lw=1.0)
        ax.text(0.5, 8.85, "radio delivers 0.3 (input)", fontsize=7, color="grey")
        ax.text(0.5, 10.05, "range limit (input)", fontsize=7)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("s since the goto was sent")
        ax.set_ylim(5.5, 11.0)
        if col == 0:
            ax.set_ylabel("distance from its relay (m)")
    for v in speeds:
        axes[0][0].plot([], [], color=colours[v], label=f"{v:g} m/s")
    axes[0][0].legend(fontsize=7, loc="lower right")
    for k, (key, label) in enumerate((("closest_m", "closest approach to the range limit (m)"),
                                      ("stop_after_crossing_s", "stood after crossing 0.3 (s; < 0: before)"))):
        ax = axes[1][k]
        for col, run in enumerate(runs):
            for i, v in enumerate(speeds):
                ys = [t[key] for t in run["trials"] if t["speed"] == v and t[key] is not None]
                x = i + (col - (len(runs) - 1) / 2) * 0.8 / max(1, len(runs))
                ax.scatter([x] * len(ys), ys, s=10, color=f"C{col}", label=names[col] if i == 0 else None)
        ax.axhline(0.0, color="black", lw=0.8)
        ax.set_xticks(range(len(speeds)), [f"{v:g} m/s" for v in speeds])
        ax.set_ylabel(label, fontsize=9)
        ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
        ax.legend(fontsize=7)
    for ax in axes[1][2:]:
        ax.axis("off")
    fig.suptitle("Creeping out of radio range: end robots driving away from their only neighbour, guard on",
                 fontsize=11)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def _s(x: float | None) -> str:
    return "never" if x is None else f"{x:+.1f} s"


def _range(xs: list[float]) -> str:
    if not xs:
        return "-"
    return f"{min(xs):.2f} / {statistics.median(xs):.2f} / {max(xs):.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
