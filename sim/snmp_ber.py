"""Fast BER encoding of SNMP v1/v2c responses (and of the PDUs SNMPv3 carries) for the simulated agent.

Requests are read with MobiNet's `decode_message`; responses can be large (a 120-node
topology walk), so the agent encodes them from pre-encoded OID/value TLVs: a response is
then a concatenation of bytes. Tags follow RFC 1157 / RFC 3416; the BER
primitives are MobiNet's (`erni.plugins.mobinet.ber`), which reads these responses.
"""

from __future__ import annotations

import ipaddress

from erni.blackboard.errors import UsageError
from erni.plugins.mobinet import ber
from erni.plugins.mobinet.ber import BerError, int_content, length, oid_content, tlv

__all__ = ["length", "oid", "response", "response_pdu", "signed", "tlv", "unsigned", "value", "varbind"]

NO_SUCH_OBJECT = bytes((ber.NO_SUCH_OBJECT, 0))
NO_SUCH_INSTANCE = bytes((ber.NO_SUCH_INSTANCE, 0))
END_OF_MIB_VIEW = bytes((ber.END_OF_MIB_VIEW, 0))
NULL = bytes((ber.NULL, 0))


def signed(tag: int, value: int) -> bytes:
    """A two's-complement INTEGER-like TLV (Integer32)."""
    return tlv(tag, int_content(value))


def unsigned(tag: int, value: int) -> bytes:
    """An unsigned application TLV (Counter32, Gauge32, TimeTicks): leading 0 when needed."""
    if value < 0:
        raise UsageError(f"unsigned SNMP value must be >= 0, got {value}")
    return tlv(tag, int_content(value))


def oid(arcs: tuple[int, ...]) -> bytes:
    """An OBJECT IDENTIFIER TLV (zeroDotZero, 0.0, included)."""
    try:
        return tlv(ber.OBJECT_IDENTIFIER, oid_content(arcs))
    except BerError:
        raise UsageError(f"invalid OID {arcs!r}") from None


def value(kind: str, v: object) -> bytes:
    """A typed value TLV: kinds int, str, ip, gauge, uns, counter, ticks, oid."""
    if kind == "int":
        return signed(ber.INTEGER, int(v))  # type: ignore[call-overload]
    if kind == "str":
        return tlv(ber.OCTET_STRING, v.encode() if isinstance(v, str) else bytes(v))  # type: ignore[call-overload]  # bytes-like by contract
    if kind == "ip":
        return tlv(ber.IP_ADDRESS, ipaddress.IPv4Address(str(v)).packed)
    if kind in ("gauge", "uns"):
        return unsigned(ber.GAUGE32, int(v))  # type: ignore[call-overload]
    if kind == "counter":
        return unsigned(ber.COUNTER32, int(v))  # type: ignore[call-overload]
    if kind == "ticks":
        return unsigned(ber.TIME_TICKS, int(v))  # type: ignore[call-overload]
    if kind == "oid":
        return oid(tuple(v))  # type: ignore[arg-type]  # a tuple of arcs by contract
    raise UsageError(f"unknown SNMP value kind {kind!r}")


def response(version: int, community: bytes, request_id: int, error_status: int,
             error_index: int, varbinds: list[bytes]) -> bytes:
    """A whole GetResponse message from encoded varbinds (each `SEQUENCE {oid, value}`)."""
    return tlv(ber.SEQUENCE, signed(ber.INTEGER, version) + tlv(ber.OCTET_STRING, community)
               + response_pdu(request_id, error_status, error_index, varbinds))


def response_pdu(request_id: int, error_status: int, error_index: int, varbinds: list[bytes]) -> bytes:
    """The Response PDU alone (SNMPv3 carries it in a scoped PDU)."""
    return tlv(ber.RESPONSE, signed(ber.INTEGER, request_id) + signed(ber.INTEGER, error_status)
               + signed(ber.INTEGER, error_index) + tlv(ber.SEQUENCE, b"".join(varbinds)))


def varbind(encoded_oid: bytes, encoded_value: bytes) -> bytes:
    """One VarBind from an encoded OID and value."""
    return tlv(ber.SEQUENCE, encoded_oid + encoded_value)
