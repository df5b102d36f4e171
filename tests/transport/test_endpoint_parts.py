"""The endpoint is composed of parts with explicit interfaces: each sending part (fast messages,
reliable delivery, beacons, the sender pool) is a class the endpoint holds, built from the queues
they share (`outbox.SendQueues`), a wire, clocks, settings and a narrow `Protocol` for what it
needs back, never a mixin that borrows the endpoint's attributes.

The source is read with `ast` for the shape; each part is then built alone, with fakes of what it
is handed, and does its one job.
"""

from __future__ import annotations

import ast
import logging
import threading
from pathlib import Path
from typing import Any

from erni.transport.batching import FastMessages
from erni.transport.discovery import Beacons
from erni.transport.limits import Limits
from erni.transport.outbox import Batch, Dest, MessageIds, Outgoing, SenderPool, SendQueues
from erni.transport.reliable import ReliableDelivery
from erni.transport.wire import KIND, PLAIN, encode_body

TRANSPORT = Path(__file__).resolve().parents[2] / "transport"
PARTS = ("batching.py", "reliable.py", "discovery.py", "outbox.py")
ADDR = ("127.0.0.1", 9)


def _classes(module: str) -> list[ast.ClassDef]:
    tree = ast.parse((TRANSPORT / module).read_text())
    return [node for node in ast.walk(tree) if isinstance(node, ast.ClassDef)]


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def test_no_part_declares_borrowed_attributes_under_type_checking() -> None:
    borrowed = [f"{module}: {cls.name}" for module in PARTS for cls in _classes(module)
                for node in ast.walk(cls) if isinstance(node, ast.If) and _is_type_checking(node.test)]
    assert borrowed == []


def test_the_endpoint_is_no_mixin() -> None:
    (endpoint,) = [cls for cls in _classes("endpoint.py") if cls.name == "Endpoint"]
    bases = [ast.unparse(base) for base in endpoint.bases]
    assert bases in ([], ["object"]), bases


def test_the_parts_are_classes_of_their_own() -> None:
    from erni.transport.endpoint import Endpoint

    ep = Endpoint("parts", insecure=True)
    assert Endpoint.__mro__ == (Endpoint, object)
    assert isinstance(ep.fast, FastMessages) and isinstance(ep.reliable, ReliableDelivery)
    assert isinstance(ep.beacons, Beacons) and isinstance(ep.pool, SenderPool)
    # one shared state, handed to each part that queues or sends
    assert ep.fast.queues is ep.reliable.queues is ep.pool.queues is ep.queues
    assert ep._dests is ep.queues.dests and ep._cond is ep.queues.cond


# -- fakes of what the parts are handed ---------------------------------------------------------


class Clock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Counters:
    def __init__(self) -> None:
        self.counters: dict[str, int] = {}
        self.warnings: list[tuple[str, str]] = []

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def warn(self, reason: str, text: str) -> None:
        self.warnings.append((reason, text))


class Host(Counters):
    """A fake endpoint: frames are the envelope's bytes behind a plain header; reports are kept."""

    hint_wanted = None

    def __init__(self, clock: Clock) -> None:
        super().__init__()
        self.clock = clock
        self.delivered: list[str] = []
        self.undeliverable: list[str] = []

    def outgoing(self, msg_id: str, kind: str, type_name: str | None, body: Any, data: bytes, seq: int,
                 ttl: float | None, to: str | None) -> Outgoing:
        return Outgoing(msg_id, kind, type_name, body, data, seq, self.clock() + (ttl or 30.0), to or "")

    def envelope(self, out: Outgoing, to: str) -> bytes:
        return b"env:" + out.id.encode()

    def frame(self, out: Outgoing, session: Any, max_frame: int) -> bytes:
        payload = self.envelope(out, out.to)
        return KIND.pack(1 + len(payload), PLAIN) + payload

    def head(self, peer: str) -> bytes:
        return b'{"to":"%b"}' % peer.encode()

    def head_open(self, peer: str) -> bytes:
        return self.head(peer)[:-1] + b","

    def accept_frame(self, raw: bytes, channel: str, src: Any) -> None:
        return None

    def admit(self, sender: str, role: str) -> None:
        pass

    def report_delivered(self, addr: Any, msg_id: str) -> None:
        self.delivered.append(msg_id)

    def report_undeliverable(self, addr: Any, msg_id: str, kind: str, body: Any) -> None:
        self.undeliverable.append(msg_id)


