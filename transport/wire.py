"""Frames on the wire: a length prefix, a kind byte, and a kind-specific body.

    frame    = LEN (4 bytes, big-endian, counts what follows) | KIND (1 byte) | body
    'D' data = SESSION (8) | COUNTER (8) | ChaCha20-Poly1305(payload JSON), the header as AAD;
               the payload is one envelope, or a batch of statuses `[head, [message, ...]]`
    'H' hello, 'R' reply, 'B' beacon = BODYLEN (2) | JSON | CERTLEN (2) | certificate DER | proof
    'K' hint = SESSION (8): "I do not know this session" (unauthenticated: it only starts a handshake)
    'P' plain = envelope JSON (insecure mode only: no authentication, no encryption)

The same bytes travel as one UDP datagram or on a TCP stream. The envelope names the sender,
its role, the receiver, the sender's instance (random per start, never a clock), its reply
address, a per-instance sequence number, a message id, a kind and a body of a registered
pydantic type, so any typed value travels (no "longs only"). An envelope is a head (`v`, sender,
role, receiver, instance, reply address) and one message (`seq`, `id`, `kind`, `type`, `body`) in one
object; a batch states its head once for all its messages. Sessions and handshakes are in
`session.py`.
"""

from __future__ import annotations

import functools
import json
import re
import struct
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, Union

import msgspec
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, create_model
from pydantic_core import PydanticSerializationError, from_json, to_json

from erni.blackboard import AllocationResult, NetInfo, Pose, Task
from erni.blackboard.clock import monotonic
from erni.blackboard.errors import ErniError, UsageError, shown
from erni.blackboard.messages import (  # the messages themselves (erni.blackboard.schemas adds configs)
    Beacon,
    Cancel,
    Fresh,
    PeerList,
    ResultUpdate,
    StatusRemoved,
    StatusResend,
    TaskQuery,
    TaskRescind,
    TaskUnknown,
    WatchEvent,
    WatchRequest,
)
from erni.blackboard.objects import FiniteAny, Model
from erni.blackboard.peer import Peer
from erni.blackboard.text import Name, NameOrEmpty

HEADER = struct.Struct(">I")
KIND = struct.Struct(">IB")  # length, kind
DATA_HEADER = struct.Struct(">IB8sQ")  # length, kind, session, counter
SESSION_END = 13  # a data frame's session id ends here: enough to refuse a stream early
DATA, HELLO, REPLY, BEACON, HINT, PLAIN = b"D"[0], b"H"[0], b"R"[0], b"B"[0], b"K"[0], b"P"[0]
REFUSAL = b"X"[0]  # an unsigned answer to a handshake whose certificate this agent does not trust
KINDS = {DATA: "data", HELLO: "hello", REPLY: "reply", BEACON: "beacon", HINT: "hint", PLAIN: "plain",
         REFUSAL: "refusal"}
TAG_SIZE = 16
MIN_FRAME = HEADER.size + 1 + 8  # a hint: the shortest frame of any kind
DEFAULT_MAX_FRAME = 256 * 1024
UDP_MAX_FRAME = 60_000
VERSION = 2
MAX_JSON_DEPTH = 64


