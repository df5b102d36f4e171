"""Frames: round trip, size limits, authentication, stream cutting, replay window, fuzzing."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from erni.blackboard import Pose, Task
from erni.transport.wire import (
    HEADER,
    TAG_SIZE,
    Envelope,
    FrameError,
    ReplayWindow,
    SeenIds,
    StreamDecoder,
    body_of,
    decode,
    encode,
)

KEY = b"team-key"


def envelope(seq: int = 1, body=None, **kw) -> Envelope:
    body = body if body is not None else Task(verb="BotMotion", preposition="goto", params={"x": 1, "y": 2})
    return Envelope(sender="r1", reply=("127.0.0.1", 5000), epoch=7, seq=seq, id=f"m{seq}",
                    kind="task.add", type=type(body).__name__, body=body.model_dump(mode="json"), **kw)


def test_round_trip_keeps_typed_body():
    frame = encode(envelope(), KEY)
    (length,) = struct.unpack(">I", frame[:4])
    assert length == len(frame) - 4
    env = decode(frame, KEY)
    task = body_of(env.type, env.body)
    assert isinstance(task, Task) and task.params.y == 2.0
    pose = Pose(robot="r1", x=1.5, sonar=[0.5, 1.0])
    env = decode(encode(envelope(body=pose), KEY), KEY)
    assert body_of(env.type, env.body) == pose


@pytest.mark.parametrize("mutate, reason", [
    (lambda f: f[:-1] + bytes([f[-1] ^ 1]), "auth"),            # tag flipped
    (lambda f: f[:10] + bytes([f[10] ^ 1]) + f[11:], "auth"),   # payload flipped
    (lambda f: f[:20], "size"),                                 # truncated
    (lambda f: b"\x00\x00\x00\x05" + f[4:], "size"),            # length lies
    (lambda f: b"\xff\xff\xff\xff" + f[4:], "size"),            # absurd length
    (lambda f: b"", "size"),
])
def test_damaged_frames_are_refused_with_a_reason(mutate, reason):
    with pytest.raises(FrameError) as info:
        decode(mutate(encode(envelope(), KEY)), KEY)
    assert info.value.reason == reason


def test_wrong_key_and_insecure_mode():
    frame = encode(envelope(), b"other-key")
    with pytest.raises(FrameError, match="auth: HMAC does not match"):
        decode(frame, KEY)
    assert decode(frame, None).sender == "r1"  # insecure mode does not check


def test_size_limit_on_encode_and_decode():
    big = Pose(robot="r1", sonar=[1.0] * 5000)
    with pytest.raises(FrameError, match="exceeds the limit of 1024"):
        encode(envelope(body=big), KEY, max_frame=1024)
    frame = encode(envelope(body=big), KEY)
    with pytest.raises(FrameError, match="exceeds the limit"):
        decode(frame, KEY, max_frame=1024)


def test_bad_envelopes_and_bodies_are_parse_errors():
    for payload in (b"not json", b"[1,2]", b'{"sender": ""}'):
        head = HEADER.pack(len(payload) + TAG_SIZE)
        import hashlib
        import hmac
        frame = head + payload + hmac.new(KEY, head + payload, hashlib.sha256).digest()
        with pytest.raises(FrameError) as info:
            decode(frame, KEY)
        assert info.value.reason == "parse"
    with pytest.raises(FrameError, match="unknown body type 'Rocket'"):
        body_of("Rocket", {})
    with pytest.raises(FrameError, match="invalid Task: goto: missing 'x'"):
        body_of("Task", {"verb": "BotMotion", "preposition": "goto", "params": {"y": 1}})


@given(st.lists(st.integers(1, 40), min_size=1, max_size=30), st.integers(1, 64))
def test_stream_decoder_cuts_any_chunking(sizes, chunk):
    frames = [encode(envelope(seq=i + 1, body=Pose(robot="r", sonar=[0.1] * n)), KEY)
              for i, n in enumerate(sizes)]
    stream = b"".join(frames)
    dec = StreamDecoder()
    out = []
    for i in range(0, len(stream), chunk):
        out.extend(dec.feed(stream[i:i + chunk]))
    assert out == frames


def test_stream_decoder_refuses_absurd_lengths():
    dec = StreamDecoder(max_frame=4096)
    with pytest.raises(FrameError, match="stream declares a frame of 4294967295 bytes"):
        dec.feed(b"\xff\xff\xff\xff rest")


@settings(max_examples=500)
@given(st.binary(max_size=300))
def test_random_bytes_never_raise_anything_but_frame_error(data):
    try:
        decode(data, KEY)
    except FrameError:
        pass
    try:
        StreamDecoder(1024).feed(data)
    except FrameError:
        pass


@given(st.permutations(list(range(1, 60))))
def test_replay_window_accepts_each_sequence_once_in_any_order(order):
    window = ReplayWindow(size=64)
    for seq in order:
        window.check("r1", 5, seq)
    for seq in order[:10]:
        with pytest.raises(FrameError, match="already received"):
            window.check("r1", 5, seq)


def test_replay_window_epochs():
    window = ReplayWindow(size=8)
    window.check("r1", 10, 100)
    with pytest.raises(FrameError, match="earlier boot"):
        window.check("r1", 9, 500)
    window.check("r1", 11, 1)  # a restarted robot starts again from 1
    window.check("r1", 11, 50)
    with pytest.raises(FrameError, match="older than the window"):
        window.check("r1", 11, 2)
    window.check("r2", 1, 1)  # senders are independent
    assert window.epoch_of("r1") == 11


def test_seen_ids_forget_the_oldest():
    seen = SeenIds(limit=3)
    assert all(seen.first_time("a", i) for i in "wxyz")
    assert not seen.first_time("a", "z")
    assert seen.first_time("a", "w")  # forgotten
    assert seen.first_time("b", "z")
