"""The frame path: what the caller's thread sends itself, and what it leaves to the sender pool.

A status goes out from the caller's thread when a session is up and nothing is queued before
it; a reliable message is written there when its connection is idle. Neither may ever block
the caller: a full socket leaves the message to the pool, which delivers it in order.
"""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

import pytest

from erni.blackboard import Pose
from erni.blackboard.errors import UsageError
from erni.blackboard.testing import wait_until
from erni.transport import Endpoint, batching
from erni.transport.identity import load_identity
from erni.transport.limits import Limits
from erni.transport.wire import BATCH_BYTES, encode_body, head_bytes, item_bytes
from tests.transport.helpers import FullSocket, endpoint, identity, session_up


def returns(call: Any) -> bool:
    """Run `call` in a thread; True when it returned (while the test still holds the peer stuck)."""
    done = threading.Event()

    def run() -> None:
        call()
        done.set()

    threading.Thread(target=run, daemon=True).start()
    return done.wait(10)


def test_a_status_goes_out_from_the_callers_thread_once_a_session_is_up():
    with session_up("fp-a", "fp-b") as (a, b, got):
        sender = threading.current_thread().name
        seen: list[str] = []
        real = a.send_udp
        a.send_udp = lambda frame, addr: (seen.append(threading.current_thread().name), real(frame, addr))[1]
        for i in range(1, 6):
            time.sleep(0.001)  # kept: statuses apart, as a robot's are, not a burst (the pace is what is tested)
            a.send(b.address, "status", Pose(robot=f"r{i}"), reliable=False, to="fp-b")
        wait_until(lambda: len(got) == 6)
        assert seen == [sender] * 5  # sent by the caller, no sender thread involved
        assert [m.body.robot for m in got] == [f"r{i}" for i in range(6)]
        assert [m.seq for m in got] == sorted(m.seq for m in got)


@pytest.fixture
def burst_window(monkeypatch):
    """A test's loop of sends is a burst on any machine: the caller's next status within 1 ms of its
    last, not `batching.COALESCE`'s 20 us, which a slow interpreter's loop building a Pose and sending it
    can miss every time (then nothing is gathered, and these tests would measure the machine)."""
    monkeypatch.setattr(batching, "COALESCE", 1e-3)


def test_a_burst_of_statuses_goes_several_to_a_datagram_and_arrives_whole(burst_window):
    """After the first status of a burst (the caller's thread sends it), the caller gathers the
    rest and seals as many as fit in BATCH_BYTES into each datagram; the sender pool sends the
    last, partly filled one."""
    with session_up("fp-burst-a", "fp-burst-b") as (a, b, got):
        b.receive_buffer(1 << 20)  # a burst on loopback: room for all of it (UDP drops what overflows)
        datagrams: list[int] = []
        real = a.send_udp
        a.send_udp = lambda frame, addr: (datagrams.append(len(frame)), real(frame, addr))[1]
        for i in range(1, 201):
            a.send(b.address, "status", Pose(robot=f"r{i}", x=float(i)), reliable=False, to="fp-burst-b")
        wait_until(lambda: len(got) == 201, message=f"{len(got)} of 201 arrived; sent {a.counters}")
        assert sorted(m.body.robot for m in got) == sorted(f"r{i}" for i in range(201))
        # four of these Poses fill a datagram under one head: about 50 without a pause; the test
        # allows for pauses of the sending thread (a partly filled datagram then goes after FLUSH_AFTER)
        assert len(datagrams) <= 150 and max(datagrams) <= BATCH_BYTES + 64, datagrams  # header and tag
        assert a.counters["sent.batched"] >= 100 and a.counters["sent.fast"] == 201
        assert b.counters["received"] == 201


def sealed_batch(a: Endpoint, b: Endpoint, items: list[bytes], head: bytes | None = None) -> bytes:
    """A data frame of a's session with b carrying `items` as one batch under `head` (a's own)."""
    session = a.session_with(b.address)
    assert session is not None
    head = head or head_bytes(a.name, "robot", b.name, a.inst, a.address)
    return session.seal(b"[" + head + b",[" + b",".join(items) + b"]]", 65536)


