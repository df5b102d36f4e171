"""SNMP agent of the simulated MANET: every node served on its own UDP endpoint, one thread.

One asyncio loop (thread `manet-snmp`) serves any number of nodes, each on its own
(host, port) and each its own SNMP entity (sysUpTime from when it was served, its own snmp
counters), speaking SNMPv1 and SNMPv2c: GET, GETNEXT, GETBULK and SET as RFC 3416 defines
them (errors mapped to v1 as RFC 3584 says), from the node's `NodeView` through the rows of
sim/manet_mib.py. A node has a read community and, optionally, a distinct write community:
a SET with the read community is refused (noAccess; v1 noSuchName) and counted in
snmpInBadCommunityUses; a SET of the position scalars with the write community reports the
node's position to the network.

A node given v3 users (`v3_users`) speaks SNMPv3 only, USM authPriv (sim/snmp_v3.py, through
pysnmp): its users read and write, a request without privacy is refused
(usmStatsUnsupportedSecLevels), and v1/v2c requests are dropped (snmpInBadCommunityNames: it accepts no
community). Its requests are answered by the same code as v2c requests.

Dropped and counted, never answered: undecodable datagrams (snmpInASNParseErrs), other SNMP
versions (snmpInBadVersions), unknown communities (snmpInBadCommunityNames), and every
response-class or notification PDU — GetResponse, Trap, Report, InformRequest — for which a
command responder has no handler (snmpUnknownPDUHandlers, RFC 3412 4.2.2.1): no datagram,
spoofed or not, makes two agents answer each other.
"""

from __future__ import annotations

import asyncio
import bisect
import logging
import threading
from collections import Counter
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from erni.blackboard.errors import NetworkError, UsageError
from erni.plugins.mobinet import ber as wire
from erni.plugins.mobinet.ber import INTEGER, BerError, Message, Value
from erni.plugins.mobinet.usm import UsmUser
from erni.sim import snmp_ber as ber
from erni.sim.manet import ManetNetwork, NodeView
from erni.sim.manet_mib import (
    OID,
    UINT32_MAX,
    WRITABLE,
    Row,
    build_table,
    object_of,
    own_topology_prefixes,
    parse_position_write,
    resolve,
    topology_rows,
)

if TYPE_CHECKING:
    from erni.sim.snmp_v3 import V3Entity

log = logging.getLogger("erni.sim.snmp")

MAX_VARBINDS = 500           # per GETBULK response
MAX_RESPONSE_BYTES = 60000   # the local constraint on a response message (under the UDP limit)
# SNMP error-status codes (RFC 3416)
TOO_BIG, NO_SUCH_NAME, BAD_VALUE, GEN_ERR, NO_ACCESS = 1, 2, 3, 5, 6
WRONG_TYPE, WRONG_VALUE, NO_CREATION, AUTHORIZATION_ERROR, NOT_WRITABLE = 7, 10, 11, 16, 17
V1_OF = {NO_ACCESS: NO_SUCH_NAME, WRONG_TYPE: BAD_VALUE, WRONG_VALUE: BAD_VALUE,
         NO_CREATION: NO_SUCH_NAME, NOT_WRITABLE: NO_SUCH_NAME}   # RFC 3584 section 4.4
V1, V2C, V3 = 0, 1, 3
V1_PDUS = frozenset({wire.GET, wire.GET_NEXT, wire.RESPONSE, wire.SET, wire.TRAP_V1})   # RFC 1157
V2C_PDUS = wire.PDUS                                                                 # RFC 3416
KINDS = {wire.GET: "get", wire.GET_NEXT: "getnext", wire.SET: "set", wire.GET_BULK: "getbulk"}

Answer = tuple[int, int, list[bytes] | None]
"""What a PDU handler returns: error status, error index, the encoded varbinds (None: echo the request)."""


