"""The robot host's SIP stream in time: a SIP every period whatever the physics grid's jitter."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from erni.sim.robot import SimRobotConfig, _packet
from erni.sim.robot_host import RobotHost
from erni.sim.world import World

OPEN = b"".join(_packet(bytes([c])) for c in (0, 1, 2, 1))  # SYNC0, SYNC1, SYNC2, OPEN


def sip_times(physics_hz: float, phase: float, late: list[float], stall: tuple[int, float] = (0, 0.0),
              first_late: float = 0.0, counts: dict[str, int] | None = None) -> list[float]:
    """Drive a host through its own loop on a fake clock: the robot opens at `phase` into the
    grid, tick k comes `late[k]` of a step after its grid time (`stall` = (k, steps): tick k comes
    that many steps late; the first tick after the robot opens comes `first_late` late); return
    when each SIP went (and the firmware's counters in `counts`)."""
    now = [0.0]
    host = RobotHost(World(), physics_hz=physics_hz, clock=lambda: now[0])
    step = host.period
    try:
        host.add_robot(SimRobotConfig(name="r"), port=0)
        fw = host.firmware(0)
        fw.receive(OPEN, phase * step)
        assert fw.state == "open"
        times: list[float] = []
        for k in range(1, round(4.0 / step)):
            grid = host._next  # the host's next step on its grid
            if grid > 4.0:
                break
            now[0] = grid + ((stall[1] if k == stall[0] else 0.0) + (first_late if k == 1 else late[k % len(late)])) * step
            host.run_once(0.0)
            if fw.counts["sips"] > len(times):
                times.append(now[0])
        if counts is not None:
            counts.update(fw.counts)
        return times
    finally:
        host.stop()


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([20.0, 50.0, 100.0]), st.floats(0.0, 0.999),
       st.lists(st.floats(0.0, 0.45), min_size=1, max_size=30), st.floats(0.0, 0.95))
def test_sips_keep_their_period_whatever_the_phase_and_the_ticks_lateness(physics_hz: float, phase: float,
                                                                         late: list[float], first_late: float) -> None:
    """A robot that opens anywhere between two physics steps, on a host whose ticks come up to
    0.45 of a step late (the first one after it opens up to 0.95): every SIP interval is the
    100 ms period within that lateness."""
    times = sip_times(physics_hz, phase, late, first_late=first_late)[1:]
    step = 1.0 / physics_hz
    intervals = [b - a for a, b in zip(times, times[1:])]
    assert len(times) >= 38
    assert all(abs(iv - 0.1) <= 0.45 * step + 1e-9 for iv in intervals), (min(intervals), max(intervals))


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, 0.999), st.lists(st.floats(0.0, 0.3), min_size=1, max_size=10), st.floats(1.05, 3.95))
def test_a_stalled_tick_does_not_shift_the_stream_off_its_grid(phase: float, late: list[float], stall: float) -> None:
    """One tick comes 1-4 steps late (the host skips the steps it missed): the SIP it held back
    goes late, and the stream goes on at the period, on the ticks it used before."""
    times = sip_times(20.0, phase, late, stall=(40, stall))
    intervals = [b - a for a, b in zip(times, times[1:])]
    odd = [iv for iv in intervals if abs(iv - 0.1) > 0.3 * 0.05 + 1e-9]
    assert len(odd) <= 2, intervals  # the stalled one and the one after it
    off_grid = [t for t in times if abs((t - times[0]) / 0.1 - round((t - times[0]) / 0.1)) * 0.1 > 0.3 * 0.05 + 1e-9]
    assert len(off_grid) <= 1, off_grid  # only the stalled tick's SIP
    assert len(times) >= 36  # a stall skips at most the SIPs it held back


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 0.999), st.lists(st.floats(0.0, 0.45), min_size=1, max_size=10),
       st.one_of(st.just(0.0), st.floats(1.05, 7.95)))
def test_the_host_counts_the_sips_a_stall_skipped(phase: float, late: list[float], stall: float) -> None:
    """Every slot of the SIP schedule is either sent or counted as skipped, so `erni sim` can say
    when the machine is too busy for its team; ticks late by less than half a step skip none."""
    counts: dict[str, int] = {}
    times = sip_times(20.0, phase, late, stall=(40, stall), counts=counts)
    slots = round((times[-1] - times[0]) / 0.1) + 1  # the last SIP is on the schedule's grid
    assert counts["sips"] == len(times)
    assert counts["skipped"] == slots - len(times), (counts, slots)
    if stall == 0.0:
        assert counts["skipped"] == 0
    if stall >= 4.0:  # 200 ms late or more: at least one 100 ms slot went by unsent
        assert counts["skipped"] >= 1
