"""The one-way status path, written out for speed: what it must still do exactly as the general path.

A status's body is written by msgspec (`wire.encode_body`) and must parse back to the values
pydantic's JSON gives; the UDP receive thread's `Endpoint.receive_datagram` opens, decodes and
delivers a data frame of a confirmed session in one call, and must deliver, refuse and count
every frame as `accept_frame` (the general path every other frame takes) does.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from erni.blackboard import Pose
from erni.blackboard.testing import wait_until
from erni.transport import Endpoint, batching, codec, outbox
from erni.transport.wire import (
    DATA_HEADER,
    EnvelopeHead,
    batch_payload,
    encode_body,
    head_bytes,
    item_bytes,
    join_envelope,
)
from tests.transport.helpers import SkipClock, session_up
from tests.transport.test_codec import _heads, _items, _same_pose
from tests.transport.test_wire import _two_step

_floats = st.floats(allow_nan=False, allow_infinity=False) | st.floats(-1e308, 1e308) | st.integers(-2**53, 2**53).map(float)
_poses = st.builds(  # a Pose holds finite numbers and a robot's name only (tests/core/test_finite_numbers.py, test_text.py)
    Pose, robot=st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,19}\Z"), x=_floats, y=_floats, theta=_floats, v=_floats, w=_floats,
    battery=st.none() | _floats, stall_left=st.booleans(), stall_right=st.booleans(),
    bumpers=st.integers(-2**63, 2**63), motors_enabled=st.booleans(), sonar=st.lists(_floats, max_size=16),
    stamp=_floats)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    if isinstance(a, dict) and isinstance(b, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


@settings(max_examples=300, deadline=None)
@given(_poses)
def test_a_pose_body_is_the_json_pydantic_writes_value_for_value(pose):
    type_name, data = encode_body(pose)
    assert type_name == "Pose"
    assert _same(json.loads(data), json.loads(pose.model_dump_json())), data


@contextmanager
def pair(a_name: str, b_name: str, **a_kw: Any) -> Iterator[tuple[Endpoint, Endpoint, list]]:
    """Two endpoints in a confirmed session (a's first status has reached b, and is forgotten)."""
    with session_up(a_name, b_name, **a_kw) as (a, b, got):
        got.clear()
        yield a, b, got


def _frames(a: Endpoint, b: Endpoint) -> list[tuple[str, bytes]]:
    """Data frames of a's session with b, sealed in order: good, damaged, replayed, misaddressed ..."""
    session = a.session_with(b.address)
    assert session is not None
    head = a.head(session.peer)

    def seal(item: bytes, to_head: bytes = head) -> bytes:
        return session.seal(join_envelope(to_head, item), 65536)

    def item(i: int, body: bytes = b"", type_name: str | None = "Pose") -> bytes:
        return item_bytes(1000 + i, f"m{i}", "status", type_name, body or encode_body(Pose(robot=f"r{i}", x=i, stamp=1.0))[1])

    good = seal(item(1))
    tampered = bytearray(seal(item(2)))
    tampered[-1] ^= 1
    elsewhere = head_bytes(a.name, a.role, "someone-else", a.inst, a.address)
    forged = head_bytes("mallory", a.role, b.name, a.inst, a.address)
    unknown = bytearray(seal(item(9)))
    unknown[5:13] = b"\x00" * 8
    cut = seal(item(10))
    long = bytearray(seal(item(11)))
    long[:4] = (len(long) - 3).to_bytes(4, "big")  # declares one byte more than follows
    return [
        ("good", good),
        ("replayed", good),
        ("tampered", bytes(tampered)),
        ("untyped", seal(item(3, b'"just text"', None))),
        ("bad body", seal(item(4, b'{"robot": 7}'))),
        ("pose with fields left out", seal(item(5, b'{"robot": "r5", "x": 5.0, "stamp": 2.0}'))),
        ("another receiver", seal(item(6), elsewhere)),
        ("another sender", seal(item(7), forged)),
        ("a batch", session.seal(b"[" + head + b",[" + item(8) + b"," + item(12, b'{"robot": 7}') + b"]]", 65536)),
        ("unknown session", bytes(unknown)),
        ("cut short", cut[:DATA_HEADER.size + 3]),
        ("wrong length", bytes(long)),
        ("a second good one", seal(item(13))),
    ]


def _outcome(ep: Endpoint, got: list, before: dict[str, int]) -> tuple[list[tuple], dict[str, int]]:
    delivered = [(m.sender, m.role, m.reply, m.epoch, m.seq, m.id, m.kind, m.body) for m in got]
    counted = {k: v - before.get(k, 0) for k, v in ep.counters.items() if v != before.get(k, 0)}
    return delivered, counted


def test_the_datagram_path_delivers_refuses_and_counts_each_frame_as_the_general_path_does():
    """Each frame through `receive_datagram` at one receiver and through `accept_frame` (and
    delivery) at another, in sessions with the same sender: the same messages, field by field,
    and the same counters moved, frame by frame."""
    with pair("ow-a", "ow-b") as (a, b, got_b), pair("ow-a2", "ow-c") as (a2, c, got_c):
        frames_b, frames_c = _frames(a, b), _frames(a2, c)
        assert [label for label, _ in frames_b] == [label for label, _ in frames_c]
        for (label, raw_b), (_, raw_c) in zip(frames_b, frames_c):
            got_b.clear()
            got_c.clear()
            before_b, before_c = dict(b.counters), dict(c.counters)
            b.receive_datagram(raw_b, a.address)
            accepted = c.accept_frame(raw_c, "udp", a2.address)
            for msg in accepted[0] if accepted is not None else ():
                c.deliver(msg)
            delivered_b, counted_b = _outcome(b, got_b, before_b)
            delivered_c, counted_c = _outcome(c, got_c, before_c)
            assert counted_b == counted_c, label
            assert len(delivered_b) == len(delivered_c), label
            for mb, mc in zip(delivered_b, delivered_c):
                assert (mb[0], mb[2], mc[0], mc[2]) == ("ow-a", a.address, "ow-a2", a2.address), label
                assert mb[1] == mc[1] and mb[3:7] == mc[3:7], label  # role, epoch, seq, id, kind
                assert type(mb[7]) is type(mc[7]) and mb[7] == mc[7], label
                assert getattr(mb[7], "model_fields_set", None) == getattr(mc[7], "model_fields_set", None), label
        assert b.counters.get("dropped.replay") == 1 and b.counters.get("dropped.auth", 0) >= 2


def test_a_status_on_its_own_arrives_through_the_datagram_path_with_its_fields():
    with pair("ow-d", "ow-e") as (a, b, got):
        pose = Pose(robot="r1", x=1.5, y=-2.0, theta=0.25, battery=12.5, sonar=[0.5, 1.0], bumpers=3)
        a.send(b.address, "status", pose, reliable=False, msg_id="one", to="ow-e")
        wait_until(lambda: len(got) == 1)
        msg = got[0]
        assert (msg.sender, msg.role, msg.id, msg.kind) == ("ow-d", "robot", "one", "status")
        want = Pose.model_validate_json(pose.model_dump_json())  # what pydantic makes of the JSON sent
        assert msg.body == want and msg.body.model_fields_set == want.model_fields_set
        assert a.counters["sent.fast"] == 2 and b.counters["received"] == 2


def test_a_status_for_another_agent_than_the_one_in_session_is_not_sealed_by_the_caller():
    """The caller's one-piece send checks the intended peer: a status meant for an agent that is
    not the one in session at that address goes to the sender pool, which refuses it."""
    with pair("ow-f", "ow-g") as (a, b, got):
        sealed: list[bytes] = []
        real = a.send_udp
        a.send_udp = lambda frame, addr: (sealed.append(frame), real(frame, addr))[1]  # type: ignore[method-assign]
        a.send(b.address, "status", Pose(robot="r1"), reliable=False, to="someone-else")
        wait_until(lambda: a.counters.get("dropped.wrong_peer", 0) == 1)
        a.send(b.address, "status", Pose(robot="r2"), reliable=False, to="ow-g")
        wait_until(lambda: len(got) == 1)
        assert [m.body.robot for m in got] == ["r2"] and len(sealed) == 1


def test_a_status_too_big_for_a_datagram_is_dropped_at_once_and_not_queued():
    with pair("ow-h", "ow-i") as (a, b, got):
        a.send(b.address, "status", Pose(robot="r1", sonar=[0.5] * 20_000), reliable=False, to="ow-i")
        assert a.counters.get("dropped.too_big") == 1
        dest = a._dests.get(b.address)
        assert dest is None or not dest.fast  # nothing queued for the pool
        assert a.counters.get("sent.deferred", 0) == 0
        a.send(b.address, "status", Pose(robot="r2"), reliable=False, to="ow-i")
        wait_until(lambda: len(got) == 1)
        assert got[0].body.robot == "r2"


def test_a_status_the_inbound_filter_refuses_is_dropped_on_the_datagram_path():
    """Authorization holds on the one-pass path: a frame from a sender the filter refuses is
    dropped and counted, and nothing reaches on_message; once allowed, the next one arrives."""
    with pair("ow-j", "ow-k") as (a, b, got):
        allowed = [False]
        b.inbound_filter = lambda sender, role: allowed[0]
        frames = _frames(a, b)
        good, later = frames[0][1], frames[-1][1]
        b.receive_datagram(good, a.address)
        assert got == [] and b.counters.get("dropped.unreachable") == 1
        allowed[0] = True
        b.receive_datagram(later, a.address)
        assert [m.id for m in got] == ["m13"]


@settings(max_examples=500, deadline=None)
@given(_heads(), _items())
def test_a_status_the_one_pass_decode_takes_is_the_frame_pydantic_gives(head, item):
    """`codec.decode_status` takes only one envelope of a Pose with every field given; what it
    takes is what the pydantic parse gives, field by field, and it takes nothing pydantic refuses."""
    payload = batch_payload(head, [item])
    want, got = _two_step(payload), codec.decode_status(payload)
    if want is None:
        assert got is None, f"took a frame pydantic refuses: {payload!r}"
        return
    if got is None:
        return  # left to the general decode
    env, pose = got
    assert {f: getattr(env, f) for f in EnvelopeHead.model_fields} == want[0]
    ((want_item, want_body),) = want[1]
    assert {f: getattr(env, f) for f in ("seq", "id", "kind", "type")} == want_item
    _same_pose(pose, want_body)
    assert pose.model_fields_set == want_body.model_fields_set


def test_every_status_an_endpoint_sends_is_taken_by_the_one_pass_decode():
    pose = Pose(robot="r1", x=1.5, battery=None, sonar=[0.5, 2.0], bumpers=-3)
    payload = join_envelope(head_bytes("r1", "robot", "control", "a" * 32, ("127.0.0.1", 5000)),
                            item_bytes(7, "m1", "status", *encode_body(pose)))
    got = codec.decode_status(payload)
    assert got is not None and got[1] == pose and got[0].to == "control"


_EDGES: list[Any] = [None, True, 0, -1, 1.5, "", "x" * 32, "x" * 33, "é" * 64, "é" * 65, [], ["h", 1], ["h", "1"], {}]


def test_the_one_pass_decode_agrees_with_pydantic_on_every_edge_of_every_envelope_field():
    """Each envelope field (and an extra one) set to each edge value: taken only where pydantic
    takes it, with the same value."""
    pose = json.loads(encode_body(Pose(robot="r1", x=1.5))[1])
    base = {"v": 2, "sender": "r1", "role": "robot", "to": "control", "inst": "a" * 32,
            "reply": ["127.0.0.1", 5000], "seq": 7, "id": "m1", "kind": "status", "type": "Pose", "body": pose}
    taken = 0
    for field in [*base, "extra"]:
        for value in _EDGES:
            payload = json.dumps({**base, field: value}, separators=(",", ":")).encode()  # as ERNI writes
            want, got = _two_step(payload), codec.decode_status(payload)
            if want is None or got is None:
                assert want is not None or got is None, f"{field}={value!r}: taken, but pydantic refuses it"
                continue
            taken += 1
            assert {f: getattr(got[0], f) for f in EnvelopeHead.model_fields} == want[0], (field, value)
            assert {f: getattr(got[0], f) for f in ("seq", "id", "kind", "type")} == want[1][0][0], (field, value)
    assert taken >= 10


def test_a_caller_that_waits_for_each_status_is_not_taken_for_a_burst(monkeypatch):
    """A caller whose statuses follow each other within COALESCE but that waits for each one's
    delivery (a ping-pong in one process) sends its first follow-up into a batch that leaves with
    one status; from then on the caller's thread sends each status at once, none held back."""
    monkeypatch.setattr(batching, "COALESCE", 10.0)  # every follow-up counts as quick
    monkeypatch.setattr(outbox, "SOLO_FOR", 10.0)  # and the test's own waits do not outlast the solo time
    with pair("ow-l", "ow-m") as (a, b, got):
        caller = threading.current_thread().name
        seen: list[str] = []
        real = a.send_udp
        a.send_udp = lambda frame, addr: (seen.append(threading.current_thread().name), real(frame, addr))[1]  # type: ignore[method-assign]
        for i in range(1, 6):
            a.send(b.address, "status", Pose(robot=f"r{i}"), reliable=False, to="ow-m")
            wait_until(lambda n=i: len(got) == n)  # the caller waits for each one's delivery
        assert seen[0] != caller  # the first follow-up: gathered, and left to the sender pool
        assert seen[1:] == [caller] * 4, seen
        assert [m.body.robot for m in got] == [f"r{i}" for i in range(1, 6)]


def test_statuses_are_gathered_again_once_the_solo_time_is_over(monkeypatch):
    monkeypatch.setattr(batching, "COALESCE", 10.0)
    monkeypatch.setattr(outbox, "SOLO_FOR", 0.05)
    pace = SkipClock()  # a's threads' own time: the test skips past its solo time
    with pair("ow-n", "ow-o", pace=pace) as (a, b, got):
        for i in range(1, 3):  # a ping-pong: the second goes out alone from a batch, gathering stops
            a.send(b.address, "status", Pose(robot=f"p{i}"), reliable=False, to="ow-o")
            wait_until(lambda n=i: len(got) == n)
        assert a._dests[b.address].solo_until > 0
        pace.skip(0.1)  # past the solo time (SOLO_FOR 0.05 s here)
        assert a.pace() >= a._dests[b.address].solo_until
        for i in range(40):  # a burst after the solo time: several to a datagram again
            a.send(b.address, "status", Pose(robot=f"b{i}"), reliable=False, to="ow-o")
        wait_until(lambda: len(got) == 42)
        assert a.counters.get("sent.batched", 0) >= 20
