"""Typed decoding of a data frame's JSON straight from bytes, with msgspec: the receive path's codec.

A frame that opens in its session is one envelope or a batch `[head, [item, ...]]` (`wire.py`).
`decode_data` checks its head and items against msgspec structs that state the same limits as
`wire.EnvelopeHead` and `wire.EnvelopeItem`, and builds each body into its registered pydantic
type: a `Pose` (every robot's status, the hot path) from a msgspec struct of the same fields,
set into the model without validating it twice; any other registered type by that type's own
pydantic validator, from the body's bytes.

It takes only the frames it can type exactly as pydantic would. Anything it refuses (an untyped
body, an unknown type, a field outside its limits, and also a form pydantic's lax mode would
coerce, such as a number in a string or NaN) returns None, and the pydantic parse
(`wire.parse_typed`, then the two steps) decides and names what is wrong. So what it accepts is
a subset of what pydantic accepts, with the same values: tests/transport/test_codec.py holds the
two to that on generated input, and pydantic stays the plugins' and the blackboard's API.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec
from msgspec import UNSET, Meta, Raw, Struct, UnsetType

from erni.blackboard import Pose
from erni.blackboard.clock import wall
from erni.blackboard.text import is_name
from erni.transport.wire import TYPES, VERSION

Name = Annotated[str, Meta(min_length=1, max_length=63)]  # and `is_name` after the decode (`_named`)
NameOrEmpty = Annotated[str, Meta(max_length=63)]
Str64 = Annotated[str, Meta(max_length=64)]
Str32 = Annotated[str, Meta(max_length=32)]


class Head(Struct, kw_only=True, forbid_unknown_fields=True):
    """`wire.EnvelopeHead`: who sent a frame, to whom, from which instance, where to answer."""

    v: int = VERSION
    sender: Name
    role: Str32 = ""
    to: NameOrEmpty = ""
    inst: Str32 = ""
    reply: tuple[str, int] = ("", 0)


class Item(Struct, kw_only=True, forbid_unknown_fields=True):
    """`wire.EnvelopeItem` with its body still JSON (typed after, by its tag)."""

    seq: Annotated[int, Meta(ge=0)] = 0
    id: Str64
    kind: Str64
    type: Str64 | None = None
    body: Raw


class Envelope(Head, kw_only=True, forbid_unknown_fields=True):
    """`wire.Envelope`: a head and one item in one object."""

    seq: Annotated[int, Meta(ge=0)] = 0
    id: Str64
    kind: Str64
    type: Str64 | None = None
    body: Raw


class PoseBody(Struct, kw_only=True, forbid_unknown_fields=True):
    """`blackboard.Pose`'s fields, in its order, with its types; a field left out is UNSET, so
    the model gets pydantic's default for it and the same set of fields given."""

    uid: str | UnsetType = UNSET
    robot: Name
    x: float | UnsetType = UNSET
    y: float | UnsetType = UNSET
    theta: float | UnsetType = UNSET
    v: float | UnsetType = UNSET
    w: float | UnsetType = UNSET
    battery: float | None | UnsetType = UNSET
    stall_left: bool | UnsetType = UNSET
    stall_right: bool | UnsetType = UNSET
    bumpers: int | UnsetType = UNSET
    motors_enabled: bool | UnsetType = UNSET
    sonar: list[float] | UnsetType = UNSET
    stamp: float | UnsetType = UNSET


class PoseFull(Struct, kw_only=True, forbid_unknown_fields=True, gc=False):
    """`PoseBody` with every field given, as every ERNI sender writes a Pose (pydantic dumps all its
    fields): the common case, typed without looking for fields left out."""

    uid: str
    robot: Name
    x: float
    y: float
    theta: float
    v: float
    w: float
    battery: float | None
    stall_left: bool
    stall_right: bool
    bumpers: int
    motors_enabled: bool
    sonar: list[float]
    stamp: float


class PoseEnvelope(Head, kw_only=True, forbid_unknown_fields=True, gc=False):
    """`Envelope` of one status whose body is a Pose with every field given: the frame every robot
    sends several times a second, decoded in one pass (`decode_status`)."""

    seq: Annotated[int, Meta(ge=0)] = 0
    id: Str64
    kind: Str64
    type: Literal["Pose"]
    body: PoseFull