def test_a_batchs_bad_message_is_dropped_alone_and_a_head_naming_another_sender_drops_the_frame():
    with session_up("fp-bad-a", "fp-bad-b") as (a, b, got):
        good = item_bytes(50, "g1", "status", "Pose", encode_body(Pose(robot="ok"))[1])
        bad_body = item_bytes(51, "g2", "status", "Pose", b'{"robot": 7}')
        msgs, _ = b.accept_frame(sealed_batch(a, b, [good, bad_body, b'{"v": 2}', good]), "udp", a.address)
        assert [m.id for m in msgs] == ["g1", "g1"]  # the good ones, the bad ones counted and named
        assert [m.sender for m in msgs] == ["fp-bad-a"] * 2 and msgs[0].body.robot == "ok"
        assert b.counters["dropped.parse"] == 2
        forged = head_bytes("someone-else", "robot", "fp-bad-b", a.inst, a.address)
        assert b.accept_frame(sealed_batch(a, b, [good], head=forged), "udp", a.address) is None
        assert b.counters["dropped.auth"] == 1
        elsewhere = head_bytes("fp-bad-a", "robot", "someone-else", a.inst, a.address)
        assert b.accept_frame(sealed_batch(a, b, [good], head=elsewhere), "udp", a.address) is None
        assert b.counters["dropped.receiver"] == 1
        assert b.accept_frame(sealed_batch(a, b, []), "udp", a.address) is None  # no message: no batch
        assert b.accept_frame(sealed_batch(a, b, [good], head=b'{"v": 2}'), "udp", a.address) is None  # a bad head
        assert b.counters["dropped.parse"] == 4


def test_a_body_without_a_json_form_is_refused_to_the_caller_at_once():
    a, _ = endpoint("fp-g")
    try:
        with pytest.raises(UsageError, match="cannot send a dict"):
            a.send(("127.0.0.1", 9), "status", {"when": object()}, reliable=False)
        with pytest.raises(UsageError, match="cannot send a set"):
            a.send(("127.0.0.1", 9), "task", {object()}, reliable=True)
        assert not a._dests  # nothing queued
    finally:
        a.stop()


def test_a_status_never_blocks_on_a_full_socket_and_the_pool_sends_it_later():
    with session_up("fp-c", "fp-d") as (a, b, got):
        full = FullSocket(a._udp)
        a._udp = full  # type: ignore[assignment]  # the same socket, its send buffer full at will
        full.full.set()
        assert returns(lambda: [a.send(b.address, "status", Pose(robot=f"r{i}"), reliable=False, to="fp-d")
                                for i in range(1, 4)])
        wait_until(lambda: full.refused >= 3)  # the caller's try, then the pool's (it keeps trying)
        assert a.counters.get("sent.deferred", 0) >= 3 and len(got) == 1  # nothing sent while full
        full.full.clear()  # the buffer drains: the sender pool sends what waited, in order
        wait_until(lambda: len(got) == 4)
        assert [m.body.robot for m in got] == ["r0", "r1", "r2", "r3"]


