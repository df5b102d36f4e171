"""Sessions between endpoints on loopback: restarts of either side, crossing handshakes, loss, a wrong peer."""

from __future__ import annotations

import threading

from erni.blackboard import Pose
from erni.blackboard.testing import wait_until
from erni.transport import Endpoint
from erni.transport.identity import load_identity
from tests.transport.helpers import identity


def endpoint(name: str, **kw) -> tuple[Endpoint, list]:
    ep = Endpoint(name, identity=load_identity(identity(name)), ack_timeout=0.3, connect_timeout=0.5, **kw)
    got: list = []
    ep.on_message = got.append
    ep.start()
    return ep, got


def test_a_restarted_receiver_gets_a_new_session_at_once():
    """Its old session is unknown to it: it says so on the stream, and the sender shakes hands again.
    Without the hint the sender would go on with the old session until it gave up on the message
    (20 attempts), so the message arriving at all, on a new session, is what shows it; the wait
    for it is a progress bound only."""
    a, _ = endpoint("alpha")
    b, got = endpoint("beta")
    port = b.address
    try:
        a.send(port, "one", Pose(robot="x"), reliable=True, to="beta")
        wait_until(lambda: got)
        old = a.session_with(port)
        b.stop()
        b, got = endpoint("beta", listen=port)  # the same address, a new instance
        a.send(port, "two", Pose(robot="x"), reliable=True, to="beta")
        wait_until(lambda: got, timeout=30)
        assert a.session_with(port) is not old and a.counters.get("hints.received", 0) >= 1
        assert [m.kind for m in got] == ["two"]
    finally:
        a.stop()
        b.stop()


def test_a_restarted_sender_is_a_new_instance_and_its_old_sessions_go():
    a, _ = endpoint("alpha")
    b, got = endpoint("beta")
    port = a.address
    try:
        a.send(b.address, "one", None, reliable=True)
        wait_until(lambda: got)
        first = got[-1]
        a.stop()
        a, _ = endpoint("alpha", listen=port)
        a.send(b.address, "two", None, reliable=True)
        wait_until(lambda: len(got) == 2)
        assert (first.epoch, got[-1].epoch) == (1, 2), "the receiver counts the sender's instances"
        assert sum(1 for s in b.sessions.by_sid.values() if s.peer == "alpha") == 1, "the old instance's session is gone"
    finally:
        a.stop()
        b.stop()


def test_crossing_handshakes_both_work():
    a, got_a = endpoint("alpha")
    b, got_b = endpoint("beta")
    try:
        go = threading.Barrier(2)

        def shoot(src, dst):
            go.wait()
            for i in range(20):
                src.send(dst.address, "x", {"i": i}, reliable=False)

        threads = [threading.Thread(target=shoot, args=pair) for pair in ((a, b), (b, a))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wait_until(lambda: len(got_a) == 20 and len(got_b) == 20)
        assert [m.body["i"] for m in got_b] == list(range(20))
    finally:
        a.stop()
        b.stop()


def test_handshakes_survive_loss():
    a, _ = endpoint("alpha", udp_loss=0.3, seed=1)
    b, got = endpoint("beta", udp_loss=0.3, seed=2)
    try:
        for round_ in range(5):  # a new pair of instances each round: five handshakes under loss
            for i in range(4):
                a.send(b.address, "x", {"i": i}, reliable=True, ttl=20)
            wait_until(lambda received=got: len(received) == 4, timeout=20)
            got.clear()
            b.stop()
            b, got = endpoint("beta", udp_loss=0.3, seed=10 + round_, listen=b.address)
        lost = a.counters.get("dropped.injected", 0)
        assert lost >= 1, "some handshake datagrams were lost on the way"
    finally:
        a.stop()
        b.stop()


def test_a_message_for_one_agent_is_never_delivered_to_another_at_its_address():
    a, _ = endpoint("alpha")
    b, got = endpoint("beta")
    failed: list = []
    a.on_undeliverable = lambda addr, mid, kind, body: failed.append(kind)
    try:
        a.send(b.address, "task.add", None, reliable=True, ttl=1.5, to="gamma")  # gamma was here once
        wait_until(lambda: failed == ["task.add"], timeout=5)
        assert not got and b.counters.get("received", 0) == 0
        assert b.counters.get("dropped.receiver", 0) >= 1, "beta refuses a handshake meant for gamma"
    finally:
        a.stop()
        b.stop()


def test_a_handshake_answer_that_cannot_be_sent_leaves_the_receiver_listening():
    """On a mesh whose routes are still forming, answering a handshake can fail with 'No route to
    host': the receive thread reports it and goes on, and the sender's retransmission gets through."""
    a, _ = endpoint("alpha")
    b, got = endpoint("beta")
    real = b.send_udp
    failures = []

    def no_route_once(frame: bytes, addr) -> None:
        if not failures:
            failures.append(addr)
            raise OSError(113, "No route to host")
        real(frame, addr)

    b.send_udp = no_route_once  # type: ignore[method-assign]
    try:
        a.send(b.address, "one", Pose(robot="x"), reliable=True, to="beta")
        wait_until(lambda: got, timeout=5)
        assert failures and b.counters.get("dropped.answer") == 1
        a.send(b.address, "two", Pose(robot="x"), reliable=False, to="beta")  # the receive thread still runs
        wait_until(lambda: len(got) == 2, timeout=5)
    finally:
        a.stop()
        b.stop()
