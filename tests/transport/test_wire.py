"""Frames and sessions: plain round trip, the handshake, AEAD frames, damage, replay window, stream cutting."""

from __future__ import annotations

import json
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel
from pydantic_core import to_json

from erni.blackboard import NetInfo, Pose, Task, UsageError
from erni.transport import wire
from erni.transport.identity import load_identity
from erni.transport.session import (
    Hello,
    IdentityAuth,
    TeamKeyAuth,
    complete,
    cut_signed,
    initiate,
    parse_hello,
    respond,
)
from erni.transport.wire import (
    HELLO,
    SESSION_END,
    Envelope,
    EnvelopeHead,
    FrameError,
    ReplayWindow,
    SeenIds,
    StreamDecoder,
    batch_payload,
    body_of,
    check_frame,
    decode_plain,
    encode_body,
    encode_plain,
    envelope_bytes,
    head_bytes,
    item_bytes,
    json_depth,
    loads,
    parse_batch,
    parse_envelope,
    parse_item,
    parse_typed,
    register_type,
)
from tests.transport.helpers import identity


def envelope(seq: int = 1, body=None, **kw) -> Envelope:
    body = body if body is not None else Task(verb="BotMotion", preposition="goto", params={"x": 1, "y": 2})
    return Envelope(sender="r1", reply=("127.0.0.1", 5000), inst="a" * 32, seq=seq, id=f"m{seq}",
                    kind="task.add", type=type(body).__name__, body=body.model_dump(mode="json"), **kw)


def auth(name: str, role: str = "robot") -> IdentityAuth:
    return IdentityAuth(load_identity(identity(name, role)))


def handshake(a: IdentityAuth | TeamKeyAuth, b: IdentityAuth | TeamKeyAuth):
    """Run a whole handshake between `a` (initiator) and `b`; return (session of a, session of b)."""
    init = initiate(a, "1" * 32, ("127.0.0.1", 1), ("127.0.0.1", 2), b.name)
    signed = cut_signed(init.frame, 65536)
    hello = parse_hello(signed.body)
    serial = b.verify(signed, hello.sender, hello.role)
    reply, at_b = respond(b, hello, init.frame, serial, "2" * 32, ("127.0.0.1", 2))
    signed = cut_signed(reply, 65536)
    answer = parse_hello(signed.body)
    at_a = complete(a, init, answer, reply, a.verify(signed, answer.sender, answer.role))
    return at_a, at_b


def test_plain_round_trip_keeps_typed_body():
    frame = encode_plain(envelope())
    (length,) = struct.unpack(">I", frame[:4])
    assert length == len(frame) - 4
    env = decode_plain(frame)
    task = body_of(env.type, env.body)
    assert isinstance(task, Task) and task.params.y == 2.0
    pose = Pose(robot="r1", x=1.5, sonar=[0.5, 1.0])
    env = decode_plain(encode_plain(envelope(body=pose)))
    assert body_of(env.type, env.body) == pose


def test_a_handshake_gives_both_sides_the_same_session_and_frames_open_once():
    a, b = auth("alpha"), auth("beta")
    at_a, at_b = handshake(a, b)
    assert at_a.sid == at_b.sid and at_a.peer == "beta" and at_b.peer == "alpha"
    payload = envelope().model_dump_json().encode()
    frame = at_a.seal(payload, 65536)
    assert payload not in frame and b"goto" not in frame  # encrypted
    assert at_b.open(frame) == payload
    with pytest.raises(FrameError, match="replay: counter 1 was already received"):
        at_b.open(frame)
    at_b.seal(b"{}", 65536)
    back = at_b.seal(b"{}", 65536)  # counter 2: new to both windows
    assert at_a.open(back) == b"{}"
    with pytest.raises(FrameError) as info:
        at_b.open(back)  # a frame never opens in the direction it was sealed for
    assert info.value.reason == "auth"


def test_two_handshakes_between_the_same_pair_share_nothing():
    a, b = auth("alpha"), auth("beta")
    first_a, first_b = handshake(a, b)
    second_a, second_b = handshake(a, b)
    assert first_a.sid != second_a.sid
    frame = first_a.seal(b"{}", 65536)
    forged = frame[:5] + second_b.sid + frame[13:]  # even under the other session's id
    with pytest.raises(FrameError) as info:
        second_b.open(forged)
    assert info.value.reason == "auth"


@pytest.mark.parametrize("where", [0, 4, 5, 12, 13, 20, -17, -1])
def test_a_flipped_bit_anywhere_in_a_data_frame_is_refused(where):
    at_a, at_b = handshake(auth("alpha"), auth("beta"))
    frame = bytearray(at_a.seal(envelope().model_dump_json().encode(), 65536))
    frame[where] ^= 0x10
    with pytest.raises(FrameError) as info:
        check_frame(bytes(frame))
        at_b.open(bytes(frame))
    assert info.value.reason in ("auth", "size", "parse", "replay")


