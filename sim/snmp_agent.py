"""SNMP agent of the simulated MANET: every node served on its own UDP endpoint, one thread.

One asyncio loop (thread `manet-snmp`) serves any number of nodes, each on its own
(host, port), speaking SNMPv1 and SNMPv2c (GET, GETNEXT, GETBULK, SET) with pysnmp's
protocol layer. Each node answers from its `NodeView` (sim/manet.py) through the table of
sim/manet_mib.py; a SET of the position scalars reports the node's position to the
network. Malformed datagrams and wrong communities are dropped and counted.
"""

from __future__ import annotations

import asyncio
import bisect
import logging
import threading
from collections import Counter
from typing import Any

from pyasn1.codec.ber import decoder, encoder
from pyasn1.error import PyAsn1Error
from pyasn1.type import univ
from pysnmp.proto import api
from pysnmp.proto.api import v2c

from erni.blackboard.errors import NetworkError
from erni.sim import snmp_ber as ber
from erni.sim.manet import ManetNetwork
from erni.sim.manet_mib import (
    INT32,
    OID,
    WRITABLE,
    Value,
    build_table,
    parse_position_write,
    topology_rows,
)

log = logging.getLogger("erni.sim.snmp")

MAX_VARBINDS = 500           # per response (GETBULK is trimmed to this)
MAX_RESPONSE_BYTES = 60000   # stays under the UDP datagram limit
# SNMP error-status codes (RFC 3416)
NO_SUCH_NAME, BAD_VALUE, GEN_ERR = 2, 3, 5
WRONG_TYPE, WRONG_VALUE, NOT_WRITABLE = 7, 10, 17


Answer = tuple[int, int, list[bytes] | None]
"""What a PDU handler returns: error status, error index, the encoded varbinds (None on error)."""


class _Rows:
    """Sorted OIDs whose entries are a `Value` until first read, then the encoded varbind
    (ages are encoded at every read)."""

    __slots__ = ("entries", "keys")

    def __init__(self, rows: list[tuple[OID, Value]]) -> None:
        self.keys = [r[0] for r in rows]
        self.entries: list[Value | bytes] = [r[1] for r in rows]

    def bind(self, i: int) -> bytes:
        entry = self.entries[i]
        if isinstance(entry, bytes):
            return entry
        val = entry.resolve()
        bound = ber.varbind(ber.oid(self.keys[i]), ber.value(val.kind, val.value))
        if entry.kind != "age":
            self.entries[i] = bound
        return bound


class _Table:
    """A node's served OIDs, rebuilt when the network's version changes: its own rows with
    an optional block shared by several nodes (the component's topology) spliced in."""

    __slots__ = ("at", "block", "keys", "own", "version")

    def __init__(self, version: int, own: _Rows, block: _Rows | None = None) -> None:
        self.version = version
        self.own = own
        self.block = block if block is not None and block.keys else None
        if self.block is None:
            self.keys, self.at = own.keys, len(own.keys)
        else:
            self.at = bisect.bisect_left(own.keys, self.block.keys[0])
            self.keys = own.keys[: self.at] + self.block.keys + own.keys[self.at:]

    def _bind(self, i: int) -> bytes:
        if i < self.at or self.block is None:
            return self.own.bind(i)
        j = i - self.at
        if j < len(self.block.keys):
            return self.block.bind(j)
        return self.own.bind(i - len(self.block.keys))

    def get(self, oid: OID) -> bytes | None:
        """The encoded varbind of `oid`, or None."""
        i = bisect.bisect_left(self.keys, oid)
        if i < len(self.keys) and self.keys[i] == oid:
            return self._bind(i)
        return None

    def next(self, oid: OID) -> tuple[OID, bytes] | None:
        """The first OID after `oid` and its encoded varbind, or None at the end."""
        i = bisect.bisect_right(self.keys, oid)
        if i < len(self.keys):
            return self.keys[i], self._bind(i)
        return None

    def has_prefix(self, prefix: OID) -> bool:
        i = bisect.bisect_left(self.keys, prefix)
        return i < len(self.keys) and self.keys[i][: len(prefix)] == prefix


class _NodeEndpoint(asyncio.DatagramProtocol):
    def __init__(self, agent: ManetSnmpAgent, name: str) -> None:
        self.agent = agent
        self.name = name
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: Any) -> None:
        reply = self.agent.handle(self.name, data)
        if reply is not None and self.transport is not None:
            self.transport.sendto(reply, addr)


