"""Bounds per sender: what one authenticated peer sends never grows the control node without limit.

Real agents on loopback with their own identities; the hostile sender is an endpoint holding
robot2's (or the cli's) real key, speaking inside its own session: authenticated, and allowed to
send what it sends, only too much of it.
"""

from __future__ import annotations

import logging
import time

import pytest

from erni.blackboard import NetInfo, Pose, Task, TaskState
from erni.blackboard.schemas import ResultUpdate
from erni.blackboard.testing import wait_until
from erni.transport import Peer
from erni.transport.endpoint import Endpoint
from erni.transport.identity import load_identity
from tests.transport.helpers import free_port, identity, make_agent, make_client


def robot_key(name: str = "robot2") -> Endpoint:
    """A started endpoint holding `name`'s real identity (role robot)."""
    endpoint = Endpoint(name, identity=load_identity(identity(name)), role="robot", senders=1)
    endpoint.start()
    return endpoint


def held(control, sender: str) -> list[NetInfo]:
    return [o for o in control.query(NetInfo) if o.node == sender]


def counter(agent, name: str) -> int:
    return agent.plugin("transport").endpoint.counters.get(name, 0)


def test_status_objects_of_one_sender_are_bounded_in_number_refused_counted_and_warned_of_rate_limited(caplog):
    """robot2's key sends 600 NetInfo objects under fresh uids: the control node holds 50 (its
    bound), refuses and counts the rest, and says so in a warning or two, not 550; robot2's own
    Pose still lands."""
    caplog.set_level(logging.WARNING, logger="erni.control")
    control = make_agent("control", 0, echo=False, status_objects=50)
    robot2 = robot_key()
    try:
        address = control.plugin("transport").address
        base = counter(control, "received")
        for i in range(600):
            robot2.send(address, "status", NetInfo(uid=f"netinfo:flood-{i}", node="robot2", kind="neighbor list"),
                        reliable=False, to="control")
            if i % 50 == 49:  # the kernel's buffer keeps them all: the batch before this one is in before more go
                wait_until(lambda i=i: counter(control, "received") >= base + i + 1 - 50, timeout=30)
        # robot2's own Pose after them, on the same path: once it lands, every NetInfo before it is in
        robot2.send(address, "status", Pose(uid="pose:robot2", robot="robot2", x=1.0, y=2.0), reliable=False,
                    to="control")
        wait_until(lambda: control.blackboard.get("pose:robot2") is not None, timeout=30)
        assert counter(control, "received") >= base + 550
        assert len(held(control, "robot2")) == 50
        assert counter(control, "refused.status_bound") >= 400  # (a loaded machine's kernel may drop some)
    finally:
        robot2.stop()
        control.stop()
    warnings = [r for r in caplog.records if "over a bound" in r.getMessage()]
    assert 1 <= len(warnings) <= 3, [r.getMessage() for r in warnings]
    assert "robot2 holds 50 NetInfo objects here (status_objects = 50)" in warnings[0].getMessage()


def test_status_objects_of_one_sender_are_bounded_in_bytes_and_a_removal_makes_room():
    control = make_agent("control", 0, echo=False, status_bytes=20_000)
    robot2 = robot_key()
    try:
        address = control.plugin("transport").address
        big = "x" * 6000
        for i in range(5):
            robot2.send(address, "status", NetInfo(uid=f"netinfo:big-{i}", node="robot2", kind="topology", message=big),
                        reliable=True, to="control")
        wait_until(lambda: counter(control, "refused.status_bound") == 2, timeout=10)
        assert sorted(o.uid for o in held(control, "robot2")) == ["netinfo:big-0", "netinfo:big-1", "netinfo:big-2"]
        from erni.blackboard.schemas import StatusRemoved

        robot2.send(address, "status.remove", StatusRemoved(uid="netinfo:big-0"), reliable=True, to="control")
        robot2.send(address, "status", NetInfo(uid="netinfo:big-9", node="robot2", kind="topology", message=big),
                    reliable=True, to="control")
        wait_until(lambda: control.blackboard.get("netinfo:big-9") is not None, timeout=10)
        assert control.blackboard.get("netinfo:big-0") is None
    finally:
        robot2.stop()
        control.stop()