def test_handshake_proofs_bind_name_role_and_team():
    a, b = auth("alpha"), auth("beta")
    init = initiate(a, "1" * 32, ("127.0.0.1", 1), ("127.0.0.1", 2), "beta")
    signed = cut_signed(init.frame, 65536)
    with pytest.raises(FrameError, match="certificate of alpha .robot. but the frame claims control"):
        b.verify(signed, "control", "robot")
    with pytest.raises(FrameError, match="claims alpha .control."):
        b.verify(signed, "alpha", "control")
    tampered = bytearray(init.frame)
    tampered[10] ^= 1  # inside the signed body
    with pytest.raises(FrameError):
        b.verify(cut_signed(bytes(tampered), 65536), "alpha", "robot")
    team_a, team_b = TeamKeyAuth("alpha", "robot", b"k1"), TeamKeyAuth("beta", "robot", b"k2")
    init = initiate(team_a, "1" * 32, ("127.0.0.1", 1), ("127.0.0.1", 2), "beta")
    with pytest.raises(FrameError, match="not signed with the team key"):
        team_b.verify(cut_signed(init.frame, 65536), "alpha", "robot")
    with pytest.raises(FrameError, match="certificate not signed"):  # a team-key frame at an identity agent
        b.verify(cut_signed(init.frame, 65536), "alpha", "robot")


def test_team_key_sessions_work_too():
    at_a, at_b = handshake(TeamKeyAuth("alpha", "robot", b"team"), TeamKeyAuth("beta", "robot", b"team"))
    assert at_b.open(at_a.seal(b"{}", 1024)) == b"{}"


def test_hello_fields_are_validated():
    good = Hello(sender="a", inst="0" * 32, reply=("h", 1), eph="0" * 64, nonce="0" * 32)
    assert parse_hello(good.model_dump_json().encode()) == good
    for bad in (b"[]", b"{}", good.model_dump_json().replace('"eph":"', '"eph":"zz').encode()):
        with pytest.raises(FrameError) as info:
            parse_hello(bad)
        assert info.value.reason == "parse"


def test_signed_frames_that_do_not_hold_together_are_refused():
    frame = auth("alpha").sign(HELLO, b"{}")
    assert cut_signed(frame, 65536).body == b"{}"
    for damaged in (frame[:6], frame[:5] + b"\xff\xff" + frame[7:], frame[:4] + b"D" + frame[5:]):
        fixed = struct.pack(">I", len(damaged) - 4) + damaged[4:]
        with pytest.raises(FrameError):
            cut_signed(fixed, 65536)


def test_size_limits():
    at_a, _ = handshake(auth("alpha"), auth("beta"))
    big = Pose(robot="r1", sonar=[1.0] * 5000)
    with pytest.raises(FrameError, match="exceeds the limit of 1024"):
        at_a.seal(envelope(body=big).model_dump_json().encode(), 1024)
    with pytest.raises(FrameError, match="exceeds the limit of 1024"):
        encode_plain(envelope(body=big), max_frame=1024)
    with pytest.raises(FrameError, match="exceeds the limit"):
        check_frame(encode_plain(envelope(body=big)), 1024)


def test_bad_envelopes_and_bodies_are_parse_errors():
    for payload in (b"not json", b"[1,2]", b'{"sender": ""}'):
        with pytest.raises(FrameError) as info:
            parse_envelope(payload)
        assert info.value.reason == "parse"
    with pytest.raises(FrameError, match="unknown body type 'Rocket'"):
        body_of("Rocket", {})
    with pytest.raises(FrameError, match="invalid Task: goto: missing 'x'"):
        body_of("Task", {"verb": "BotMotion", "preposition": "goto", "params": {"y": 1}})


@given(st.lists(st.integers(1, 40), min_size=1, max_size=30), st.integers(1, 64))
def test_stream_decoder_cuts_any_chunking(sizes, chunk):
    frames = [encode_plain(envelope(seq=i + 1, body=Pose(robot="r", sonar=[0.1] * n)))
              for i, n in enumerate(sizes)]
    stream = b"".join(frames)
    dec = StreamDecoder()
    out = []
    for i in range(0, len(stream), chunk):
        out.extend(dec.feed(stream[i:i + chunk]))
    assert out == frames and dec.buffered == 0


