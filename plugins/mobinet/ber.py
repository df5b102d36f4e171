"""SNMPv2c messages in BER (RFC 3416 PDUs, X.690 encoding) for MobiNet's client, without objects per value.

A robot agent reads its network subsystem twice a second and, while it moves, walks its
neighbour and topology tables on every read. Through pysnmp's command generator each value
becomes a pyasn1 object and each OID is resolved against a MIB view: about 7 ms of CPU per
request, half of a moving robot agent's CPU. Here a request is a few bytes built directly and
an answer is read into plain Python values (int, bytes, OID tuples) in one pass, with every
length and tag checked: anything malformed raises `BerError` naming what was wrong.

What an SNMPv2c manager needs: GetRequest, GetBulkRequest and SetRequest out, Response in; and
`decode_message`, any v1/v2c message, with which the simulator's agent reads its requests. Both
sides are checked against pysnmp and net-snmp in the tests.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

from erni.blackboard.errors import NetworkError

OID = tuple[int, ...]

# universal and SNMP application tags (RFC 2578 / RFC 3416)
INTEGER, OCTET_STRING, NULL, OBJECT_IDENTIFIER, SEQUENCE = 0x02, 0x04, 0x05, 0x06, 0x30
IP_ADDRESS, COUNTER32, GAUGE32, TIME_TICKS, OPAQUE, COUNTER64 = 0x40, 0x41, 0x42, 0x43, 0x44, 0x46
NO_SUCH_OBJECT, NO_SUCH_INSTANCE, END_OF_MIB_VIEW = 0x80, 0x81, 0x82
GET, GET_NEXT, RESPONSE, SET, GET_BULK = 0xA0, 0xA1, 0xA2, 0xA3, 0xA5
TRAP_V1, INFORM, TRAP_V2, REPORT = 0xA4, 0xA6, 0xA7, 0xA8
PDUS = frozenset({GET, GET_NEXT, RESPONSE, SET, GET_BULK, INFORM, TRAP_V2, REPORT})  # the request/response layout

EXCEPTIONS = frozenset({NO_SUCH_OBJECT, NO_SUCH_INSTANCE, END_OF_MIB_VIEW})

TYPE_NAMES = {INTEGER: "Integer", OCTET_STRING: "OctetString", NULL: "Null", OBJECT_IDENTIFIER: "ObjectIdentifier",
              IP_ADDRESS: "IpAddress", COUNTER32: "Counter32", GAUGE32: "Gauge32", TIME_TICKS: "TimeTicks",
              OPAQUE: "Opaque", COUNTER64: "Counter64", NO_SUCH_OBJECT: "NoSuchObject",
              NO_SUCH_INSTANCE: "NoSuchInstance", END_OF_MIB_VIEW: "EndOfMibView"}

ERROR_STATUS = ("noError", "tooBig", "noSuchName", "badValue", "readOnly", "genErr", "noAccess", "wrongType",
                "wrongLength", "wrongEncoding", "wrongValue", "noCreation", "inconsistentValue",
                "resourceUnavailable", "commitFailed", "undoFailed", "authorizationError", "notWritable",
                "inconsistentName")

_UNSIGNED = frozenset({COUNTER32, GAUGE32, TIME_TICKS, COUNTER64})


class BerError(NetworkError, ValueError):
    """A message that is not well-formed BER or not an SNMPv2c Response, or a value BER cannot carry."""


class Value(NamedTuple):
    """One varbind's value: its tag and its content (int, bytes, an OID tuple, or None)."""

    tag: int
    value: int | bytes | OID | None

    @property
    def type_name(self) -> str:
        """The SMI name of the value's type (`Counter32`, `NoSuchObject` ...)."""
        return TYPE_NAMES.get(self.tag, f"tag 0x{self.tag:02x}")

    def shown(self) -> str:
        """The content as text, for error messages."""
        v = self.value
        return v.decode("utf-8", "replace") if isinstance(v, bytes) else ".".join(map(str, v)) \
            if isinstance(v, tuple) else str(v)


class Response(NamedTuple):
    """A decoded Response PDU."""

    version: int
    community: bytes
    request_id: int
    error_status: int
    error_index: int
    varbinds: list[tuple[OID, Value]]


class Message(NamedTuple):
    """A decoded message of any PDU (for a GetBulkRequest the two middle fields are non-repeaters and
    max-repetitions); `values` holds each varbind's value as it came, to echo it unchanged."""

    version: int
    community: bytes
    pdu: int
    request_id: int
    error_status: int
    error_index: int
    varbinds: list[tuple[OID, Value]]
    values: list[bytes]