class Carrier:
    """A fake wire: what it is handed, kept; reliable messages acknowledged at once."""

    name = "fake"
    batch_limit = None

    def __init__(self) -> None:
        self.frames: list[tuple[bytes, Any]] = []
        self.delivered: list[str] = []

    def sendto(self, frame: bytes, addr: Any) -> None:
        self.frames.append((frame, addr))

    def write_now(self, addr: Any, out: Outgoing) -> bool:
        return False

    def deliver(self, dest: Dest, out: Outgoing, session: Any) -> bool:
        self.delivered.append(out.id)
        return True


def out(msg_id: str, *, deadline: float = 1e9, kind: str = "status") -> Outgoing:
    type_name, data = encode_body({"n": msg_id})
    return Outgoing(msg_id, kind, type_name, {"n": msg_id}, data, 1, deadline)


# -- each part alone ------------------------------------------------------------------------------


def test_the_queues_refuse_a_full_reliable_queue_drop_the_oldest_status_and_serve_what_is_due() -> None:
    counters, pace = Counters(), Clock()
    queues = SendQueues(counters, 2, pace)
    assert queues.queue(ADDR, out("r1", kind="task"), "reliable") and queues.queue(ADDR, out("r2"), "reliable")
    assert not queues.queue(ADDR, out("r3"), "reliable")  # full: refused, for the caller to report
    assert counters.counters["dropped.queue_full"] == 1 and counters.warnings[0][0] == "queue"
    for i in range(3):
        queues.queue(ADDR, out(f"f{i}"), "fast")
    dest = queues.dests[ADDR]
    assert [o.id for o in dest.fast] == ["f1", "f2"] and counters.counters["dropped.fast_oldest"] == 1
    assert queues.take() is dest and dest.busy  # ready: taken at once
    queues.release(dest, pace.now + 5.0)  # work left, due later: scheduled, not ready
    assert not dest.ready and queues.delayed
    pace.now += 5.0
    assert queues.take() is dest  # due now on the pool's clock: taken without waiting
    queues.stop()
    assert queues.take() is None


def test_the_sender_pool_serves_a_ready_destination_on_its_own_thread() -> None:
    counters, pace = Counters(), Clock()
    queues = SendQueues(counters, 100, pace)
    served = threading.Event()
    seen: list[tuple[str, list[str]]] = []

    class Fast:
        def send_datagram(self, addr: Any, batch: Batch) -> bool:
            return True

        def send_fast(self, dest: Dest, session: Any, outs: list[Outgoing]) -> float | None:
            seen.append(("fast", [o.id for o in outs]))
            return None

    class Reliable:
        def send_reliable(self, dest: Dest, session: Any) -> float | None:
            seen.append(("reliable", [o.id for o in dest.reliable]))
            dest.reliable.clear()
            served.set()
            return None

        def expired(self, dest: Dest, o: Outgoing, now: float) -> bool:
            return False

    class Announcer:
        def send_beacon(self, dest: Dest, o: Outgoing) -> None:
            seen.append(("beacon", [o.id]))

    pool = SenderPool(queues, Carrier(), None, counters, Fast(), Reliable(), Announcer(),  # type: ignore[arg-type]
                      secure=False, clock=pace, pace=pace, handshake_timeout=1.0, retry_max=2.0,
                      log=logging.getLogger("test.parts"))
    queues.queue(ADDR, out("t1", kind="task"), "reliable")
    queues.queue(ADDR, out("s1"), "fast")
    queues.queue(ADDR, out("b1", kind="beacon"), "announce")
    threads = pool.start("parts-tx", 1)
    try:
        assert served.wait(10), f"not served: {seen}"
    finally:
        queues.stop()
        for t in threads:
            t.join(10)
    assert not any(t.is_alive() for t in threads)
    # in one turn, in the pool's order: announcements, then statuses, then reliable messages
    assert seen == [("beacon", ["b1"]), ("fast", ["s1"]), ("reliable", ["t1"])]


