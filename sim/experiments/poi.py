"""Paper 000, section 5.1: three robots cover a point of interest past an obstacle (WiDep, Figure 5).

Agents mode (default): one agent process per robot; the control node sends each a
`Deploy widep` task through the transport; each robot's mission plugin takes WiDep steps from
the positions its agent learns through MobiNet (SNMP) and drives them as BotMotion gotos over
ARCOS. The simulator only watches: coverage and connectivity are judged on its truth (a robot
within `tolerance` of the PoI; the radio model's components at 10 Hz, with the base station),
energy is what each agent metered from its own odometry (paper 000's model), and the tasks'
results say how each robot ended (covered, or failed saying what held it).

Kinematic mode: every `period` seconds all robots take one WiDep decision from the same
snapshot (`widep.widep_round`), then drive there as unicycles: the synchronous algorithm.

`--seeds N` repeats the run N times (seeds K, K+1, ...): each seed changes the start poses
(within `jitter` m and `jitter_heading` degrees of the scenario's) and the simulated robots'
noise, and the result counts the runs that covered the PoI without ever losing the base.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color, draw_world, map_axes, range_circle, time_axes
from erni.sim.experiments.stats import fmt_ci, mean_ci, wilson
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import energy as paper_energy
from erni.strategies import widep


@dataclass
class Run:
    """One PoI run: the truth over time and how each robot's task ended."""

    seed: int
    ts: NDArray[np.float64]            # (T,) s
    ps: NDArray[np.float64]            # (T, N, 2) m, the simulator's truth
    reach: NDArray[np.float64]         # (T,) share of robots connected to the base
    covered_at: float                  # s (NaN: not covered)
    outcomes: dict[str, str]           # robot -> final task message ("" in kinematic mode)
    energy: dict[str, float]           # robot -> J
    rounds: int | None = None

    @property
    def connected(self) -> bool:
        """True when every robot was connected to the base in every sample."""
        return bool(len(self.reach)) and float(self.reach.min()) >= 1.0


def jittered(scenario: Scenario, seed: int) -> Scenario:
    """The scenario with start poses moved by the seed (within strategy.jitter m and jitter_heading deg)."""
    s = scenario.strategy
    dx, dh = float(s.get("jitter", 0.0)), float(s.get("jitter_heading", 0.0))
    if dx <= 0 and dh <= 0:
        return scenario.model_copy(update={"seed": seed})
    rng = random.Random(seed)
    starts = [st.model_copy(update={"x": round(st.x + rng.uniform(-dx, dx), 3),
                                    "y": round(st.y + rng.uniform(-dx, dx), 3),
                                    "heading": round(st.heading + rng.uniform(-dh, dh), 1)})
              for st in scenario.starts()]
    return scenario.model_copy(update={"seed": seed, "robot": starts})


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, seeds: int = 1,
        **_: Any) -> Result:
    """Cover the PoI (real agents given `Deploy widep`, or kinematic WiDep rounds); return figure and metrics."""
    if not scenario.poi:
        raise ScenarioError(f"{scenario.name}: the PoI experiment needs a [[poi]] in the scenario")
    if seeds < 1:
        raise ScenarioError(f"--seeds: expected at least 1, got {seeds}")
    runs = []
    for k in range(seeds):
        sc = jittered(scenario, scenario.seed + k)
        label = f"seed {sc.seed} ({k + 1}/{seeds})" if seeds > 1 else ""
        one = _agents(sc, progress, label) if mode == "agents" else _kinematic(sc, progress, label)
        runs.append(one)
        if seeds > 1:
            progress(f"seeds: {sum(r.connected and math.isfinite(r.covered_at) for r in runs)} of {k + 1} "
                     "covered and connected", k + 1, seeds)
    return _result(scenario, experiment, mode, runs)


def _params(scenario: Scenario) -> dict[str, Any]:
    s = scenario.strategy
    poi = scenario.poi[0]
    return {"x": poi.x, "y": poi.y, "range": float(s.get("range", scenario.radio.comm_range)),
            "tolerance": float(s.get("tolerance", 0.5)), "period": float(s.get("period", 4.0))}