DecodedHead = Head | Envelope
"""A frame's head as `decode_data` gives it: a batch's head, or the one envelope of a frame."""

_frame = msgspec.json.Decoder(Envelope | tuple[Head, list[Item]])
_pose = msgspec.json.Decoder(PoseBody)
_pose_full = msgspec.json.Decoder(PoseFull)
_asdict = msgspec.structs.asdict
_POSE_FIELDS = tuple(Pose.model_fields)


def _pose_of(raw: Raw | bytes) -> Pose:
    """A Pose from its JSON: what `Pose.model_validate_json` gives (msgspec.ValidationError or
    DecodeError where this codec refuses)."""
    try:
        values = _asdict(_pose_full.decode(raw))  # every field given: the Pose of an ERNI sender
        given = set(_POSE_FIELDS)
    except msgspec.ValidationError:  # fields left out (or a value the loose decode refuses too)
        values = _asdict(_pose.decode(raw))
        given = set(values)
        for name, value in list(values.items()):
            if value is UNSET:  # pydantic's default, and not among the fields given
                if name == "uid":  # Pose's own validator names it after the robot (and counts it as given)
                    values[name] = f"pose:{values['robot']}"
                    continue
                given.discard(name)
                values[name] = wall() if name == "stamp" else \
                    Pose.model_fields[name].get_default(call_default_factory=True)
    if not is_name(values["robot"]):
        raise msgspec.ValidationError("robot: not a name")
    return Pose.trusted(values, given)  # values checked as pydantic checks them: not validated again


def _named(head: Head) -> bool:
    """Whether a head's sender and receiver keep to the name character set (checked after the decode:
    a dict lookup for the few names a team has, where a msgspec pattern would run a regex a field)."""
    return is_name(head.sender) and (head.to == "" or is_name(head.to))


_status = msgspec.json.Decoder(PoseEnvelope)


def decode_status(payload: bytes) -> tuple[PoseEnvelope, Pose] | None:
    """One envelope of a Pose with every field given, and its Pose, in one decode; None for any
    other frame (a batch, another type, fields left out, a value this codec refuses): then
    `decode_data` and, after it, the pydantic parse decide, as for every frame."""
    if payload[:1] != b"{" or b'"type":"Pose"' not in payload:
        return None
    try:
        env = _status.decode(payload)
    except msgspec.DecodeError:  # a ValidationError too
        return None
    if "Pose" not in TYPES or TYPES["Pose"] is not Pose:
        return None  # the tag taken by another type: its own validator decides
    if not (_named(env) and is_name(env.body.robot)):
        return None
    return env, Pose.trusted(_asdict(env.body), set(_POSE_FIELDS))


def body_of(type_name: str, raw: Raw) -> Any:
    """A body typed by its tag: a Pose by the struct above, any other registered type by its own
    pydantic validator (it raises what that refuses). KeyError for an unknown tag."""
    cls = TYPES[type_name]
    if cls is Pose:
        return _pose_of(raw)
    return cls.__pydantic_validator__.validate_json(bytes(raw))


def decode_data(payload: bytes) -> tuple[DecodedHead, list[tuple[Item | Envelope, Any]]] | None:
    """A data frame's head and its items with their typed bodies, or None when this codec does not
    take the frame (the pydantic parse then decides)."""
    try:
        value = _frame.decode(payload)
        if not _named(value if isinstance(value, Envelope) else value[0]):
            return None
        if isinstance(value, Envelope):
            if value.type is None:
                return None  # an untyped body: the pydantic parse reads it as plain JSON
            return value, [(value, body_of(value.type, value.body))]
        head, items = value
        if not items:
            return None
        typed: list[tuple[Item | Envelope, Any]] = []
        for item in items:
            if item.type is None:
                return None
            typed.append((item, body_of(item.type, item.body)))
        return head, typed
    except Exception:  # noqa: BLE001  # any refusal (msgspec's, a validator's, an unknown tag): pydantic decides
        return None