def test_the_sender_pool_starts_a_handshake_for_a_destination_without_a_session() -> None:
    counters, pace = Counters(), Clock()
    queues, carrier = SendQueues(counters, 100, pace), Carrier()

    class Init:
        addr, expect, started, next_try, attempts, frame = ADDR, "peer", pace.now, 0.0, 0, b"H-frame"

    class Handshakes:
        def current(self, addr: Any) -> None:
            return None

        def initiate(self, addr: Any, expect: str) -> Init:
            return Init()

        def abandon(self, init: Any) -> None:
            pass

    pool = SenderPool(queues, carrier, Handshakes(), counters, None, None, None,  # type: ignore[arg-type]
                      secure=True, clock=pace, pace=pace, handshake_timeout=1.0, retry_max=2.0,
                      log=logging.getLogger("test.parts"))
    o = out("s1")
    o.to = "peer"
    queues.queue(ADDR, o, "fast")
    dest = queues.dests[ADDR]
    when = pool.service(dest)
    assert carrier.frames == [(b"H-frame", ADDR)] and counters.counters["handshakes.sent"] == 1
    assert dest.handshake is not None and when is not None and when > pace.now
    assert [m.id for m in dest.fast] == ["s1"]  # the status waits for the session


def test_fast_messages_go_out_from_the_callers_thread_once_the_pool_runs() -> None:
    pace = Clock()
    host, carrier = Host(pace), Carrier()
    queues = SendQueues(host, 100, pace)
    fast = FastMessages(queues, MessageIds("p."), carrier, None, host, secure=False,  # type: ignore[arg-type]
                        udp_frame=1400, pace=pace)
    queued = fast.send_status(ADDR, "status", {"x": 1}, None, None, None)
    assert carrier.frames == [] and [o.id for o in queues.dests[ADDR].fast] == [queued]  # not started: queued
    queues.dests.clear()
    queues.started = True
    sent = fast.send_status(ADDR, "status", {"x": 2}, None, None, None)
    assert sent != queued and sent.startswith("p.")
    assert carrier.frames == [(host.frame(Outgoing(sent, "", None, None, b"", 0, 0.0), None, 0), ADDR)]
    assert host.counters["sent.fast"] == 1 and ADDR not in queues.dests


def test_reliable_delivery_reports_what_is_delivered_and_what_expired() -> None:
    clock = Clock()
    host, carrier = Host(clock), Carrier()
    queues = SendQueues(host, 100, clock)
    reliable = ReliableDelivery(queues, carrier, None, host, set(), secure=False,  # type: ignore[arg-type]
                                clock=clock, pace=clock, limits=Limits(), max_frame=65536, ack_timeout=1.0,
                                connect_timeout=1.0, retry_base=0.05, retry_max=2.0,
                                log=logging.getLogger("test.parts"))
    queues.queue(ADDR, out("old", deadline=clock.now - 1.0, kind="task"), "reliable")
    queues.queue(ADDR, out("new", kind="task"), "reliable")
    assert reliable.send_reliable(queues.dests[ADDR], None) is None
    assert host.undeliverable == ["old"] and host.counters["dropped.expired"] == 1
    assert carrier.delivered == host.delivered == ["new"] and host.counters["sent.reliable"] == 1
    assert not queues.dests[ADDR].reliable


def test_beacons_send_an_announcement_on_the_wire() -> None:
    clock = Clock()
    host, carrier = Host(clock), Carrier()
    beacons = Beacons(carrier, host, None, None, name="parts", inst="i", max_frame=65536)  # type: ignore[arg-type]
    beacons.send_beacon(Dest(ADDR), out("b1", kind="beacon"))
    assert carrier.frames == [(host.frame(out("b1"), None, 0), ADDR)] and host.counters["sent.announce"] == 1
