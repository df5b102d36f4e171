"""Paper 000, section 5.2: one or two robots relay a flow between a source and a destination (Figures 7, 8).

The source S and the destination D stand still; the relays form a chain S - r1 - ... - D and
each moves along S-D toward its worse link, one decision every `period` seconds (16 s in the
paper), until its two links balance.

Agents mode (default): S, D and every relay are agent processes (S and D robots that are
never tasked). The control node sends each relay `Deploy relay` with its two chain
neighbours; the relay's mission plugin reads its link qualities from MobiNet (the delivery
ratios the network subsystem reports over SNMP: the simulated radio's, loss-free to
`lossless_range`, none beyond `comm_range`) and the others' positions from MobiNet, and
drives BotMotion gotos over ARCOS. Positions are judged on the simulator's truth at every
decision time; the run stops `after` decisions once every relay stayed at its slot.

Kinematic mode: each relay measures its two links with `probes` hello packets over the
radio model (a seeded binomial draw, noisy as a real measurement is), then takes one
`relay.relay_step` and drives there as a unicycle.

Metrics: decisions until every relay stays within `settle` m of its equal-spacing slot,
final error, spread of the position after settling, and the link qualities (the CSV holds
each relay's two link qualities at every decision, the series the figure draws).

Settle rule, the same for one relay and for two: a relay is at its slot once it stays within
`SETTLE` = 1.5 m of it (`strategy.settle` overrides it). In kinematic mode each link is
measured with 50 noisy hello packets, which leaves a settled relay's position scattered with a
standard deviation of 0.33-0.57 m (relay1 and relay2, seeds 1-10): 1.5 m is about three of
them, so the noise of a relay that stays does not count as leaving. A relay that starts `gap`
m from its slot and moves at most `step` m a decision needs at least ceil((gap - settle) / step)
decisions to be within `settle` m of it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.netaware import tier_name
from erni.sim.experiments.plots import color
from erni.sim.manet import RadioModel
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import relay

SETTLE = 1.5  # m: a relay within this distance of its equal-spacing slot is at its slot (module docstring)


def fewest_decisions(gap: float, settle: float, step: float) -> int:
    """The fewest decisions of at most `step` m that bring a relay `gap` m away within `settle` m."""
    return max(0, math.ceil((gap - settle) / step - 1e-9))


def ends(scenario: Scenario, experiment: str) -> tuple[np.ndarray, np.ndarray]:
    """The source and the destination of a relay experiment: the scenario's first two [[poi]]."""
    if len(scenario.poi) < 2:
        raise ScenarioError(f"{scenario.name}: the {experiment} experiment needs two [[poi]]: the source and the "
                            "destination")
    return (np.array([scenario.poi[0].x, scenario.poi[0].y]), np.array([scenario.poi[1].x, scenario.poi[1].y]))


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, netns: bool = False,
        **_: Any) -> Result:
    """Run the relays' decisions for the scenario's duration; return figure and metrics."""
    s = scenario.strategy
    src, dst = ends(scenario, "relay")
    period = float(s.get("period", 16.0))
    settle = float(s.get("settle", SETTLE))
    names = scenario.robot_names()
    n = len(names)
    slots = relay.chain_slots(src, dst, n)
    length = float(np.hypot(*(dst - src)))
    unit = (dst - src) / length
    slot_along = (slots - src) @ unit
    if netns and mode != "agents":
        raise ScenarioError(f"{experiment.name} --netns runs its agents on the real-mesh tier: agents mode only")
    if mode == "agents":
        a, qualities, outcomes = _agents(scenario, progress, src, dst, slot_along, settle, netns)
    else:
        a, qualities = _kinematic(scenario, progress, src, dst)
        outcomes = {}
    err = np.abs(a - slot_along)
    inside = (err <= settle).all(axis=1)
    settled = next((k for k in range(len(inside)) if inside[k:].all()), None)
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = ("S, D and each relay are agent processes; the control node sent each relay Deploy relay; "
                     "link qualities and positions from MobiNet ("
                     + (tier_name(True, scenario.radio.channel) if netns else "SNMP") + "); gotos over ARCOS; "
                     "positions judged on the simulator's truth" if mode == "agents" else
                     f"relays stepped in one process; links measured with {int(s.get('probes', 50))} hello "
                     "packets per decision over the radio model")
    res.metrics["source-destination distance"] = (length, "m")
    res.metrics["decisions until every relay stays at its slot"] = (
        float(settled) if settled is not None else float("nan"), f"decisions of {period:g} s")
    res.metrics["final distance from the equal-spacing slot, worst"] = (float(err[-1].max()), "m")
    spread = float(a[settled:].std(axis=0).max()) if settled is not None and settled < len(a) - 1 else math.nan
    res.metrics["position spread after settling (std), worst relay"] = (spread, "m")
    last = np.array(qualities[-1]) if qualities else np.full((n, 2), np.nan)
    res.metrics["weakest link quality at the end"] = (float(np.nanmin(last)) if np.isfinite(last).any()
                                                     else math.nan, "delivery ratio")
    _robot_rows(res, names, a, qualities, outcomes, slot_along, last, period, mode)
    start_gap = float(np.max(np.abs(a[0] - slot_along)))
    step = float(s.get("step", 1.0))
    res.compare("relays / S-D distance / decision period", "1-2 / <= 30 m / 16 s",
                f"{n} / {length:g} m / {period:g} s", "", "the scenario's setting", "input")
    res.compare("start: farthest relay from its slot; longest move", "not stated",
                f"{start_gap:.1f} m; {step:g} m", "m", "the scenario's setting: with the settle distance "
                f"({settle:g} m) they bound the decisions to settle from below "
                f"({fewest_decisions(start_gap, settle, step)})", "input")
    if n == 1:
        res.compare("decisions until the relay reaches the middle", "about 10 (Figure 7)",
                    float(settled) if settled is not None else "never", "decisions",
                    f"first decision after which it stays within {settle:g} m of the midpoint")
        res.compare("after that", "slight oscillation around the middle",
                    f"std {spread:.2f} m" if math.isfinite(spread) else "-", "", "spread of its position "
                    "over the remaining decisions" + ("; MobiNet reports babeld's reading of its Hellos" if netns
                                                      else "; MobiNet reports the simulated radio's delivery ratio, "
                                                      "a noiseless function of distance" if mode == "agents"
                                                      else "; each link probed with noisy hello counts"))
    else:
        res.compare("relays settle at about equal spacing", "yes (Figure 8)",
                    f"after {settled} decisions" if settled is not None else "never", "",
                    f"every relay within {settle:g} m of its equal-spacing slot from then on")
        res.compare("final positions along S-D", ", ".join(f"{x:.1f}" for x in slot_along) + " (equal spacing)",
                    ", ".join(f"{x:.1f}" for x in a[-1]), "m", "simulator's truth at the last decision")
    res.notes.append(_link_note(scenario, netns))
    res.draw = lambda fig: _draw(fig, scenario, names, a, slot_along, length, qualities, period, mode)
    return res