def _agents(scenario: Scenario, progress: Progress, label: str) -> Run:
    """Real agents: Deploy widep through the control node; the simulator records the truth."""
    from erni.sim.experiments.agents import TeamRun

    p = _params(scenario)
    duration = scenario.duration or 300.0
    names = scenario.robot_names()
    tag = f"{label}: " if label else ""
    mission = {"separation": float(scenario.strategy.get("separation", 1.0))}
    if "speed" in scenario.strategy:
        mission["speed"] = float(scenario.strategy["speed"])
    with TeamRun(scenario, lambda what, d, t: progress(tag + what, d, t), mission=mission).start() as team:
        uids = {name: team.send(name, "Deploy", "widep", **p) for name in names}
        poi = np.array([p["x"], p["y"]])
        covered: list[float] = []

        def finished() -> bool:
            pos = np.array([[r.x, r.y] for r in team.team.robots]) if team.team else np.zeros((0, 2))
            if not covered and widep.covered(pos, poi, p["tolerance"]):
                covered.append(team.now)
            # the agents end their tasks themselves: covered (succeeded) or stuck (failed, saying why)
            return team.done(list(uids.values())) or bool(covered and team.now > covered[0] + 8.0)

        team.wait("robots deploying", duration, finished)
        team.pump(1.0)
        samples = team.samples()
        outcomes, energy = {}, {}
        for name, uid in uids.items():
            r = team.results.get(uid)
            outcomes[name] = "no result" if r is None else f"{r.state.value}: {r.message}"
            e = r.values.get("energy_j") if r is not None else None
            energy[name] = float(e) if isinstance(e, (int, float)) else math.nan
    ts = np.array([x.t for x in samples]) - samples[0].t
    ps = np.array([np.stack([x.x, x.y], axis=1) for x in samples])
    reach = np.array([x.control_reach / len(names) for x in samples])
    return Run(scenario.seed, ts, ps, reach, covered[0] if covered else math.nan, outcomes, energy)


def _kinematic(scenario: Scenario, progress: Progress, label: str) -> Run:
    """WiDep rounds from one snapshot each `period` s, robots driven as unicycles in between."""
    s = scenario.strategy
    p = _params(scenario)
    period, R, tolerance = p["period"], p["range"], p["tolerance"]
    speed = float(s.get("speed", 0.3))
    dt = float(s.get("dt", 0.1))
    separation = float(s.get("separation", 0.8))
    duration = scenario.duration or 300.0
    poi = np.array([p["x"], p["y"]])
    base = np.array([[scenario.control.x, scenario.control.y]])
    obstacles = np.array([[c.center[0], c.center[1], c.radius] for c in scenario.world.circle]).reshape(-1, 3)
    starts = scenario.starts()
    pos = np.array([[st.x, st.y] for st in starts])
    th = np.radians([st.heading for st in starts])
    n = len(pos)
    movable = np.r_[np.ones(n, dtype=bool), False]
    track = kinematic.Track()
    track.add(0.0, pos, th, np.zeros(n))
    t = 0.0
    covered_at = math.nan
    rounds = 0
    tag = f"{label}: " if label else ""
    while t < duration:
        if widep.covered(pos, poi, tolerance):
            covered_at = t
            break
        targets, _ = widep.widep_round(np.vstack([pos, base]), poi, R, tolerance=tolerance, obstacles=obstacles,
                                       separation=separation, movable=movable)
        rounds += 1
        round_end = t + period
        while t < round_end - 1e-9:
            pos, th, sp = kinematic.drive(pos, th, targets[:n], dt, speed)
            t += dt
            track.add(t, pos, th, sp)
            if math.isnan(covered_at) and widep.covered(pos, poi, tolerance):
                covered_at = t
        progress(f"{tag}WiDep rounds", round(t, 1), duration)
        if not math.isnan(covered_at):
            break
    for _ in range(int(5.0 / dt)):  # the team holds its place a little after covering the PoI
        t += dt
        track.add(t, pos, th, np.zeros(n))
    ts, ps, _, _ = track.arrays()
    reach = np.array([len(kinematic.reach_of(np.vstack([ps[k], base]), R, n)) / n for k in range(len(ts))])
    names = scenario.robot_names()
    energy = {name: paper_energy.track_energy(ts, ps[:, i, 0], ps[:, i, 1])[0] for i, name in enumerate(names)}
    return Run(scenario.seed, ts, ps, reach, covered_at, {}, energy, rounds)