class ManetSnmpAgent:
    """Serve the nodes of a `ManetNetwork` over SNMP v1/v2c, one UDP endpoint per node."""

    def __init__(self, network: ManetNetwork, community: str = "public") -> None:
        self.network = network
        self.community = community.encode()
        self.stats: Counter[str] = Counter()
        self._tables: dict[str, _Table] = {}
        self._blocks: dict[int, tuple[Any, _Rows, int]] = {}
        self._endpoints: dict[str, tuple[str, int]] = {}
        self._transports: dict[str, asyncio.DatagramTransport] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> ManetSnmpAgent:
        """Start the agent's thread (endpoints are opened with `serve`)."""
        if self._thread is not None:
            return self
        loop = asyncio.new_event_loop()
        ready = threading.Event()

        def run() -> None:
            asyncio.set_event_loop(loop)
            loop.call_soon(ready.set)
            loop.run_forever()
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

        self._loop = loop
        self._thread = threading.Thread(target=run, name="manet-snmp", daemon=True)
        self._thread.start()
        ready.wait(5.0)
        return self

    def serve(self, name: str, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Open node `name`'s UDP endpoint (port 0: any free port); return (host, port)."""
        self.network.info(name)  # raises KeyError for an unknown node
        if self._loop is None:
            self.start()
        assert self._loop is not None

        async def open_endpoint() -> tuple[str, int]:
            transport, _ = await self._loop.create_datagram_endpoint(  # type: ignore[union-attr]
                lambda: _NodeEndpoint(self, name), local_addr=(host, port))
            self._transports[name] = transport
            bound = transport.get_extra_info("sockname")
            return bound[0], bound[1]

        fut = asyncio.run_coroutine_threadsafe(open_endpoint(), self._loop)
        try:
            address = fut.result(5.0)
        except OSError as err:
            raise NetworkError(f"node {name!r}: cannot serve SNMP on {host}:{port}: {err.strerror}") from None
        self._endpoints[name] = address
        return address

    def serve_all(self, ports: dict[str, int] | None = None, host: str = "127.0.0.1") -> dict[str, tuple[str, int]]:
        """Serve every node of the network (ports by name, default any free port)."""
        ports = ports or {}
        for name in self.network.names():
            if name not in self._endpoints:
                self.serve(name, host, ports.get(name, 0))
        return self.addresses()

    def addresses(self) -> dict[str, tuple[str, int]]:
        """(host, port) of every served node."""
        return dict(self._endpoints)

    def close(self) -> None:
        """Close every endpoint and join the agent's thread."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return

        def shutdown() -> None:
            for t in self._transports.values():
                t.close()
            loop.call_soon(loop.stop)

        loop.call_soon_threadsafe(shutdown)
        thread.join(5.0)
        self._loop = self._thread = None
        self._transports.clear()
        self._endpoints.clear()

    def __enter__(self) -> ManetSnmpAgent:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- request handling (runs on the agent's thread) -------------------------------------

    def table(self, name: str) -> _Table:
        """The node's current OID table (rebuilt after a network change)."""
        version = self.network.version
        table = self._tables.get(name)
        if table is None or table.version != version:
            view = self.network.view(name)
            rows = build_table(view, self.network.radio.comm_range, with_topology=False)
            table = _Table(view.version, _Rows(rows), self._topology_block(view))
            self._tables[name] = table
        return table

    def _topology_block(self, view: Any) -> _Rows:
        """The topology rows of the view's component, built (and encoded) once per topology."""
        cached = self._blocks.get(id(view.topology))
        if cached is not None and cached[0] is view.topology:
            return cached[1]
        if self._blocks and next(iter(self._blocks.values()))[2] != view.topology_version:
            self._blocks.clear()
        block = _Rows(topology_rows(view))
        self._blocks[id(view.topology)] = (view.topology, block, view.topology_version)
        return block

    def handle(self, name: str, data: bytes) -> bytes | None:
        """Answer one datagram addressed to node `name`; None drops it (counted)."""
        try:
            version = int(api.decodeMessageVersion(data))
            if version not in api.PROTOCOL_MODULES:
                self.stats["bad_version"] += 1
                return None
            p_mod = api.PROTOCOL_MODULES[version]
            msg, _ = decoder.decode(data, asn1Spec=p_mod.Message())
            community = bytes(p_mod.apiMessage.get_community(msg))
            if community != self.community:
                self.stats["bad_community"] += 1
                return None
            req = p_mod.apiMessage.get_pdu(msg)
            request_id = int(p_mod.apiPDU.get_request_id(req))
            binds = [(tuple(o), v) for o, v in p_mod.apiPDU.get_varbinds(req)]
        except (PyAsn1Error, ValueError, TypeError, KeyError, IndexError, AttributeError):
            self.stats["malformed"] += 1
            return None
        try:
            status, index, out = self._dispatch(name, version, p_mod, req, binds)
        except Exception:  # a bug must not kill the endpoint; the client sees genErr
            log.exception("node %s: failed to answer a request", name)
            status, index, out = GEN_ERR, 1, None
        if out is None:  # errors echo the request's varbinds
            out = [ber.varbind(ber.oid(o), encoder.encode(v)) for o, v in binds]
        self.stats["answered"] += 1
        return ber.response(version, community, request_id, status, index, out)

    def _dispatch(self, name: str, version: int, p_mod: Any, req: Any,
                  binds: list[tuple[OID, Any]]) -> Answer:
        if req.isSameTypeWith(p_mod.SetRequestPDU()):
            self.stats["set"] += 1
            return self._set(name, version, binds)
        table = self.table(name)
        if req.isSameTypeWith(p_mod.GetRequestPDU()):
            self.stats["get"] += 1
            return self._get(table, version, binds)
        if req.isSameTypeWith(p_mod.GetNextRequestPDU()):
            self.stats["getnext"] += 1
            return self._next(table, version, binds)
        if version == 1 and req.isSameTypeWith(v2c.GetBulkRequestPDU()):
            self.stats["getbulk"] += 1
            non_rep = int(v2c.apiBulkPDU.get_non_repeaters(req))
            max_rep = int(v2c.apiBulkPDU.get_max_repetitions(req))
            return self._bulk(table, binds, non_rep, max_rep)
        self.stats["unsupported_pdu"] += 1
        return GEN_ERR, 0, None

    def _get(self, table: _Table, version: int, binds: list[tuple[OID, Any]]) -> Answer:
        out: list[bytes] = []
        for i, (key, _) in enumerate(binds):
            bound = table.get(key)
            if bound is not None:
                out.append(bound)
            elif version == 0:
                return NO_SUCH_NAME, i + 1, None
            elif len(key) >= 10 and table.has_prefix(key[:-1]):
                out.append(ber.varbind(ber.oid(key), ber.NO_SUCH_INSTANCE))
            else:
                out.append(ber.varbind(ber.oid(key), ber.NO_SUCH_OBJECT))
        return 0, 0, out

    def _next(self, table: _Table, version: int, binds: list[tuple[OID, Any]]) -> Answer:
        out: list[bytes] = []
        for i, (key, _) in enumerate(binds):
            found = table.next(key)
            if found is not None:
                out.append(found[1])
            elif version == 0:
                return NO_SUCH_NAME, i + 1, None
            else:
                out.append(ber.varbind(ber.oid(key), ber.END_OF_MIB_VIEW))
        return 0, 0, out

    def _bulk(self, table: _Table, binds: list[tuple[OID, Any]], non_rep: int, max_rep: int) -> Answer:
        non_rep = max(0, min(non_rep, len(binds)))
        out = list(self._next(table, 1, binds[:non_rep])[2] or [])
        cursors: list[OID | None] = [key for key, _ in binds[non_rep:]]
        size = sum(map(len, out))
        for _ in range(max(0, max_rep) if cursors else 0):
            row: list[bytes] = []
            ended = True
            for j, cur in enumerate(cursors):
                found = table.next(cur) if cur is not None else None
                if found is None:
                    last = cur if cur is not None else binds[non_rep + j][0]
                    row.append(ber.varbind(ber.oid(last), ber.END_OF_MIB_VIEW))
                    cursors[j] = None
                else:
                    ended = False
                    cursors[j] = found[0]
                    row.append(found[1])
            size += sum(map(len, row))
            if len(out) + len(row) > MAX_VARBINDS or size > MAX_RESPONSE_BYTES:
                break
            out.extend(row)
            if ended:
                break
        return 0, 0, out

    def _set(self, name: str, version: int, binds: list[tuple[OID, Any]]) -> Answer:
        writes: dict[str, int] = {}
        for i, (key, value) in enumerate(binds):
            field = WRITABLE.get(key)
            if field is None:
                self.stats["set_refused"] += 1
                return (NO_SUCH_NAME if version == 0 else NOT_WRITABLE), i + 1, None
            if value.tagSet != univ.Integer.tagSet:
                self.stats["set_refused"] += 1
                return (BAD_VALUE if version == 0 else WRONG_TYPE), i + 1, None
            number = int(value)
            if not INT32[0] <= number <= INT32[1]:
                self.stats["set_refused"] += 1
                return (BAD_VALUE if version == 0 else WRONG_VALUE), i + 1, None
            writes[field] = number
        view = self.network.view(name)
        own = view.positions.get(name)
        current = (own.x, own.y, own.heading) if own else (0.0, 0.0, 0.0)
        x, y, heading = parse_position_write(current, writes)
        self.network.set_position(name, x, y, heading)
        return 0, 0, None