def test_addresses_learned_from_one_nodes_routing_table_are_bounded():
    """robot2's NetInfo names 400 routes to fresh addresses: the control node announces itself to
    at most 50 of them (the bound per source), the rest dropped and counted."""
    from erni.blackboard.tasks import Route

    control = make_agent("control", 0, echo=False, hinted_per_source=50)
    robot2 = robot_key()
    try:
        routes = [Route(destination=f"10.1.{i // 200}.{i % 200}", next_hop="10.0.0.2") for i in range(400)]
        robot2.send(control.plugin("transport").address, "status",
                    NetInfo(uid="netinfo:robot2:path_cost", node="robot2", kind="path cost", routes=routes),
                    reliable=True, to="control")
        wait_until(lambda: control.blackboard.get("netinfo:robot2:path_cost") is not None, timeout=10)
        wait_until(lambda: counter(control, "dropped.hint_bound") >= 350, timeout=10)
        assert len(control.plugin("transport").learned) == 50
    finally:
        robot2.stop()
        control.stop()


def _results(client, want: int, timeout: float = 20.0) -> dict[str, ResultUpdate]:
    got: dict[str, ResultUpdate] = {}
    deadline = time.monotonic() + timeout
    while len(got) < want and time.monotonic() < deadline:
        msg = client.receive(0.1)
        if msg is not None and msg.kind == "task.result" and isinstance(msg.body, ResultUpdate) \
                and msg.body.result.state is TaskState.FAILED:
            got[msg.body.uid] = msg.body
    return got


def test_unfinished_tasks_held_for_one_requester_are_bounded_and_the_rest_refused_to_it():
    """A cli gives the control node 30 tasks that never finish (nobody performs them there): 20
    are held (its bound), the other 10 are refused with the reason, and the cli is told."""
    control = make_agent("control", 0, echo=False, tasks_per_requester=20)
    client = make_client(tuple(control.plugin("transport").address))
    try:
        address = control.plugin("transport").address
        for i in range(30):
            client.send(address, "task.add", Task(uid=f"many-{i:02d}", verb="BotMotion", preposition="stop",
                                                  source=client.endpoint.name, destination="control"))
        refused = _results(client, 10)
        assert sorted(refused) == [f"many-{i:02d}" for i in range(20, 30)]
        assert all(f"refused by control: {client.endpoint.name} has 20 unfinished tasks here "
                   "(tasks_per_requester = 20)" == r.result.message for r in refused.values())
        assert len(control.query(Task)) == 20 and counter(control, "refused.task_bound") == 10
    finally:
        client.endpoint.stop()
        control.stop()


def test_at_a_requesters_bound_its_oldest_finished_task_leaves_early_instead():
    """Finished tasks wait for retention (600 s): a requester at its bound does not pile them up;
    its oldest finished one leaves early and every new task is taken."""
    control = make_agent("control", 0, echo=True, tasks_per_requester=20)
    client = make_client(tuple(control.plugin("transport").address))
    try:
        address = control.plugin("transport").address
        for i in range(35):
            uid = f"done-{i:02d}"
            client.send(address, "task.add", Task(uid=uid, verb="BotMotion", preposition="stop",
                                                  source=client.endpoint.name, destination="control"))
            wait_until(lambda uid=uid: (t := control.blackboard.get(uid)) is not None and t.done, timeout=10)
        held = {t.uid for t in control.query(Task)}
        assert held == {f"done-{i:02d}" for i in range(15, 35)}
        assert counter(control, "evicted.task_bound") == 15 and counter(control, "refused.task_bound") == 0
    finally:
        client.endpoint.stop()
        control.stop()


