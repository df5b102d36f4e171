"""Fast BER encoding of SNMP v1/v2c responses for the simulated agent.

Requests are decoded with pysnmp (they are small); responses can be large (a 120-node
topology walk), so the agent encodes them itself from pre-encoded OID/value TLVs:
a response is then a concatenation of bytes. Tags follow RFC 1157 / RFC 3416.
"""

from __future__ import annotations

import functools
import ipaddress

from erni.blackboard.errors import UsageError

TAG_INTEGER, TAG_OCTETS, TAG_NULL, TAG_OID, TAG_SEQUENCE = 0x02, 0x04, 0x05, 0x06, 0x30
TAG_IPADDRESS, TAG_COUNTER32, TAG_GAUGE32, TAG_TIMETICKS = 0x40, 0x41, 0x42, 0x43
TAG_NO_SUCH_OBJECT, TAG_NO_SUCH_INSTANCE, TAG_END_OF_MIB_VIEW = 0x80, 0x81, 0x82
TAG_GET_RESPONSE = 0xA2

NO_SUCH_OBJECT = bytes((TAG_NO_SUCH_OBJECT, 0))
NO_SUCH_INSTANCE = bytes((TAG_NO_SUCH_INSTANCE, 0))
END_OF_MIB_VIEW = bytes((TAG_END_OF_MIB_VIEW, 0))
NULL = bytes((TAG_NULL, 0))


def length(n: int) -> bytes:
    """BER definite length."""
    if n < 0x80:
        return bytes((n,))
    body = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes((0x80 | len(body),)) + body


def tlv(tag: int, body: bytes) -> bytes:
    """One tag-length-value."""
    return bytes((tag,)) + length(len(body)) + body


def signed(tag: int, value: int) -> bytes:
    """A two's-complement INTEGER-like TLV (Integer32)."""
    size = max(1, (value + (value < 0)).bit_length() // 8 + 1)
    return tlv(tag, value.to_bytes(size, "big", signed=True))


def unsigned(tag: int, value: int) -> bytes:
    """An unsigned application TLV (Counter32, Gauge32, TimeTicks): leading 0 when needed."""
    if value < 0:
        raise UsageError(f"unsigned SNMP value must be >= 0, got {value}")
    size = value.bit_length() // 8 + 1
    return tlv(tag, value.to_bytes(size, "big"))


@functools.lru_cache(maxsize=65536)
def _base128(n: int) -> bytes:
    chunk = [n & 0x7F]
    n >>= 7
    while n:
        chunk.append(0x80 | (n & 0x7F))
        n >>= 7
    return bytes(reversed(chunk))


def oid(arcs: tuple[int, ...]) -> bytes:
    """An OBJECT IDENTIFIER TLV (zeroDotZero, 0.0, included)."""
    if len(arcs) < 2 or arcs[0] not in (0, 1, 2) or (arcs[0] < 2 and not 0 <= arcs[1] < 40) \
            or min(arcs) < 0:
        raise UsageError(f"invalid OID {arcs!r}")
    if max(arcs) < 128:  # the common case: one byte per arc
        return tlv(TAG_OID, bytes((arcs[0] * 40 + arcs[1],)) + bytes(arcs[2:]))
    return tlv(TAG_OID, _base128(arcs[0] * 40 + arcs[1]) + b"".join(map(_base128, arcs[2:])))


def value(kind: str, v: object) -> bytes:
    """A typed value TLV: kinds int, str, ip, gauge, uns, counter, ticks, oid."""
    if kind == "int":
        return signed(TAG_INTEGER, int(v))  # type: ignore[call-overload]
    if kind == "str":
        return tlv(TAG_OCTETS, v.encode() if isinstance(v, str) else bytes(v))  # type: ignore[call-overload]  # bytes-like by contract
    if kind == "ip":
        return tlv(TAG_IPADDRESS, ipaddress.IPv4Address(str(v)).packed)
    if kind in ("gauge", "uns"):
        return unsigned(TAG_GAUGE32, int(v))  # type: ignore[call-overload]
    if kind == "counter":
        return unsigned(TAG_COUNTER32, int(v))  # type: ignore[call-overload]
    if kind == "ticks":
        return unsigned(TAG_TIMETICKS, int(v))  # type: ignore[call-overload]
    if kind == "oid":
        return oid(tuple(v))  # type: ignore[arg-type]  # a tuple of arcs by contract
    raise UsageError(f"unknown SNMP value kind {kind!r}")


def response(version: int, community: bytes, request_id: int, error_status: int,
             error_index: int, varbinds: list[bytes]) -> bytes:
    """A whole GetResponse message from encoded varbinds (each `SEQUENCE {oid, value}`)."""
    pdu = (signed(TAG_INTEGER, request_id) + signed(TAG_INTEGER, error_status)
           + signed(TAG_INTEGER, error_index) + tlv(TAG_SEQUENCE, b"".join(varbinds)))
    return tlv(TAG_SEQUENCE, signed(TAG_INTEGER, version) + tlv(TAG_OCTETS, community)
               + tlv(TAG_GET_RESPONSE, pdu))


def varbind(encoded_oid: bytes, encoded_value: bytes) -> bytes:
    """One VarBind from an encoded OID and value."""
    return tlv(TAG_SEQUENCE, encoded_oid + encoded_value)