def _result(scenario: Scenario, experiment: Experiment, mode: str, runs: list[Run]) -> Result:
    p = _params(scenario)
    names = scenario.robot_names()
    base = np.array([scenario.control.x, scenario.control.y])
    poi = np.array([p["x"], p["y"]])
    obstacles = np.array([[c.center[0], c.center[1], c.radius] for c in scenario.world.circle]).reshape(-1, 3)
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = ("each robot is an agent process; the control node sent it Deploy widep; positions of the "
                     "others from MobiNet (SNMP); gotos over ARCOS; judged on the simulator's truth"
                     if mode == "agents" else
                     "WiDep rounds stepped in one process from one shared snapshot (the synchronous algorithm)")
    last = runs[-1]
    if len(runs) > 1:
        covered_txt = _seeds_metrics(res, runs, poi)
    else:
        covered_txt = _one_run_metrics(res, last, names, base, obstacles)
    for r in runs:
        res.series[f"seed{r.seed}/distance_to_poi"] = (
            list(r.ts), list(np.min(np.hypot(*(r.ps - poi).transpose(2, 0, 1)), axis=1)), "m")
    _compare(res, runs, names, p, base, covered_txt, mode)
    res.notes.append("paper 000 gives no time or energy numbers for this run; its Figure 5 shows the "
                     "trajectories and Figure 11 the energy by position")
    if len(runs) == 1 and not math.isfinite(last.covered_at):
        res.notes.append(f"the PoI was not covered within {scenario.duration or 300.0:g} s")
    res.draw = lambda fig: _draw(fig, scenario, names, runs, base, poi, p["range"], res, mode)
    return res


def _seeds_metrics(res: Result, runs: list[Run], poi: NDArray[np.float64]) -> str:
    """The metrics of runs over several seeds, a row per seed; returns how many covered, as text."""
    ok = [r for r in runs if r.connected and math.isfinite(r.covered_at)]
    share, lo, hi = wilson(len(ok), len(runs))
    res.metrics["runs that covered the PoI, always connected to the base"] = (
        f"{len(ok)} of {len(runs)}", f"(95 % CI of the share {lo:.2f}-{hi:.2f})")
    res.metrics["runs that covered the PoI"] = (float(sum(math.isfinite(r.covered_at) for r in runs)), "runs")
    res.metrics["runs always connected to the base"] = (float(sum(r.connected for r in runs)), "runs")
    m, lo, hi = mean_ci([r.covered_at for r in runs])
    res.metrics["time to cover the PoI, mean [95 % CI]"] = (fmt_ci(m, lo, hi, 1), "s")
    for r in runs:
        res.robots[f"seed {r.seed}"] = {
            "covered_s": round(r.covered_at, 1), "min_reach": round(float(r.reach.min()), 2),
            "closest_m": round(float(np.min(np.hypot(*(r.ps - poi).transpose(2, 0, 1)))), 2),
            **({"ended": "; ".join(sorted(set(o.split(":")[0] for o in r.outcomes.values())))}
               if r.outcomes else {})}
        res.series[f"seed{r.seed}/connected_to_base"] = (list(r.ts), list(r.reach), "share")
    return f"{len(ok)} of {len(runs)} runs"


def _one_run_metrics(res: Result, r: Run, names: list[str], base: NDArray[np.float64],
                     obstacles: NDArray[np.float64]) -> str:
    """The metrics of one run, a row per robot; returns when the PoI was covered, as text."""
    res.metrics["PoI covered at"] = (r.covered_at, "s")
    if r.rounds is not None:
        res.metrics["WiDep rounds"] = (float(r.rounds), "rounds")
    res.metrics["connected to the base the whole run"] = (float(r.connected), "yes=1")
    res.metrics["lowest share connected to the base"] = (float(r.reach.min()), "share")
    res.metrics["closest approach to the obstacle surface"] = (_clearance(r.ps, obstacles), "m")
    for i, name in enumerate(names):
        res.robots[name] = {"distance_m": round(paper_energy.track_energy(r.ts, r.ps[:, i, 0], r.ps[:, i, 1])[1], 2),
                            "energy_j": round(r.energy[name], 1),
                            "from_base_m": round(float(np.hypot(*(r.ps[-1, i] - base))), 2)}
        if r.outcomes:
            res.robots[name]["task"] = r.outcomes[name][:60]
    return f"at {r.covered_at:.0f} s" if math.isfinite(r.covered_at) else "no"


