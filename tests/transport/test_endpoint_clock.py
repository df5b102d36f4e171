"""The endpoint's clock: what expires (a message's deadline, a handshake, an idle session or
connection) is timed by the clock the endpoint is given, so a test moves time instead of waiting."""

from __future__ import annotations

import socket

from erni.blackboard import Pose
from erni.blackboard.testing import wait_until
from erni.testing import ManualClock
from erni.transport import Endpoint
from erni.transport.identity import load_identity
from erni.transport.limits import Limits
from tests.transport.helpers import identity


def endpoint(name: str, clock: ManualClock, **kw) -> tuple[Endpoint, list]:
    ep = Endpoint(name, identity=load_identity(identity(name)), ack_timeout=0.3, connect_timeout=0.5,
                  clock=clock, **kw)
    got: list = []
    ep.on_message = got.append
    ep.start()
    return ep, got


def silent_address() -> tuple[str, int]:
    """A UDP port bound by nobody who answers: handshakes to it go unanswered."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    addr = s.getsockname()
    s.close()
    return addr


def test_a_message_nobody_answers_expires_when_the_clock_passes_its_deadline_not_before():
    clock = ManualClock()
    a, _ = endpoint("alpha", clock, ttl=30.0, handshake_timeout=1000.0)
    lost: list[str] = []
    a.on_undeliverable = lambda addr, msg_id, kind, body: lost.append(msg_id)
    try:
        msg_id = a.send(silent_address(), "task", Pose(robot="x"), reliable=True, to="beta")
        wait_until(lambda: a.counters.get("handshakes.sent", 0) >= 3, timeout=10)  # real time goes on
        clock.advance(29.0)
        wait_until(lambda: a.counters.get("handshakes.sent", 0) >= 5, timeout=10)
        assert lost == [], "29 s of the endpoint's clock: the 30 s deadline has not passed"
        clock.advance(2.0)
        wait_until(lambda: lost == [msg_id], timeout=5)
    finally:
        a.stop()


def test_an_unanswered_handshake_is_given_up_by_the_endpoints_clock():
    clock = ManualClock()
    a, _ = endpoint("alpha", clock, handshake_timeout=20.0)
    try:
        a.send(silent_address(), "task", Pose(robot="x"), reliable=True, to="beta")
        wait_until(lambda: a.counters.get("handshakes.sent", 0) >= 3, timeout=10)
        assert a.counters.get("handshakes.failed", 0) == 0
        clock.advance(21.0)
        wait_until(lambda: a.counters.get("handshakes.failed", 0) >= 1, timeout=5)
    finally:
        a.stop()


def test_an_idle_session_is_forgotten_when_the_clock_passes_the_idle_limit():
    clock = ManualClock()
    limits = Limits(session_idle=600.0)
    a, _ = endpoint("alpha", clock, limits=limits)
    b, got = endpoint("beta", clock, limits=limits)
    try:
        a.send(b.address, "one", Pose(robot="x"), reliable=True, to="beta")
        wait_until(lambda: got)
        # and acknowledged: an ack taken after the advance would count as traffic at 601 s
        wait_until(lambda: a.counters.get("sent.reliable", 0) == 1)
        assert a.session_with(b.address) is not None
        clock.advance(601.0)  # real time would take ten minutes
        wait_until(lambda: a.session_with(b.address) is None and not b.sessions.by_sid, timeout=5)
        a.send(b.address, "two", Pose(robot="x"), reliable=True, to="beta")  # a new session, at once
        wait_until(lambda: [m.kind for m in got] == ["one", "two"])
    finally:
        a.stop()
        b.stop()


def test_a_task_for_an_agent_never_discovered_fails_when_the_agents_clock_passes_its_ttl():
    """The transport plugin times its own waits by the agent's clock: a 600 s task_ttl passes
    when the test moves the clock, not before."""
    from erni.blackboard import Agent, Task, TaskState
    from tests.transport.helpers import auth_settings, free_port

    clock = ManualClock()
    control = Agent("control", workers=2, clock=clock)
    control.add_plugin("transport", name="transport",
                       settings={**auth_settings("control", "control"), "discovery_port": free_port(),
                                 "beacon_period": 0.5, "peer_timeout": 2.0, "task_ttl": 600.0})
    control.start()
    try:
        task = Task(verb="BotMotion", preposition="forward", params={"distance": 1.0}, source="control",
                    destination="robot9")
        with control.transaction() as tx:
            tx.add(task)
        wait_until(lambda: (sent := control.plugin("transport").tasks_out.get(task.uid)) is not None
                   and sent.pending is not None)
        counters = control.plugin("transport").endpoint.counters
        beacons = counters.get("sent.announce", 0)
        clock.advance(599.0)
        wait_until(lambda: counters.get("sent.announce", 0) > beacons)  # the plugin ran on the moved clock
        assert not control.blackboard.get(task.uid).done, "599 s of the agent's clock: still waiting"
        clock.advance(2.0)
        failed = wait_until(lambda: (t := control.blackboard.get(task.uid)).done and t)
        assert failed.result.state == TaskState.FAILED and "never discovered" in failed.result.message
    finally:
        control.stop()


def test_the_stream_thread_sleeps_until_its_next_sweep(monkeypatch):
    """With no connection and no frame, the stream thread's selector waits out the time to its next
    sweep (a second), not a quarter of a second: an agent at rest is not woken four times a second."""
    import selectors

    from erni.transport import receiver

    waits: list[float | None] = []
    base = selectors.DefaultSelector

    class Recording(base):  # type: ignore[misc, valid-type]
        def select(self, timeout=None):
            waits.append(timeout)
            return super().select(timeout)

    monkeypatch.setattr(receiver.selectors, "DefaultSelector", Recording)
    a, _ = endpoint("alpha", ManualClock())
    try:
        wait_until(lambda: waits, timeout=10)
        assert waits[0] is not None and 0.5 < waits[0] <= receiver.SWEEP_PERIOD  # just after the first sweep
    finally:
        a.stop()