class _Encoded:
    """Sorted rows whose static values are encoded once, at first read."""

    __slots__ = ("entries", "keys")

    def __init__(self, rows: list[Row]) -> None:
        self.keys = [r[0] for r in rows]
        self.entries: list[Row | bytes] = rows  # type: ignore[assignment]  # list is invariant; rows become bytes as they are read

    def bind(self, i: int, ctx: _Node) -> bytes:
        entry = self.entries[i]
        if isinstance(entry, bytes):
            return entry
        _, kind, value = entry
        dynamic = callable(value)
        bound = ber.varbind(ber.oid(self.keys[i]), ber.value(kind, resolve(value, ctx)))
        if not dynamic:
            self.entries[i] = bound
        return bound


class _Table:
    """A node's served OIDs: sorted, non-overlapping slices of row sets (its own rows and the
    topology set its component shares, without the links the node advertises itself)."""

    __slots__ = ("segments", "starts", "version")

    def __init__(self, version: int, segments: list[tuple[_Encoded, int, int]]) -> None:
        self.version = version
        self.segments = [s for s in segments if s[1] < s[2]]
        self.starts = [rows.keys[lo] for rows, lo, _ in self.segments]

    @property
    def keys(self) -> list[OID]:
        """Every served OID in order (for tests)."""
        return [k for rows, lo, hi in self.segments for k in rows.keys[lo:hi]]

    def get(self, oid: OID, ctx: _Node) -> bytes | None:
        """The encoded varbind of `oid`, or None."""
        j = bisect.bisect_right(self.starts, oid) - 1
        if j < 0:
            return None
        rows, lo, hi = self.segments[j]
        i = bisect.bisect_left(rows.keys, oid, lo, hi)
        return rows.bind(i, ctx) if i < hi and rows.keys[i] == oid else None

    def next(self, oid: OID, ctx: _Node) -> tuple[OID, bytes] | None:
        """The first OID after `oid` and its encoded varbind, or None at the end of the MIB view."""
        at = self.locate(oid)
        return None if at is None else self.entry(at, ctx)

    def locate(self, oid: OID) -> tuple[int, int] | None:
        """Where the first OID after `oid` is served (segment, row), or None at the end of the view."""
        j = max(0, bisect.bisect_right(self.starts, oid) - 1)
        for k in range(j, len(self.segments)):
            rows, lo, hi = self.segments[k]
            i = bisect.bisect_right(rows.keys, oid, lo, hi)
            if i < hi:
                return k, i
        return None

    def after(self, at: tuple[int, int]) -> tuple[int, int] | None:
        """The place of the OID that follows the one at `at` (the segments are sorted and do not
        overlap): a GETBULK's repeaters walk on from where they are without searching again."""
        k, i = at
        if i + 1 < self.segments[k][2]:
            return k, i + 1
        return (k + 1, self.segments[k + 1][1]) if k + 1 < len(self.segments) else None

    def entry(self, at: tuple[int, int], ctx: _Node) -> tuple[OID, bytes]:
        """The OID at a place and its encoded varbind."""
        rows, i = self.segments[at[0]][0], at[1]
        return rows.keys[i], rows.bind(i, ctx)


class _Node:
    """One served node: its SNMP entity's communities, start time and counters."""

    def __init__(self, network: ManetNetwork, name: str, read: bytes, write: bytes | None) -> None:
        self.network = network
        self.name = name
        self.read = read
        self.write = write
        self.started = network.clock()
        self.stats: Counter[str] = Counter()
        self.table: _Table | None = None
        self.transport: asyncio.DatagramTransport | None = None
        self.v3: V3Entity | None = None   # SNMPv3 only (USM users), else v1/v2c only
        self.usm: dict[str, int] = {}    # the v3 engine's usmStats* last seen

    # NodeContext (sim/manet_mib.py)
    def now(self) -> float:
        return self.network.clock()

    def stamp(self, when: float) -> int:
        return min(UINT32_MAX, int(max(0.0, when - self.started) * 100))

    def uptime(self) -> int:
        return self.stamp(self.now())

    def counter(self, name: str) -> int:
        return self.stats[name]