class FrameError(ErniError):
    """A frame failed a size, parse, authentication, session or replay check; `reason` names which."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


TYPES: dict[str, type[BaseModel]] = {}
_typed: dict[str, TypeAdapter[Any]] = {}  # parse_typed's adapters, built on first use


def register_type(cls: type[BaseModel], name: str | None = None) -> type[BaseModel]:
    """Make a pydantic type transportable under a tag (its class name by default)."""
    TYPES[name or cls.__name__] = cls
    _typed.clear()  # the typed envelopes are built again for the new set of types
    return cls


# the blackboard's objects and messages that travel: registered with the wire itself, so that any
# endpoint (an agent's, a command-line client's) sends and reads them (the transport plugin's own,
# Received and Relayed, are registered by erni.transport.tasking)
for _cls in (Task, Pose, NetInfo, AllocationResult, Peer, Beacon, ResultUpdate, Cancel, TaskRescind, TaskQuery,
             TaskUnknown, StatusResend, StatusRemoved, Fresh, PeerList, WatchRequest, WatchEvent):
    register_type(_cls)


class EnvelopeHead(Model):
    """Who sent a frame, to whom, and where to answer: once for each message, or once for all the
    messages of a batch of statuses."""

    model_config = ConfigDict(extra="forbid")

    v: int = VERSION
    sender: Name
    role: str = Field("", max_length=32, description="the sender's role: robot, control, cli (a client) ...")
    to: NameOrEmpty = Field("", description="the receiver's name ('' only where it is not known yet)")
    inst: str = Field("", max_length=32, description="the sender's instance: random per start")
    reply: tuple[str, int] = ("", 0)


class EnvelopeItem(Model):
    """One message of a frame: its number in the sender's instance, id, kind and body."""

    model_config = ConfigDict(extra="forbid")

    seq: int = Field(0, ge=0)
    id: str = Field(max_length=64)
    kind: str = Field(max_length=64)
    type: str | None = Field(None, max_length=64)
    body: FiniteAny = None


class Envelope(EnvelopeItem, EnvelopeHead):
    """The JSON part of a frame that carries one message (inside the encryption of a data frame):
    the head's fields and the item's in one object."""


@dataclass
class Message:
    """A verified, decoded message: who sent it and its typed body.

    `epoch` is this receiver's count of the sender's instances (1 for the first one it heard,
    2 after a restart ...), so (epoch, seq) orders a sender's messages across restarts without
    any clock. `hint` marks a broadcast beacon: signed, but replayable, so only a hint.
    """

    sender: str
    role: str
    reply: tuple[str, int]
    epoch: int
    seq: int
    id: str
    kind: str
    body: Any
    received: float = field(default_factory=monotonic)
    hint: bool = False
    ack: Callable[[], None] | None = None
    """Set on a reliable message of a kind whose acknowledgement its receiver holds back
    (`Endpoint.held_kinds`): call it once what the message asks for is durable (or refused), and
    the acknowledgement goes to its sender then. None: acknowledged already, or nothing to send."""
    source: str = ""
    """Where a hint came from, as far as the wire tells: the source host of a broadcast beacon, the
    router a Zenoh liveliness token names ('' otherwise)."""


def envelope_json(env: Envelope) -> bytes:
    """Serialise an envelope (our own fields: no validation)."""
    return env.model_dump_json().encode()


def encode_body(body: Any) -> tuple[str | None, bytes]:
    """A body's type tag (None for plain JSON values) and its JSON, serialised once when it is queued.

    A `Pose` (a frozen model of plain fields, validated when made) is written by msgspec from its
    fields, 2-3 times faster than pydantic's serialiser; its JSON parses back to the same values
    (tests/transport/test_oneway_path.py).

    Raise UsageError for a body that has no JSON form (the caller learns it at once).
    """
    if type(body) is Pose:  # every robot's status: its fields are plain JSON values, and msgspec is faster
        try:
            return "Pose", _encode(body.__dict__)
        except (TypeError, ValueError):  # a value set around validation (model_construct ...): pydantic says
            pass
    try:
        if isinstance(body, BaseModel):
            return type(body).__name__, body.__pydantic_serializer__.to_json(body)
        return None, to_json(body)
    except PydanticSerializationError as err:
        raise UsageError(f"cannot send a {type(body).__name__}: {str(err).splitlines()[0][:200]}") from None


_encode = msgspec.json.Encoder().encode


def head_bytes(sender: str, role: str, to: str, inst: str, reply: tuple[str, int]) -> bytes:
    """The JSON of an envelope's head (our own fields: no validation)."""
    return to_json({"v": VERSION, "sender": sender, "role": role, "to": to, "inst": inst, "reply": reply})


