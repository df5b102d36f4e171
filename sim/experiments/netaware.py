"""Paper 004's open question: does a network-aware team keep its connectivity and still do its task?

An A/B test of the mission plugin's network guard: both arms of a comparison start the same team
(agent processes, tasked by the control node), send it the same tasks with the same algorithm, and
differ in one mission setting alone, `network_aware` (true: the guard, with its default policy
`hold`, stops a robot whose remote motion puts the team's connectivity at risk and lets it go on
when connectivity returns; false: no guard). Over several seeds:

- goto: every robot gets a remote goto to a point drawn by the seed, `goto_near`-`goto_far` m
  from the control node in directions spread around it, which pulls the team apart;
- randomwalk: every robot gets a remote random walk of `walk` seconds (seeded).

WiDep is not split this way: the guard acts on remote motion jobs only (`RemoteBotMotion`), never
on a deployment's own moves (the mission plugin's `_guard` and `_apply_policy`), so WiDep with the
guard and WiDep without it would be one run twice. WiDep keeps the team connected by its own rule
(steps bounded by the RNG connectivity rule). What the experiment offers instead, when the
scenario's missions list it, is a comparison of two algorithms, labelled as such, with the guard
off in both arms:

- widep-vs-goto: the team must cover a PoI `poi_distance` m from the control node, more than
  one radio range away; one arm deploys WiDep (`Deploy widep` with R the longest link of quality
  `min_link_quality`), the other sends every robot a remote goto straight to the PoI.

`netns=True` (`erni experiment netaware --netns`) runs every team on the real-mesh tier: one
network namespace per agent, the radio model's links as packet-filter rules, babeld routing and
MobiNet reading babeld (`erni sim --netns`); the default is the loopback tier.

Measured on every run: connectivity kept, the share of the simulator's 10 Hz samples in which
the whole team and the control node are one radio component (the radio model's truth, on both
tiers), over the mission's whole time in both arms of a guard comparison (`goto_time`, `walk` +
15 s: a run does not end when an unguarded team has arrived, cut off) and until the PoI is covered
in widep-vs-goto; tasks completed: a goto's robot at its target and the PoI covered (both judged on the
simulator's truth, since a robot cut off from the control node cannot report it), a walk that ran
its time (from its task's result); time to complete, from the tasks being sent; and how many
successes the control node heard of. Each is averaged over the seeds with a 95 % Student-t
interval (completion also as a Wilson interval over all tasks).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.experiments.stats import fmt_ci, mean_ci, wilson
from erni.sim.scenario import Scenario, ScenarioError


@dataclass(frozen=True)
class Arm:
    """One arm of a comparison: its label, the algorithm its robots are tasked with, the guard setting."""

    label: str
    algorithm: str        # "goto", "randomwalk", "widep" or "poi-goto" (a remote goto to the PoI)
    network_aware: bool


@dataclass(frozen=True)
class Comparison:
    """Two arms run on the same seeds; `differs` says what differs between them, and only that."""

    name: str
    kind: str             # "guard": the same tasks, network_aware on / off; "algorithm": two algorithms
    arms: tuple[Arm, Arm]
    differs: str


GUARD_ON, GUARD_OFF = "guard on", "guard off"
COMPARISONS: dict[str, Comparison] = {c.name: c for c in [
    Comparison("goto", "guard", (Arm(GUARD_ON, "goto", True), Arm(GUARD_OFF, "goto", False)),
               "the mission's network_aware setting alone (the same remote gotos)"),
    Comparison("randomwalk", "guard", (Arm(GUARD_ON, "randomwalk", True), Arm(GUARD_OFF, "randomwalk", False)),
               "the mission's network_aware setting alone (the same seeded remote random walks)"),
    Comparison("widep-vs-goto", "algorithm", (Arm("WiDep", "widep", False), Arm("straight goto", "poi-goto", False)),
               "the algorithm alone (Deploy widep against a remote goto to the PoI), the guard off in both"),
]}
MISSIONS = tuple(COMPARISONS)
NO_WIDEP_SPLIT = ("WiDep is not split by the guard: the guard holds remote motion jobs only, never a "
                  "deployment's moves, so WiDep with and without it would be the same run")


@dataclass
class Outcome:
    """One comparison's arm on one seed."""

    mission: str
    arm: str
    seed: int
    connected: float       # share of samples with the team in one component
    tasks: int
    completed: int
    times: list[float]     # s from sending to success, completed tasks only
    length: float          # s the run lasted
    reported: int = 0      # successes the control node heard of
    settings: dict[str, Any] = field(default_factory=dict)  # the mission settings every robot ran with
    sent: list[tuple[str, str, str, dict[str, Any]]] = field(default_factory=list)  # robot, verb, prep, params


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, seeds: int | None = None,
        netns: bool = False, **_: Any) -> Result:
    """Run both arms of every comparison over the seeds; return figure and table."""
    s = scenario.strategy
    n_seeds = seeds or int(s.get("seeds", 10))
    missions = [str(m) for m in s.get("missions", ["goto", "randomwalk"])]
    for m in missions:
        if m == "widep":
            raise ScenarioError(f"strategy.missions: 'widep' cannot be an arm pair of the guard ({NO_WIDEP_SPLIT}); "
                                "'widep-vs-goto' compares WiDep with a straight goto as two algorithms")
        if m not in COMPARISONS:
            raise ScenarioError(f"strategy.missions: unknown mission {m!r}; expected some of {', '.join(MISSIONS)}")
    outcomes: list[Outcome] = []
    total = n_seeds * len(missions) * 2
    k = 0
    for i in range(n_seeds):
        seed = scenario.seed + i
        for mission in missions:
            for arm in COMPARISONS[mission].arms:
                k += 1
                tag = f"[{k}/{total}] seed {seed} {mission} {arm.label}"

                def told(what: str, done: float, total_: float, tag: str = tag) -> None:
                    progress(f"{tag}: {what}", done, total_)

                o = _one(scenario.model_copy(update={"seed": seed}), mission, arm, told, netns=netns)
                outcomes.append(o)
                progress(f"{tag}: connected {o.connected:.0%}, {o.completed}/{o.tasks} done", k, total)
    return _result(scenario, experiment, mode, outcomes, missions, n_seeds, netns)


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