def _compare(res: Result, runs: list[Run], names: list[str], p: dict[str, Any], base: NDArray[np.float64],
             covered_txt: str, mode: str) -> None:
    """The paper's statements beside ours: settings, coverage, connectivity, time, energy by position."""
    last = runs[-1]
    energy_note = ("each agent's own meter: its odometry poses through paper 000's model"
                   if mode == "agents" else "paper 000's model on each simulated track")
    res.compare("robots / communication range R", "3 / 4.5 m", f"{len(names)} / {p['range']:g} m", "",
                "the paper's setting", "input")
    res.compare("PoI", "(0, 11)", f"({p['x']:g}, {p['y']:g})", "m", "the paper's setting", "input")
    res.compare("PoI covered", "yes (Figure 5)", covered_txt, "",
                f"a robot within {p['tolerance']:g} m of the PoI in the simulator's truth")
    res.compare("connectivity kept", "yes (WiDep's bound)",
                f"{sum(r.connected for r in runs)} of {len(runs)} runs" if len(runs) > 1
                else ("yes" if last.connected else f"no (lowest {last.reach.min():.0%})"), "",
                "every robot reaches the base over the radio model, every 0.1 s")
    res.compare("time to cover", "not stated", fmt_ci(*mean_ci([r.covered_at for r in runs]), 1)
                if len(runs) > 1 else round(last.covered_at, 1), "s", "from the Deploy tasks being sent" if mode == "agents" else "from the first round")
    if len(runs) == 1 and len(names) > 1:
        order = [float(np.hypot(*(last.ps[-1, i] - base))) for i in range(len(names))]
        rho = _spearman(order, [last.energy[n] for n in names])
        res.compare("energy grows with distance from the base", "yes (Figure 11)", f"rank corr. {rho:.2f}", "",
                    energy_note)


def _spearman(a: list[float], b: list[float]) -> float:
    if any(not math.isfinite(x) for x in a + b):
        return math.nan
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    if np.std(ra) == 0 or np.std(rb) == 0:
        return math.nan
    return float(np.corrcoef(ra, rb)[0, 1])


def _clearance(ps: NDArray[np.float64], obstacles: NDArray[np.float64]) -> float:
    if len(obstacles) == 0:
        return math.nan
    best = math.inf
    for cx, cy, r in obstacles:
        best = min(best, float(np.min(np.hypot(ps[..., 0] - cx, ps[..., 1] - cy) - r)))
    return best


def _draw(fig: Any, scenario: Scenario, names: list[str], runs: list[Run], base: NDArray[np.float64],
          poi: NDArray[np.float64], R: float, res: Result, mode: str) -> None:
    gs = fig.add_gridspec(2, 2, width_ratios=[1.0, 1.1])
    _draw_map(fig.add_subplot(gs[:, 0]), scenario, names, runs, base, poi, R)
    _draw_distance(fig.add_subplot(gs[0, 1]), scenario, runs, res)
    ax = fig.add_subplot(gs[1, 1])
    if len(runs) > 1:
        for k, r in enumerate(runs):
            ax.plot(r.ts, r.reach * 100, color=color(k), lw=1.0)
        time_axes(ax, "Robots connected to the base, every run", "robots connected to the base (%)")
        ax.set_ylim(0, 110)
    else:
        _draw_energy(ax, names, res, mode)
    fig.suptitle(f"{scenario.title} ({mode} mode)", fontsize=13)