def item_bytes(seq: int, msg_id: str, kind: str, type_name: str | None, body: bytes) -> bytes:
    """The JSON of one message around its body, already serialised (`encode_body`)."""
    return b'{"seq":%d,"id":%b,%b,"body":%b}' % (seq, to_json(msg_id), kind_and_type(kind, type_name), body)


@functools.lru_cache(maxsize=1024)
def kind_and_type(kind: str, type_name: str | None) -> bytes:
    """`"kind":...,"type":...` of a message: the same for every status of a type, made once."""
    return to_json({"kind": kind, "type": type_name})[1:-1]


def envelope_bytes(sender: str, role: str, to: str, inst: str, reply: tuple[str, int], seq: int, msg_id: str,
                   kind: str, type_name: str | None, body: bytes) -> bytes:
    """The JSON of an envelope around a body already serialised (`encode_body`): what `envelope_json` gives."""
    return join_envelope(head_bytes(sender, role, to, inst, reply), item_bytes(seq, msg_id, kind, type_name, body))


def join_envelope(head: bytes, item: bytes) -> bytes:
    """One envelope of a head and an item (two JSON objects made one)."""
    return head[:-1] + b"," + item[1:]


def parse_envelope(payload: bytes) -> Envelope:
    """Parse the JSON of an envelope; raise FrameError('parse', ...) naming the problem."""
    try:
        return Envelope.model_validate_json(payload)
    except ValidationError as err:
        raise _envelope_error(err) from None


def _envelope_error(err: ValidationError, what: str = "envelope") -> FrameError:
    first = err.errors()[0]
    if first["type"] in ("json_invalid", "json_type", "model_type"):
        return FrameError("parse", f"{what} is not a JSON object ({first['msg']})")
    where = ".".join(str(p) for p in first["loc"])
    return FrameError("parse", f"{what} field {where}: {first['msg']}")


BATCH_BYTES = 1400
"""The most envelope bytes one sealed datagram carries when statuses are batched: with the frame's
header and tag it stays under what one 1500-byte Ethernet or Wi-Fi frame holds after the IP and
UDP headers (1452 bytes over IPv6), so a batch is not fragmented on such a link."""


def batch_payload(head: bytes, items: list[bytes]) -> bytes:
    """What a data frame seals: one message as one envelope; several (a batch of statuses) as
    `[head, [item, item, ...]]`, the head stated once for all of them."""
    if len(items) == 1:
        return join_envelope(head, items[0])
    return b"[" + head + b",[" + b",".join(items) + b"]]"


def parse_batch(payload: bytes) -> tuple[EnvelopeHead, list[Any]]:
    """A batched data frame's head, validated, and its items' JSON values (each still to be parsed
    with `parse_item`); raise FrameError('parse') naming what is wrong when the frame is not
    `[head, [item, ...]]` or its head does not validate (no item of it can then be trusted)."""
    try:
        value = from_json(payload)
    except ValueError as err:
        raise FrameError("parse", f"batch is not JSON ({str(err)[:120]})") from None
    if not (isinstance(value, list) and len(value) == 2 and isinstance(value[1], list) and value[1]):
        raise FrameError("parse", "batch is not [head, [message, ...]] with at least one message")
    try:
        return EnvelopeHead.model_validate(value[0]), value[1]
    except ValidationError as err:
        raise _envelope_error(err, "head") from None


def parse_item(value: Any) -> EnvelopeItem:
    """Validate one message of a batch (already parsed from JSON); FrameError('parse') names the problem."""
    try:
        return EnvelopeItem.model_validate(value)
    except ValidationError as err:
        raise _envelope_error(err, "message") from None


