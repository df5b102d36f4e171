"""Paper 000, section 5.2: one or two robots relay a flow between a source and a destination (Figures 7, 8).

Kinematic mode: the source S and the destination D stand still; the relays form a chain
S - r1 - ... - D. Every `period` seconds (16 s in the paper) each relay measures the
delivery ratio of its two links by sending `probes` hello packets over the scenario's radio
model (a seeded binomial draw, so the measurement is noisy as a real one is), then takes
one `relay.relay_step` toward its worse link and drives there. Metrics: decisions until
every relay stays within `settle` m of its equal-spacing slot, final error, oscillation
after settling, and the link qualities.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from erni.sim import kinematic
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.manet import RadioModel
from erni.sim.scenario import Scenario, ScenarioError
from erni.strategies import relay


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, **_: Any) -> Result:
    """Run the relays' decisions for the scenario's duration; return figure and metrics."""
    s = scenario.strategy
    if len(scenario.poi) < 2:
        raise ScenarioError(f"{scenario.name}: the relay experiment needs two [[poi]]: the source and the destination")
    src = np.array([scenario.poi[0].x, scenario.poi[0].y])
    dst = np.array([scenario.poi[1].x, scenario.poi[1].y])
    radio = RadioModel(scenario.radio.comm_range, scenario.radio.lossless_range, scenario.radio.min_quality)
    period = float(s.get("period", 16.0))
    speed = float(s.get("speed", 0.2))
    probes = int(s.get("probes", 50))
    tolerance = float(s.get("tolerance", 0.05))
    gain = float(s.get("gain", 4.0))
    settle = float(s.get("settle", 0.5))
    dt = float(s.get("dt", 0.2))
    duration = scenario.duration or 480.0
    rng = np.random.default_rng(scenario.seed)
    starts = scenario.starts()
    names = [st.name for st in starts]
    n = len(starts)
    pos = np.array([[st.x, st.y] for st in starts])
    th = np.radians([st.heading for st in starts])
    slots = relay.chain_slots(src, dst, n)
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
            move = relay.relay_step(pos[i], prev, nxt, q_prev, q_next, tolerance=tolerance, gain=gain)
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
    a = np.array(along)  # (decisions + 1, n): position along S -> D (m)
    slot_along = (slots - src) @ unit
    err = np.abs(a - slot_along)
    inside = (err <= settle).all(axis=1)
    settled = next((k for k in range(len(inside)) if inside[k:].all()), None)
    res = Result(experiment.name, experiment.title, "kinematic")
    res.metrics["source-destination distance"] = (length, "m")
    res.metrics["decisions until every relay stays at its slot"] = (
        float(settled) if settled is not None else float("nan"), f"decisions of {period:g} s")
    res.metrics["final distance from the equal-spacing slot, worst"] = (float(err[-1].max()), "m")
    if settled is not None and settled < len(a) - 1:
        res.metrics["oscillation after settling (std)"] = (float(a[settled:].std(axis=0).max()), "m")
    last = np.array(qualities[-1]) if qualities else np.zeros((n, 2))
    res.metrics["weakest link quality at the end"] = (float(last.min()), "delivery ratio")
    for i, name in enumerate(names):
        res.robots[name] = {"slot_m": round(float(slot_along[i]), 2), "final_m": round(float(a[-1, i]), 2),
                            "q_prev": round(float(last[i, 0]), 2), "q_next": round(float(last[i, 1]), 2)}
        res.series[f"{name}/position_along"] = (list(np.arange(len(a)) * period), list(a[:, i]), "m")
    if n == 1:
        res.paper.append(("decisions until the relay reaches the middle (approx.)",
                          float(settled) if settled is not None else float("nan"), 10.0, "decisions"))
    res.notes.append(f"link quality measured with {probes} hello packets per decision over the radio model "
                     f"(loss-free to {radio.lossless_range:g} m, none beyond R = {radio.comm_range:g} m)")
    res.draw = lambda fig: _draw(fig, scenario, names, a, slot_along, length, qualities, period)
    return res


def _probe(radio: RadioModel, distance: float, probes: int, rng: np.random.Generator) -> float:
    """Delivery ratio of `probes` hello packets over a link of `distance` m."""
    return float(rng.binomial(probes, radio.quality(distance)) / probes)


def _draw(fig: Any, scenario: Scenario, names: list[str], a: NDArray[np.float64], slots: NDArray[np.float64],
          length: float, qualities: list[list[tuple[float, float]]], period: float) -> None:
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
    q = np.array(qualities)  # (decisions, n, 2)
    ks = np.arange(len(q))
    for i, name in enumerate(names):
        ax.plot(ks, q[:, i, 0], color=color(i), lw=1.4, label=f"{name}: link toward S")
        ax.plot(ks, q[:, i, 1], color=color(i), lw=1.4, ls="--", label=f"{name}: link toward D")
    ax.set_xlabel(f"movement decision (one every {period:g} s)")
    ax.set_ylabel("measured delivery ratio")
    ax.set_ylim(0, 1.05)
    ax.set_title("Link quality each relay measured")
    ax.grid(True, color="#e0e0e0", lw=0.6)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=9)
    fig.suptitle(scenario.title, fontsize=13)