def _link_note(scenario: Scenario, netns: bool) -> str:
    """Where the link qualities came from: the radio model (an input), or babeld's reading on the real mesh."""
    r = scenario.radio
    if not netns:
        return (f"link quality model (input): delivery ratio 1 up to {r.lossless_range:g} m, falling linearly to 0 "
                f"at R = {r.comm_range:g} m")
    if r.channel == "ns3":
        return ("link qualities (measured): babeld's reading of its Hellos over ns-3's 802.11a channel, as MobiNet "
                f"reports them; the channel's reach follows the scenario's radio (comm_range {r.comm_range:g} m)")
    return ("link qualities (measured): babeld's reading of its Hellos through the packet-filter rules that drop as "
            f"the radio model does (input: delivery ratio 1 up to {r.lossless_range:g} m, 0 at R = {r.comm_range:g} m)")


def _robot_rows(res: Result, names: list[str], a: NDArray[np.float64], qualities: list[list[tuple[float, float]]],
                outcomes: dict[str, str], slot_along: NDArray[np.float64], last: NDArray[np.float64], period: float,
                mode: str) -> None:
    """Each relay's row (its slot, where it ended, its last link qualities) and its series over the decisions."""
    n = len(names)
    for i, name in enumerate(names):
        res.robots[name] = {"slot_m": round(float(slot_along[i]), 2), "final_m": round(float(a[-1, i]), 2),
                            "q_prev": round(float(last[i, 0]), 2), "q_next": round(float(last[i, 1]), 2)}
        if outcomes:
            res.robots[name]["task"] = outcomes[name][:50]
        res.series[f"{name}/position_along"] = (list(np.arange(len(a)) * period), list(a[:, i]), "m")
        if qualities:
            q = np.array(qualities, dtype=float).reshape(-1, n, 2)
            # kinematic: measured at the start of decision k; agents: the relay's report by its end
            ts = list((np.arange(len(q)) + (mode == "agents")) * period)
            before, after = (["S"] + names)[i], (names + ["D"])[i + 1]
            res.series[f"{name}/link_quality_to_{before}"] = (ts, [float(v) for v in q[:, i, 0]], "delivery ratio")
            res.series[f"{name}/link_quality_to_{after}"] = (ts, [float(v) for v in q[:, i, 1]], "delivery ratio")


