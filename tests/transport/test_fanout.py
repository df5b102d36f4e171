"""A status for several peers (`Endpoint.send_fanout`): one message, encoded once, sealed for each
peer; every peer gets it once, and a peer it cannot go to at once gets it as `send` would give it."""

from __future__ import annotations

from typing import Any

from erni.blackboard import Pose
from erni.blackboard.testing import wait_until
from erni.transport import Endpoint
from erni.transport.identity import load_identity
from tests.transport.helpers import FullSocket, identity


def endpoint(name: str) -> tuple[Endpoint, list[Any]]:
    ep = Endpoint(name, identity=load_identity(identity(name)), ack_timeout=2.0, connect_timeout=0.5)
    got: list[Any] = []
    ep.on_message = got.append
    ep.start()
    return ep, got


def test_every_peer_gets_the_status_once_as_one_message():
    a, _ = endpoint("fo-a")
    peers = [endpoint(f"fo-p{i}") for i in range(3)]
    try:
        for ep, got in peers:  # the sessions first
            a.send(ep.address, "status", Pose(robot="r0"), reliable=False, to=ep.name)
            wait_until(lambda got=got: len(got) == 1)
        sent = a.counters.get("sent.fast", 0)
        msg_id = a.send_fanout([(ep.address, ep.name) for ep, _ in peers], "status", Pose(robot="r1", x=1.5))
        for _, got in peers:
            wait_until(lambda got=got: len(got) == 2)
        for _, got in peers:
            msg = got[1]
            assert (msg.id, msg.kind, msg.sender, msg.body.robot, msg.body.x) == (msg_id, "status", "fo-a", "r1", 1.5)
        assert a.counters.get("sent.fast", 0) == sent + 3  # each sealed and sent by the caller's thread
        assert a.counters.get("sent.deferred", 0) == 0
    finally:
        a.stop()
        for ep, _ in peers:
            ep.stop()


def test_a_peer_without_a_session_gets_it_after_the_handshake():
    a, _ = endpoint("fo-b")
    up, got_up = endpoint("fo-up")
    new, got_new = endpoint("fo-new")
    try:
        a.send(up.address, "status", Pose(robot="r0"), reliable=False, to="fo-up")
        wait_until(lambda: len(got_up) == 1)
        msg_id = a.send_fanout([(up.address, "fo-up"), (new.address, "fo-new")], "status", Pose(robot="r1"))
        wait_until(lambda: len(got_up) == 2 and len(got_new) == 1)
        assert [m.id for m in (got_up[1], got_new[0])] == [msg_id, msg_id]
        assert got_new[0].body.robot == "r1"
    finally:
        for ep in (a, up, new):
            ep.stop()


def test_a_full_socket_leaves_it_to_the_sender_pool_after_what_waited_before_it():
    a, _ = endpoint("fo-c")
    peers = [endpoint(f"fo-q{i}") for i in range(2)]
    try:
        for ep, got in peers:
            a.send(ep.address, "status", Pose(robot="r0"), reliable=False, to=ep.name)
            wait_until(lambda got=got: len(got) == 1)
        full = FullSocket(a._udp)
        a._udp = full  # type: ignore[assignment]  # the same socket, its send buffer full at will
        full.full.set()
        first, _ = peers[0]
        a.send(first.address, "status", Pose(robot="r1"), reliable=False, to=first.name)  # waits in the queue
        a.send_fanout([(ep.address, ep.name) for ep, _ in peers], "status", Pose(robot="r2"))
        wait_until(lambda: full.refused >= 3)
        assert all(len(got) == 1 for _, got in peers)  # nothing left while full
        full.full.clear()
        wait_until(lambda: all(len(got) == n for (_, got), n in zip(peers, (3, 2), strict=True)))
        assert [m.body.robot for m in peers[0][1]] == ["r0", "r1", "r2"]  # in the order sent
        assert [m.body.robot for m in peers[1][1]] == ["r0", "r2"]
    finally:
        a.stop()
        for ep, _ in peers:
            ep.stop()
