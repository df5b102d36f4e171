"""The receive path's msgspec codec against the pydantic models it stands in for.

`codec.decode_data` may refuse a frame pydantic takes (pydantic then decides), but whatever it
takes pydantic must take too, giving the same values: every field, its Python type, and the
set of fields given. Generated input, valid and not, holds the two to that.
"""

from __future__ import annotations

import json
import math

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from pydantic_core import to_json

from erni.blackboard import NetInfo, Pose, Task
from erni.transport import codec
from erni.transport.wire import (
    EnvelopeHead,
    batch_payload,
)
from tests.transport.test_wire import _two_step  # the pydantic parse of a whole frame

_POSE_FIELDS = list(Pose.model_fields)


def _pydantic_pose(raw: bytes) -> Pose | None:
    try:
        return Pose.model_validate_json(raw)
    except ValidationError:
        return None


def _codec_pose(raw: bytes) -> Pose | None:
    try:
        return codec.body_of("Pose", msgspec.Raw(raw))
    except (msgspec.ValidationError, msgspec.DecodeError):
        return None


def _same_pose(got: Pose, want: Pose) -> None:
    """Field by field, with each value's type (an int given for a float field is a float in both)."""
    assert list(got.__dict__) == list(want.__dict__) == _POSE_FIELDS
    for name in _POSE_FIELDS:
        a, b = got.__dict__[name], want.__dict__[name]
        if name == "stamp" and "stamp" not in want.model_fields_set:
            assert type(a) is float and abs(a - b) < 5.0  # each side's own time.time()
            continue
        assert type(a) is type(b), name
        if isinstance(a, float) and math.isnan(a):
            assert math.isnan(b)
        else:
            assert a == b, name
        if isinstance(a, list):
            assert [type(x) for x in a] == [type(x) for x in b], name
    assert got.model_fields_set == want.model_fields_set
    assert got.model_dump_json(exclude={"stamp"}) == want.model_dump_json(exclude={"stamp"})


_finite = st.floats(allow_nan=False, allow_infinity=False)
_names = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,10}\Z")  # a robot's name (blackboard/text.py)
_any_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=6) | st.sampled_from(["1.5", "true", "0", "", "yes", "1e3", "nan"]),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=6,
)
_poses = st.builds(Pose, robot=_names, x=_finite, y=_finite, theta=_finite, v=_finite,
                   w=_finite, battery=st.none() | _finite, stall_left=st.booleans(), bumpers=st.integers(-2**70, 2**70),
                   motors_enabled=st.booleans(), sonar=st.lists(_finite, max_size=6))


@st.composite
def _pose_objects(draw: st.DrawFn) -> dict:
    """A Pose as a sender serialises it, then maybe fields left out, replaced by any JSON value, or added."""
    data = draw(_poses).model_dump(mode="json")
    for name in draw(st.lists(st.sampled_from(_POSE_FIELDS), max_size=3)):
        data.pop(name, None)
    for name in draw(st.lists(st.sampled_from(_POSE_FIELDS + ["extra", "Robot"]), max_size=2)):
        data[name] = draw(_any_json | st.sampled_from([math.nan, math.inf, -math.inf, [1.0, math.nan]]))
    return data


@settings(max_examples=600, deadline=None)
@given(_pose_objects())
def test_a_pose_the_codec_takes_is_the_pose_pydantic_gives_and_it_refuses_all_pydantic_refuses(data):
    raw = json.dumps(data).encode()
    want, got = _pydantic_pose(raw), _codec_pose(raw)
    if want is None:
        assert got is None, f"the codec took a Pose pydantic refuses: {raw!r}"
    elif got is not None:
        _same_pose(got, want)


@settings(max_examples=200, deadline=None)
@given(_poses)
def test_every_pose_as_a_sender_serialises_it_is_taken_by_the_codec(pose):
    raw = pose.__pydantic_serializer__.to_json(pose)
    got = _codec_pose(raw)
    assert got is not None, raw
    _same_pose(got, Pose.model_validate_json(raw))
    assert got == pose