def _typed_adapters() -> dict[str, TypeAdapter[Any]]:
    """One envelope model and one batch item model per registered type, its `body` field that type,
    chosen by the `type` tag: validating a frame through them checks the envelope and builds its
    typed body in one call from the JSON bytes, without the dict a two-step parse makes and
    validates again."""
    if not _typed:
        def typed(base: type[BaseModel]) -> Any:
            models = []
            for name, cls in TYPES.items():
                tag: Any = Literal[name]  # a tag known only here: a type form to pydantic, a value to mypy
                models.append(create_model(f"{name}{base.__name__}", __base__=base, type=(tag, ...), body=(cls, ...)))
            return Annotated[Union[tuple(models)], Field(discriminator="type")]  # noqa: UP007  # a tuple of models

        one, item = typed(Envelope), typed(EnvelopeItem)
        batch: Any = tuple[EnvelopeHead, list[item]]  # type: ignore[valid-type]  # a union built above
        _typed["one"], _typed["batch"] = TypeAdapter(one), TypeAdapter(batch)
    return _typed


def parse_typed(payload: bytes) -> tuple[EnvelopeHead, list[EnvelopeItem]] | None:
    """A data frame's head and messages (one envelope, or a batch) with their bodies validated
    into their registered types in the same step, or None when the frame is anything else: an
    untyped body, an unknown type, any field that does not validate. Then the two-step parse
    (`parse_envelope`, or `parse_batch` and `parse_item`, then `body_of`) takes it and names what is
    wrong; on the frames it accepts, this gives what that parse would give."""
    if b'"type":null' in payload:
        return None  # an untyped body (or one that looks so): the two-step parse, without a try first
    adapters = _typed_adapters()
    try:
        if payload[:1] == b"[":
            head, items = adapters["batch"].validate_json(payload)
            return (head, items) if items else None
        envelope = adapters["one"].validate_json(payload)
        return envelope, [envelope]
    except Exception:  # noqa: BLE001  # any refusal, a validator's own errors too: the two-step parse decides
        return None


def encode_plain(env: Envelope, max_frame: int = DEFAULT_MAX_FRAME) -> bytes:
    """A 'P' frame: the envelope in clear, unauthenticated (insecure mode and the mock network)."""
    payload = envelope_json(env)
    length = 1 + len(payload)
    if HEADER.size + length > max_frame:
        raise FrameError("size", f"frame of {HEADER.size + length} bytes exceeds the limit of {max_frame}")
    return KIND.pack(length, PLAIN) + payload


def check_frame(frame: bytes, max_frame: int = DEFAULT_MAX_FRAME) -> int:
    """Check a whole frame's length prefix; return its kind byte (raise FrameError('size'|'parse'))."""
    if len(frame) < MIN_FRAME:
        raise FrameError("size", f"frame of {len(frame)} bytes is shorter than the minimum of {MIN_FRAME}")
    if len(frame) > max_frame:
        raise FrameError("size", f"frame of {len(frame)} bytes exceeds the limit of {max_frame}")
    length, kind = KIND.unpack_from(frame)
    if length != len(frame) - HEADER.size:
        raise FrameError("size", f"declared length {length} but {len(frame) - HEADER.size} bytes follow")
    if kind not in KINDS:
        raise FrameError("parse", f"unknown frame kind {kind:#04x}")
    return int(kind)


def decode_plain(frame: bytes, max_frame: int = DEFAULT_MAX_FRAME) -> Envelope:
    """Check and parse a 'P' frame."""
    kind = check_frame(frame, max_frame)
    if kind != PLAIN:
        raise FrameError("auth", f"expected a plain frame, got a {KINDS[kind]} frame (is the sender secured?)")
    return parse_envelope(frame[HEADER.size + 1:])


def body_of(kind_type: str | None, body: Any) -> Any:
    """Validate a body against its registered type (raise FrameError if unknown or invalid)."""
    if kind_type is None:
        return body
    cls = TYPES.get(kind_type)
    if cls is None:
        raise FrameError("parse", f"unknown body type {shown(kind_type)}")
    try:
        parse = getattr(cls, "parse", None)  # Task.parse names the bad field
        return parse(body) if callable(parse) else cls.model_validate(body)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or kind_type
        raise FrameError("parse", f"invalid {kind_type}: {where}: {first['msg']}") from None
    except (ErniError, ValueError, TypeError, RecursionError) as err:
        raise FrameError("parse", f"invalid {kind_type}: {str(err).splitlines()[0][:200]}") from None