def _draw_map(ax: Any, scenario: Scenario, names: list[str], runs: list[Run], base: NDArray[np.float64],
              poi: NDArray[np.float64], R: float) -> None:
    """The trajectories on the world, the base and the PoI; for one run, the ranges and links at the end."""
    draw_world(ax, scenario.world)
    many = len(runs) > 1
    last = runs[-1]
    for r in runs:
        for i, name in enumerate(names):
            ax.plot(r.ps[:, i, 0], r.ps[:, i, 1], color=color(i), lw=0.9 if many else 1.8,
                    alpha=0.55 if many else 1.0, label=f"{name} trajectory" if r is last else None)
            ax.plot(*r.ps[0, i], "o", color=color(i), mfc="white", ms=5 if many else 7)
            ax.plot(*r.ps[-1, i], "o", color=color(i), ms=5 if many else 8)
    if not many:
        for i in range(len(names)):
            range_circle(ax, last.ps[-1, i, 0], last.ps[-1, i, 1], R, color=color(i), alpha=0.5)
        final = np.vstack([last.ps[-1], base])
        adj = widep.comm_adjacency(final, R)
        for a in range(len(final)):
            for b in range(a + 1, len(final)):
                if adj[a, b]:
                    ax.plot(*zip(final[a], final[b]), color="#555555", lw=0.8, alpha=0.6, zorder=1)
        ax.plot([], [], ls="--", color="grey", label=f"range R = {R:g} m")
        ax.plot([], [], color="#555555", lw=0.8, label="radio link at the end")
    ax.plot(*base, "s", color="black", ms=10, label="base station (control node)")
    ax.plot(*poi, "*", color="#e6a100", ms=18, mec="black", label=f"PoI ({poi[0]:g}, {poi[1]:g})")
    ax.plot([], [], "o", color="grey", mfc="white", label="start")
    ax.plot([], [], "o", color="grey", label="end")
    bounds = scenario.world.bounds
    if bounds is not None:
        ax.set_xlim(bounds[0] - 0.5, bounds[2] + 0.5)
        ax.set_ylim(bounds[1] - 0.5, bounds[3] + 0.5)
    map_axes(ax, f"Trajectories of {len(runs)} runs (seeds {runs[0].seed}-{last.seed})" if many
             else "Trajectories (WiDep, one obstacle)")
    ax.legend(loc="upper left", fontsize=7.5, framealpha=0.92)


def _draw_distance(ax: Any, scenario: Scenario, runs: list[Run], res: Result) -> None:
    """The closest robot's distance to the PoI over time, each run."""
    many = len(runs) > 1
    for k, r in enumerate(runs):
        t, d, _ = res.series[f"seed{r.seed}/distance_to_poi"]
        ax.plot(t, d, color=color(k) if many else color(0), lw=1.0 if many else 1.5,
                label=f"seed {r.seed}" if many else "closest robot to the PoI")
        if math.isfinite(r.covered_at) and not many:
            ax.axvline(r.covered_at, color="#e6a100", lw=1, label=f"PoI covered at {r.covered_at:.0f} s")
    ax.axhline(_params(scenario)["tolerance"], color="#e6a100", ls=":", lw=1, label="covered within")
    time_axes(ax, "Closest robot to the PoI over time", "distance to the PoI (m)")
    ax.legend(loc="upper right", fontsize=7, ncol=2 if many else 1)


def _draw_energy(ax: Any, names: list[str], res: Result, mode: str) -> None:
    """One run's energy by robot, in the order of their final distance from the base."""
    order = sorted(range(len(names)), key=lambda i: float(res.robots[names[i]]["from_base_m"]))
    xs = np.arange(len(order))
    vals = [float(res.robots[names[i]]["energy_j"]) for i in order]
    ax.bar(xs, vals, color=[color(i) for i in order])
    for x, v in zip(xs, vals):
        ax.text(x, v, f"{v:.0f} J", ha="center", va="bottom", fontsize=9)
    ax.set_xticks(xs, [f"{names[i]}\n{res.robots[names[i]]['from_base_m']} m" for i in order])
    ax.set_xlabel("robot, and its final distance from the base station")
    ax.set_ylabel("energy (J)")
    ax.set_title("Energy by robot position: " + ("each agent's meter on its own odometry (paper 000's model)"
                                                 if mode == "agents" else "paper 000's model on each track"),
                 fontsize=10)
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    ax.set_ylim(0, max(vals) * 1.18 if vals and max(vals) > 0 else 1)
