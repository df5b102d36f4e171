"""SNMPv3 for a simulated node: pysnmp's message processing and USM (RFC 3412, RFC 3414) around the
node's own command responder.

Each node that requires v3 users gets its own `V3Entity`: a pysnmp engine with its own engine ID,
boots and time and the node's USM users. The node's UDP endpoint hands it every SNMPv3 datagram;
pysnmp checks the digest, decrypts, answers discovery and refusals with its Reports
(usmStatsUnknownEngineIDs, usmStatsWrongDigests, ...), and gives the node the plain PDU. The node
answers that PDU exactly as it answers a v2c request (`answer(pdu) -> response PDU`, BER both ways)
and pysnmp encrypts and signs the Response. Key localisation, HMAC and AES are pysnmp's.

Only authPriv is served: every user has a privacy key, so pysnmp's USM refuses a request without
privacy (usmStatsUnsupportedSecLevels); should one reach the node, it answers authorizationError.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Sequence
from typing import Any

from pyasn1.codec.ber import decoder, encoder
from pysnmp.carrier.asyncio.dgram import udp
from pysnmp.carrier.asyncio.dispatch import AsyncioDispatcher
from pysnmp.carrier.base import AbstractTransport
from pysnmp.entity import config, engine
from pysnmp.proto import error, rfc1905
from pysnmp.proto.api import v2c

from erni.plugins.mobinet.usm import AUTH_PROTOCOLS, PRIV_PROTOCOLS, UsmUser

log = logging.getLogger("erni.sim.snmp")

AUTH_PRIV = 3   # securityLevel (RFC 3411)
USM_STATS = ("usmStatsUnsupportedSecLevels", "usmStatsNotInTimeWindows", "usmStatsUnknownUserNames",
             "usmStatsUnknownEngineIDs", "usmStatsWrongDigests", "usmStatsDecryptionErrors")
REQUESTS = (rfc1905.GetRequestPDU.tagSet, rfc1905.GetNextRequestPDU.tagSet, rfc1905.SetRequestPDU.tagSet,
            rfc1905.GetBulkRequestPDU.tagSet)

Answer = Callable[[bytes, bool], bytes]
"""The node's responder: (a request PDU's BER, authPriv?) -> the Response PDU's BER."""


class _Carrier(AbstractTransport):  # type: ignore[misc]  # pysnmp is untyped
    """pysnmp's view of the node's UDP endpoint: datagrams in through `deliver`, answers out through `send`."""

    PROTO_TRANSPORT_DISPATCHER = AsyncioDispatcher
    ADDRESS_TYPE = udp.UdpTransportAddress

    def __init__(self, send: Callable[[bytes, Any], None]) -> None:
        self._send = send

    def deliver(self, data: bytes, addr: Any) -> None:
        if self._callback_function is not None:
            self._callback_function(self, udp.UdpTransportAddress(addr), data)

    def send_message(self, outgoingMessage: Any, transportAddress: Any) -> None:  # noqa: N803  # pysnmp's names
        self._send(bytes(outgoingMessage), tuple(transportAddress))


class V3Entity:
    """One node's SNMPv3 engine (made on the agent's loop, which runs its timer)."""

    def __init__(self, users: Sequence[UsmUser], answer: Answer, send: Callable[[bytes, Any], None],
                 loop: asyncio.AbstractEventLoop) -> None:
        from pysnmp.hlapi.v3arch import asyncio as hl

        self.engine = engine.SnmpEngine()
        for user in users:
            config.add_v3_user(self.engine, user.name, getattr(hl, AUTH_PROTOCOLS[user.auth_protocol]),
                               user.auth_key, getattr(hl, PRIV_PROTOCOLS[user.priv_protocol]), user.priv_key)
        self._answer = answer
        self._dispatcher = AsyncioDispatcher(loop=loop)
        self._dispatcher.set_timer_resolution(1.0)   # only expires pysnmp's per-request state
        self.engine.register_transport_dispatcher(self._dispatcher)
        self._carrier = _Carrier(send)
        self._dispatcher.register_transport(udp.DOMAIN_NAME, self._carrier)
        self.engine.message_dispatcher.register_context_engine_id(self.engine.snmpEngineID, REQUESTS, self._process)
        self.failures = 0

    @property
    def engine_id(self) -> bytes:
        """The node's snmpEngineID."""
        return bytes(self.engine.snmpEngineID)

    def receive(self, data: bytes, addr: Any) -> None:
        """Process one SNMPv3 datagram (pysnmp answers, reports or drops it)."""
        try:
            self._carrier.deliver(data, addr)
        except Exception:  # a malformed or hostile message must not kill the endpoint
            self.failures += 1
            log.debug("SNMPv3 message from %s not processed", addr, exc_info=True)

    def usm_stats(self) -> dict[str, int]:
        """The engine's USM counters (RFC 3414 usmStats*): the requests refused and why."""
        symbols = self.engine.get_mib_builder().import_symbols("__SNMP-USER-BASED-SM-MIB", *USM_STATS)
        return {name: int(s.syntax) for name, s in zip(USM_STATS, symbols)}

    def close(self) -> None:
        """Close the engine's dispatcher and timer (on the agent's loop)."""
        self.engine.close_dispatcher()

    def _process(self, snmpEngine: Any, messageProcessingModel: Any, securityModel: Any,  # noqa: N803
                 securityName: Any, securityLevel: Any, contextEngineId: Any, contextName: Any,  # noqa: N803
                 pduVersion: Any, PDU: Any, maxSizeResponseScopedPDU: Any, stateReference: Any) -> None:  # noqa: N803
        """pysnmp's application callback: a verified, decrypted request PDU to answer."""
        answered = self._answer(encoder.encode(PDU), int(securityLevel) == AUTH_PRIV)
        response, _ = decoder.decode(answered, asn1Spec=v2c.ResponsePDU())
        try:
            snmpEngine.message_dispatcher.return_response_pdu(
                snmpEngine, messageProcessingModel, securityModel, securityName, securityLevel, contextEngineId,
                contextName, pduVersion, response, maxSizeResponseScopedPDU, stateReference, {})
        except error.StatusInformation:   # larger than the manager accepts: RFC 3416 4.2.1's tooBig
            v2c.apiPDU.set_error_status(response, 1)
            v2c.apiPDU.set_error_index(response, 0)
            v2c.apiPDU.set_varbinds(response, [])
            try:
                snmpEngine.message_dispatcher.return_response_pdu(
                    snmpEngine, messageProcessingModel, securityModel, securityName, securityLevel,
                    contextEngineId, contextName, pduVersion, response, maxSizeResponseScopedPDU, stateReference, {})
            except error.StatusInformation:
                self.failures += 1