def _poi(scenario: Scenario) -> tuple[float, float]:
    c = scenario.control
    a = random.Random(scenario.seed).uniform(0, 2 * math.pi)
    d = float(scenario.strategy.get("poi_distance", 14.0))
    return round(c.x + d * math.cos(a), 2), round(c.y + d * math.sin(a), 2)


def widep_range(scenario: Scenario) -> float:
    """WiDep's R: the longest link of quality `min_link_quality` (m).

    The radio's `comm_range` is where delivery falls to 0: a link kept just short of it loses
    almost every packet (and is not even used for routing below the radio's `min_quality`), so a
    team spread to it is one component on paper and cut off in fact.
    """
    from erni.sim.manet import RadioModel

    r = scenario.radio
    q = float(scenario.strategy.get("min_link_quality", 0.3))
    return round(RadioModel(r.comm_range, r.lossless_range, r.min_quality).range_for(max(q, r.min_quality)), 3)


def arm_settings(scenario: Scenario, arm: Arm) -> dict[str, Any]:
    """The mission settings every robot of `arm` runs with (arms of a guard comparison differ in
    `network_aware` alone)."""
    s = scenario.strategy
    return {"network_aware": arm.network_aware, "speed": float(s.get("speed", 0.4)), "separation": 1.0,
            "min_link_quality": float(s.get("min_link_quality", 0.3))}


def arm_tasks(scenario: Scenario, arm: Arm) -> list[tuple[str, str, str, dict[str, Any]]]:
    """The tasks the control node sends, as (robot, verb, preposition, params), for `arm` on the
    scenario's seed: the same for both arms of a guard comparison."""
    s = scenario.strategy
    names = scenario.robot_names()
    speed = float(s.get("speed", 0.4))
    if arm.algorithm == "goto":
        return [(name, "RemoteBotMotion", "goto", {"x": x, "y": y, "speed": speed, "tolerance": 0.3})
                for name, (x, y) in zip(names, _targets(scenario, len(names)))]
    if arm.algorithm == "randomwalk":
        walk = float(s.get("walk", 45.0))
        return [(name, "RemoteBotMotion", "randomwalk", {"speed": speed, "duration": walk,
                                                         "seed": scenario.seed * 100 + i})
                for i, name in enumerate(names)]
    poi = _poi(scenario)
    if arm.algorithm == "widep":
        return [(name, "Deploy", "widep", {"x": poi[0], "y": poi[1], "range": widep_range(scenario),
                                           "tolerance": 0.5, "period": float(s.get("period", 4.0))})
                for name in names]
    return [(name, "RemoteBotMotion", "goto", {"x": poi[0], "y": poi[1], "speed": speed, "tolerance": 0.5})
            for name in names]


