"""A live peer on a lossy link stays up; a dead one still goes down: numbered beacons, counted."""

from __future__ import annotations

import logging
import math
import re

from hypothesis import given
from hypothesis import strategies as st

from erni.blackboard import Agent, Peer
from erni.blackboard.testing import wait_until
from erni.testing import MockTeam
from erni.transport import MockNetwork, TransportPlugin
from erni.transport.liveness import FALSE_DOWN, MAX_STRETCH, MIN_SENT, BeaconCount, silence_stretch


def test_a_count_of_every_third_beacon_says_a_third_arrive():
    count = BeaconCount()
    assert count.delivery() == 1.0  # nothing counted: the limit is not stretched
    for seq in range(1, 200, 3):
        count.heard(seq)
    assert math.isclose(count.share(), 1 / 3, rel_tol=1e-9)
    assert 0.2 < count.delivery() < 1 / 3  # a standard error lower


def test_duplicates_and_late_beacons_change_nothing_and_a_restart_counts_afresh():
    count = BeaconCount()
    for seq in range(1, 60, 2):  # half arrive
        count.heard(seq)
    half = count.share()
    assert math.isclose(half, 0.5, rel_tol=1e-9)
    count.heard(59)  # again
    count.heard(54)  # late: its number stays counted as lost
    count.heard(0)   # not numbered
    assert count.share() == half
    count.heard(1)   # the peer restarted and numbers from 1
    assert count.delivery() == 1.0
    for seq in range(2, 40):
        count.heard(seq)
    assert count.delivery() == 1.0


@given(st.lists(st.booleans(), min_size=1, max_size=300))
def test_the_count_is_a_share_of_the_numbered_beacons(arrived):
    count = BeaconCount()
    numbers = [seq for seq, ok in enumerate(arrived, 1) if ok]
    for seq in numbers:
        count.heard(seq)
    share = count.share()
    assert 0.0 < share <= 1.0 or not numbers
    assert 0.0 <= count.delivery() <= share
    if len(numbers) == len(arrived) or count.sent < MIN_SENT:
        assert share == count.delivery() == 1.0


@given(st.lists(st.integers(-5, 400), max_size=300))
def test_any_numbers_in_any_order_give_a_share_of_at_most_one(numbers):
    """Duplicated, late, restarted or unnumbered beacons (a lossy, reordering mesh; a peer that
    restarts): the count never claims more arrived than were sent."""
    count = BeaconCount()
    for seq in numbers:
        count.heard(seq)
        assert 0.0 <= count.got <= count.sent + 1e-9
        assert 0.0 <= count.delivery() <= count.share() <= 1.0


@given(st.floats(0.0, 1.0), st.floats(1.0, 50.0))
def test_a_stretched_limit_loses_all_its_beacons_at_most_rarely(delivery, beacons):
    stretch = silence_stretch(delivery, beacons)
    assert 1.0 <= stretch <= MAX_STRETCH
    if stretch < MAX_STRETCH and delivery < 1.0:
        assert (1.0 - delivery) ** (beacons * stretch) <= FALSE_DOWN * (1 + 1e-9)
    if (1.0 - delivery) ** beacons <= FALSE_DOWN:
        assert stretch == 1.0  # a link that loses little keeps peer_timeout


def test_a_dead_peers_limit_is_at_most_ten_times_the_lossless_one():
    assert silence_stretch(0.0, 4) == silence_stretch(0.01, 4) == MAX_STRETCH
    assert silence_stretch(0.9, 4) == 1.0


def test_a_live_peer_on_a_link_losing_most_frames_stays_up_and_a_dead_one_goes_down(caplog):
    """Two agents that send each other nothing but beacons, on a link that loses 60 % of them: four
    beacon periods of silence come about once in eight periods, so with `peer_timeout` alone they
    took each other for down 6-7 times in six seconds. Counting the beacons that arrive, each
    waits out the silence a live peer can have; when one agent stops, the other still finds it
    down, at a limit of at most ten times `peer_timeout`."""
    net = MockNetwork(seed=11, loss=0.6)

    class Mocked(TransportPlugin):
        endpoint_factory = staticmethod(net.endpoint)

    timings = {"insecure": True, "discovery_port": 0, "beacon_period": 0.1, "peer_timeout": 0.4}
    agents = []
    for k, name in enumerate(["a", "b"]):
        agent = Agent(name, workers=2)
        agent.add_plugin(Mocked, settings={**timings, "peers": ["a@mock:1"] if k else []}, name="transport")
        agents.append(agent.start())
    a, b = agents
    try:
        up = lambda agent, name: any(p.name == name and p.up for p in agent.query(Peer))  # noqa: E731
        wait_until(lambda: up(a, "b") and up(b, "a"), timeout=10)

        def numbered(agent: Agent, name: str) -> int:
            """The number of the newest beacon of `name` that reached `agent` (one a beacon period)."""
            count = next(p for p in agent.plugins if isinstance(p, TransportPlugin)).peers[name].beacon_count
            return count.last if count is not None else 0

        # the first beacons counted: twenty periods of each
        wait_until(lambda: numbered(a, "b") >= 20 and numbered(b, "a") >= 20, timeout=60)
        with caplog.at_level(logging.WARNING):
            caplog.clear()
            ab, ba = numbered(a, "b"), numbered(b, "a")
            # six seconds of them: sixty beacon periods of each
            wait_until(lambda: numbered(a, "b") >= ab + 60 and numbered(b, "a") >= ba + 60, timeout=60)
            downs = [r.getMessage() for r in caplog.records if " is down" in r.getMessage()]
        assert len(downs) <= 2, downs
        transport = next(p for p in a.plugins if isinstance(p, TransportPlugin))
        assert transport.presence.down_after("b") > 2 * timings["peer_timeout"]  # stretched: most beacons go lost
        counted = transport.peers["b"].beacon_count
        assert counted is not None and 0.1 < counted.share() < 0.75  # 40 % arrive (the last ten or so)
        with caplog.at_level(logging.WARNING):
            caplog.clear()
            b.stop()
            wait_until(lambda: not up(a, "b"), timeout=60)  # a progress bound: the limit is checked below
        # down when its silence passed the limit in force, which is at most ten times peer_timeout
        # (the limit a's transport names, not the wall clock of a loaded machine's test run)
        (down,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("peer b is down:")]
        said = re.fullmatch(r"peer b is down: not heard for ([\d.]+) s \(limit ([\d.]+) s; .*\)", down)
        assert said, down
        assert float(said[1]) >= float(said[2]), down
        assert 2 * timings["peer_timeout"] < float(said[2]) <= MAX_STRETCH * timings["peer_timeout"], down
        assert net.counters["lost"] > 0
    finally:
        for agent in agents:
            agent.stop()


def test_beacons_to_a_quiet_peer_are_numbered_one_by_one():
    with MockTeam(seed=1) as team:
        for name in ("a", "b"):
            team.add(name, beacon_period=0.1, peer_timeout=0.4)
        team.start(timeout=10)
        transport = team["b"].plugin("transport")
        assert isinstance(transport, TransportPlugin)
        wait_until(lambda: "a" in transport.peers and transport.peers["a"].beacons_sent >= 4)
        sent = transport.peers["a"].beacons_sent
        receiver = team["a"].plugin("transport")
        assert isinstance(receiver, TransportPlugin)
        count = receiver.peers["b"].beacon_count
        assert count is not None
        assert count.last >= sent - 2 and count.delivery() == 1.0  # nothing lost: every number came
