"""The mock network: seeded loss, delay, duplication, reordering and partitions, usable by plugin tests."""

from __future__ import annotations

import threading

import pytest

from erni.blackboard import Task, TaskState
from erni.blackboard.testing import wait_until
from erni.testing import MockTeam, post_task, wait_for_task
from erni.transport import MockEndpoint, MockNetwork
from erni.transport.wire import Message


def pair(net: MockNetwork):
    a, b = net.endpoint("a"), net.endpoint("b")
    got: list[Message] = []
    lock = threading.Lock()

    def collect(m: Message) -> None:
        with lock:
            got.append(m)

    b.on_message = collect
    a.start()
    b.start()
    return a, b, got


def test_loss_hits_fast_messages_and_reliable_ones_still_arrive():
    net = MockNetwork(seed=3, loss=0.3)
    a, b, got = pair(net)
    try:
        for i in range(200):
            a.send(b.address, "fast", i, reliable=False)
        for i in range(50):
            a.send(b.address, "rel", i, reliable=True)
        wait_until(lambda: sum(m.kind == "rel" for m in got) == 50)
        fast = sum(m.kind == "fast" for m in got)
        assert 100 < fast < 180, fast
        assert sorted(m.body for m in got if m.kind == "rel") == list(range(50))
    finally:
        a.stop()
        b.stop()


def test_same_seed_same_losses():
    def run(seed: int) -> list[int]:
        net = MockNetwork(seed=seed, loss=0.5)
        a, b, got = pair(net)
        try:
            for i in range(100):
                a.send(b.address, "fast", i, reliable=False)
            wait_until(lambda: net.counters["delivered"] + net.counters["lost"] == 100)
            return sorted(m.body for m in got)
        finally:
            a.stop()
            b.stop()

    assert run(7) == run(7)
    assert run(7) != run(8)


def test_duplicates_and_reordering():
    net = MockNetwork(seed=1, duplicate=0.5, jitter=0.02)
    a, b, got = pair(net)
    try:
        for i in range(100):
            a.send(b.address, "fast", i, reliable=False)
        for i in range(30):
            a.send(b.address, "rel", i, reliable=True)
        wait_until(lambda: sum(m.kind == "rel" for m in got) == 30)
        wait_until(lambda: sum(m.kind == "fast" for m in got) > 100)  # duplicated
        bodies = [m.body for m in got if m.kind == "fast"]
        assert bodies != sorted(bodies), "jitter reorders"
        assert sorted(m.body for m in got if m.kind == "rel") == list(range(30)), "reliable: once each"
    finally:
        a.stop()
        b.stop()


def test_partition_holds_reliable_messages_until_healed_and_ttl_gives_up():
    net = MockNetwork(seed=2)
    a, b, got = pair(net)
    failed: list[str] = []
    a.on_undeliverable = lambda addr, mid, kind, body: failed.append(body)
    try:
        net.partition({"a"}, {"b"})
        a.send(b.address, "rel", "held", reliable=True)
        a.send(b.address, "rel", "expires", reliable=True, ttl=0.1)
        a.send(b.address, "fast", "lost", reliable=False)
        wait_until(lambda: failed == ["expires"])
        assert got == []
        net.heal()
        wait_until(lambda: [m.body for m in got] == ["held"])
    finally:
        a.stop()
        b.stop()


def test_probabilities_are_checked():
    with pytest.raises(ValueError, match="loss: expected a probability in 0..1, got 1.5"):
        MockNetwork(loss=1.5)


def test_transport_plugin_runs_unchanged_on_the_mock_network():
    """`erni.testing.MockTeam` puts each agent's TransportPlugin on one MockNetwork."""
    with MockTeam(seed=5, loss=0.2, jitter=0.005) as team:
        control = team.add("control", role="control")
        robot = team.add("robot1")
        robot.add_plugin("echo", settings={"verbs": ["BotMotion"]}, name="motion")
        team.start()
        assert isinstance(robot.plugin("transport").endpoint, MockEndpoint)
        tasks = [post_task(control, "BotMotion", "forward", destination="robot1", distance=i + 1) for i in range(10)]
        for task in tasks:
            assert wait_for_task(control, task).state is TaskState.SUCCEEDED
        assert len(robot.query(Task)) == 10