def _limit(scenario: Scenario, mission: str) -> float:
    s = scenario.strategy
    if mission == "goto":
        return float(s.get("goto_time", 75.0))
    if mission == "randomwalk":
        return float(s.get("walk", 45.0)) + 15.0
    return float(s.get("widep_time", 150.0))


def _one(scenario: Scenario, mission: str, arm: Arm, progress: Progress, *, netns: bool = False) -> Outcome:
    from erni.sim.experiments.agents import TeamRun

    s = scenario.strategy
    names = scenario.robot_names()
    settings = arm_settings(scenario, arm)
    sent = arm_tasks(scenario, arm)
    limit = _limit(scenario, mission)
    targets = _targets(scenario, len(names))
    poi = _poi(scenario)
    with TeamRun(scenario, progress, mission=settings, netns=netns).start() as team:
        uids = [team.send(robot, verb, prep, **params) for robot, verb, prep, params in sent]
        arrived: dict[int, float] = {}  # robot index -> when the simulator saw it at its goto target
        covered: list[float] = []

        # both arms of a guard comparison are judged over the same window, the mission's whole time:
        # an unguarded team that arrived early stays cut off, and that time counts too
        whole = COMPARISONS[mission].kind == "guard"

        def finished() -> bool:
            assert team.team is not None
            if mission == "widep-vs-goto":
                if not covered and any(math.hypot(r.x - poi[0], r.y - poi[1]) <= 0.5 for r in team.team.robots):
                    covered.append(team.now)
                return bool(covered)
            if mission == "goto":
                for i, (r, (x, y)) in enumerate(zip(team.team.robots, targets)):
                    if i not in arrived and math.hypot(r.x - x, r.y - y) <= 0.4:
                        arrived[i] = team.now
                return not whole and (len(arrived) == len(names) or team.done(uids))
            return not whole and team.done(uids)

        team.wait(f"{mission} ({arm.label})", limit, finished)
        samples = team.samples()
        length = team.now
        # the last results on their way (a WiDep robot learns of the coverage at its next round)
        team.pump(2.0 + (float(s.get("period", 4.0)) if arm.algorithm == "widep" else 0.0))
        reported = sum(1 for u in uids if math.isfinite(team.succeeded_at(u)))
        if mission == "widep-vs-goto":
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
    return Outcome(mission, arm.label, scenario.seed, connected, tasks, done, times, length, reported,
                   settings, sent)


def tier_name(netns: bool, channel: str = "nftables") -> str:
    """How the teams' network ran, for titles and notes."""
    if not netns:
        return "loopback tier: the simulated radio, MobiNet over SNMP"
    medium = ("ns-3's 802.11a ad-hoc channel (fading, CSMA/CA, retries, Minstrel) moved by the robots' poses"
              if channel == "ns3" else "the radio as packet-filter rules")
    return f"real-mesh tier: network namespaces, {medium}, babeld, MobiNet reading babeld"