class _NodeEndpoint(asyncio.DatagramProtocol):
    def __init__(self, agent: ManetSnmpAgent, name: str) -> None:
        self.agent = agent
        self.name = name
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: Any) -> None:
        reply = self.agent.handle(self.name, data, addr)
        if reply is not None and self.transport is not None:
            self.transport.sendto(reply, addr)


class ManetSnmpAgent:
    """Serve the nodes of a `ManetNetwork` over SNMP v1/v2c, or v3 only, one UDP endpoint per node.

    `read_community` reads; `write_community` (None: the agent accepts no SET) reads and
    writes; `v3_users` (USM, authPriv) replace both: a node with users speaks only SNMPv3.
    `serve()` may give a node communities or users of its own.
    """

    def __init__(self, network: ManetNetwork, read_community: str = "public",
                 write_community: str | None = None, v3_users: Sequence[UsmUser] = ()) -> None:
        _check_communities(read_community, write_community)
        self.network = network
        self.read_community = read_community
        self.write_community = write_community
        self.v3_users = tuple(v3_users)
        self.stats: Counter[str] = Counter()   # every node's counters added up
        self._nodes: dict[str, _Node] = {}
        self._blocks: dict[int, tuple[Any, _Encoded, int]] = {}
        self._endpoints: dict[str, tuple[str, int]] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

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

    def serve(self, name: str, host: str = "127.0.0.1", port: int = 0, read_community: str | None = None,
              write_community: str | None = None, v3_users: Sequence[UsmUser] | None = None) -> tuple[str, int]:
        """Open node `name`'s UDP endpoint (port 0: any free port); return (host, port).

        The node's communities and v3 users default to the agent's; with users it speaks only SNMPv3.
        """
        self.network.info(name)  # raises NotFoundError for an unknown node
        read = read_community if read_community is not None else self.read_community
        write = write_community if write_community is not None else self.write_community
        users = tuple(v3_users) if v3_users is not None else self.v3_users
        _check_communities(read, write)
        if len({u.name for u in users}) != len(users):
            raise UsageError(f"node {name!r}: SNMPv3 user names must differ, got {[u.name for u in users]}")
        if self._loop is None:
            self.start()
        assert self._loop is not None
        node = self.node(name)
        node.read, node.write = read.encode(), write.encode() if write is not None else None

        async def open_endpoint() -> tuple[str, int]:
            transport, _ = await self._loop.create_datagram_endpoint(  # type: ignore[union-attr]
                lambda: _NodeEndpoint(self, name), local_addr=(host, port))
            node.transport = transport
            if node.v3 is not None:
                node.v3.close()
                node.v3 = None
            if users:   # pysnmp only for a node that speaks v3; its engine belongs to this loop
                from erni.sim.snmp_v3 import V3Entity

                def send(data: bytes, addr: Any) -> None:
                    if node.transport is not None:
                        node.transport.sendto(data, addr)

                node.v3 = V3Entity(users, lambda pdu, priv: self._answer_v3(node, pdu, priv), send,
                                   asyncio.get_running_loop())
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

    def node_stats(self, name: str) -> Counter[str]:
        """The SNMP counters of one node (snmpInPkts, snmpUnknownPDUHandlers, usmStatsWrongDigests, ...)."""
        return self.node(name).stats

    def close(self) -> None:
        """Close every endpoint and join the agent's thread."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return

        def shutdown() -> None:
            for node in self._nodes.values():
                if node.v3 is not None:
                    node.v3.close()
                    node.v3 = None
                if node.transport is not None:
                    node.transport.close()
                    node.transport = None
            loop.call_soon(loop.stop)

        loop.call_soon_threadsafe(shutdown)
        thread.join(5.0)
        self._loop = self._thread = None
        self._endpoints.clear()

    def __enter__(self) -> ManetSnmpAgent:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- request handling (runs on the agent's thread) -------------------------------------

    def node(self, name: str) -> _Node:
        """The SNMP entity of node `name` (made with the agent's communities on first use)."""
        node = self._nodes.get(name)
        if node is None:
            self.network.info(name)
            node = _Node(self.network, name, self.read_community.encode(),
                         self.write_community.encode() if self.write_community is not None else None)
            self._nodes[name] = node
        return node

    def table(self, name: str) -> _Table:
        """The node's current OID table (rebuilt when its rows change; a position report changes values only)."""
        node = self.node(name)
        version = self.network.rows_version
        table = node.table
        if table is None or table.version != version:
            view = self.network.view(name)
            own = _Encoded(build_table(view, self.network, with_topology=False))
            block = self._topology_block(view)
            segments: list[tuple[_Encoded, int, int]] = []
            if block.keys:
                at = bisect.bisect_left(own.keys, block.keys[0])
                cuts = [0]
                for prefix in own_topology_prefixes(view):  # the node's own links: not in its set
                    cuts.append(bisect.bisect_left(block.keys, prefix))
                    cuts.append(bisect.bisect_left(block.keys, prefix[:-1] + (prefix[-1] + 1,)))
                cuts.append(len(block.keys))
                segments.append((own, 0, at))
                segments.extend((block, cuts[k], cuts[k + 1]) for k in range(0, len(cuts), 2))
                segments.append((own, at, len(own.keys)))
            else:
                segments.append((own, 0, len(own.keys)))
            table = _Table(version, segments)
            node.table = table
        return table

    def _topology_block(self, view: NodeView) -> _Encoded:
        """The topology rows of the view's component, built (and encoded) once per topology."""
        cached = self._blocks.get(id(view.topology))
        if cached is not None and cached[0] is view.topology:
            return cached[1]
        if self._blocks and next(iter(self._blocks.values()))[2] != view.topology_version:
            self._blocks.clear()
        block = _Encoded(topology_rows(view))
        self._blocks[id(view.topology)] = (view.topology, block, view.topology_version)
        return block

    def _count(self, node: _Node, key: str) -> None:
        node.stats[key] += 1
        self.stats[key] += 1

    def handle(self, name: str, data: bytes, addr: Any = None) -> bytes | None:
        """Answer one datagram addressed to node `name` from `addr`; None drops it (counted), or
        leaves an SNMPv3 message to the node's v3 engine, which sends its answer itself."""
        node = self.node(name)
        self._count(node, "snmpInPkts")
        try:
            version = wire.message_version(data)
        except BerError:
            self._count(node, "snmpInASNParseErrs")
            return None
        if node.v3 is not None:
            if version == V3:
                node.v3.receive(data, addr)
                self._count_usm(node)
            elif version in (V1, V2C):   # a v3-only node accepts no community
                self._count(node, "snmpInBadCommunityNames")
            else:
                self._count(node, "snmpInBadVersions")
            return None
        if version not in (V1, V2C):
            self._count(node, "snmpInBadVersions")
            return None
        try:
            msg = wire.decode_message(data)
        except BerError:
            self._count(node, "snmpInASNParseErrs")
            return None
        if msg.pdu not in (V1_PDUS if version == V1 else V2C_PDUS):   # not in the version's PDU CHOICE
            self._count(node, "snmpInASNParseErrs")
            return None
        community, request_id = msg.community, msg.request_id
        kind = KINDS.get(msg.pdu, "other")
        if community == node.write and node.write is not None:
            may_write = True
        elif community == node.read:
            may_write = False
        else:
            self._count(node, "snmpInBadCommunityNames")
            return None
        if kind == "other":
            # responses, traps, reports and informs: a command responder has no handler for them
            self._count(node, "snmpUnknownPDUHandlers")
            return None
        self._count(node, kind)
        try:
            status, index, out = self._dispatch(node, version, kind, msg, may_write)
        except Exception:  # a bug must not kill the endpoint; the client sees genErr
            log.exception("node %s: failed to answer a request", name)
            status, index, out = GEN_ERR, 1, None
        if status and version == V1:
            status = V1_OF.get(status, status)
        reply = self._response(version, community, request_id, status, index, out, msg)
        if len(reply) > MAX_RESPONSE_BYTES:  # RFC 3416 4.2.1: the alternate tooBig response
            reply = self._response(version, community, request_id, TOO_BIG, 0,
                                   None if version == V1 else [], msg)
            if len(reply) > MAX_RESPONSE_BYTES:
                self._count(node, "snmpSilentDrops")
                return None
        self._count(node, "answered")
        return reply

    def _answer_v3(self, node: _Node, pdu: bytes, auth_priv: bool) -> bytes:
        """The Response PDU to a request PDU that came authenticated (and, if `auth_priv`, encrypted)."""
        # the PDU in a v2c envelope: the v2c reader and handlers answer it
        msg = wire.decode_message(ber.tlv(wire.SEQUENCE, b"\x02\x01\x01\x04\x00" + pdu))
        kind = KINDS.get(msg.pdu, "other")
        if not auth_priv:
            self._count(node, "snmpv3NoPriv")
            status, index, out = AUTHORIZATION_ERROR, 0, None
        else:
            self._count(node, kind)
            try:
                status, index, out = self._dispatch(node, V2C, kind, msg, True)
            except Exception:  # a bug must not kill the endpoint; the client sees genErr
                log.exception("node %s: failed to answer a request", node.name)
                status, index, out = GEN_ERR, 1, None
        if out is None:
            out = [ber.varbind(ber.oid(o), raw) for (o, _), raw in zip(msg.varbinds, msg.values)]
        reply = ber.response_pdu(msg.request_id, status, index, out)
        if len(reply) > MAX_RESPONSE_BYTES:
            reply = ber.response_pdu(msg.request_id, TOO_BIG, 0, [])
        self._count(node, "answered")
        return reply

    def _count_usm(self, node: _Node) -> None:
        """Add what the node's v3 engine refused since the last message to the node's and agent's counters."""
        assert node.v3 is not None
        for key, total in node.v3.usm_stats().items():
            new = total - node.usm.get(key, 0)
            if new:
                node.stats[key] += new
                self.stats[key] += new
            node.usm[key] = total

    @staticmethod
    def _response(version: int, community: bytes, request_id: int, status: int, index: int,
                  out: list[bytes] | None, msg: Message) -> bytes:
        if out is None:  # errors echo the request's varbinds
            out = [ber.varbind(ber.oid(o), raw) for (o, _), raw in zip(msg.varbinds, msg.values)]
        return ber.response(version, community, request_id, status, index, out)

    def _dispatch(self, node: _Node, version: int, kind: str, msg: Message, may_write: bool) -> Answer:
        binds = msg.varbinds
        if kind == "set":
            if not may_write:
                self._count(node, "snmpInBadCommunityUses")
                return NO_ACCESS, 1 if binds else 0, None
            return self._set(node, binds)
        table = self.table(node.name)
        if kind == "get":
            return self._get(table, node, version, binds)
        if kind == "getnext":
            return self._next(table, node, version, binds)
        return self._bulk(table, node, binds, msg.error_status, msg.error_index)  # non-repeaters, max-repetitions

    @staticmethod
    def _get(table: _Table, node: _Node, version: int, binds: list[tuple[OID, Value]]) -> Answer:
        out: list[bytes] = []
        for i, (key, _) in enumerate(binds):
            bound = table.get(key, node)
            if bound is not None:
                out.append(bound)
            elif version == V1:
                return NO_SUCH_NAME, i + 1, None
            elif object_of(key) is not None:  # a served object without that instance
                out.append(ber.varbind(ber.oid(key), ber.NO_SUCH_INSTANCE))
            else:
                out.append(ber.varbind(ber.oid(key), ber.NO_SUCH_OBJECT))
        return 0, 0, out

    @staticmethod
    def _next(table: _Table, node: _Node, version: int, binds: list[tuple[OID, Value]]) -> Answer:
        out: list[bytes] = []
        for i, (key, _) in enumerate(binds):
            found = table.next(key, node)
            if found is not None:
                out.append(found[1])
            elif version == V1:
                return NO_SUCH_NAME, i + 1, None
            else:
                out.append(ber.varbind(ber.oid(key), ber.END_OF_MIB_VIEW))
        return 0, 0, out

    @staticmethod
    def _bulk(table: _Table, node: _Node, binds: list[tuple[OID, Value]], non_rep: int, max_rep: int) -> Answer:
        """RFC 3416 4.2.3: N non-repeaters, then up to M rows of the R repeaters; past the end a
        repeater names the last OID it reached (or its request OID) with endOfMibView."""
        non_rep = max(0, min(non_rep, len(binds)))
        out = list(ManetSnmpAgent._next(table, node, V2C, binds[:non_rep])[2] or [])
        size = sum(map(len, out))
        cursors: list[OID] = [key for key, _ in binds[non_rep:]]
        rounds = max(0, max_rep) if cursors else 0
        # where each repeater's next row is: searched once, then stepped to (None: past the end)
        places = [table.locate(cur) for cur in cursors] if rounds else []
        ended = [False] * len(cursors)
        for _ in range(rounds):
            row: list[bytes] = []
            for j, at in enumerate(places):
                if at is None:
                    ended[j] = True
                    row.append(ber.varbind(ber.oid(cursors[j]), ber.END_OF_MIB_VIEW))
                else:
                    cursors[j], bound = table.entry(at, node)
                    row.append(bound)
                    places[j] = table.after(at)
            size += sum(map(len, row))
            if len(out) + len(row) > MAX_VARBINDS or size > MAX_RESPONSE_BYTES - 200:
                break
            out.extend(row)
            if all(ended):
                break
        return 0, 0, out

    def _set(self, node: _Node, binds: list[tuple[OID, Value]]) -> Answer:
        """RFC 3416 4.2.5: check every varbind first, then apply them all (or none)."""
        writes: dict[str, int] = {}
        for i, (key, value) in enumerate(binds):
            status = self._check_write(key, value)
            if status:
                self._count(node, "set_refused")
                return status, i + 1, None
            assert isinstance(value.value, int)   # checked above
            writes[WRITABLE[key[:-1]]] = value.value
        if writes:
            own = self.network.known_position(node.name, node.name)
            current = (own.x, own.y, own.heading) if own else (0.0, 0.0, 0.0)
            x, y, heading = parse_position_write(current, writes)
            self.network.set_position(node.name, x, y, heading)
        return 0, 0, None

    @staticmethod
    def _check_write(key: OID, value: Value) -> int:
        """0 if `value` may be written to `key`, else the error status (RFC 3416 order)."""
        obj = object_of(key)
        if obj is None or obj.oid not in WRITABLE:
            return NOT_WRITABLE
        if key != obj.oid + (0,):
            return NO_CREATION
        if value.tag != INTEGER or not isinstance(value.value, int):
            return WRONG_TYPE
        low, high = obj.range or (-(2**31), 2**31 - 1)
        if not low <= value.value <= high:
            return WRONG_VALUE
        return 0


def _check_communities(read: str, write: str | None) -> None:
    if not read:
        raise UsageError("SNMP read community must not be empty")
    if write is not None and (not write or write == read):
        raise UsageError(f"SNMP write community must be non-empty and differ from the read community "
                         f"{read!r}, got {write!r}")