def test_reliable_sends_never_block_on_a_peer_that_stops_reading_and_arrive_in_order():
    """The first is written by the caller's thread, but only in part (the peer's buffers are full of
    it); the pool finishes that frame and sends the rest in order once the peer reads again."""
    huge = 48 * 1024 * 1024  # a frame far larger than any socket buffer takes at once
    a, _ = endpoint("fp-e", max_frame=huge)
    b, got = endpoint("fp-f", max_frame=huge, limits=Limits(buffer_budget=huge))
    stuck = threading.Event()
    release = threading.Event()
    received: list[str] = []

    def on_message(msg: Any) -> None:
        received.append(msg.kind)
        if msg.kind == "stop-reading":
            stuck.set()
            release.wait(30)  # b's receive thread stops here: its sockets fill up

    b.on_message = on_message
    delivered: list[str] = []
    a.on_delivered = lambda addr, mid: delivered.append(mid)
    try:
        a.send(b.address, "hello", Pose(robot="r0"), reliable=True, to="fp-f", msg_id="m0")
        wait_until(lambda: delivered == ["m0"])  # session and connection up, destination idle
        a.send(b.address, "stop-reading", None, reliable=True, to="fp-f", msg_id="m1")
        assert stuck.wait(5)
        wait_until(lambda: delivered == ["m0", "m1"])  # acknowledged before the handler stopped
        ids = [f"m{i}" for i in range(2, 8)]
        bodies = [{"blob": "x" * (16 * 1024 * 1024)}] + [{"n": i} for i in range(5)]
        assert returns(lambda: [a.send(b.address, "bulk", body, reliable=True, to="fp-f", msg_id=mid)
                                for mid, body in zip(ids, bodies, strict=True)])
        assert a.counters.get("sent.partial") == 1 and delivered == ["m0", "m1"]
        release.set()
        wait_until(lambda: len(delivered) == 8, timeout=20)
        assert delivered == ["m0", "m1", *ids] and received == ["hello", "stop-reading"] + ["bulk"] * 6
        assert len(got) == 0 and a.counters.get("retries", 0) == 0  # the frame was finished, not sent again
    finally:
        release.set()
        a.stop()
        b.stop()


def test_a_receiver_may_ask_for_a_larger_udp_receive_buffer_and_is_told_what_it_got():
    """A watcher that shares its process with busy work (the team benchmark's, beside the
    simulator) asks for room for a burst; the size the kernel granted is returned."""
    from pathlib import Path

    ep, _ = endpoint("a")
    try:
        default = ep._udp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        want = 4 * default
        got = ep.receive_buffer(want)
        assert got == ep._udp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
        assert got >= min(want, rmem_max), (got, want, rmem_max)  # the kernel doubles what it grants
        assert got > default or rmem_max * 2 <= default
    finally:
        ep.stop()
    with pytest.raises(Exception, match="not started"):
        Endpoint("b", identity=load_identity(identity("b"))).receive_buffer(1 << 20)


def test_a_client_that_stops_reading_keeps_its_newest_messages_up_to_its_limit(monkeypatch):
    """A script that sent tasks and stopped reading must not hold every update of them forever:
    the inbox keeps the newest INBOX_LIMIT, counting what it dropped."""
    import erni.transport.client as client_module
    from erni.blackboard.schemas import WatchEvent
    from tests.transport.helpers import make_client

    monkeypatch.setattr(client_module, "INBOX_LIMIT", 5)
    client = make_client(("127.0.0.1", 9))
    sender, _ = endpoint("a")
    try:
        for i in range(12):
            sender.send(client.endpoint.address, "watch.event",
                        WatchEvent(agent="a", op="change", type="Pose", data={"n": i}), reliable=True)
        wait_until(lambda: client.inbox.qsize() + client.overflowed == 12, timeout=10)
        held = [client.receive(0.1) for _ in range(client.inbox.qsize())]
        assert client.overflowed == 7
        assert [m.body.data["n"] for m in held] == [7, 8, 9, 10, 11]
    finally:
        sender.stop()
        client.endpoint.stop()


def test_the_control_node_asks_for_room_for_every_robots_poses_and_a_robot_keeps_the_default():
    from pathlib import Path

    from erni.transport.endpoint import STREAM_BUFFER
    from tests.transport.helpers import free_port, make_agent

    def rcvbuf(agent) -> int:
        return agent.plugin("transport").endpoint._udp.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        default = s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    disc = free_port()
    agents = [make_agent("control", disc, echo=False, role="control"), make_agent("robot1", disc, echo=False),
              make_agent("quiet", disc, echo=False, role="control", receive_buffer=0)]
    try:
        control, robot, quiet = map(rcvbuf, agents)
        assert control >= min(STREAM_BUFFER, rmem_max) > default or rmem_max <= default
        assert robot == default and quiet == default
    finally:
        for agent in agents:
            agent.stop()