def _result(scenario: Scenario, experiment: Experiment, mode: str, outcomes: list[Outcome], missions: list[str],
            n_seeds: int, netns: bool = False) -> Result:
    res = Result(experiment.name, experiment.title, mode)
    n = scenario.count
    channel = scenario.radio.channel
    res.mode_note = (f"{n} robot agent processes and a control node per run, a new team for every mission, arm and "
                     f"seed; {tier_name(netns, channel)}; connectivity judged on the simulator's radio model every 0.1 s")
    summary: dict[tuple[str, str], dict[str, tuple[float, float, float]]] = {}
    for mission in missions:
        for arm in COMPARISONS[mission].arms:
            runs = [o for o in outcomes if o.mission == mission and o.arm == arm.label]
            summary[(mission, arm.label)] = _arm_metrics(res, f"{mission}, {arm.label}", runs)
    res.compare("robots / radio range R / lossless", "not stated (paper 004 asks the question)",
                f"{n} / {scenario.radio.comm_range:g} m / {scenario.radio.lossless_range:g} m", "",
                "the scenario's setting", "input")
    res.compare("network", "-", f"netns + babeld, {channel} channel" if netns else "loopback", "",
                tier_name(netns, channel), "input")
    if "widep-vs-goto" in missions:
        res.compare("widep-vs-goto: WiDep's R", "R = communication range", f"{widep_range(scenario):g}", "m",
                    "the longest link of quality min_link_quality on the radio model", "input")
    res.compare("seeds per mission and arm", "-", n_seeds, "", "start layout fixed; the seed draws targets, walks, "
                "the PoI's direction and the simulated robots' noise", "input")
    for mission in missions:
        _mission_rows(res, mission, summary, outcomes)
    if any(COMPARISONS[m].kind == "guard" for m in missions):
        res.notes.append("guard on / guard off: the same team, tasks and seeds; only the mission's network_aware "
                         "setting differs (true: the guard with its policy hold; false: no guard)")
    res.notes.append(NO_WIDEP_SPLIT + "; widep-vs-goto, when run, compares two algorithms with the guard off in both")
    res.draw = lambda fig: _draw(fig, summary, missions, outcomes, netns, channel)
    return res


def _arm_metrics(res: Result, key: str, runs: list[Outcome]) -> dict[str, tuple[float, float, float]]:
    """The metrics of one arm of one mission over its runs, a row per run; returns its summary (mean and
    95 % interval of connectivity, completed share, pooled completions and time to complete)."""
    conn = mean_ci([o.connected for o in runs], bounds=(0.0, 1.0))
    share = mean_ci([o.completed / o.tasks for o in runs], bounds=(0.0, 1.0))
    pooled = wilson(sum(o.completed for o in runs), sum(o.tasks for o in runs))
    per_run_time = [float(np.mean(o.times)) for o in runs if o.times]
    tcomp = mean_ci(per_run_time, bounds=(0.0, math.inf))
    res.metrics[f"{key}: connectivity kept (share of time)"] = (fmt_ci(*conn), "mean [95 % CI]")
    res.metrics[f"{key}: tasks completed"] = (
        f"{sum(o.completed for o in runs)}/{sum(o.tasks for o in runs)} = {fmt_ci(*pooled)}", "Wilson 95 %")
    res.metrics[f"{key}: tasks completed per run"] = (fmt_ci(*share), "share, mean [95 % CI]")
    res.metrics[f"{key}: time to complete"] = (fmt_ci(*tcomp, 1), f"s, mean [95 % CI] over {len(per_run_time)} runs")
    res.metrics[f"{key}: successes the control node heard of"] = (
        f"{sum(o.reported for o in runs)}/{sum(o.tasks for o in runs)}", "tasks")
    for o in runs:
        res.robots[f"{o.mission}/{o.arm}/s{o.seed}"] = {
            "connected": round(o.connected, 3), "completed": f"{o.completed}/{o.tasks}",
            "time_s": round(float(np.mean(o.times)), 1) if o.times else "-",
            "heard": f"{o.reported}/{o.tasks}", "length_s": round(o.length, 1)}
    return {"connected": conn, "completed": share, "pooled": pooled, "time": tcomp}


def _mission_rows(res: Result, mission: str, summary: dict[tuple[str, str], dict[str, tuple[float, float, float]]],
                  outcomes: list[Outcome]) -> None:
    """One mission's rows of the comparison: its two arms side by side."""
    c = COMPARISONS[mission]
    (la, lb) = (arm.label for arm in c.arms)
    a, b = summary[(mission, la)], summary[(mission, lb)]
    pair = f"{la} / {lb}"
    res.compare(f"{mission}: what differs between the arms", "-", c.kind, "", c.differs, "input")
    res.compare(f"{mission}: connectivity kept, {pair}", "open question",
                f"{a['connected'][0]:.2f} / {b['connected'][0]:.2f}", "share",
                f"{la} {fmt_ci(*a['connected'])}, {lb} {fmt_ci(*b['connected'])}")
    res.compare(f"{mission}: tasks completed, {pair}", "open question",
                f"{a['pooled'][0]:.2f} / {b['pooled'][0]:.2f}", "share",
                f"{la} {fmt_ci(*a['pooled'])}, {lb} {fmt_ci(*b['pooled'])} (Wilson)")
    heard = {arm.label: (sum(o.reported for o in outcomes if o.mission == mission and o.arm == arm.label),
                         sum(o.tasks for o in outcomes if o.mission == mission and o.arm == arm.label))
             for arm in c.arms}
    res.compare(f"{mission}: successes the control node heard of, {pair}", "open question",
                f"{heard[la][0]}/{heard[la][1]} / {heard[lb][0]}/{heard[lb][1]}", "tasks",
                "task results that reached the control node")
    res.compare(f"{mission}: time to complete, {pair}", "open question",
                f"{a['time'][0]:.0f} / {b['time'][0]:.0f}", "s",
                f"{la} {fmt_ci(*a['time'], 1)}, {lb} {fmt_ci(*b['time'], 1)}")


