"""MobiNet's SNMPv2c messages against pysnmp's and pyasn1's reading and writing of the same PDUs.

Requests built by `ber` are decoded by pysnmp's v2c message specification; Responses built by
pysnmp are decoded by `ber`; damaged messages only ever raise BerError.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyasn1.codec.ber import decoder, encoder
from pyasn1.type import univ
from pysnmp.proto import api, rfc1902, rfc1905
from pysnmp.proto.api import v2c

from erni.plugins.mobinet import ber
from erni.plugins.mobinet.ber import BerError, Value
from tests.reliability.test_fuzz import EXAMPLES

oids = st.tuples(st.sampled_from([0, 1, 2]), st.integers(0, 39)).flatmap(
    lambda head: st.lists(st.integers(0, 2**32 - 1), min_size=0, max_size=12).map(lambda rest: head + tuple(rest)))

values = st.one_of(
    st.integers(-(2**31), 2**31 - 1).map(lambda v: (Value(ber.INTEGER, v), rfc1902.Integer32(v))),
    st.binary(max_size=300).map(lambda v: (Value(ber.OCTET_STRING, v), rfc1902.OctetString(v))),
    st.integers(0, 2**32 - 1).map(lambda v: (Value(ber.COUNTER32, v), rfc1902.Counter32(v))),
    st.integers(0, 2**32 - 1).map(lambda v: (Value(ber.GAUGE32, v), rfc1902.Gauge32(v))),
    st.integers(0, 2**32 - 1).map(lambda v: (Value(ber.TIME_TICKS, v), rfc1902.TimeTicks(v))),
    st.integers(0, 2**64 - 1).map(lambda v: (Value(ber.COUNTER64, v), rfc1902.Counter64(v))),
    st.binary(min_size=4, max_size=4).map(lambda v: (Value(ber.IP_ADDRESS, v), rfc1902.IpAddress(v))),
    oids.map(lambda v: (Value(ber.OBJECT_IDENTIFIER, v), rfc1902.ObjectName(v))),
    st.just((Value(ber.NO_SUCH_OBJECT, None), rfc1905.noSuchObject)),
    st.just((Value(ber.NO_SUCH_INSTANCE, None), rfc1905.noSuchInstance)),
    st.just((Value(ber.END_OF_MIB_VIEW, None), rfc1905.endOfMibView)),
)


def pysnmp_response(request_id: int, status: int, index: int, binds: list, community: bytes = b"public") -> bytes:
    pdu = v2c.ResponsePDU()
    v2c.apiPDU.set_defaults(pdu)
    v2c.apiPDU.set_request_id(pdu, request_id)
    v2c.apiPDU.set_error_status(pdu, status)
    v2c.apiPDU.set_error_index(pdu, index)
    v2c.apiPDU.set_varbinds(pdu, binds)
    msg = v2c.Message()
    v2c.apiMessage.set_defaults(msg)
    v2c.apiMessage.set_community(msg, community)
    v2c.apiMessage.set_pdu(msg, pdu)
    return encoder.encode(msg)


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.sampled_from([ber.GET, ber.GET_BULK, ber.SET]), st.integers(1, 2**31 - 1),
       st.lists(st.tuples(oids, values), max_size=10), st.integers(0, 500), st.binary(min_size=1, max_size=32))
def test_pysnmp_reads_our_requests(pdu, request_id, binds, reps, community):
    varbinds = [(oid, v[0] if pdu == ber.SET else Value(ber.NULL, None)) for oid, v in binds
                if pdu != ber.SET or v[0].tag not in ber.EXCEPTIONS]
    wire = ber.encode_request(pdu, community, request_id, varbinds, 0, reps)
    msg, rest = decoder.decode(wire, asn1Spec=v2c.Message())
    assert rest == b""
    assert int(msg["version"]) == api.SNMP_VERSION_2C
    assert bytes(msg["community"]) == community
    got = v2c.apiMessage.get_pdu(msg)
    kind = {ber.GET: v2c.GetRequestPDU, ber.GET_BULK: v2c.GetBulkRequestPDU, ber.SET: v2c.SetRequestPDU}[pdu]
    assert got.tagSet == kind.tagSet
    if pdu == ber.GET_BULK:
        assert int(v2c.apiBulkPDU.get_request_id(got)) == request_id
        assert int(v2c.apiBulkPDU.get_max_repetitions(got)) == reps
        theirs = v2c.apiBulkPDU.get_varbinds(got)
    else:
        assert int(v2c.apiPDU.get_request_id(got)) == request_id
        theirs = v2c.apiPDU.get_varbinds(got)
    assert [tuple(o) for o, _ in theirs] == [o for o, _ in varbinds]
    for (_, ours), (_, their) in zip(varbinds, theirs):
        if ours.tag == ber.NULL:
            assert their.tagSet == rfc1902.Null.tagSet
        elif isinstance(ours.value, (int, tuple)):
            assert (int(their) if isinstance(ours.value, int) else tuple(their)) == ours.value


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 18), st.integers(0, 10), st.lists(st.tuples(oids, values), max_size=12))
def test_we_read_pysnmps_responses(request_id, status, index, binds):
    wire = pysnmp_response(request_id, status, index, [(o, v[1]) for o, v in binds])
    got = ber.decode_response(wire)
    assert (got.version, got.community, got.request_id, got.error_status, got.error_index) == \
        (1, b"public", request_id, status, index)
    assert got.varbinds == [(o, v[0]) for o, v in binds]


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.lists(st.tuples(oids, values), min_size=1, max_size=6), st.data())
def test_damaged_responses_raise_only_ber_errors(binds, data):
    wire = bytearray(pysnmp_response(7, 0, 0, [(o, v[1]) for o, v in binds]))
    how = data.draw(st.sampled_from(["truncate", "flip", "append"]))
    if how == "truncate":
        wire = wire[:data.draw(st.integers(0, len(wire) - 1))]
    elif how == "flip":
        at = data.draw(st.integers(0, len(wire) - 1))
        wire[at] ^= data.draw(st.integers(1, 255))
    else:
        wire += data.draw(st.binary(min_size=1, max_size=8))
    try:
        ber.decode_response(bytes(wire))
    except BerError:
        pass


def test_a_request_is_not_a_response_and_says_so():
    wire = ber.encode_request(ber.GET, b"public", 5, [((1, 3, 6, 1, 2, 1, 1, 5, 0), Value(ber.NULL, None))])
    with pytest.raises(BerError, match="not a Response PDU: tag 0xa0"):
        ber.decode_response(wire)
    with pytest.raises(BerError, match="cannot encode OID 1.40"):
        ber.encode_request(ber.GET, b"public", 5, [((1, 40), Value(ber.NULL, None))])


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.integers(-(2**63), 2**63 - 1), oids)
def test_integers_are_minimal_and_read_by_pyasn1_and_oids_are_encoded_as_pyasn1_does(n, oid):
    ours = ber.tlv(ber.INTEGER, ber.int_content(n))
    value, rest = decoder.decode(ours, asn1Spec=univ.Integer())
    assert rest == b"" and int(value) == n
    content = ours[2:]
    if len(content) > 1:  # X.690 8.3.2: the first nine bits are neither all ones nor all zeros
        assert not (content[0] == 0xFF and content[1] & 0x80) and not (content[0] == 0 and not content[1] & 0x80)
    if n != -(2 ** (8 * len(content) - 1)):  # pyasn1 spends an octet more on -128, -32768 ... only
        assert ours == encoder.encode(univ.Integer(n))
    assert ber.tlv(ber.OBJECT_IDENTIFIER, ber.oid_content(oid)) == encoder.encode(univ.ObjectIdentifier(oid))


def test_the_most_negative_values_take_the_fewest_octets():
    assert ber.int_content(-128) == b"\x80" and ber.int_content(-129) == b"\xff\x7f"
    assert ber.int_content(-(2**31)) == b"\x80\x00\x00\x00"


PYSNMP_PDUS = {ber.GET: v2c.GetRequestPDU, ber.GET_NEXT: v2c.GetNextRequestPDU, ber.SET: v2c.SetRequestPDU,
               ber.GET_BULK: v2c.GetBulkRequestPDU, ber.INFORM: v2c.InformRequestPDU,
               ber.TRAP_V2: v2c.SNMPv2TrapPDU, ber.REPORT: v2c.ReportPDU, ber.RESPONSE: v2c.ResponsePDU}


@settings(max_examples=EXAMPLES, deadline=None)
@given(st.sampled_from(sorted(PYSNMP_PDUS)), st.integers(-(2**31), 2**31 - 1), st.integers(0, 2**31 - 1),
       st.integers(0, 2**31 - 1), st.lists(st.tuples(oids, values), max_size=10), st.binary(max_size=32))
def test_the_simulated_agent_reads_pysnmps_messages_of_every_pdu(pdu, request_id, second, third, binds, community):
    """What the simulator's agent reads its requests with (`decode_message`), against pysnmp building
    every v2c PDU; each value comes back as it was sent, to be echoed in an error response."""
    p = PYSNMP_PDUS[pdu]()
    api_pdu = v2c.apiBulkPDU if pdu == ber.GET_BULK else v2c.apiPDU
    api_pdu.set_defaults(p)
    api_pdu.set_request_id(p, request_id)
    if pdu == ber.GET_BULK:
        v2c.apiBulkPDU.set_non_repeaters(p, second)
        v2c.apiBulkPDU.set_max_repetitions(p, third)
    else:
        v2c.apiPDU.set_error_status(p, second)
        v2c.apiPDU.set_error_index(p, third)
    api_pdu.set_varbinds(p, [(o, v[1]) for o, v in binds])
    msg = v2c.Message()
    v2c.apiMessage.set_defaults(msg)
    v2c.apiMessage.set_community(msg, community)
    v2c.apiMessage.set_pdu(msg, p)
    got = ber.decode_message(encoder.encode(msg))
    assert (got.version, got.community, got.pdu, got.request_id, got.error_status, got.error_index) == \
        (1, community, pdu, request_id, second, third)
    assert got.varbinds == [(o, v[0]) for o, v in binds]
    assert got.values == [encoder.encode(v[1]) for _, v in binds]
    assert ber.message_version(encoder.encode(msg)) == 1


def test_a_v1_trap_is_framed_and_anything_else_is_refused():
    from pysnmp.proto.api import v1
    trap = v1.TrapPDU()
    v1.apiTrapPDU.set_defaults(trap)
    msg = v1.Message()
    v1.apiMessage.set_defaults(msg)
    v1.apiMessage.set_community(msg, "public")
    v1.apiMessage.set_pdu(msg, trap)
    got = ber.decode_message(encoder.encode(msg))
    assert (got.version, got.community, got.pdu, got.varbinds) == (0, b"public", ber.TRAP_V1, [])
    with pytest.raises(BerError, match="unknown PDU tag 0xa9"):
        ber.decode_message(b"\x30\x0b\x02\x01\x01\x04\x01p\xa9\x03\x02\x01\x00")
    with pytest.raises(BerError, match="1 byte\\(s\\) after the PDU"):
        ber.decode_message(b"\x30\x0b\x02\x01\x01\x04\x01p\xa0\x02\x02\x00\x00")