def test_a_burst_wakes_the_sender_pool_for_its_last_datagram_not_for_every_one(monkeypatch, burst_window):
    """Each datagram of a burst that the caller opens asks for a flush after FLUSH_AFTER; a sender
    thread is woken for that only when no earlier flush is already waited for. A sender thread
    woken for each datagram takes the interpreter lock from the caller every time (a burst then
    cost the caller about twice its own work). FLUSH_AFTER is made longer than the burst here, so
    that a pause of the test's thread on a loaded machine cannot let a flush come due mid-burst."""
    monkeypatch.setattr(batching, "FLUSH_AFTER", 0.5)
    with session_up("fp-wake-a", "fp-wake-b") as (a, b, got):
        b.receive_buffer(1 << 20)
        notified = [0]
        notify = a._cond.notify

        def counting(n: int = 1) -> None:
            notified[0] += 1
            notify(n)

        a._cond.notify = counting  # type: ignore[method-assign]
        for i in range(1, 301):
            a.send(b.address, "status", Pose(robot=f"r{i}", x=float(i)), reliable=False, to="fp-wake-b")
        wait_until(lambda: len(got) == 301, message=f"{len(got)} of 301 arrived; sent {a.counters}")
        batches = a.counters["sent.batched"] // 3
        assert batches >= 50  # the burst went out several to a datagram
        assert notified[0] <= batches // 4, f"{notified[0]} wake-ups of the sender pool for {batches} datagrams"


@pytest.mark.parametrize("host", ["127.0.0.1", "0.0.0.0"])
def test_stop_ends_the_thread_blocked_in_recvfrom_at_once(host: str) -> None:
    """The UDP socket is read by a thread blocked in recvfrom; stop() wakes it (the socket shut for
    reading, an empty datagram to itself) instead of leaving it to the join's timeout. The socket
    has no timeout of its own: a thread not woken would still be blocked after the 30 s join."""
    ep = Endpoint("fp-stop", insecure=True, listen=(host, 0))
    ep.start()
    threads = list(ep._threads)
    assert any(t.name.endswith("-net-udp") for t in threads)
    started = time.monotonic()
    ep.stop(timeout=30.0)
    assert not any(t.is_alive() for t in threads)
    assert time.monotonic() - started < 20.0  # joined, not given up at the timeout


def test_an_empty_datagram_is_no_frame_and_the_next_status_arrives() -> None:
    with session_up("fp-empty-a", "fp-empty-b") as (a, b, got):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
            raw.sendto(b"", b.address)
        a.send(b.address, "status", Pose(robot="r9"), reliable=False, to="fp-empty-b")
        wait_until(lambda: any(m.body.robot == "r9" for m in got))
        assert not any(k.startswith("dropped") for k in b.counters)


def test_a_burst_to_a_peer_that_began_the_session_is_gathered(burst_window):
    """The session was the peer's doing, so nothing was ever queued here for it (no destination
    record): a burst to it is still gathered, several statuses to a datagram."""
    with session_up("fp-began-b", "fp-began-a") as (b, a, got_a):
        b_addr = b.address
        a.send(b_addr, "status", Pose(robot="r0"), reliable=False, to="fp-began-b")  # a's way back is in session
        assert b_addr not in a._dests, "the test needs a destination never queued for"
        sizes: list[int] = []
        put = a.send_udp
        a.send_udp = lambda frame, addr: (sizes.append(len(frame)), put(frame, addr))[1]  # type: ignore[method-assign]
        for i in range(200):
            a.send(b_addr, "status", Pose(uid=f"p{i}", robot="r0", x=float(i)), reliable=False, to="fp-began-b")
        wait_until(lambda: not a._dests.get(b_addr) or a._dests[b_addr].batch is None)
        # gathered at all: one datagram each would be 200 (at load 19, 104 datagrams were seen; 53-58 at load 5)
        assert len(sizes) < 200 * 3 / 4, f"{len(sizes)} datagrams for 200 statuses"
