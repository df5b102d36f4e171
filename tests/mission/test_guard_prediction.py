"""The network guard predicts: late readings of a critical link, projected over latency and braking.

Pure decision code with time passed in. The readings below are shaped like babeld's on the
real-mesh tier (a robot creeping at 0.3 m/s from its only neighbour read 1.0 until 7.3 m, then
0.87, 0.61, 0.50, 0.59 ... and 0.29 only at 9.7 m, where the radio's 0.3 lies at 8.8 m).
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from erni.blackboard.tasks import Link
from erni.plugins.mission.netaware import NetGuard, _bridges

LEAF = [Link(a="relay", b="end", quality=0.9), Link(a="relay", b="control", quality=1.0)]


def creeping(guard: NetGuard, speed: float, readings: list[float], *, start: float = 6.0,
             period: float = 0.5) -> tuple[float, str]:
    """Drive `guard`'s robot away from `relay` at `speed` m/s, one reading each `period` s;
    return (distance, reason) at the first risk, or (inf, "") when none came."""
    guard.topology(LEAF)
    guard.positions({"relay": (0.0, 0.0)})
    for k, q in enumerate(readings):
        t = k * period
        d = start + speed * t
        guard.quality({"relay": q}, t)
        if guard.update(t, (d, 0.0)) == "risk":
            return d, guard.state.reason
    return float("inf"), ""


def test_a_leaf_link_is_critical_and_a_triangle_has_none():
    assert _bridges("end", (("relay", "end"), ("relay", "control"))) == {"relay"}
    assert _bridges("relay", (("relay", "end"), ("relay", "control"))) == {"end", "control"}
    assert _bridges("a", (("a", "b"), ("b", "c"), ("a", "c"))) == set()
    assert _bridges("a", ()) == set()


def test_babelds_late_readings_at_0_3_m_s_hold_the_robot_before_the_threshold_reading_arrives():
    readings = [1.0] * 10 + [0.87, 0.87, 0.61, 0.50, 0.59, 0.59, 0.53, 0.48, 0.45, 0.29]
    d, reason = creeping(NetGuard("end", min_quality=0.3), 0.3, readings)
    assert d < 8.8, f"held at {d:.2f} m, beyond where the radio delivers 0.3"
    assert reason.startswith("the link to relay (0.") and "predicted to fall below 0.30" in reason
    # the threshold guard of before: at risk only once a reading is below 0.3 (at 9.0 m here)
    late, why = creeping(NetGuard("end", min_quality=0.3, predict=False), 0.3, readings)
    assert late == pytest.approx(6.0 + 0.3 * 19 * 0.5) and why.startswith("best link quality 0.29")


def test_the_faster_the_robot_the_earlier_the_first_sign_of_loss_holds_it():
    first_sign = [1.0, 1.0, 0.87]
    fast, reason = creeping(NetGuard("end"), 1.0, first_sign)
    assert fast == pytest.approx(7.0) and "moving away at 1.00 m/s" in reason
    slow, _ = creeping(NetGuard("end"), 0.1, first_sign + [0.87] * 6)
    assert slow == float("inf")  # 0.87 at a creep: time enough to read again


def test_a_standing_robot_and_one_driving_towards_its_neighbour_are_not_held_by_a_prediction():
    g = NetGuard("end")
    g.topology(LEAF)
    g.positions({"relay": (0.0, 0.0)})
    for k, q in enumerate([0.9, 0.8, 0.7, 0.6, 0.5]):
        g.quality({"relay": q}, k * 0.5)
        assert g.update(k * 0.5, (8.0, 0.0)) is None  # standing
    for k, q in enumerate([0.5, 0.45, 0.4, 0.35]):
        t = 3.0 + k * 0.5
        g.quality({"relay": q}, t)
        assert g.update(t, (8.0 - 0.5 * k, 0.0)) is None  # nearer at 1 m/s: nothing predicted


def test_hysteresis_a_flicker_of_good_readings_clears_nothing():
    g = NetGuard("end", min_quality=0.3, resume_after=3.0)
    g.topology(LEAF)
    g.positions({"relay": (0.0, 0.0)})
    g.quality({"relay": 0.25}, 0.0)
    assert g.update(0.0, (9.0, 0.0)) == "risk"
    t = 0.5
    for q in (0.6, 0.6, 0.45, 0.6, 0.6, 0.6, 0.6, 0.6):  # 0.45 < resume quality 0.5: the clock restarts
        g.quality({"relay": q}, t)
        assert g.update(t, (9.0, 0.0)) is None, f"cleared at t={t}"
        t += 0.5
    for q in (0.6, 0.6):
        g.quality({"relay": q}, t)
        change = g.update(t, (9.0, 0.0))
        t += 0.5
    assert change == "clear"  # 3 s of readings at least 0.5 since the dip at t = 1.5


def test_clearing_is_not_resuming_away_from_the_only_link():
    g = NetGuard("end")
    g.topology(LEAF)
    g.positions({"relay": (0.0, 0.0)})
    g.quality({"relay": 0.6}, 0.0)
    g.update(0.0, (8.0, 0.0))
    assert g.away((8.0, 0.0), (20.0, 0.0)) == "relay"     # further out
    assert g.away((8.0, 0.0), (8.0, 5.0)) == "relay"      # sideways also stretches the link
    assert g.away((8.0, 0.0), (2.0, 0.0)) == ""           # back towards it
    g.positions({})
    assert g.away((8.0, 0.0), (2.0, 0.0)) == "relay"      # where the relay is, unknown: stay
    g.positions({"relay": (0.0, 0.0)})
    g.quality({"relay": 1.0}, 1.0)
    assert g.away((8.0, 0.0), (20.0, 0.0)) == "relay"     # one good reading: the loss was a second ago
    g.quality({"relay": 1.0}, 11.0)
    assert g.away((8.0, 0.0), (20.0, 0.0)) == ""          # loss-free for 10 s: room to stretch


@settings(max_examples=60, deadline=None)
@given(speed=st.floats(0.05, 2.0), latency=st.floats(0.5, 20.0),
       noise=st.lists(st.floats(-0.08, 0.08), min_size=60, max_size=60))
def test_a_robot_the_guard_reads_late_is_held_while_the_link_still_carries(speed, latency, noise):
    """A radio whose quality falls linearly from 1 at 6 m to 0 at 10 m, read `latency` s late
    with noise, and a robot driving away at `speed`, capped as the mission caps a motion away from
    the neighbour of a critical link (`safe_speed`: loss-free readings tell nothing of where the
    lossy band begins, and the first sign of loss comes `latency` s after the robot entered it):
    when the guard's latency covers the readings' and it brakes at 0.5 m/s^2, the robot stands
    before its link is gone, at every speed asked."""
    g = NetGuard("end", min_quality=0.3, latency=latency)
    g.topology(LEAF)
    g.positions({"relay": (0.0, 0.0)})
    period, d, v, t = 0.25, 6.0, min(speed, g.safe_speed()), 0.0
    history: list[tuple[float, float]] = []
    held = False
    for k in range(4000):
        t = k * period
        history.append((t, d))
        seen = next((dist for ts, dist in reversed(history) if ts <= t - latency), 6.0)
        q = max(0.0, min(1.0, (10.0 - seen) / 4.0 + noise[k % len(noise)])) if seen > 6.0 else 1.0
        g.quality({"relay": q}, t)
        if g.update(t, (d, 0.0)) == "risk":
            held = True
        if held:
            v = max(0.0, v - 0.5 * period)
        if held and v == 0.0:
            break
        d += v * period
    assert held and d < 10.0, f"stood at {d:.2f} m (speed {speed:.2f} m/s, readings {latency:.2f} s late)"


def test_the_speed_away_from_an_only_link_leaves_room_to_stand_on_the_first_sign_of_loss():
    g = NetGuard("end", latency=2.5, braking=0.5, fade_distance=4.0)
    v = g.safe_speed()
    assert v == pytest.approx(0.605, abs=0.001)
    assert v * (2.5 + 0.2) + v * v / (2 * 0.5) == pytest.approx(2.0)
    assert NetGuard("end", latency=20.0).safe_speed() < 0.1  # babeld's default 4 s Hellos: a creep
    g.topology(LEAF)
    g.positions({"relay": (0.0, 0.0)})
    g.quality({"relay": 1.0}, 0.0)
    assert g.leaving((6.0, 0.0), (20.0, 0.0)) == "relay"  # loss-free, and still its only link
    assert g.leaving((6.0, 0.0), (1.0, 0.0)) == ""
    assert g.away((6.0, 0.0), (20.0, 0.0)) == ""          # no loss seen: a held motion may resume


def test_with_no_bridge_the_best_link_is_projected_and_anchors_the_resume():
    """Robots walking off in all directions from a cluster: every link of this one is shared with
    others (no bridge), and it moves away from them all. Before: only a reading below the
    threshold held it, seconds late on babeld."""
    mesh = [Link(a="me", b="r1"), Link(a="me", b="r2"), Link(a="r1", b="r2"), Link(a="r1", b="control"),
            Link(a="r2", b="control")]
    g = NetGuard("me", min_quality=0.3)
    g.topology(mesh)
    assert g.critical() == []
    g.positions({"r1": (0.0, 0.0), "r2": (0.0, 1.0)})
    change = None
    for k in range(8):  # driving off at 1 m/s, both links showing loss
        t = 0.5 * k
        g.quality({"r1": 0.8 - 0.05 * k, "r2": 0.75 - 0.05 * k}, t)
        change = g.update(t, (6.0 + 0.5 * k, 0.0)) or change
        if change == "risk":
            break
    assert change == "risk" and g.state.reason.startswith("every link of me is predicted to fall below 0.30")
    assert g.readings["r1"][-1].quality > 0.3  # it stood while its best link still carried
    here = (6.0 + 0.5 * k, 0.0)
    for j in range(1, 10):  # standing, the best link reads 0.45: below the resume quality 0.5
        g.quality({"r1": 0.45, "r2": 0.4}, t + 0.5 * j)
        assert g.update(t + 0.5 * j, here) is None
    changes = []
    for j in range(10, 18):
        g.quality({"r1": 0.55, "r2": 0.4}, t + 0.5 * j)
        changes.append(g.update(t + 0.5 * j, here))
    assert changes == [None] * 6 + ["clear", None]  # after 3 s at 0.55 on the best link
    # cleared is not resumed: not away from r1, whose link held it and showed loss lately
    assert g.cause == "r1" and g.away(here, (20.0, 0.0)) == "r1" and g.away(here, (0.0, 0.0)) == ""