def _agents(scenario: Scenario, progress: Progress, src: NDArray[np.float64], dst: NDArray[np.float64],
            slot_along: NDArray[np.float64], settle: float, netns: bool = False
            ) -> tuple[NDArray[np.float64], list[list[tuple[float, float]]], dict[str, str]]:
    """S and D as untasked robot agents, the relays given Deploy relay; positions at each decision. On the
    real-mesh tier the start waits for the control node to hear the relays and S only: D is never tasked, and
    its one link (to the farthest relay, near the edge of the range) is too weak for handshakes to complete
    soon."""
    from erni.sim.experiments.agents import TeamRun
    from erni.sim.world import RobotStart

    s = scenario.strategy
    period = float(s.get("period", 16.0))
    after = int(s.get("after", 5))
    duration = scenario.duration or 480.0
    relays = scenario.starts()
    names = [r.name for r in relays]
    ends = [RobotStart(name=scenario.poi[0].name, x=float(src[0]), y=float(src[1]), heading=0.0),
            RobotStart(name=scenario.poi[1].name, x=float(dst[0]), y=float(dst[1]), heading=180.0)]
    team_scenario = scenario.model_copy(update={"robot": relays + ends, "robots": scenario.robots.model_copy(
        update={"count": len(relays) + 2})})
    chain = [ends[0].name] + names + [ends[1].name]
    length = float(np.hypot(*(dst - src)))
    unit = (dst - src) / length
    mission = {"relay_period": period, "relay_step": float(s.get("step", 1.0)),
               "speed": float(s.get("speed", 0.2)), "network_aware": False}
    along: list[list[float]] = []
    qualities: list[list[tuple[float, float]]] = []
    if netns:
        _check_mesh_start(scenario, [ends[0]] + relays + [ends[1]])
    heard = [*names, ends[0].name] if netns else None
    with TeamRun(team_scenario, progress, mission=mission, netns=netns, heard=heard).start() as team:
        assert team.team is not None
        idx = [team.team.names.index(nm) for nm in names]

        def where() -> list[float]:
            assert team.team is not None
            return [float((np.array([team.team.robots[i].x, team.team.robots[i].y]) - src) @ unit) for i in idx]

        along.append(where())
        uids = {nm: team.send(nm, "Deploy", "relay", source=chain[k], destination=chain[k + 2],
                              tolerance=float(s.get("tolerance", 0.05))) for k, nm in enumerate(names)}
        decisions = int(duration // period)
        for k in range(decisions):
            team.wait(f"relay decisions ({k + 1}/{decisions})", period)
            along.append(where())
            qualities.append([_q(team.results.get(uids[nm])) for nm in names])
            ok: list[bool] = np.all(np.abs(np.array(along) - slot_along) <= settle, axis=1).tolist()
            first = next((j for j in range(len(ok)) if all(ok[j:])), None)
            if first is not None and len(along) - 1 - first >= after:
                break
        outcomes = {nm: (f"{r.state.value}: {r.message}" if (r := team.results.get(uids[nm])) else "no result")
                    for nm in names}
    return np.array(along), qualities, outcomes


NETNS_START_QUALITY = 0.3  # the weakest chain link a real-mesh run starts on (by the radio model; see below)


def _check_mesh_start(scenario: Scenario, chain: list[Any]) -> None:
    """Refuse a real-mesh start where a link of the chain S - relays - D is weaker than `NETNS_START_QUALITY` by the
    radio model: a relay learns its neighbours' positions from their Poses, shared over transport sessions, and a
    session's handshake over a link that delivers one datagram in ten did not complete in 480 s (relay1's robot1,
    11 m from D at comm_range 12 m), so the relay never moved."""
    radio = RadioModel(scenario.radio.comm_range, scenario.radio.lossless_range, scenario.radio.min_quality)
    for a, b in zip(chain, chain[1:]):
        d = math.hypot(a.x - b.x, a.y - b.y)
        q = radio.quality(d)
        if q < NETNS_START_QUALITY:
            reach = radio.range_for(NETNS_START_QUALITY)
            raise ScenarioError(
                f"{scenario.name} --netns: {a.name} and {b.name} start {d:.1f} m apart, link quality {q:.2f} by the "
                f"radio model; a relay needs its neighbours' Poses over the mesh, and handshakes over a link below "
                f"{NETNS_START_QUALITY:g} rarely complete: start the chain's links within {reach:.1f} m, or widen "
                f"radio.comm_range (for example examples/scenario-{scenario.name}-mesh.toml)")


def _q(result: Any) -> tuple[float, float]:
    if result is None:
        return math.nan, math.nan
    v = result.values
    qs, qd = v.get("q_source"), v.get("q_destination")
    return (float(qs) if qs is not None else 0.0, float(qd) if qd is not None else 0.0)


def _kinematic(scenario: Scenario, progress: Progress, src: NDArray[np.float64], dst: NDArray[np.float64]
               ) -> tuple[NDArray[np.float64], list[list[tuple[float, float]]]]:
    s = scenario.strategy
    radio = RadioModel(scenario.radio.comm_range, scenario.radio.lossless_range, scenario.radio.min_quality)
    period = float(s.get("period", 16.0))
    speed = float(s.get("speed", 0.2))
    probes = int(s.get("probes", 50))
    tolerance = float(s.get("tolerance", 0.05))
    gain = float(s.get("gain", 4.0))
    step = float(s.get("step", 1.0))
    dt = float(s.get("dt", 0.2))
    duration = scenario.duration or 480.0
    rng = np.random.default_rng(scenario.seed)
    starts = scenario.starts()
    n = len(starts)
    pos = np.array([[st.x, st.y] for st in starts])
    th = np.radians([st.heading for st in starts])
    length = float(np.hypot(*(dst - src)))
    unit = (dst - src) / length
    decisions = int(duration // period)
    along = [list((pos - src) @ unit)]
    qualities: list[list[tuple[float, float]]] = []
    track = kinematic.Track()
    track.add(0.0, pos, th, np.zeros(n))
    t = 0.0
    for k in range(decisions):
        chain = np.vstack([src, pos, dst])
        targets = pos.copy()
        measured = []
        for i in range(n):
            prev, nxt = chain[i], chain[i + 2]
            q_prev = _probe(radio, float(np.hypot(*(chain[i + 1] - prev))), probes, rng)
            q_next = _probe(radio, float(np.hypot(*(chain[i + 1] - nxt))), probes, rng)
            move = relay.relay_step(pos[i], prev, nxt, q_prev, q_next, tolerance=tolerance, gain=gain,
                                    max_step=step)
            targets[i] = move.target
            measured.append((q_prev, q_next))
        qualities.append(measured)
        end = t + period
        while t < end - 1e-9:
            pos, th, sp = kinematic.drive(pos, th, targets, dt, speed)
            t += dt
            track.add(t, pos, th, sp)
        along.append(list((pos - src) @ unit))
        progress("relay decisions", k + 1, decisions)
    return np.array(along), qualities


def _probe(radio: RadioModel, distance: float, probes: int, rng: np.random.Generator) -> float:
    """Delivery ratio of `probes` hello packets over a link of `distance` m."""
    return float(rng.binomial(probes, radio.quality(distance)) / probes)


def _draw(fig: Any, scenario: Scenario, names: list[str], a: NDArray[np.float64], slots: NDArray[np.float64],
          length: float, qualities: list[list[tuple[float, float]]], period: float, mode: str) -> None:
    gs = fig.add_gridspec(2, 1, height_ratios=[1.6, 1])
    ax = fig.add_subplot(gs[0])
    steps = np.arange(len(a))
    ax.axhline(0, color="black", lw=2, label="source S")
    ax.axhline(length, color="black", lw=2, ls="-.", label="destination D")
    for i, name in enumerate(names):
        ax.plot(steps, a[:, i], "o-", color=color(i), ms=4, lw=1.6, label=f"{name} position")
        ax.axhline(slots[i], color=color(i), ls=":", lw=1.2, label=f"{name} equal-spacing slot ({slots[i]:.1f} m)")
    ax.set_xlabel(f"movement decision (one every {period:g} s)")
    ax.set_ylabel("distance from the source along S-D (m)")
    ax.set_title("Relay position between the source and the destination")
    ax.set_ylim(-1, length + 1)
    ax.grid(True, color="#e0e0e0", lw=0.6)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=9)
    ax = fig.add_subplot(gs[1], sharex=ax)
    q = np.array(qualities).reshape(-1, len(names), 2)  # (decisions, n, 2)
    ks = np.arange(1, len(q) + 1)
    for i, name in enumerate(names):
        before, after = (["S"] + names)[i], (names + ["D"])[i + 1]
        ax.plot(ks, q[:, i, 0], color=color(i), lw=1.4, label=f"{name}: link to {before}")
        ax.plot(ks, q[:, i, 1], color=color(i), lw=1.4, ls="--", label=f"{name}: link to {after}")
    ax.set_xlabel(f"movement decision (one every {period:g} s)")
    ax.set_ylabel("measured delivery ratio")
    ax.set_ylim(0, 1.05)
    ax.set_title("Link quality each relay measured" + (" (reported by MobiNet)" if mode == "agents" else
                                                       " (hello packets over the radio model)"))
    ax.grid(True, color="#e0e0e0", lw=0.6)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=9)
    fig.suptitle(f"{scenario.title} ({mode} mode)", fontsize=13)
