"""Paper 004's open question: does a network-aware team keep its connectivity and still do its task?

The same missions run on the same team (agent processes, tasked by the control node) with the
mission plugin's network awareness on and off, over several seeds:

- goto: every robot gets a remote goto to a point drawn by the seed, `goto_near`-`goto_far` m
  from the control node in directions spread around it, which pulls the team apart;
- randomwalk: every robot gets a remote random walk of `walk` seconds (seeded);
- widep: the team must cover a PoI `poi_distance` m from the control node, more than one
  radio range away. Aware: `Deploy widep` (steps bounded by the RNG connectivity rule, with R
  the longest link of quality `min_link_quality`, as the aware policy judges links).
  Blind: every robot a remote goto straight to the PoI.

Network-aware means the mission's `network_aware` setting with its default policy (`hold`: a
robot whose best link falls below `min_link_quality` or that becomes an articulation point
stops and resumes when connectivity returns); blind means `network_aware = false`.

Measured on every run: connectivity kept, the share of the simulator's 10 Hz samples in which
the whole team and the control node are one radio component; tasks completed: a goto's robot
at its target and the PoI covered (both judged on the simulator's truth, since a robot cut off
from the control node cannot report it), a walk that ran its time (from its task's result);
time to complete, from the tasks being sent; and how many successes the control node heard of. Each is averaged over the seeds with a 95 % Student-t
interval (completion also as a Wilson interval over all tasks).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Any

import numpy as np

from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.experiments.stats import fmt_ci, mean_ci, wilson
from erni.sim.scenario import Scenario, ScenarioError

MISSIONS = ("goto", "randomwalk", "widep")
ARMS = ("aware", "blind")


@dataclass
class Outcome:
    """One mission on one seed with one arm."""

    mission: str
    arm: str
    seed: int
    connected: float       # share of samples with the team in one component
    tasks: int
    completed: int
    times: list[float]     # s from sending to success, completed tasks only
    length: float          # s the run lasted
    reported: int = 0      # successes the control node heard of


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, seeds: int | None = None,
        **_: Any) -> Result:
    """Run every mission with awareness on and off over the seeds; return figure and table."""
    s = scenario.strategy
    n_seeds = seeds or int(s.get("seeds", 10))
    missions = [str(m) for m in s.get("missions", list(MISSIONS))]
    for m in missions:
        if m not in MISSIONS:
            raise ScenarioError(f"strategy.missions: unknown mission {m!r}; expected some of {', '.join(MISSIONS)}")
    outcomes: list[Outcome] = []
    total = n_seeds * len(missions) * len(ARMS)
    k = 0
    for i in range(n_seeds):
        seed = scenario.seed + i
        for mission in missions:
            for arm in ARMS:
                k += 1
                tag = f"[{k}/{total}] seed {seed} {mission} {arm}"

                def told(what: str, done: float, total_: float, tag: str = tag) -> None:
                    progress(f"{tag}: {what}", done, total_)

                outcomes.append(_one(scenario.model_copy(update={"seed": seed}), mission, arm, told))
                o = outcomes[-1]
                progress(f"{tag}: connected {o.connected:.0%}, {o.completed}/{o.tasks} done", k, total)
    return _result(scenario, experiment, mode, outcomes, missions, n_seeds)


def _targets(scenario: Scenario, n: int) -> list[tuple[float, float]]:
    s = scenario.strategy
    rng = random.Random(scenario.seed * 7919 + 17)
    near, far = float(s.get("goto_near", 8.0)), float(s.get("goto_far", 14.0))
    c = scenario.control
    base = rng.uniform(0, 2 * math.pi)
    out = []
    for i in range(n):
        a = base + 2 * math.pi * i / n + rng.uniform(-0.4, 0.4)
        r = rng.uniform(near, far)
        out.append((round(c.x + r * math.cos(a), 2), round(c.y + r * math.sin(a), 2)))
    return out


def widep_range(scenario: Scenario) -> float:
    """WiDep's R for the aware team: the longest link of quality `min_link_quality` (m).

    The radio's `comm_range` is where delivery falls to 0: a link kept just short of it loses
    almost every packet (and is not even used for routing below the radio's `min_quality`), so a
    team spread to it is one component on paper and cut off in fact.
    """
    from erni.sim.manet import RadioModel

    r = scenario.radio
    q = float(scenario.strategy.get("min_link_quality", 0.3))
    return round(RadioModel(r.comm_range, r.lossless_range, r.min_quality).range_for(max(q, r.min_quality)), 3)


def _one(scenario: Scenario, mission: str, arm: str, progress: Progress) -> Outcome:
    from erni.sim.experiments.agents import TeamRun

    s = scenario.strategy
    names = scenario.robot_names()
    aware = arm == "aware"
    settings = {"network_aware": aware, "speed": float(s.get("speed", 0.4)), "separation": 1.0,
                "min_link_quality": float(s.get("min_link_quality", 0.3))}
    speed = float(s.get("speed", 0.4))
    with TeamRun(scenario, progress, mission=settings).start() as team:
        uids: list[str] = []
        targets = _targets(scenario, len(names))
        arrived: dict[int, float] = {}  # robot index -> when the simulator saw it at its goto target
        if mission == "goto":
            limit = float(s.get("goto_time", 75.0))
            for name, (x, y) in zip(names, targets):
                uids.append(team.send(name, "RemoteBotMotion", "goto", x=x, y=y, speed=speed, tolerance=0.3))
        elif mission == "randomwalk":
            walk = float(s.get("walk", 45.0))
            limit = walk + 15.0
            for i, name in enumerate(names):
                uids.append(team.send(name, "RemoteBotMotion", "randomwalk", speed=speed, duration=walk,
                                      seed=scenario.seed * 100 + i))
        else:
            limit = float(s.get("widep_time", 150.0))
            c = scenario.control
            a = random.Random(scenario.seed).uniform(0, 2 * math.pi)
            d = float(s.get("poi_distance", 14.0))
            poi = (round(c.x + d * math.cos(a), 2), round(c.y + d * math.sin(a), 2))
            reach = widep_range(scenario)
            for name in names:
                if aware:
                    uids.append(team.send(name, "Deploy", "widep", x=poi[0], y=poi[1],
                                          range=reach, tolerance=0.5,
                                          period=float(s.get("period", 4.0))))
                else:
                    uids.append(team.send(name, "RemoteBotMotion", "goto", x=poi[0], y=poi[1], speed=speed,
                                          tolerance=0.5))
        covered: list[float] = []

        def finished() -> bool:
            assert team.team is not None
            if mission == "widep":
                if not covered and any(math.hypot(r.x - poi[0], r.y - poi[1]) <= 0.5 for r in team.team.robots):
                    covered.append(team.now)
                return bool(covered)
            if mission == "goto":
                for i, (r, (x, y)) in enumerate(zip(team.team.robots, targets)):
                    if i not in arrived and math.hypot(r.x - x, r.y - y) <= 0.4:
                        arrived[i] = team.now
                return len(arrived) == len(names) or team.done(uids)
            return team.done(uids)

        team.wait(f"{mission} ({arm})", limit, finished)
        samples = team.samples()
        length = team.now
        # the last results on their way (a WiDep robot learns of the coverage at its next round)
        team.pump(2.0 + (float(s.get("period", 4.0)) if mission == "widep" else 0.0))
        reported = sum(1 for u in uids if math.isfinite(team.succeeded_at(u)))
        if mission == "widep":
            done, times = (1, [covered[0]]) if covered else (0, [])
            tasks = 1
            reported = int(any(math.isfinite(team.succeeded_at(u)) for u in uids))
        elif mission == "goto":  # arrival judged on the simulator's truth: a cut-off robot cannot report it
            times = sorted(arrived.values())
            done, tasks = len(times), len(uids)
        else:
            times = [t for u in uids if math.isfinite(t := team.succeeded_at(u))]
            done, tasks = len(times), len(uids)
    connected = float(np.mean([x.components == 1 for x in samples])) if samples else math.nan
    return Outcome(mission, arm, scenario.seed, connected, tasks, done, times, length, reported)


def _result(scenario: Scenario, experiment: Experiment, mode: str, outcomes: list[Outcome], missions: list[str],
            n_seeds: int) -> Result:
    res = Result(experiment.name, experiment.title, mode)
    n = scenario.count
    res.mode_note = (f"{n} robot agent processes and a control node per run, a new team for every mission, arm and "
                     "seed; connectivity judged on the simulator's radio model every 0.1 s")
    summary: dict[tuple[str, str], dict[str, tuple[float, float, float]]] = {}
    for mission in missions:
        for arm in ARMS:
            runs = [o for o in outcomes if o.mission == mission and o.arm == arm]
            conn = mean_ci([o.connected for o in runs], bounds=(0.0, 1.0))
            share = mean_ci([o.completed / o.tasks for o in runs], bounds=(0.0, 1.0))
            pooled = wilson(sum(o.completed for o in runs), sum(o.tasks for o in runs))
            per_run_time = [float(np.mean(o.times)) for o in runs if o.times]
            tcomp = mean_ci(per_run_time)
            summary[(mission, arm)] = {"connected": conn, "completed": share, "pooled": pooled, "time": tcomp}
            res.metrics[f"{mission}, {arm}: connectivity kept (share of time)"] = (fmt_ci(*conn), "mean [95 % CI]")
            res.metrics[f"{mission}, {arm}: tasks completed"] = (
                f"{sum(o.completed for o in runs)}/{sum(o.tasks for o in runs)} = {fmt_ci(*pooled)}", "Wilson 95 %")
            res.metrics[f"{mission}, {arm}: time to complete"] = (fmt_ci(*tcomp, 1),
                                                                 f"s, mean [95 % CI] over {len(per_run_time)} runs")
            res.metrics[f"{mission}, {arm}: successes the control node heard of"] = (
                f"{sum(o.reported for o in runs)}/{sum(o.tasks for o in runs)}", "tasks")
            for o in runs:
                res.robots[f"{mission}/{arm}/s{o.seed}"] = {
                    "connected": round(o.connected, 3), "completed": f"{o.completed}/{o.tasks}",
                    "time_s": round(float(np.mean(o.times)), 1) if o.times else "-"}
    res.compare("robots / radio range R / lossless", "not stated (paper 004 asks the question)",
                f"{n} / {scenario.radio.comm_range:g} m / {scenario.radio.lossless_range:g} m", "",
                "the scenario's setting", "input")
    if "widep" in missions:
        res.compare("widep: WiDep's R (aware)", "R = communication range", f"{widep_range(scenario):g}", "m",
                    "the longest link of quality min_link_quality on the radio model", "input")
    res.compare("seeds per mission and arm", "-", n_seeds, "", "start layout fixed; the seed draws targets, walks, "
                "the PoI's direction and the simulated robots' noise", "input")
    for mission in missions:
        a, b = summary[(mission, "aware")], summary[(mission, "blind")]
        res.compare(f"{mission}: connectivity kept, aware / blind", "open question",
                    f"{a['connected'][0]:.2f} / {b['connected'][0]:.2f}", "share",
                    f"aware {fmt_ci(*a['connected'])}, blind {fmt_ci(*b['connected'])}")
        res.compare(f"{mission}: tasks completed, aware / blind", "open question",
                    f"{a['pooled'][0]:.2f} / {b['pooled'][0]:.2f}", "share",
                    f"aware {fmt_ci(*a['pooled'])}, blind {fmt_ci(*b['pooled'])} (Wilson)")
        heard = {arm: (sum(o.reported for o in outcomes if o.mission == mission and o.arm == arm),
                       sum(o.tasks for o in outcomes if o.mission == mission and o.arm == arm)) for arm in ARMS}
        res.compare(f"{mission}: successes the control node heard of, aware / blind", "open question",
                    f"{heard['aware'][0]}/{heard['aware'][1]} / {heard['blind'][0]}/{heard['blind'][1]}", "tasks",
                    "task results that reached the control node")
        res.compare(f"{mission}: time to complete, aware / blind", "open question",
                    f"{a['time'][0]:.0f} / {b['time'][0]:.0f}", "s",
                    f"aware {fmt_ci(*a['time'], 1)}, blind {fmt_ci(*b['time'], 1)}")
    res.draw = lambda fig: _draw(fig, summary, missions, outcomes)
    return res


def _draw(fig: Any, summary: dict[tuple[str, str], dict[str, tuple[float, float, float]]], missions: list[str],
          outcomes: list[Outcome]) -> None:
    gs = fig.add_gridspec(1, 3)
    panels = [("connected", "connectivity kept (share of time)", 1.05), ("pooled", "tasks completed (share)", 1.05),
              ("time", "time to complete (s)", None)]
    for col, (key, title, top) in enumerate(panels):
        ax = fig.add_subplot(gs[0, col])
        for j, arm in enumerate(ARMS):
            xs = np.arange(len(missions)) + (j - 0.5) * 0.36
            m = [summary[(mi, arm)][key][0] for mi in missions]
            lo = [summary[(mi, arm)][key][1] for mi in missions]
            hi = [summary[(mi, arm)][key][2] for mi in missions]
            err = [[max(0.0, a - b) if math.isfinite(b) else 0.0 for a, b in zip(m, lo)],
                   [max(0.0, c - a) if math.isfinite(c) else 0.0 for a, c in zip(m, hi)]]
            ax.bar(xs, [v if math.isfinite(v) else 0.0 for v in m], width=0.34, color=color(0 if arm == "aware" else 1),
                   alpha=0.75, label=f"network-{arm}", yerr=err, capsize=4)
            if key != "pooled":
                per = "connected" if key == "connected" else None
                for i, mi in enumerate(missions):
                    runs = [o for o in outcomes if o.mission == mi and o.arm == arm]
                    vals = [o.connected for o in runs] if per else [float(np.mean(o.times)) for o in runs if o.times]
                    ax.scatter(np.full(len(vals), xs[i]) + np.linspace(-0.1, 0.1, len(vals)), vals, s=8,
                               color="black", alpha=0.6, zorder=3)
        ax.set_xticks(range(len(missions)), missions)
        ax.set_title(title, fontsize=11)
        if top:
            ax.set_ylim(0, top)
        ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
        ax.legend(fontsize=8, loc="lower right" if key != "time" else "upper left")
    fig.suptitle("Paper 004's open question: network-aware against network-blind, same missions "
                 "(bars: mean, whiskers: 95 % CI, dots: runs)", fontsize=12)