def test_a_directory_larger_than_a_frame_reaches_erni_peers_whole(capsys):
    """300 peers make a directory of about 70 kB, over a 16 kB frame: it goes in parts, and
    `erni peers` puts them together."""
    from erni.cli import main

    peers = [f"r{i:03d}@127.0.0.1:{9}" for i in range(300)]
    control = make_agent("control", 0, echo=False, max_frame=16384, peers=peers, listen=f"127.0.0.1:{free_port()}")
    try:
        host, port = control.plugin("transport").address
        assert main(["peers", "--via", f"{host}:{port}", "--identity", identity("cli", "cli")]) == 0
        out = capsys.readouterr().out
        assert sorted(line.split()[0] for line in out.splitlines()[2:]) == [f"r{i:03d}" for i in range(300)]
        assert counter(control, "dropped.too_big") == 0
    finally:
        control.stop()


zenoh = pytest.importorskip("zenoh")
TEAM = "zbounds"


@pytest.fixture(scope="module")
def router():
    from erni.transport.zenoh_wire import open_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_router([endpoint])
    yield endpoint
    session.close()


def test_liveliness_tokens_in_fresh_names_are_bounded_and_forgotten_when_undeclared(router):
    """A router without access control lets anyone declare tokens: 600 in fresh names never leave
    more than 100 peers (the bound) on the control node, counted, and none once they are undeclared;
    a real robot that shares the router comes up and stays. (A hint that leads to no session is
    forgotten after three handshake timeouts and given again later, so the fakes come and go while
    their tokens are held: their number is sampled all along.)"""
    from erni.transport.zenoh_keys import Keys, ZenohSettings
    from erni.transport.zenoh_wire import open_session

    zconf = {"team": TEAM, "mode": "client", "connect": [router]}
    control = make_agent("control", 0, echo=False, wire="zenoh", zenoh=zconf, hinted_peers=100, hinted_per_source=1000)
    robot = make_agent("robot1", 0, wire="zenoh", zenoh=zconf)
    stranger = open_session(ZenohSettings(mode="client", connect=[router]))
    keys = Keys(TEAM)
    tokens = []
    seen: list[int] = []  # the number of fake peers on the control node's board, each time looked at

    def fakes() -> int:
        seen.append(len([p for p in control.query(Peer) if p.name.startswith("fake")]))
        return seen[-1]

    try:
        wait_until(lambda: any(p.name == "robot1" and p.up for p in control.query(Peer)), timeout=20)
        for i in range(600):
            tokens.append(stranger.liveliness().declare_token(keys.token(f"fake{i:03d}", "robot", f"i{i}", "")))
            fakes()
            if i % 100 == 99:
                time.sleep(0.6)  # kept: within the rate (real time, the endpoint's token bucket) at which hints are looked at
        # until every token has come and some hint was refused for the bound, and fakes are on the board
        wait_until(lambda: fakes() > 0 and counter(control, "zenoh.tokens") >= 600
                   and counter(control, "dropped.hint_bound") > 0, timeout=30, interval=0.05,
                   message="not every token came, or none was refused for the bound, or no fake is on the board")
        assert 0 < max(seen) <= 100, f"at most {max(seen)} fake peers at once (the bound is 100)"
        gone = counter(control, "zenoh.gone")
        for token in tokens:
            token.undeclare()
        # every token's end has come (a token's end, not a forgotten hint, takes its name off the wire's
        # records) and no fake is left on the board
        wait_until(lambda: counter(control, "zenoh.gone") >= gone + 600 and fakes() == 0, timeout=20, interval=0.05,
                   message="the control node did not see every token's end, or fakes are left on its board")
        endpoint = control.plugin("transport").endpoint
        assert not [n for n in endpoint.alive() if n.startswith("fake")]
        assert not [n for n in endpoint._hints if n.startswith("fake")]
        assert any(p.name == "robot1" and p.up for p in control.query(Peer))
    finally:
        stranger.close()
        robot.stop()
        control.stop()
