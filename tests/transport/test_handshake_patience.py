"""A handshake whose answer comes later than the endpoint's `handshake_timeout` (a machine too busy
to answer in time): each handshake given up makes the next one to that destination wait longer,
so a later one is answered in time, instead of every one giving up just before its answer."""

from __future__ import annotations

import threading

from erni.blackboard import Pose
from erni.blackboard.testing import wait_until
from erni.transport.endpoint import Endpoint
from erni.transport.identity import load_identity
from erni.transport.session import PATIENCE_GROWTH, patience
from tests.transport.helpers import identity


def test_the_wait_for_an_answer_doubles_with_each_handshake_given_up_up_to_a_bound():
    assert [patience(0.5, n) for n in range(6)] == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0] == \
        [0.5 * min(PATIENCE_GROWTH, 2 ** n) for n in range(6)]


def test_answers_later_than_the_timeout_make_a_session_on_a_later_handshake():
    a = Endpoint("alpha", identity=load_identity(identity("alpha", "robot")), handshake_timeout=0.3, ttl=30.0)
    b = Endpoint("beta", identity=load_identity(identity("beta", "robot")), handshake_timeout=0.3)
    got: list[object] = []
    b.on_message = got.append
    a.start()
    b.start()
    send = b.send_datagram  # every datagram beta sends (its handshake answers) leaves 0.45 s late

    def late(frame: bytes, addr: tuple[str, int]) -> None:
        def send_now() -> None:
            try:
                send(frame, addr)
            except (OSError, AttributeError):  # beta stopped meanwhile: its socket is gone
                pass
        threading.Timer(0.45, send_now).start()

    b.send_datagram = late  # type: ignore[method-assign]
    try:
        a.send(b.address, "task", Pose(robot="x"), reliable=True, to="beta")
        wait_until(lambda: got, timeout=15, message=f"no session: {a.counters}")
        assert a.counters.get("handshakes.failed", 0) >= 1, a.counters  # the first gave up at 0.3 s
    finally:
        a.stop()
        b.stop()