def test_stream_decoder_refuses_absurd_lengths_and_shows_the_head():
    dec = StreamDecoder(max_frame=4096)
    with pytest.raises(FrameError, match="stream declares a frame of 4294967295 bytes"):
        dec.feed(b"\xff\xff\xff\xff rest")
    dec = StreamDecoder()
    assert dec.feed(b"\x00\x00\x01\x00D1234567") == [] and dec.head(SESSION_END) is None
    dec.feed(b"8abcd")
    assert dec.head(SESSION_END) == b"\x00\x00\x01\x00D12345678"


@settings(max_examples=300)
@given(st.binary(max_size=300))
def test_random_bytes_never_raise_anything_but_frame_error(data):
    for step in (lambda: check_frame(data), lambda: decode_plain(data), lambda: cut_signed(data, 65536),
                 lambda: StreamDecoder(1024).feed(data)):
        try:
            step()
        except FrameError:
            pass


@given(st.permutations(list(range(1, 60))))
def test_replay_window_accepts_each_counter_once_in_any_order(order):
    window = ReplayWindow(size=64)
    for counter in order:
        window.check(counter)
    for counter in order[:10]:
        with pytest.raises(FrameError, match="already received"):
            window.check(counter)


def test_replay_window_refuses_what_it_can_no_longer_tell():
    window = ReplayWindow(size=8)
    window.check(100)
    with pytest.raises(FrameError, match="older than the window"):
        window.check(50)
    window.check(95)  # inside the window, new
    window.fresh(101)  # fresh does not record
    window.check(101)


def test_seen_ids_forget_the_oldest():
    seen = SeenIds(limit=3)
    assert all(seen.first_time("a", i) for i in "wxyz")
    assert not seen.first_time("a", "z")
    assert seen.first_time("a", "w")  # forgotten
    assert seen.first_time("b", "z")


def test_json_nesting_is_bounded_without_recursion():
    assert json_depth('{"a": [1, {"b": "[[[["}]}') == 3
    assert loads('{"x": [1, 2]}') == {"x": [1, 2]}
    deep = "[" * 100_000 + "]" * 100_000
    with pytest.raises(UsageError, match="nested deeper than 64 levels"):
        loads(deep)
    assert loads("[" * 64 + "]" * 64) is not None


def test_frames_name_their_receiver_inside_the_encryption():
    at_a, at_b = handshake(auth("alpha"), auth("beta"))
    env = envelope()
    env = env.model_copy(update={"to": "beta"})
    opened = parse_envelope(at_b.open(at_a.seal(env.model_dump_json().encode(), 65536)))
    assert opened.to == "beta"  # (the endpoint refuses a `to` that is not its own name: test_security.py)


@given(st.lists(st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,11}\Z"), min_size=1, max_size=6))
def test_a_batch_states_its_head_once_and_parses_back_to_each_message(robots):
    head = head_bytes("r1", "robot", "control", "a" * 32, ("127.0.0.1", 5000))
    bodies = [Pose(robot=r) for r in robots]
    items = [item_bytes(i + 1, f"m{i + 1}", "status", "Pose", encode_body(b)[1]) for i, b in enumerate(bodies)]
    payload = batch_payload(head, items)
    if len(items) == 1:  # one message goes as one envelope
        assert payload == envelope_bytes("r1", "robot", "control", "a" * 32, ("127.0.0.1", 5000), 1, "m1",
                                         "status", "Pose", encode_body(bodies[0])[1])
        env = parse_envelope(payload)
        assert (env.sender, env.to, env.seq, body_of(env.type, env.body)) == ("r1", "control", 1, bodies[0])
        return
    assert payload.count(b'"sender"') == 1  # the head once, not once a message
    parsed, values = parse_batch(payload)
    assert (parsed.sender, parsed.role, parsed.to, parsed.reply) == ("r1", "robot", "control", ("127.0.0.1", 5000))
    messages = [parse_item(v) for v in values]
    assert [(m.seq, m.id, body_of(m.type, m.body)) for m in messages] == \
        [(i + 1, f"m{i + 1}", b) for i, b in enumerate(bodies)]


@pytest.mark.parametrize("payload, why", [
    (b"[", "batch is not JSON"), (b"[]", r"not \[head, \[message"), (b'[{"sender": "a"}, []]', "at least one"),
    (b'[{"sender": "a"}, [1], 3]', r"not \[head"), (b'[{"v": 2}, [1]]', "head field sender: Field required"),
    (b'[{"sender": "a", "seq": 1}, [1]]', "head field seq: Extra inputs"), (b'[{"sender": "a"}, [1, {}]]', None)])
def test_a_bad_batch_is_refused_with_what_is_wrong(payload, why):
    if why is None:  # messages that do not validate: each is refused on its own
        _, values = parse_batch(payload)
        for value, problem in zip(values, ("message is not a JSON object", "message field id: Field required")):
            with pytest.raises(FrameError, match=problem):
                parse_item(value)
    else:
        with pytest.raises(FrameError, match=why):
            parse_batch(payload)


# Bodies as a sender would serialise them, some with one field replaced by any JSON value (valid or not).
_finite = st.floats(-1e6, 1e6, allow_nan=False)
_names = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,7}\Z")  # a robot's or an agent's name (blackboard/text.py)
_json_values = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12), _finite, st.text(max_size=8),
                         st.lists(_finite, max_size=3))