def _draw(fig: Any, summary: dict[tuple[str, str], dict[str, tuple[float, float, float]]], missions: list[str],
          outcomes: list[Outcome], netns: bool = False, channel: str = "nftables") -> None:
    gs = fig.add_gridspec(1, 3)
    panels = [("connected", "connectivity kept (share of time)", 1.05), ("pooled", "tasks completed (share)", 1.05),
              ("time", "time to complete (s)", None)]
    # every arm label keeps one colour across panels: the guard arms 0 and 1, the algorithm arms 2 and 3
    labels = list(dict.fromkeys(arm.label for m in missions for arm in COMPARISONS[m].arms))
    legend = {GUARD_ON: "guard on (network_aware = true)", GUARD_OFF: "guard off (network_aware = false)",
              "WiDep": "WiDep (guard off)", "straight goto": "straight goto to the PoI (guard off)"}
    for col, (key, title, top) in enumerate(panels):
        ax = fig.add_subplot(gs[0, col])
        _draw_bars(ax, key, summary, missions, outcomes, labels, legend)
        ax.set_xticks(range(len(missions)), [m if COMPARISONS[m].kind == "guard" else f"{m}\n(two algorithms)"
                                             for m in missions])
        ax.set_title(title, fontsize=11)
        if top:
            ax.set_ylim(0, top)
        ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
        ax.legend(fontsize=8, loc="lower right" if key != "time" else "upper left")
    tier = f"the real-mesh tier (netns, babeld, {channel} channel)" if netns else "the loopback tier"
    widep = ("; widep-vs-goto compares two algorithms, the guard off in both" if "widep-vs-goto" in missions
             else "")
    fig.suptitle(f"Paper 004's open question on {tier}: the mission's network guard on against off\n"
                 "guard on / guard off: the same team, tasks and seeds; only network_aware differs "
                 "(bars: mean, whiskers: 95 % CI, dots: runs)\n"
                 "WiDep is no arm pair of the guard (the guard holds remote motion jobs only, never a deployment's "
                 f"moves){widep}", fontsize=10.5)


def _draw_bars(ax: Any, key: str, summary: dict[tuple[str, str], dict[str, tuple[float, float, float]]],
               missions: list[str], outcomes: list[Outcome], labels: list[str], legend: dict[str, str]) -> None:
    """One panel's bars: each arm of each mission, its mean and 95 % interval of `key`, and (but for the
    pooled share) a dot per run."""
    drawn: set[str] = set()
    for i, mi in enumerate(missions):
        for j, arm in enumerate(COMPARISONS[mi].arms):
            x = i + (j - 0.5) * 0.36
            m, lo, hi = summary[(mi, arm.label)][key]
            err = [[max(0.0, m - lo) if math.isfinite(lo) else 0.0], [max(0.0, hi - m) if math.isfinite(hi) else 0.0]]
            ax.bar([x], [m if math.isfinite(m) else 0.0], width=0.34, color=color(labels.index(arm.label)),
                   alpha=0.75, yerr=err, capsize=4,
                   label=None if arm.label in drawn else legend.get(arm.label, arm.label))
            drawn.add(arm.label)
            if key != "pooled":
                runs = [o for o in outcomes if o.mission == mi and o.arm == arm.label]
                vals = [o.connected for o in runs] if key == "connected" else \
                    [float(np.mean(o.times)) for o in runs if o.times]
                ax.scatter(np.full(len(vals), x) + np.linspace(-0.1, 0.1, len(vals)), vals, s=8,
                           color="black", alpha=0.6, zorder=3)