@pytest.mark.parametrize("raw", [
    b'{"robot":"r1","x":NaN}', b'{"robot":"r1","x":Infinity}', b'{"robot":"r1","x":1e400}',
    b'{"robot":"r1","x":"1.5"}', b'{"robot":"r1","stall_left":1}', b'{"robot":"r1","stall_left":"true"}',
    b'{"robot":"r1","bumpers":2.0}', b'{"robot":"r1","bumpers":2.5}', b'{"robot":"r1","bumpers":' + b"9" * 30 + b"}",
    b'{"robot":"r1","robot":"r2"}', b'{"robot":"r1","x":1,"x":"a"}', b'{"robot":"\\ud800"}', b'{"robot":"r1","uid":null}',
    b'{"robot":"r1","sonar":[1,"2"]}', b'{"robot":"r1","sonar":null}', b'{"robot":"r1","battery":null}',
    b'{"robot":"r1"} ', b'{"robot":"r1"}x', b'{"robot":1}', b'{}', b'[]', b'{"robot":"r1","x":true}',
    b'{"robot":"r1","stamp":-0.0}', b'{"robot":"r1","x":-1e308,"y":5e-324}',
])
def test_edge_inputs_agree_or_are_left_to_pydantic(raw):
    want, got = _pydantic_pose(raw), _codec_pose(raw)
    if want is None:
        assert got is None
    elif got is not None:
        _same_pose(got, want)


# Whole frames: a head and items as `wire.py` frames them, some fields of any JSON value.
_bodies = st.one_of(
    _poses,
    st.builds(lambda x, y: Task(verb="BotMotion", preposition="goto", params={"x": x, "y": y}),
              st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)),
    st.builds(lambda node, msg: NetInfo(node=node, kind="neighbor list", message=msg),
              _names, st.text(max_size=12)),
)
_HEAD = {"v": 2, "sender": "r1", "role": "robot", "to": "control", "inst": "a" * 8, "reply": ["127.0.0.1", 5000]}
_ITEM = {"seq": 7, "id": "m1", "kind": "status"}


@st.composite
def _heads(draw: st.DrawFn) -> bytes:
    head = dict(_HEAD)
    if draw(st.integers(0, 2)) == 0:
        head[draw(st.sampled_from(sorted(_HEAD) + ["seq", "extra"]))] = draw(
            _any_json | st.text(min_size=30, max_size=70) | st.sampled_from(["é" * 32, "é" * 33, "x" * 64, "x" * 65]))
    return to_json(head)


@st.composite
def _items(draw: st.DrawFn) -> bytes:
    body = draw(_bodies)
    data = body.model_dump(mode="json")
    item: dict = {**_ITEM, "type": draw(st.sampled_from([type(body).__name__] * 6 + ["Rocket", None]))}
    if draw(st.integers(0, 3)) == 0:
        data[draw(st.sampled_from(sorted(data)))] = draw(_any_json)
    if draw(st.integers(0, 3)) == 0:
        item[draw(st.sampled_from(["seq", "id", "kind", "type", "v", "extra"]))] = draw(
            _any_json | st.integers(-5, 5) | st.sampled_from(["ü" * 64, "ü" * 65]))
    return to_json({**item, "body": data})


@settings(max_examples=500, deadline=None)
@given(_heads(), st.lists(_items(), min_size=1, max_size=4))
def test_a_frame_the_codec_takes_is_the_frame_pydantic_gives(head, items):
    payload = batch_payload(head, items)
    want, got = _two_step(payload), codec.decode_data(payload)
    if want is None:
        assert got is None, f"the codec took a frame pydantic refuses: {payload!r}"
        return
    if got is None:
        return  # left to pydantic
    got_head, pairs = got
    assert {f: getattr(got_head, f) for f in EnvelopeHead.model_fields} == want[0]
    assert len(pairs) == len(want[1])
    for (item, body), (want_item, want_body) in zip(pairs, want[1]):
        assert {f: getattr(item, f) for f in ("seq", "id", "kind", "type")} == want_item
        assert type(body) is type(want_body)
        if isinstance(body, Pose):
            _same_pose(body, want_body)
        else:
            assert _same(body.model_dump(), want_body.model_dump())


