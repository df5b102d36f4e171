"""Discovery by beacons, the peer directory on the blackboard, liveness, static and learned peers."""

from __future__ import annotations

from erni.blackboard import Agent, NetInfo, Task
from erni.blackboard.testing import wait_until
from erni.transport import Peer
from tests.transport.helpers import free_port, make_agent


def peers(agent: Agent) -> dict[str, Peer]:
    return {p.name: p for p in agent.query(Peer)}


def test_agents_find_each_other_without_a_peer_list():
    port = free_port()
    agents = [make_agent(f"a{i}", port, role="robot" if i else "control", capabilities=[f"c{i}"])
              for i in range(3)]
    try:
        for agent in agents:
            wait_until(lambda agent=agent: sum(p.up for p in peers(agent).values()) == 2)
        seen = peers(agents[1])["a0"]
        assert seen.role == "control" and seen.capabilities == ["c0"]
        assert seen.address == "{}:{}".format(*agents[0].plugin("transport").address)
    finally:
        for a in agents:
            a.stop()


def test_silent_peer_is_marked_down_and_up_again_and_beacons_of_a_peer_up_are_not_checked():
    """Every agent broadcasts a signed beacon each period: with N peers up that would be N
    signature checks a period that change nothing. They are skipped while the peer is up, and a
    restarted peer is still found."""
    port = free_port()
    a, b = make_agent("a", port), make_agent("b", port)
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        endpoint = a.plugin("transport").endpoint
        checked = endpoint.counters.get("received.beacons", 0)
        wait_until(lambda: endpoint.counters.get("received.beacons.known", 0) >= 5, timeout=5)
        # b's broadcasts (10 a second here) are heard, none checked: a's view of b rests on its session
        assert endpoint.counters.get("received.beacons", 0) - checked <= 1
        assert peers(a)["b"].up
        b.stop()
        wait_until(lambda: not peers(a)["b"].up, timeout=3)
        b = make_agent("b", port)
        wait_until(lambda: peers(a)["b"].up, timeout=3)
    finally:
        a.stop()
        b.stop()


def test_static_peer_list_works_with_discovery_off():
    a = make_agent("a", 0)
    addr = "{}:{}".format(*a.plugin("transport").address)
    b = make_agent("b", 0, peers=[f"a@{addr}"])
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)  # a learns b from b's beacons
        task = Task(verb="BotMotion", preposition="stop", source="b", destination="a")
        with b.transaction() as tx:
            tx.add(task)
        wait_until(lambda: b.blackboard.get(task.uid).done)
    finally:
        a.stop()
        b.stop()


def test_addresses_learned_from_the_network_topology():
    port = free_port()
    # beacons go nowhere by default here: only addresses learned from NetInfo are tried
    a = make_agent("a", port, beacon_to=[])
    b = make_agent("b", port, beacon_to=[])
    try:
        assert not peers(a).get("b")
        a_addr = "{}:{}".format(*a.plugin("transport").address)
        with b.transaction() as tx:
            tx.add(NetInfo(node="b", kind="neighbor_list", neighbors=[{"name": "a", "address": a_addr}]))
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
    finally:
        a.stop()
        b.stop()


def test_an_inbound_filter_fed_through_a_pipe_drops_traffic_between_unconnected_agents():
    import json
    import os
    import time

    from erni.blackboard import Task, TaskState
    from erni.sim.radio import RadioFilter, install

    def radio() -> tuple[RadioFilter, int]:
        read, write = os.pipe()
        return RadioFilter(read), write

    def tell(write: int, names: list[str]) -> None:
        os.write(write, (json.dumps(names) + "\n").encode())

    (radio_a, pipe_a), (radio_b, pipe_b) = radio(), radio()
    tell(pipe_a, ["b"])
    tell(pipe_b, ["a"])
    wait_until(lambda: radio_a.updates and radio_b.updates)
    port = free_port()
    a = make_agent("a", port, peer_timeout=0.5, start=False)
    b = make_agent("b", port, peer_timeout=0.5, start=False)
    install(a, radio_a)
    install(b, radio_b)
    a.start()
    b.start()
    try:
        wait_until(lambda: peers(a).get("b") and peers(a)["b"].up)
        tell(pipe_a, [])  # b drives out of range
        tell(pipe_b, [])
        wait_until(lambda: not peers(a)["b"].up, timeout=3)
        task = Task(verb="BotMotion", preposition="stop", source="a", destination="b")
        with a.transaction() as tx:
            tx.add(task)
        time.sleep(0.5)
        assert not b.blackboard.contains(task.uid)
        assert b.plugin("transport").endpoint.counters.get("dropped.unreachable", 0) > 0
        tell(pipe_a, ["b"])  # back in range: the queued task gets through
        tell(pipe_b, ["a"])
        wait_until(lambda: a.blackboard.get(task.uid).state is TaskState.SUCCEEDED, timeout=5)
    finally:
        a.stop()
        b.stop()
        os.close(pipe_a)
        os.close(pipe_b)

