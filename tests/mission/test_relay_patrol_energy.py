"""Relay balancing (paper 000 5.2), territory takeover (paper 002 II.C) and the energy model (000 5.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from erni.strategies.energy import (
    P0,
    EnergyMeter,
    energy,
    power,
    track_energy,
)
from erni.strategies.patrol import (
    TakeoverTable,
    backoff,
    claim_order,
    split,
    sweep_path,
    touching,
)
from erni.strategies.relay import (
    chain_slots,
    distance_quality,
    project,
    relay_step,
)

# --- relay -------------------------------------------------------------------------------

def run_relay(start: float, src=(0.0, 0.0), dst=(20.0, 0.0), R=15.0, clean=4.0, steps=60):
    pos = np.array([start, 3.0])  # off the line: it is projected onto S-D first
    trace = []
    for _ in range(steps):
        qs = float(distance_quality(math.dist(pos, src), R, clean))
        qd = float(distance_quality(math.dist(pos, dst), R, clean))
        move = relay_step(pos, src, dst, qs, qd, tolerance=0.05, gain=2.0, min_step=0.05)
        pos = move.target
        trace.append((pos.copy(), move.balanced))
    return pos, trace


@pytest.mark.parametrize("start", [1.0, 6.0, 17.5])
def test_relay_settles_in_the_middle(start):
    pos, trace = run_relay(start)
    assert trace[-1][1], "never balanced"
    assert abs(pos[0] - 10.0) < 0.6 and abs(pos[1]) < 1e-9
    # once balanced it holds
    first = next(k for k, (_, bal) in enumerate(trace) if bal)
    assert all(bal for _, bal in trace[first:])


def test_relay_moves_toward_the_missing_link_and_clamps_to_the_segment():
    move = relay_step((2.0, 0.0), (0, 0), (10, 0), 0.9, None, max_step=1.0)
    assert move.along == pytest.approx(1.0) and move.target == pytest.approx([3.0, 0.0])
    end = relay_step((9.9, 0.0), (0, 0), (10, 0), 0.9, 0.0, max_step=1.0)
    assert end.target == pytest.approx([10.0, 0.0])
    with pytest.raises(ValueError, match="q_source"):
        relay_step((0, 0), (0, 0), (1, 0), 1.5, 0.5)


def test_chain_slots_and_projection():
    slots = chain_slots((0, 0), (9, 0), 2)
    assert slots == pytest.approx(np.array([[3, 0], [6, 0]]))
    point, t = project((4, 5), (0, 0), (8, 0))
    assert point == pytest.approx([4, 0]) and t == pytest.approx(0.5)


# --- patrol ------------------------------------------------------------------------------

def test_blocks_paths_and_touching():
    blocks = split((0, 0, 10, 4), 2, 1)
    assert blocks == [(0, 0, 5, 4), (5, 0, 10, 4)]
    assert touching(*blocks)
    assert not touching((0, 0, 1, 1), (2, 0, 3, 1))
    path = sweep_path((0, 0, 5, 4), spacing=1.0, margin=0.5)
    assert np.all((path[:, 0] >= 0.5) & (path[:, 0] <= 4.5) & (path[:, 1] >= 0.5) & (path[:, 1] <= 3.5))
    assert len(path) == 8  # four lanes, two ends each


def team(blocks: dict[str, tuple], silence=2.0):
    # base 0.8 s > heartbeat period 0.25 s + the largest latency 0.4 s
    return {n: TakeoverTable(n, b, silence=silence, base=0.8) for n, b in blocks.items()}


def simulate_team(tables: dict[str, TakeoverTable], dead: str, until: float, latency: float = 0.1,
                  period: float = 0.25):
    """Heartbeats every `period` s, delivered after `latency` s; `dead` stops at t = 1."""
    inbox: list[tuple[float, str, dict]] = []
    events: list[tuple[float, str, str, str]] = []
    t = 0.0
    while t < until:
        for name, table in tables.items():
            if name == dead and t >= 1.0:
                continue
            for ev in table.tick(t):
                events.append((t, name, ev.kind, ev.about))
            inbox.append((t + latency, name, table.heartbeat()))
        due = [m for m in inbox if m[0] <= t]
        inbox = [m for m in inbox if m[0] > t]
        for _, sender, hb in due:
            for name, table in tables.items():
                if name != sender and not (name == dead and t >= 1.0):
                    for ev in table.heard(sender, tuple(hb["block"]), t, tuple(hb["holds"]), hb["claims"]):
                        events.append((t, name, ev.kind, ev.about))
        t = round(t + period, 6)
    return events


GRID = {f"r{i}": b for i, b in enumerate(split((0, 0, 30, 20), 3, 2))}


@given(st.sampled_from(sorted(GRID)), st.floats(0.0, 0.4))
def test_exactly_one_robot_takes_over_a_dead_neighbour(dead, latency):
    tables = team(GRID)
    events = simulate_team(tables, dead, until=12.0, latency=latency)
    claims = [e for e in events if e[2] == "claim" and e[3] == dead]
    holders = [n for n, t in tables.items() if n != dead and dead in t.holds]
    assert len(holders) == 1, (holders, events)
    assert len(claims) == 1, claims
    assert claims[0][1] == holders[0]
    assert touching(GRID[holders[0]], GRID[dead])
    # the other neighbours noticed the silence and yielded on hearing the claim
    noticed = {e[1] for e in events if e[2] == "silent" and e[3] == dead}
    assert noticed == set(GRID) - {dead}


def test_crossing_claims_are_settled_by_the_earlier_one():
    a = TakeoverTable("a", (0, 0, 1, 1))
    a.heard("x", (1, 0, 2, 1), 0.0)
    a.tick(10.0)
    events = a.tick(20.0)
    assert [e.kind for e in events] == ["claim"] and "x" in a.holds
    out = a.heard("b", (2, 0, 3, 1), 20.1, ("b", "x"), {"x": 19.0})  # b claimed first
    assert [e.kind for e in out] == ["yield"] and "x" not in a.holds


def test_a_silent_robot_heard_again_gets_its_block_back():
    a = TakeoverTable("a", (0, 0, 1, 1), silence=1.0, base=0.1)
    a.heard("x", (1, 0, 2, 1), 0.0)
    a.tick(2.0)
    a.tick(5.0)
    assert "x" in a.holds
    out = a.heard("x", (1, 0, 2, 1), 6.0)
    assert [e.kind for e in out] == ["return"] and "x" not in a.holds


def test_claim_order_prefers_nearer_touching_blocks_then_names():
    failed = (1, 0, 2, 1)
    cands = {"b": (0, 0, 1, 1), "a": (2, 0, 3, 1), "c": (0, 1, 1, 2), "far": (5, 5, 6, 6)}
    assert claim_order(failed, cands) == ["a", "b", "c"]
    assert backoff(0, 0.5) == 0.5 and backoff(2, 0.5) == 1.5
    with pytest.raises(ValueError, match="rank"):
        backoff(-1)


# --- energy ------------------------------------------------------------------------------

def test_power_model_of_the_paper():
    assert power([0.0, 0.5, -0.5]) == pytest.approx([8.568, 11.55 * 0.5 + 14.838, 11.55 * 0.5 + 14.838])
    assert energy(np.zeros(600), 1.0) == pytest.approx(8.568 * 600)  # the paper's 600 s standby


def test_track_energy_and_meter_agree():
    t = np.arange(0, 21, 1.0)
    x = np.concatenate([np.zeros(6), np.arange(1, 11) * 0.5, np.full(5, 5.0)])
    y = np.zeros_like(x)
    e, d = track_energy(t, x, y)
    assert d == pytest.approx(5.0)
    # 10 s moving at 0.5 m/s, 10 s standing
    assert e == pytest.approx(10 * (11.55 * 0.5 + 14.838) + 10 * P0)
    meter = EnergyMeter()
    for ti, xi in zip(t, x):
        meter.update(float(ti), float(xi), 0.0)
    assert meter.energy_j == pytest.approx(e) and meter.distance_m == pytest.approx(5.0)
    assert meter.values()["moving_s"] == pytest.approx(10.0)
    # a standing robot's poses are keep-alives: the 4 s since the last one were spent at standby power
    later = meter.values(until=24.0)
    assert later["energy_j"] == pytest.approx(round(e + 4 * P0, 2)) and later["elapsed_s"] == pytest.approx(24.0)
    assert later["distance_m"] == pytest.approx(5.0) and later["moving_s"] == pytest.approx(10.0)
    assert meter.values(until=24.0) == later and meter.values(until=19.0)["energy_j"] == round(e, 2)  # reading adds nothing
    with pytest.raises(ValueError, match="times must not decrease"):
        track_energy([0, 2, 1], [0, 0, 0], [0, 0, 0])
