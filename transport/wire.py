"""Frames on the wire: length prefix, one typed JSON envelope, HMAC-SHA256, replay window.

A frame is `LEN (4 bytes, big-endian) | JSON envelope | TAG (32 bytes)`; LEN counts the
envelope and the tag. TAG is HMAC-SHA256 with the team key over LEN and the envelope. The
same bytes travel as one UDP datagram or on a TCP stream. The envelope carries the sender's
name, reply address, boot epoch and sequence number, a message id, a kind and a body of a
registered pydantic type, so any typed value travels (no "longs only").
"""

from __future__ import annotations

import hashlib
import hmac
import struct
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from erni.blackboard import AllocationResult, NetInfo, Pose, Task
from erni.blackboard.errors import ErniError

HEADER = struct.Struct(">I")
TAG_SIZE = 32
DEFAULT_MAX_FRAME = 256 * 1024
UDP_MAX_FRAME = 60_000
VERSION = 1


class FrameError(ErniError):
    """A frame failed a size, parse, authentication or replay check; `reason` names which."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


TYPES: dict[str, type[BaseModel]] = {}


def register_type(cls: type[BaseModel], name: str | None = None) -> type[BaseModel]:
    """Make a pydantic type transportable under a tag (its class name by default)."""
    TYPES[name or cls.__name__] = cls
    return cls


for _cls in (Task, Pose, NetInfo, AllocationResult):
    register_type(_cls)


class Envelope(BaseModel):
    """The JSON part of a frame."""

    model_config = ConfigDict(extra="forbid")

    v: int = VERSION
    sender: str = Field(min_length=1, max_length=64)
    role: str = Field("", max_length=32, description="the sender's role: robot, control, cli (a client) ...")
    reply: tuple[str, int] = ("", 0)
    epoch: int = Field(ge=0)
    seq: int = Field(ge=0)
    id: str = Field(max_length=64)
    kind: str = Field(max_length=64)
    type: str | None = None
    body: Any = None


@dataclass
class Message:
    """A verified, decoded message: who sent it and its typed body."""

    sender: str
    role: str
    reply: tuple[str, int]
    epoch: int
    seq: int
    id: str
    kind: str
    body: Any
    received: float = field(default_factory=time.monotonic)


def encode(env: Envelope, key: bytes, max_frame: int = DEFAULT_MAX_FRAME) -> bytes:
    """Serialise and sign an envelope; raise FrameError when it exceeds `max_frame`."""
    payload = env.model_dump_json().encode()
    length = len(payload) + TAG_SIZE
    if length > max_frame:
        raise FrameError("size", f"frame of {length} bytes exceeds the limit of {max_frame}")
    head = HEADER.pack(length)
    tag = hmac.new(key, head + payload, hashlib.sha256).digest()
    return head + payload + tag


def body_of(kind_type: str | None, body: Any) -> Any:
    """Validate a body against its registered type (raise FrameError if unknown or invalid)."""
    if kind_type is None:
        return body
    cls = TYPES.get(kind_type)
    if cls is None:
        raise FrameError("parse", f"unknown body type {kind_type!r}")
    try:
        parse = getattr(cls, "parse", None)  # Task.parse names the bad field
        return parse(body) if callable(parse) else cls.model_validate(body)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or kind_type
        raise FrameError("parse", f"invalid {kind_type}: {where}: {first['msg']}") from None
    except (ErniError, ValueError, TypeError) as err:
        raise FrameError("parse", f"invalid {kind_type}: {str(err).splitlines()[0]}") from None


def decode(frame: bytes, key: bytes | None, max_frame: int = DEFAULT_MAX_FRAME) -> Envelope:
    """Check and parse one whole frame; `key=None` skips authentication (insecure mode)."""
    if len(frame) < HEADER.size + TAG_SIZE:
        raise FrameError("size", f"frame of {len(frame)} bytes is shorter than the minimum")
    (length,) = HEADER.unpack_from(frame)
    if length > max_frame:
        raise FrameError("size", f"declared length {length} exceeds the limit of {max_frame}")
    if length != len(frame) - HEADER.size:
        raise FrameError("size", f"declared length {length} but {len(frame) - HEADER.size} bytes follow")
    payload, tag = frame[HEADER.size:-TAG_SIZE], frame[-TAG_SIZE:]
    if key is not None:
        expect = hmac.new(key, frame[:-TAG_SIZE], hashlib.sha256).digest()
        if not hmac.compare_digest(expect, tag):
            raise FrameError("auth", "HMAC does not match the team key")
    try:
        return Envelope.model_validate_json(payload)
    except ValidationError as err:
        first = err.errors()[0]
        if first["type"] in ("json_invalid", "json_type", "model_type"):
            raise FrameError("parse", f"envelope is not a JSON object ({first['msg']})") from None
        where = ".".join(str(p) for p in first["loc"])
        raise FrameError("parse", f"envelope field {where}: {first['msg']}") from None


class StreamDecoder:
    """Cut a TCP byte stream into frames; a bad length poisons the stream (FrameError)."""

    def __init__(self, max_frame: int = DEFAULT_MAX_FRAME):
        self.max_frame = max_frame
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the whole frames now available."""
        self._buf += data
        frames = []
        while len(self._buf) >= HEADER.size:
            (length,) = HEADER.unpack_from(self._buf)
            if length > self.max_frame or length < TAG_SIZE + 2:
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
    """Accept each (sender, epoch, seq) once: a newer epoch resets, an older one is refused."""

    def __init__(self, size: int = 4096):
        self.size = size
        self._state: dict[str, tuple[int, int, int]] = {}  # sender -> (epoch, highest seq, bitmap)

    def check(self, sender: str, epoch: int, seq: int) -> None:
        """Record the frame or raise FrameError('replay', ...)."""
        known = self._state.get(sender)
        if known is None or epoch > known[0]:
            self._state[sender] = (epoch, seq, 1)
            return
        k_epoch, top, bitmap = known
        if epoch < k_epoch:
            raise FrameError("replay", f"{sender}: frame from an earlier boot (epoch {epoch} < {k_epoch})")
        if seq > top:
            shift = seq - top
            bitmap = ((bitmap << shift) | 1) & ((1 << self.size) - 1) if shift < self.size else 1
            self._state[sender] = (epoch, seq, bitmap)
            return
        offset = top - seq
        if offset >= self.size:
            raise FrameError("replay", f"{sender}: sequence {seq} is older than the window")
        if bitmap >> offset & 1:
            raise FrameError("replay", f"{sender}: sequence {seq} was already received")
        self._state[sender] = (epoch, top, bitmap | (1 << offset))

    def epoch_of(self, sender: str) -> int | None:
        """Return the boot epoch last seen from `sender`."""
        known = self._state.get(sender)
        return known[0] if known else None


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