class StreamDecoder:
    """Cut a TCP byte stream into frames; a bad length poisons the stream (FrameError)."""

    def __init__(self, max_frame: int = DEFAULT_MAX_FRAME):
        self.max_frame = max_frame
        self._buf = bytearray()

    @property
    def buffered(self) -> int:
        """Bytes held for a frame not yet complete."""
        return len(self._buf)

    def head(self, size: int) -> bytes | None:
        """The first `size` bytes of the frame being received, once they are there."""
        return bytes(self._buf[:size]) if len(self._buf) >= size else None

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the whole frames now available."""
        self._buf += data
        frames = []
        while len(self._buf) >= HEADER.size:
            (length,) = HEADER.unpack_from(self._buf)
            if length + HEADER.size > self.max_frame or length + HEADER.size < MIN_FRAME:
                self._buf.clear()
                raise FrameError("size", f"stream declares a frame of {length} bytes "
                                 f"(limit {self.max_frame})")
            end = HEADER.size + length
            if len(self._buf) < end:
                break
            frames.append(bytes(self._buf[:end]))
            del self._buf[:end]
        return frames


class ReplayWindow:
    """Accept each counter of one session once: a sliding window over the highest counter seen."""

    def __init__(self, size: int = 4096):
        self.size = size
        self._mask = (1 << size) - 1
        self.top = 0  # the highest counter received (0: none yet): anything above it is fresh
        self._bitmap = 0  # bit i: counter top - i was received

    def fresh(self, counter: int) -> None:
        """Raise FrameError('replay', ...) if `counter` was received already or is too old to tell."""
        if counter > self.top:
            return
        offset = self.top - counter
        if offset >= self.size:
            raise FrameError("replay", f"counter {counter} is older than the window")
        if self._bitmap >> offset & 1:
            raise FrameError("replay", f"counter {counter} was already received")

    def mark(self, counter: int) -> None:
        """Record `counter` as received (after `fresh` and authentication)."""
        if counter > self.top:
            shift = counter - self.top
            self._bitmap = ((self._bitmap << shift) | 1) & self._mask if shift < self.size else 1
            self.top = counter
        else:
            self._bitmap |= 1 << (self.top - counter)

    def check(self, counter: int) -> None:
        """`fresh` then `mark`, in one call (once a frame, on the receive path)."""
        top = self.top
        if counter > top:  # the common case: the next counter, fresh
            shift = counter - top
            self._bitmap = ((self._bitmap << shift) | 1) & self._mask if shift < self.size else 1
            self.top = counter
            return
        self.fresh(counter)
        self._bitmap |= 1 << (top - counter)


class SeenIds:
    """A bounded memory of message ids, to de-duplicate retried reliable messages."""

    def __init__(self, limit: int = 20_000):
        self.limit = limit
        self._ids: OrderedDict[tuple[str, str], None] = OrderedDict()

    def first_time(self, sender: str, msg_id: str) -> bool:
        """Return True the first time (sender, id) is seen."""
        key = (sender, msg_id)
        if key in self._ids:
            self._ids.move_to_end(key)
            return False
        self._ids[key] = None
        if len(self._ids) > self.limit:
            self._ids.popitem(last=False)
        return True


_TOKENS = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]')


def json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in JSON text (strings skipped; no recursion)."""
    depth = deepest = 0
    for match in _TOKENS.finditer(text):
        token = match.group()
        if token in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif token in "]}":
            depth -= 1
    return deepest


def loads(text: str, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """`json.loads` with nesting bounded: UsageError beyond `max_depth` instead of a RecursionError.

    NaN and infinities are read (as Python does) so that the validator of the field they land
    in can name it; every number field of ERNI refuses them.
    """
    if text.count("[") + text.count("{") > max_depth and json_depth(text) > max_depth:
        raise UsageError(f"JSON nested deeper than {max_depth} levels")
    return json.loads(text)