def _same(a: object, b: object) -> bool:
    """Equal field by field, where a NaN the frame carries equals itself and a time the frame left
    out (a result's `stamp`, filled from the clock at each decode) may differ by the decodes' gap."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(
            abs(a[k] - b[k]) < 1.0 if k in ("stamp", "created") and isinstance(a[k], float) and
            isinstance(b[k], float) and a[k] == a[k] and b[k] == b[k] else _same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and a != a:
        return b != b
    return type(a) is type(b) and a == b


@settings(max_examples=100, deadline=None)
@given(st.lists(_bodies, min_size=1, max_size=4))
def test_every_frame_an_endpoint_sends_is_taken_by_the_codec(bodies):
    head = to_json(_HEAD)
    items = [to_json({**_ITEM, "type": type(b).__name__})[:-1] + b',"body":' + b.__pydantic_serializer__.to_json(b) + b"}"
             for b in bodies]
    got = codec.decode_data(batch_payload(head, items))
    assert got is not None
    assert [body for _, body in got[1]] == bodies


def test_untyped_bodies_and_unknown_types_are_left_to_pydantic():
    assert codec.decode_data(to_json({**_HEAD, **_ITEM, "type": None, "body": "AAAA"})) is None
    assert codec.decode_data(to_json({**_HEAD, **_ITEM, "type": "Rocket", "body": {}})) is None
    assert codec.decode_data(b"[" + to_json(_HEAD) + b",[]]") is None
    assert codec.decode_data(b"not json") is None


_FLOAT_FIELDS = ["x", "y", "theta", "v", "w", "battery", "stamp"]
_NON_FINITE_TOKENS = [b"NaN", b"Infinity", b"-Infinity", b"1e400", b"-1e999"]


@st.composite
def _spoiled_pose(draw: st.DrawFn) -> bytes:
    """A Pose as a sender writes it, one float (a field, or a sonar range) a JSON token for NaN or an infinity."""
    pose = draw(_poses)
    token = draw(st.sampled_from(_NON_FINITE_TOKENS))
    data = pose.model_dump(mode="json")
    mark = "@@"
    if data["sonar"] and draw(st.booleans()):
        data["sonar"][draw(st.integers(0, len(data["sonar"]) - 1))] = mark
    else:
        data[draw(st.sampled_from(_FLOAT_FIELDS))] = mark
    return to_json(data).replace(b'"@@"', token)


@settings(max_examples=300, deadline=None)
@given(_spoiled_pose(), st.integers(0, 3))
def test_nan_and_infinities_are_refused_by_the_codec_and_by_pydantic_in_every_frame_form(raw, others):
    """A Pose body with NaN, Infinity or a number beyond a float's range: pydantic refuses it (the
    models' `allow_inf_nan=False`), and so does each fast path of the codec (msgspec reads no such
    token): alone, in a batch beside good statuses, and the one-pass status decode."""
    assert _pydantic_pose(raw) is None
    assert _codec_pose(raw) is None
    good = [to_json({**_ITEM, "type": "Pose"})[:-1] + b',"body":' + to_json(Pose(robot=f"r{i}").model_dump(mode="json"))
            + b"}" for i in range(others)]
    bad = to_json({**_ITEM, "type": "Pose"})[:-1] + b',"body":' + raw + b"}"
    payload = batch_payload(to_json(_HEAD), [*good, bad])
    assert codec.decode_data(payload) is None  # the codec takes the frame whole or leaves it to pydantic
    assert codec.decode_status(payload) is None
    want = _two_step(payload)
    assert want is None  # the pydantic parse refuses the frame (a batch: it names the bad message)


def test_the_codecs_pose_structs_have_poses_fields_in_its_order():
    """The codec's msgspec structs copy Pose's fields for speed: a field added to, dropped from or
    moved in Pose and not in them (or the other way round) fails here, not on the wire."""
    from erni.blackboard import Pose
    from erni.transport.codec import PoseBody, PoseFull

    fields = tuple(Pose.model_fields)
    assert PoseBody.__struct_fields__ == fields
    assert PoseFull.__struct_fields__ == fields
    required = tuple(name for name, f in Pose.model_fields.items() if f.is_required())
    assert tuple(f.name for f in msgspec.structs.fields(PoseBody) if f.required) == required
    assert all(f.required for f in msgspec.structs.fields(PoseFull))  # every field given, as ERNI sends