_bodies = st.one_of(
    st.builds(Pose, robot=_names, x=_finite, y=_finite, theta=_finite, v=_finite,
              battery=st.none() | _finite, bumpers=st.integers(0, 255), sonar=st.lists(_finite, max_size=8)),
    st.builds(lambda x, y, speed: Task(verb="BotMotion", preposition="goto",
                                       params={"x": x, "y": y, "speed": speed}), _finite, _finite,
              st.floats(0.01, 2.0)),
    st.builds(lambda node, msg: NetInfo(node=node, kind="neighbor list", message=msg),
              _names, st.text(max_size=12)),
)


@st.composite
def _item_json(draw: st.DrawFn) -> bytes:
    body = draw(_bodies)
    data = body.model_dump(mode="json")
    if draw(st.integers(0, 3)) == 0:  # one field replaced: maybe still valid (an int for a float), maybe not
        data[draw(st.sampled_from(sorted(data)))] = draw(_json_values)
    item = {"seq": draw(st.integers(0, 10**9)), "id": "m1", "kind": "status",
            "type": draw(st.sampled_from([type(body).__name__] * 5 + ["Rocket"]))}
    return to_json({**item, "body": data})


_heads = st.sampled_from([to_json({"v": 2, "sender": "r1", "role": "robot", "to": "control", "inst": "a" * 8,
                                    "reply": ["127.0.0.1", 5000]})] * 3
                          + [b'{"v":2,"sender":""}', b'{"sender":"r1","seq":3}', b'{"sender":"r1","reply":[1]}'])


def _two_step(payload: bytes) -> tuple[dict, list[tuple[dict, object]]] | None:
    """What the two-step parse gives for a whole frame, or None when it refuses any part of it."""
    fields = set(EnvelopeHead.model_fields)
    try:
        if payload[:1] == b"[":
            head, values = parse_batch(payload)
            items = [parse_item(v) for v in values]
        else:
            head = parse_envelope(payload)
            items = [head]
        return head.model_dump(include=fields), [(m.model_dump(exclude=fields | {"body"}), body_of(m.type, m.body))
                                                 for m in items]
    except FrameError:
        return None


@settings(max_examples=300, deadline=None)
@given(_heads, st.lists(_item_json(), min_size=1, max_size=4))
def test_the_one_step_parse_gives_what_the_two_steps_give_and_takes_every_frame_they_take(head, items):
    payload = batch_payload(head, items)
    expected = _two_step(payload)
    typed = parse_typed(payload)
    if expected is None:
        assert typed is None  # a refused part is left to the two steps, which name it
        return
    assert typed is not None, "a frame the two steps take must not fall back to them"
    fields = set(EnvelopeHead.model_fields)
    got_head, got_items = typed
    assert (got_head.model_dump(include=fields), [(m.model_dump(exclude=fields | {"body"}), m.body)
                                                  for m in got_items]) == expected


def test_the_one_step_parse_leaves_untyped_bodies_to_the_two_steps_and_learns_new_types(monkeypatch):
    monkeypatch.setattr(wire, "TYPES", dict(wire.TYPES))  # Sighting stays registered in this test only
    monkeypatch.setattr(wire, "_typed", {})
    plain = to_json({"v": 2, "sender": "r1", "id": "m1", "kind": "crl", "type": None, "body": "AAAA"})
    assert parse_typed(plain) is None and parse_envelope(plain).body == "AAAA"

    class Sighting(BaseModel):
        what: str

    sighting = to_json({"v": 2, "sender": "r1", "id": "m2", "kind": "status", "type": "Sighting",
                        "body": {"what": "door"}})
    assert parse_typed(sighting) is None  # not registered yet: unknown to both parses
    register_type(Sighting)
    typed = parse_typed(sighting)
    assert typed is not None and typed[1][0].body == Sighting(what="door")


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**63), st.text(max_size=64), st.text(max_size=64), st.none() | st.text(max_size=64))
def test_a_message_built_around_its_body_is_the_json_of_its_fields(seq, msg_id, kind, type_name):
    body = Pose(robot="r1", x=1.5)
    got = item_bytes(seq, msg_id, kind, type_name, encode_body(body)[1])
    assert json.loads(got) == {"seq": seq, "id": msg_id, "kind": kind, "type": type_name,
                               "body": json.loads(body.model_dump_json())}