# --- encoding -----------------------------------------------------------------------------

def length(n: int) -> bytes:
    """A BER definite length."""
    if n < 0x80:
        return bytes((n,))
    body = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes((0x80 | len(body),)) + body


def tlv(tag: int, content: bytes) -> bytes:
    """One tag-length-value."""
    return bytes((tag,)) + length(len(content)) + content


def int_content(n: int) -> bytes:
    """The shortest two's-complement content of an INTEGER (unsigned types get a leading 0 when needed)."""
    return n.to_bytes((n if n >= 0 else ~n).bit_length() // 8 + 1, "big", signed=True)


@functools.lru_cache(maxsize=65536)
def _base128(n: int) -> bytes:
    chunk = [n & 0x7F]
    n >>= 7
    while n:
        chunk.append(0x80 | (n & 0x7F))
        n >>= 7
    return bytes(reversed(chunk))


def oid_content(oid: OID) -> bytes:
    """The content of an OBJECT IDENTIFIER (zeroDotZero, 0.0, included)."""
    if len(oid) < 2 or oid[0] > 2 or (oid[0] < 2 and oid[1] > 39) or min(oid) < 0:
        raise BerError(f"cannot encode OID {'.'.join(map(str, oid))}: not a valid object identifier")
    first = oid[0] * 40 + oid[1]
    if first < 128 and max(oid) < 128:  # the common case: one byte per arc
        return bytes((first,)) + bytes(oid[2:])
    return _base128(first) + b"".join(map(_base128, oid[2:]))


def encode_value(value: Value) -> bytes:
    """A value as a TLV (Integer32 and the unsigned types from int, strings from bytes, NULL)."""
    tag, v = value
    if tag == NULL:
        return b"\x05\x00"
    if tag == INTEGER or tag in _UNSIGNED:
        assert isinstance(v, int)
        return tlv(tag, int_content(v))
    if tag in (OCTET_STRING, IP_ADDRESS, OPAQUE):
        assert isinstance(v, bytes)
        return tlv(tag, v)
    if tag == OBJECT_IDENTIFIER:
        assert isinstance(v, tuple)
        return tlv(tag, oid_content(v))
    raise BerError(f"cannot encode a value of type {TYPE_NAMES.get(tag, hex(tag))}")


def encode_request(pdu: int, community: bytes, request_id: int, varbinds: list[tuple[OID, Value]],
                   non_repeaters: int = 0, max_repetitions: int = 0) -> bytes:
    """An SNMPv2c message carrying a GetRequest, GetBulkRequest or SetRequest PDU."""
    if pdu not in (GET, GET_NEXT, SET, GET_BULK):
        raise BerError(f"not a request PDU: 0x{pdu:02x}")
    binds = b"".join(tlv(SEQUENCE, tlv(OBJECT_IDENTIFIER, oid_content(oid)) + encode_value(v))
                     for oid, v in varbinds)
    second, third = (non_repeaters, max_repetitions) if pdu == GET_BULK else (0, 0)
    body = (tlv(INTEGER, int_content(request_id)) + tlv(INTEGER, int_content(second))
            + tlv(INTEGER, int_content(third)) + tlv(SEQUENCE, binds))
    return tlv(SEQUENCE, tlv(INTEGER, b"\x01") + tlv(OCTET_STRING, community) + tlv(pdu, body))


# --- decoding -----------------------------------------------------------------------------

def _header(data: bytes, at: int, end: int) -> tuple[int, int, int]:
    """(tag, start of content, end of content) of the TLV at `at`, checked against `end`."""
    if at + 2 > end:
        raise BerError(f"truncated at byte {at}: a tag and a length expected")
    tag, first = data[at], data[at + 1]
    at += 2
    if tag & 0x1F == 0x1F:
        raise BerError(f"multi-byte tag at byte {at - 2}: none is used by SNMP")
    if first < 0x80:
        n = first
    else:
        size = first & 0x7F
        if size == 0 or size > 4 or at + size > end:
            raise BerError(f"bad length at byte {at - 1}: {size} length bytes")
        n = int.from_bytes(data[at:at + size], "big")
        at += size
    if at + n > end:
        raise BerError(f"length {n} at byte {at} runs past the end of its container ({end - at} bytes left)")
    return tag, at, at + n


def _expect(data: bytes, at: int, end: int, tag: int, what: str) -> tuple[int, int]:
    got, start, stop = _header(data, at, end)
    if got != tag:
        raise BerError(f"{what}: expected tag 0x{tag:02x}, got 0x{got:02x} at byte {at}")
    return start, stop


def _integer(data: bytes, start: int, stop: int, signed: bool = True) -> int:
    if start == stop:
        raise BerError(f"empty integer at byte {start}")
    return int.from_bytes(data[start:stop], "big", signed=signed)


def _oid(data: bytes, start: int, stop: int) -> OID:
    if start == stop:
        raise BerError(f"empty object identifier at byte {start}")
    arcs: list[int] = []
    arc = 0
    for b in data[start:stop]:
        arc = (arc << 7) | (b & 0x7F)
        if not b & 0x80:
            arcs.append(arc)
            arc = 0
    if data[stop - 1] & 0x80:
        raise BerError(f"object identifier at byte {start} ends inside an arc")
    first = arcs[0]
    head = (0, first) if first < 40 else (1, first - 40) if first < 80 else (2, first - 80)
    return head + tuple(arcs[1:])


def _value(data: bytes, at: int, end: int) -> tuple[Value, int]:
    tag, start, stop = _header(data, at, end)
    if tag == INTEGER:
        v: int | bytes | OID | None = _integer(data, start, stop)
    elif tag in _UNSIGNED:
        v = _integer(data, start, stop, signed=False)
        if stop - start > (9 if tag == COUNTER64 else 5):
            raise BerError(f"{TYPE_NAMES[tag]} of {stop - start} bytes at byte {at}")
    elif tag in (OCTET_STRING, IP_ADDRESS, OPAQUE):
        v = bytes(data[start:stop])
    elif tag == OBJECT_IDENTIFIER:
        v = _oid(data, start, stop)
    elif tag == NULL or tag in EXCEPTIONS:
        if stop != start:
            raise BerError(f"{TYPE_NAMES[tag]} with content at byte {at}")
        v = None
    else:
        raise BerError(f"unknown value type 0x{tag:02x} at byte {at}")
    return Value(tag, v), stop


def message_version(data: bytes) -> int:
    """The version field of an SNMP message (0: v1, 1: v2c, 3: v3); BerError if there is none."""
    start, end = _expect(data, 0, len(data), SEQUENCE, "message")
    s, e = _expect(data, start, end, INTEGER, "version")
    return _integer(data, s, e)


def decode_message(data: bytes) -> Message:
    """Read a whole SNMP v1/v2c message: any PDU of the request/response layout (RFC 3416 section 3),
    or a v1 Trap, whose fields are only framed (its varbinds are left empty); BerError otherwise."""
    start, end = _expect(data, 0, len(data), SEQUENCE, "message")
    if end != len(data):
        raise BerError(f"{len(data) - end} byte(s) after the message")
    s, e = _expect(data, start, end, INTEGER, "version")
    version = _integer(data, s, e)
    s, e2 = _expect(data, e, end, OCTET_STRING, "community")
    community = bytes(data[s:e2])
    tag, at, pdu_end = _header(data, e2, end)
    if pdu_end != end:
        raise BerError(f"{end - pdu_end} byte(s) after the PDU")
    if tag == TRAP_V1:
        while at < pdu_end:
            at = _header(data, at, pdu_end)[2]
        return Message(version, community, tag, 0, 0, 0, [], [])
    if tag not in PDUS:
        raise BerError(f"unknown PDU tag 0x{tag:02x}")
    fields = []
    for what in ("request-id", "error-status", "error-index"):
        s, at = _expect(data, at, pdu_end, INTEGER, what)
        fields.append(_integer(data, s, at))
    at, binds_end = _expect(data, at, pdu_end, SEQUENCE, "varbind list")
    if binds_end != pdu_end:
        raise BerError(f"{pdu_end - binds_end} byte(s) after the varbind list")
    varbinds: list[tuple[OID, Value]] = []
    values: list[bytes] = []
    while at < binds_end:
        s, stop = _expect(data, at, binds_end, SEQUENCE, "varbind")
        o1, o2 = _expect(data, s, stop, OBJECT_IDENTIFIER, "varbind name")
        value, after = _value(data, o2, stop)
        if after != stop:
            raise BerError(f"varbind at byte {at} has {stop - after} byte(s) after its value")
        varbinds.append((_oid(data, o1, o2), value))
        values.append(bytes(data[o2:stop]))
        at = stop
    return Message(version, community, tag, fields[0], fields[1], fields[2], varbinds, values)


def decode_response(data: bytes) -> Response:
    """Read an SNMPv2c (or v1) Response message; raise BerError if it is anything else or malformed."""
    m = decode_message(data)
    if m.pdu != RESPONSE:
        raise BerError(f"not a Response PDU: tag 0x{m.pdu:02x}")
    return Response(m.version, m.community, m.request_id, m.error_status, m.error_index, m.varbinds)
