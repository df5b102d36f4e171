"""The MIB a simulated MANET node serves, object by object as the MIB modules define it.

Served modules: SNMPv2-MIB (RFC 3418: the system group, sysORTable, the snmp group),
SNMP-MPD-MIB (RFC 3412: snmpMPDStats), NHDP-MIB (RFC 7939: state group, neighbour interface
performance), OLSRv2-MIB (RFC 7184: originator, state tables, recalculation counters),
IP-FORWARD-MIB (RFC 4292: inetCidrRouteNumber, inetCidrRouteDiscards, every column of
inetCidrRouteTable) and ERNI-MOBINET-MIB (shipped in erni/plugins/mobinet/mibs).

`OBJECTS` registers every served scalar and column with its module, SYNTAX (as the base
type on the wire), MAX-ACCESS and range; the agent answers noSuchInstance under a registered
object and noSuchObject elsewhere, and checks SETs against it. `build_table(view, ...)` turns
a node's `NodeView` into sorted `(oid, kind, value)` rows; `topology_rows(view)` is the
Router Topology Set of a connected component, shared by its members (each leaves out the
links it advertises itself). A callable value is computed at every read from the serving
node's `NodeContext` (uptime, HELLO counters, SNMP counters, ages).

Model choices the RFCs leave open: one interface (ifIndex 1) and one address per router, so
a neighbour's nhdpDiscIfSetIndex, nhdpDiscIfIndex and nhdpDiscRouterIndex are all its node
index; a heard link below `min_quality` is an NHDP lost link (L_lost true, N_symmetric
false) whose OLSRv2 neighbour metrics are MAXIMUM_METRIC; HELLOs every 2 s with
L_HOLD_TIME 6 s, TCs every 5 s with T_HOLD_TIME 15 s; routes are learned by no protocol
IANA lists (inetCidrRouteProto other(1)); a route to a 1-hop neighbour is local(3) with an
empty next hop (RFC 4292), the others remote(4).
"""

from __future__ import annotations

import functools
import ipaddress
import math
from collections.abc import Callable, Iterable
from typing import Literal, NamedTuple, Protocol

from erni.sim.manet import (
    H_HOLD_TIME,
    HELLO_INTERVAL,
    L_HOLD_TIME,
    MAX_METRIC,
    T_HOLD_TIME,
    TC_INTERVAL,
    ManetNetwork,
    NodeView,
)

OID = tuple[int, ...]
Syntax = Literal["Integer32", "Unsigned32", "Gauge32", "Counter32", "TimeTicks", "OCTET STRING",
                 "IpAddress", "OBJECT IDENTIFIER"]
Access = Literal["read-only", "read-write", "read-create"]
INT32 = (-(2**31), 2**31 - 1)
UINT32_MAX = 2**32 - 1
TRUE, FALSE = 1, 2  # SNMPv2-TC TruthValue
IF_INDEX = 1        # the one MANET interface of every simulated router


Kind = Literal["int", "str", "ip", "gauge", "counter", "ticks", "oid"]
KIND_OF: dict[Syntax, Kind] = {
    "Integer32": "int", "Unsigned32": "gauge", "Gauge32": "gauge", "Counter32": "counter",
    "TimeTicks": "ticks", "OCTET STRING": "str", "IpAddress": "ip", "OBJECT IDENTIFIER": "oid",
}


class Obj(NamedTuple):
    """One served object type (scalar or column) as its MIB module declares it."""

    name: str
    module: str
    oid: OID
    syntax: Syntax
    access: Access
    scalar: bool
    range: tuple[int, int] | None


OBJECTS: dict[OID, Obj] = {}
KIND: dict[OID, Kind] = {}       # the BER kind of each object's values
MAX_OBJECT_LEN = 0


def _obj(module: str, name: str, oid: OID, syntax: Syntax, access: Access = "read-only",
         scalar: bool = False, range: tuple[int, int] | None = None) -> OID:
    global MAX_OBJECT_LEN
    OBJECTS[oid] = Obj(name, module, oid, syntax, access, scalar, range)
    KIND[oid] = KIND_OF[syntax]
    MAX_OBJECT_LEN = max(MAX_OBJECT_LEN, len(oid))
    return oid


def object_of(oid: OID) -> Obj | None:
    """The served object type `oid` is an instance (or a prefix) of, or None."""
    for n in range(min(len(oid), MAX_OBJECT_LEN), 0, -1):
        obj = OBJECTS.get(oid[:n])
        if obj is not None:
            return obj
    return None


# --- SNMPv2-MIB (RFC 3418) --------------------------------------------------------------
M = "SNMPv2-MIB"
SYSTEM = (1, 3, 6, 1, 2, 1, 1)
SYS_DESCR = _obj(M, "sysDescr", SYSTEM + (1,), "OCTET STRING", scalar=True, range=(0, 255))
SYS_OBJECT_ID = _obj(M, "sysObjectID", SYSTEM + (2,), "OBJECT IDENTIFIER", scalar=True)
SYS_UP_TIME = _obj(M, "sysUpTime", SYSTEM + (3,), "TimeTicks", scalar=True)
SYS_CONTACT = _obj(M, "sysContact", SYSTEM + (4,), "OCTET STRING", "read-write", True, (0, 255))
SYS_NAME = _obj(M, "sysName", SYSTEM + (5,), "OCTET STRING", "read-write", True, (0, 255))
SYS_LOCATION = _obj(M, "sysLocation", SYSTEM + (6,), "OCTET STRING", "read-write", True, (0, 255))
SYS_SERVICES = _obj(M, "sysServices", SYSTEM + (7,), "Integer32", scalar=True, range=(0, 127))
SYS_OR_LAST_CHANGE = _obj(M, "sysORLastChange", SYSTEM + (8,), "TimeTicks", scalar=True)
SYS_OR_ENTRY = SYSTEM + (9, 1)
SYS_OR_ID = _obj(M, "sysORID", SYS_OR_ENTRY + (2,), "OBJECT IDENTIFIER")
SYS_OR_DESCR = _obj(M, "sysORDescr", SYS_OR_ENTRY + (3,), "OCTET STRING", range=(0, 255))
SYS_OR_UP_TIME = _obj(M, "sysORUpTime", SYS_OR_ENTRY + (4,), "TimeTicks")
SNMP = (1, 3, 6, 1, 2, 1, 11)
SNMP_COUNTERS: dict[str, OID] = {   # SNMP counter name -> OID; the agent keeps them per node
    "snmpInPkts": _obj(M, "snmpInPkts", SNMP + (1,), "Counter32", scalar=True),
    "snmpInBadVersions": _obj(M, "snmpInBadVersions", SNMP + (3,), "Counter32", scalar=True),
    "snmpInBadCommunityNames": _obj(M, "snmpInBadCommunityNames", SNMP + (4,), "Counter32", scalar=True),
    "snmpInBadCommunityUses": _obj(M, "snmpInBadCommunityUses", SNMP + (5,), "Counter32", scalar=True),
    "snmpInASNParseErrs": _obj(M, "snmpInASNParseErrs", SNMP + (6,), "Counter32", scalar=True),
    "snmpSilentDrops": _obj(M, "snmpSilentDrops", SNMP + (31,), "Counter32", scalar=True),
    "snmpProxyDrops": _obj(M, "snmpProxyDrops", SNMP + (32,), "Counter32", scalar=True),
}
SNMP_ENABLE_AUTHEN_TRAPS = _obj(M, "snmpEnableAuthenTraps", SNMP + (30,), "Integer32", "read-write",
                                True, (1, 2))
SNMP_MODULES = (1, 3, 6, 1, 6, 3)
SNMP_MIB = SNMP_MODULES + (1,)

# --- SNMP-MPD-MIB (RFC 3412) -------------------------------------------------------------
M = "SNMP-MPD-MIB"
SNMP_MPD_MIB = SNMP_MODULES + (11,)
MPD_STATS = SNMP_MPD_MIB + (2, 1)
SNMP_COUNTERS.update({
    "snmpUnknownSecurityModels": _obj(M, "snmpUnknownSecurityModels", MPD_STATS + (1,), "Counter32",
                                      scalar=True),
    "snmpInvalidMsgs": _obj(M, "snmpInvalidMsgs", MPD_STATS + (2,), "Counter32", scalar=True),
    "snmpUnknownPDUHandlers": _obj(M, "snmpUnknownPDUHandlers", MPD_STATS + (3,), "Counter32", scalar=True),
})

# --- NHDP-MIB (RFC 7939) -----------------------------------------------------------------
M = "NHDP-MIB"
NHDP_MIB = (1, 3, 6, 1, 2, 1, 213)
NHDP = NHDP_MIB + (1,)                                   # nhdpObjects
NHDP_STATE = NHDP + (2,)
NHDP_UP_TIME = _obj(M, "nhdpUpTime", NHDP_STATE + (1,), "TimeTicks", scalar=True)
NHDP_IF_STATE_UP_TIME = _obj(M, "nhdpIfStateUpTime", NHDP_STATE + (2, 1, 1), "TimeTicks")
NHDP_DISC_IF = NHDP_STATE + (3, 1)                       # INDEX { nhdpDiscIfSetIndex }
NHDP_DISC_IF_INDEX = _obj(M, "nhdpDiscIfIndex", NHDP_DISC_IF + (2,), "Unsigned32", range=(1, INT32[1]))
NHDP_DISC_ROUTER_INDEX = _obj(M, "nhdpDiscRouterIndex", NHDP_DISC_IF + (3,), "Unsigned32",
                              range=(1, INT32[1]))
NHDP_DISC_IF_ADDR_TYPE = _obj(M, "nhdpDiscIfSetIpAddrType", NHDP_DISC_IF + (4,), "Integer32", range=(0, 16))
NHDP_DISC_IF_ADDR = _obj(M, "nhdpDiscIfSetIpAddr", NHDP_DISC_IF + (5,), "OCTET STRING", range=(4, 16))
NHDP_DISC_IF_PREFIX = _obj(M, "nhdpDiscIfSetIpAddrPrefixLen", NHDP_DISC_IF + (6,), "Unsigned32",
                           range=(0, 2040))
NHDP_LINK = NHDP_STATE + (4, 1)                          # INDEX { nhdpIfIndex, nhdpDiscIfIndex }
NHDP_LINK_HEARD_TIME = _obj(M, "nhdpIibLinkSetLHeardTime", NHDP_LINK + (1,), "TimeTicks")
NHDP_LINK_SYM_TIME = _obj(M, "nhdpIibLinkSetLSymTime", NHDP_LINK + (2,), "TimeTicks")
NHDP_LINK_PENDING = _obj(M, "nhdpIibLinkSetLPending", NHDP_LINK + (3,), "Integer32", range=(1, 2))
NHDP_LINK_LOST = _obj(M, "nhdpIibLinkSetLLost", NHDP_LINK + (4,), "Integer32", range=(1, 2))
NHDP_LINK_TIME = _obj(M, "nhdpIibLinkSetLTime", NHDP_LINK + (5,), "TimeTicks")
NHDP_2HOP = NHDP_STATE + (5, 1)   # INDEX { nhdpIfIndex, nhdpDiscIfIndex, addrType, addr }
NHDP_2HOP_PREFIX = _obj(M, "nhdpIib2HopSetIpAddrPrefixLen", NHDP_2HOP + (3,), "Unsigned32",
                        range=(0, 2040))
NHDP_2HOP_1HOP_IF = _obj(M, "nhdpIib2HopSet1HopIfIndex", NHDP_2HOP + (4,), "Unsigned32",
                         range=(1, INT32[1]))
NHDP_2HOP_TIME = _obj(M, "nhdpIib2HopSetN2Time", NHDP_2HOP + (5,), "TimeTicks")
NHDP_2HOP_LOST = _obj(M, "nhdpIib2HopSetN2Lost", NHDP_2HOP + (6,), "Integer32", range=(1, 2))
NHDP_NIB_NEIGHBOR = NHDP_STATE + (6, 1)                  # INDEX { nhdpDiscRouterIndex }
NHDP_NIB_SYMMETRIC = _obj(M, "nhdpNibNeighborSetNSymmetric", NHDP_NIB_NEIGHBOR + (1,), "Integer32",
                          range=(1, 2))
NHDP_PERF = NHDP + (3,)
NHDP_DISC_IF_PERF = NHDP_PERF + (2, 1)                   # INDEX { nhdpDiscIfIndex }
NHDP_PERF_RECVD = _obj(M, "nhdpDiscIfRecvdPackets", NHDP_DISC_IF_PERF + (1,), "Counter32")
NHDP_PERF_EXPECTED = _obj(M, "nhdpDiscIfExpectedPackets", NHDP_DISC_IF_PERF + (2,), "Counter32")
NHDP_NEIGHBOR_CHANGES = _obj(M, "nhdpNibNeighborSetChanges", NHDP_PERF + (3,), "Counter32", scalar=True)

# --- OLSRv2-MIB (RFC 7184) ---------------------------------------------------------------
M = "OLSRv2-MIB"
OLSRV2_MIB = (1, 3, 6, 1, 2, 1, 219)
OLSRV2 = OLSRV2_MIB + (1,)                               # olsrv2MIBObjects
OLSRV2_CONFIG = OLSRV2 + (1,)
OLSRV2_ADMIN_STATUS = _obj(M, "olsrv2AdminStatus", OLSRV2_CONFIG + (1,), "Integer32", "read-write",
                           True, (1, 2))
OLSRV2_ORIG_ADDR_TYPE = _obj(M, "olsrv2OrigIpAddrType", OLSRV2_CONFIG + (3,), "Integer32", "read-write",
                             True, (1, 2))
OLSRV2_ORIG_ADDR = _obj(M, "olsrv2OrigIpAddr", OLSRV2_CONFIG + (4,), "OCTET STRING", "read-write", True,
                        (4, 16))
OLSRV2_STATE = OLSRV2 + (2,)
OLSRV2_LINK = OLSRV2_STATE + (1, 1)                      # AUGMENTS { nhdpIibLinkSetEntry }
OLSRV2_LINK_IN_METRIC = _obj(M, "olsrv2IibLinkSetInMetricValue", OLSRV2_LINK + (1,), "Unsigned32",
                             range=(0, MAX_METRIC))
OLSRV2_LINK_OUT_METRIC = _obj(M, "olsrv2IibLinkSetOutMetricValue", OLSRV2_LINK + (2,), "Unsigned32",
                              "read-write", range=(0, MAX_METRIC))
OLSRV2_LINK_MPR_SELECTOR = _obj(M, "olsrv2IibLinkSetMprSelector", OLSRV2_LINK + (3,), "Integer32",
                                range=(1, 2))
OLSRV2_2HOP = OLSRV2_STATE + (2, 1)                      # AUGMENTS { nhdpIib2HopSetEntry }
OLSRV2_2HOP_IN_METRIC = _obj(M, "olsrv2Iib2HopSetInMetricValue", OLSRV2_2HOP + (1,), "Unsigned32",
                             range=(0, MAX_METRIC))
OLSRV2_2HOP_OUT_METRIC = _obj(M, "olsrv2Iib2HopSetOutMetricValue", OLSRV2_2HOP + (2,), "Unsigned32",
                              range=(0, MAX_METRIC))
OLSRV2_NIB = OLSRV2_STATE + (5, 1)                       # AUGMENTS { nhdpNibNeighborSetEntry }
OLSRV2_NIB_ADDR_TYPE = _obj(M, "olsrv2NibNeighborSetNOrigIpAddrType", OLSRV2_NIB + (1,), "Integer32",
                            range=(1, 2))
OLSRV2_NIB_ADDR = _obj(M, "olsrv2NibNeighborSetNOrigIpAddr", OLSRV2_NIB + (2,), "OCTET STRING",
                       range=(4, 16))
OLSRV2_NIB_IN_METRIC = _obj(M, "olsrv2NibNeighborSetNInMetricValue", OLSRV2_NIB + (3,), "Unsigned32",
                            range=(0, MAX_METRIC))
OLSRV2_NIB_OUT_METRIC = _obj(M, "olsrv2NibNeighborSetNOutMetricValue", OLSRV2_NIB + (4,), "Unsigned32",
                             range=(0, MAX_METRIC))
OLSRV2_NIB_WILL_FLOODING = _obj(M, "olsrv2NibNeighborSetNWillFlooding", OLSRV2_NIB + (5,), "Unsigned32",
                                range=(0, 15))
OLSRV2_NIB_WILL_ROUTING = _obj(M, "olsrv2NibNeighborSetNWillRouting", OLSRV2_NIB + (6,), "Unsigned32",
                               range=(0, 15))
OLSRV2_NIB_FLOODING_MPR = _obj(M, "olsrv2NibNeighborSetNFloodingMpr", OLSRV2_NIB + (7,), "Integer32",
                               range=(1, 2))
OLSRV2_NIB_ROUTING_MPR = _obj(M, "olsrv2NibNeighborSetNRoutingMpr", OLSRV2_NIB + (8,), "Integer32",
                              range=(1, 2))
OLSRV2_NIB_MPR_SELECTOR = _obj(M, "olsrv2NibNeighborSetNMprSelector", OLSRV2_NIB + (9,), "Integer32",
                               range=(1, 2))
OLSRV2_NIB_ADVERTISED = _obj(M, "olsrv2NibNeighborSetNAdvertised", OLSRV2_NIB + (10,), "Integer32",
                             range=(1, 2))
OLSRV2_ANSN = _obj(M, "olsrv2NibNeighborSetTableAnsn", OLSRV2_STATE + (6,), "Unsigned32", scalar=True,
                   range=(0, 65535))
OLSRV2_REMOTE = OLSRV2_STATE + (7, 1)                    # INDEX { addrType, addr }
OLSRV2_REMOTE_SEQNO = _obj(M, "olsrv2TibAdRemoteRouterSetMaxSeqNo", OLSRV2_REMOTE + (3,), "Unsigned32",
                           range=(0, 65535))
OLSRV2_REMOTE_EXPIRE = _obj(M, "olsrv2TibAdRemoteRouterSetExpireTime", OLSRV2_REMOTE + (4,), "TimeTicks")
OLSRV2_TOPOLOGY = OLSRV2_STATE + (8, 1)                  # INDEX { fromType, from, toType, to }
OLSRV2_TOPO_SEQNO = _obj(M, "olsrv2TibRouterTopologySetSeqNo", OLSRV2_TOPOLOGY + (5,), "Unsigned32",
                         range=(0, 65535))
OLSRV2_TOPO_METRIC = _obj(M, "olsrv2TibRouterTopologySetMetricValue", OLSRV2_TOPOLOGY + (6,), "Unsigned32",
                          range=(0, MAX_METRIC))
OLSRV2_TOPO_EXPIRE = _obj(M, "olsrv2TibRouterTopologySetExpireTime", OLSRV2_TOPOLOGY + (7,), "TimeTicks")
OLSRV2_ROUTING = OLSRV2_STATE + (11, 1)                  # INDEX { destType, dest, prefixLen }
OLSRV2_ROUTE_NEXT_TYPE = _obj(M, "olsrv2TibRoutingSetNextIfIpAddrType", OLSRV2_ROUTING + (4,), "Integer32",
                              range=(1, 2))
OLSRV2_ROUTE_NEXT = _obj(M, "olsrv2TibRoutingSetNextIfIpAddr", OLSRV2_ROUTING + (5,), "OCTET STRING",
                         range=(4, 16))
OLSRV2_ROUTE_LOCAL_TYPE = _obj(M, "olsrv2TibRoutingSetLocalIfIpAddrType", OLSRV2_ROUTING + (6,),
                               "Integer32", range=(1, 2))
OLSRV2_ROUTE_LOCAL = _obj(M, "olsrv2TibRoutingSetLocalIfIpAddr", OLSRV2_ROUTING + (7,), "OCTET STRING",
                          range=(4, 16))
OLSRV2_ROUTE_DIST = _obj(M, "olsrv2TibRoutingSetDist", OLSRV2_ROUTING + (8,), "Unsigned32", range=(0, 255))
OLSRV2_ROUTE_METRIC = _obj(M, "olsrv2TibRoutingSetMetricValue", OLSRV2_ROUTING + (9,), "Unsigned32",
                           range=(0, 4294901760))
OLSRV2_PERF = OLSRV2 + (3,)
OLSRV2_ROUTE_RECALCS = _obj(M, "olsrv2RoutingSetRecalculationCount", OLSRV2_PERF + (2,), "Counter32",
                            scalar=True)
OLSRV2_MPR_RECALCS = _obj(M, "olsrv2MPRSetRecalculationCount", OLSRV2_PERF + (3,), "Counter32", scalar=True)
WILL_DEFAULT = 7  # RFC 7181

# --- IP-FORWARD-MIB (RFC 4292) -----------------------------------------------------------
M = "IP-FORWARD-MIB"
IP_FORWARD = (1, 3, 6, 1, 2, 1, 4, 24)
INET_CIDR_ROUTE_NUMBER = _obj(M, "inetCidrRouteNumber", IP_FORWARD + (6,), "Gauge32", scalar=True)
INET_CIDR_ROUTE_DISCARDS = _obj(M, "inetCidrRouteDiscards", IP_FORWARD + (8,), "Counter32", scalar=True)
INET_CIDR_ROUTE = IP_FORWARD + (7, 1)   # INDEX { destType, dest, pfxLen, policy, nextHopType, nextHop }
CIDR_IF_INDEX = _obj(M, "inetCidrRouteIfIndex", INET_CIDR_ROUTE + (7,), "Integer32", "read-create",
                     range=(0, INT32[1]))
CIDR_TYPE = _obj(M, "inetCidrRouteType", INET_CIDR_ROUTE + (8,), "Integer32", "read-create", range=(1, 5))
CIDR_PROTO = _obj(M, "inetCidrRouteProto", INET_CIDR_ROUTE + (9,), "Integer32", range=(1, 18))
CIDR_AGE = _obj(M, "inetCidrRouteAge", INET_CIDR_ROUTE + (10,), "Gauge32")
CIDR_NEXT_HOP_AS = _obj(M, "inetCidrRouteNextHopAS", INET_CIDR_ROUTE + (11,), "Unsigned32", "read-create")
CIDR_METRIC1 = _obj(M, "inetCidrRouteMetric1", INET_CIDR_ROUTE + (12,), "Integer32", "read-create")
CIDR_METRIC2 = _obj(M, "inetCidrRouteMetric2", INET_CIDR_ROUTE + (13,), "Integer32", "read-create")
CIDR_METRIC3 = _obj(M, "inetCidrRouteMetric3", INET_CIDR_ROUTE + (14,), "Integer32", "read-create")
CIDR_METRIC4 = _obj(M, "inetCidrRouteMetric4", INET_CIDR_ROUTE + (15,), "Integer32", "read-create")
CIDR_METRIC5 = _obj(M, "inetCidrRouteMetric5", INET_CIDR_ROUTE + (16,), "Integer32", "read-create")
CIDR_STATUS = _obj(M, "inetCidrRouteStatus", INET_CIDR_ROUTE + (17,), "Integer32", "read-create",
                   range=(1, 6))
ZERO_DOT_ZERO = (0, 0)
ROUTE_LOCAL, ROUTE_REMOTE = 3, 4
PROTO_OTHER = 1
ROW_ACTIVE = 1

# --- ERNI-MOBINET-MIB (the product's subtree) --------------------------------------------
# 1.3.6.1.4.1.32473 is IANA's enterprise number for documentation (RFC 5612); a deployment
# with its own PEN changes ERNI_ROOT here, in the client and in the shipped MIB module.
M = "ERNI-MOBINET-MIB"
ERNI_ROOT = (1, 3, 6, 1, 4, 1, 32473)
ERNI = ERNI_ROOT + (1,)                  # erniMobiNetMIB
ERNI_NODE = ERNI + (1,)
ERNI_NODE_NAME = _obj(M, "erniNodeName", ERNI_NODE + (1,), "OCTET STRING", scalar=True, range=(1, 64))
ERNI_NODE_INDEX = _obj(M, "erniNodeIndex", ERNI_NODE + (2,), "Integer32", scalar=True, range=(1, INT32[1]))
ERNI_NODE_ADDRESS = _obj(M, "erniNodeAddress", ERNI_NODE + (3,), "IpAddress", scalar=True)
ERNI_POS_X = _obj(M, "erniPosX", ERNI_NODE + (4,), "Integer32", "read-write", True, INT32)
ERNI_POS_Y = _obj(M, "erniPosY", ERNI_NODE + (5,), "Integer32", "read-write", True, INT32)
ERNI_POS_HEADING = _obj(M, "erniPosHeading", ERNI_NODE + (6,), "Integer32", "read-write", True,
                        (-18000, 18000))
ERNI_POS_UPDATES = _obj(M, "erniPosUpdates", ERNI_NODE + (7,), "Counter32", scalar=True)
ERNI_COMM_RANGE = _obj(M, "erniCommRange", ERNI_NODE + (8,), "Integer32", scalar=True, range=(0, INT32[1]))
ERNI_TOPOLOGY_VERSION = _obj(M, "erniTopologyVersion", ERNI_NODE + (9,), "Counter32", scalar=True)
ERNI_STATE_VERSION = _obj(M, "erniStateVersion", ERNI_NODE + (10,), "Counter32", scalar=True)
ERNI_NODE_TABLE = ERNI + (2, 1, 1)       # erniNodeEntry: INDEX { erniNodesIndex }
ERNI_NODES_NAME = _obj(M, "erniNodesName", ERNI_NODE_TABLE + (2,), "OCTET STRING", range=(1, 64))
ERNI_NODES_ADDRESS = _obj(M, "erniNodesAddress", ERNI_NODE_TABLE + (3,), "IpAddress")
ERNI_POSITION_TABLE = ERNI + (2, 2, 1)   # erniPositionEntry: INDEX { erniNodesIndex }
ERNI_POSITION_X = _obj(M, "erniPositionX", ERNI_POSITION_TABLE + (1,), "Integer32", range=INT32)
ERNI_POSITION_Y = _obj(M, "erniPositionY", ERNI_POSITION_TABLE + (2,), "Integer32", range=INT32)
ERNI_POSITION_HEADING = _obj(M, "erniPositionHeading", ERNI_POSITION_TABLE + (3,), "Integer32",
                             range=(-18000, 18000))
ERNI_POSITION_AGE = _obj(M, "erniPositionAge", ERNI_POSITION_TABLE + (4,), "TimeTicks")
ERNI_LINK_TABLE = ERNI + (3, 1, 1)       # erniLinkEntry: INDEX { erniLinkNeighborIndex }
ERNI_LINK_ADDRESS = _obj(M, "erniLinkAddress", ERNI_LINK_TABLE + (2,), "IpAddress")
ERNI_LINK_QUALITY = _obj(M, "erniLinkQuality", ERNI_LINK_TABLE + (3,), "Gauge32", range=(0, 1000))
ERNI_LINK_SYMMETRIC = _obj(M, "erniLinkSymmetric", ERNI_LINK_TABLE + (4,), "Integer32", range=(1, 2))
ERNI_SIMULATED_NODE = ERNI + (4, 1)      # erniSimulatedNode: this agent's sysObjectID
del M

WRITABLE: dict[OID, str] = {ERNI_POS_X: "x", ERNI_POS_Y: "y", ERNI_POS_HEADING: "heading"}
"""Objects a SET may change (their instance is `.0`) and the position field each sets."""

SYS_OR = (  # sysORTable: what this agent implements
    (SNMP_MIB, "SNMPv2-MIB (RFC 3418): the system and snmp groups"),
    (SNMP_MPD_MIB, "SNMP-MPD-MIB (RFC 3412): message processing statistics"),
    (NHDP_MIB, "NHDP-MIB (RFC 7939): state and neighbour performance of NHDP"),
    (OLSRV2_MIB, "OLSRv2-MIB (RFC 7184): state and recalculation counters of OLSRv2"),
    (IP_FORWARD, "IP-FORWARD-MIB (RFC 4292): the inetCidrRouteTable"),
    (ERNI, "ERNI-MOBINET-MIB: node identity, reported positions, link quality"),
)
SYS_SERVICES_VALUE = 4 + 8 + 64  # internet (a router), end-to-end and application layers


# --- values --------------------------------------------------------------------------------

class NodeContext(Protocol):
    """What a value computed at read time may ask of the node serving it."""

    def uptime(self) -> int:
        """sysUpTime now (hundredths of a second since the node's agent started)."""
        ...

    def stamp(self, when: float) -> int:
        """The sysUpTime value at network-clock time `when` (0 before the agent started)."""
        ...

    def now(self) -> float:
        """The network clock now (s)."""
        ...

    def counter(self, name: str) -> int:
        """One of the node's SNMP counters (SNMP_COUNTERS names)."""
        ...


Raw = int | str | bytes | tuple[int, ...]
Dynamic = Callable[[NodeContext], Raw]
Row = tuple[OID, Kind, Raw | Dynamic]
"""One served instance: its OID, the BER kind of its value, and the value (or how to compute it)."""


def resolve(value: Raw | Dynamic, ctx: NodeContext) -> Raw:
    """The value as served now (a callable one is computed from the serving node)."""
    return value(ctx) if callable(value) else value


@functools.lru_cache(maxsize=4096)
def _addr(address: str) -> bytes:
    return ipaddress.IPv4Address(address).packed


@functools.lru_cache(maxsize=4096)
def inet_index(address: str) -> tuple[int, ...]:
    """`InetAddressType, InetAddress` as an index: ipv4(1), length 4, the four octets."""
    return (1, 4) + tuple(_addr(address))


def _mm(metres: float) -> int:
    return max(INT32[0], min(INT32[1], round(metres * 1000)))


def _cdeg(degrees: float) -> int:
    return round(((degrees + 180.0) % 360.0 - 180.0) * 100)


class _Rows:
    """Collects rows, typing each value from its object's declared SYNTAX."""

    def __init__(self) -> None:
        self.rows: list[Row] = []

    def add(self, column: OID, index: tuple[int, ...], value: Raw | Dynamic) -> None:
        self.rows.append((column + index, KIND[column], value))

    def scalar(self, obj: OID, value: Raw | Dynamic) -> None:
        self.add(obj, (0,), value)


def _since_grid(start: float, period: float, now: float) -> float:
    """The last tick of a `period` grid started at `start`, at or before `now`."""
    return start + math.floor(max(0.0, now - start) / period) * period


def _tc_expire(ctx: NodeContext) -> int:
    """When the topology learned from the last TC expires (TCs every TC_INTERVAL)."""
    now = ctx.now()
    return ctx.stamp(_since_grid(0.0, TC_INTERVAL, now) + T_HOLD_TIME)


def topology_rows(view: NodeView) -> list[Row]:
    """The OLSRv2 Router Topology Set of the node's component, sorted (the same for every member).

    A member serves it without the links it advertises itself (`own_topology_range`).
    """
    index = {n.name: n for n in view.known_nodes}
    out = _Rows()
    for a, b, metric in view.topology:
        idx = inet_index(index[a].address) + inet_index(index[b].address)
        out.add(OLSRV2_TOPO_SEQNO, idx, view.ansn.get(a, 0) % 65536)
        out.add(OLSRV2_TOPO_METRIC, idx, metric)
        out.add(OLSRV2_TOPO_EXPIRE, idx, _tc_expire)
    out.rows.sort()   # by OID: OIDs are unique, so values are never compared
    return out.rows


def own_topology_prefixes(view: NodeView) -> list[OID]:
    """Prefixes of the topology rows a node leaves out: the links it advertises itself."""
    own = inet_index(view.node.address)
    return [col + own for col in (OLSRV2_TOPO_SEQNO, OLSRV2_TOPO_METRIC, OLSRV2_TOPO_EXPIRE)]


def build_table(view: NodeView, net: ManetNetwork, with_topology: bool = True) -> list[Row]:
    """Every OID the node serves, sorted, with its value (without the shared topology set if asked)."""
    out = _Rows()
    _system(out, view)
    _erni(out, view, net)
    _nhdp(out, view, net)
    _olsrv2(out, view)
    _ip_forward(out, view)
    rows = out.rows
    if with_topology:
        own = own_topology_prefixes(view)
        rows.extend(r for r in topology_rows(view) if not any(r[0][:len(p)] == p for p in own))
    rows.sort()   # by OID: OIDs are unique, so values are never compared
    return rows


def _system(out: _Rows, view: NodeView) -> None:
    me = view.node
    out.scalar(SYS_DESCR, f"ERNI simulated MANET node {me.name} ({me.address}): NHDP/OLSRv2 model")
    out.scalar(SYS_OBJECT_ID, ERNI_SIMULATED_NODE)
    out.scalar(SYS_UP_TIME, lambda ctx: ctx.uptime())
    out.scalar(SYS_CONTACT, "")
    out.scalar(SYS_NAME, me.name)
    out.scalar(SYS_LOCATION, "simulated MANET")
    out.scalar(SYS_SERVICES, SYS_SERVICES_VALUE)
    out.scalar(SYS_OR_LAST_CHANGE, 0)
    for i, (oid, descr) in enumerate(SYS_OR, start=1):
        out.add(SYS_OR_ID, (i,), oid)
        out.add(SYS_OR_DESCR, (i,), descr)
        out.add(SYS_OR_UP_TIME, (i,), 0)
    for name, oid in SNMP_COUNTERS.items():
        out.scalar(oid, functools.partial(_counter, name))
    out.scalar(SNMP_ENABLE_AUTHEN_TRAPS, 2)  # disabled: the agent sends no notifications


def _counter(name: str, ctx: NodeContext) -> int:
    return ctx.counter(name) % 2**32


def _erni(out: _Rows, view: NodeView, net: ManetNetwork) -> None:
    """ERNI-MANET-MIB rows. Positions, their ages, the update count and the state version are read
    live from the network, so a position report changes what is served without rebuilding rows."""
    me = view.node
    out.scalar(ERNI_NODE_NAME, me.name)
    out.scalar(ERNI_NODE_INDEX, me.index)
    out.scalar(ERNI_NODE_ADDRESS, me.address)
    out.scalar(ERNI_POS_X, functools.partial(_position, net, me.name, me.name, "x"))
    out.scalar(ERNI_POS_Y, functools.partial(_position, net, me.name, me.name, "y"))
    out.scalar(ERNI_POS_HEADING, functools.partial(_position, net, me.name, me.name, "heading"))
    out.scalar(ERNI_POS_UPDATES, lambda ctx: net.position_updates(me.name) % 2**32)
    out.scalar(ERNI_COMM_RANGE, _mm(net.radio.comm_range))
    out.scalar(ERNI_TOPOLOGY_VERSION, view.topology_version % 2**32)
    out.scalar(ERNI_STATE_VERSION, lambda ctx: net.version % 2**32)
    for node in view.known_nodes:
        idx = (node.index,)
        out.add(ERNI_NODES_NAME, idx, node.name)
        out.add(ERNI_NODES_ADDRESS, idx, node.address)
        if node.name in view.positions:   # the rows stand once known: positions are never forgotten
            for column, field in ((ERNI_POSITION_X, "x"), (ERNI_POSITION_Y, "y"),
                                  (ERNI_POSITION_HEADING, "heading"), (ERNI_POSITION_AGE, "age")):
                out.add(column, idx, functools.partial(_position, net, me.name, node.name, field))
    for nb in view.neighbors:
        idx = (nb.index,)
        out.add(ERNI_LINK_ADDRESS, idx, nb.address)
        out.add(ERNI_LINK_QUALITY, idx, round(nb.quality * 1000))
        out.add(ERNI_LINK_SYMMETRIC, idx, TRUE if nb.symmetric else FALSE)


def _position(net: ManetNetwork, name: str, origin: str, field: str, ctx: NodeContext) -> int:
    """One field of the newest position of `origin` known to `name`, as served (0: none known)."""
    pos = net.known_position(name, origin)
    if pos is None:
        return 0
    if field == "x":
        return _mm(pos.x)
    if field == "y":
        return _mm(pos.y)
    if field == "heading":
        return _cdeg(pos.heading)
    return min(UINT32_MAX, int(max(0.0, ctx.now() - pos.reported) * 100))


def _hello_expiry(since: float | None, hold: float, ctx: NodeContext) -> int:
    """When a tuple refreshed by HELLOs (every HELLO_INTERVAL since `since`) expires."""
    if since is None:
        return 0
    return ctx.stamp(_since_grid(since, HELLO_INTERVAL, ctx.now()) + hold)


def _nhdp(out: _Rows, view: NodeView, net: ManetNetwork) -> None:
    me = view.node
    out.scalar(NHDP_UP_TIME, 0)                 # NHDP starts with the agent
    out.add(NHDP_IF_STATE_UP_TIME, (IF_INDEX,), 0)
    out.scalar(NHDP_NEIGHBOR_CHANGES, view.counters.neighbor_changes % 2**32)
    index = {n.name: n for n in view.known_nodes}
    sym_of: dict[str, dict[str, int]] = {}
    for a, b, metric in view.topology:
        sym_of.setdefault(a, {})[b] = metric
    for nb in view.neighbors:
        i = nb.index
        since = net.link_since(me.name, nb.name)
        heard = functools.partial(_hello_expiry, since, L_HOLD_TIME)
        out.add(NHDP_DISC_IF_INDEX, (i,), i)
        out.add(NHDP_DISC_ROUTER_INDEX, (i,), i)
        out.add(NHDP_DISC_IF_ADDR_TYPE, (i,), 1)
        out.add(NHDP_DISC_IF_ADDR, (i,), _addr(nb.address))
        out.add(NHDP_DISC_IF_PREFIX, (i,), 32)
        link = (IF_INDEX, i)
        out.add(NHDP_LINK_HEARD_TIME, link, heard)
        out.add(NHDP_LINK_SYM_TIME, link, heard if nb.symmetric else 0)
        out.add(NHDP_LINK_PENDING, link, FALSE)
        out.add(NHDP_LINK_LOST, link, FALSE if nb.symmetric else TRUE)
        out.add(NHDP_LINK_TIME, link, heard)
        out.add(NHDP_NIB_SYMMETRIC, (i,), TRUE if nb.symmetric else FALSE)
        out.add(NHDP_PERF_RECVD, (i,), functools.partial(_hellos, net, me.name, nb.name, 0))
        out.add(NHDP_PERF_EXPECTED, (i,), functools.partial(_hellos, net, me.name, nb.name, 1))
        if not nb.symmetric:
            continue
        two_hop_time = functools.partial(_hello_expiry, since, H_HOLD_TIME)
        for other, metric in sorted(sym_of.get(nb.name, {}).items()):
            if other == me.name:
                continue
            idx = link + inet_index(index[other].address)
            out.add(NHDP_2HOP_PREFIX, idx, 32)
            out.add(NHDP_2HOP_1HOP_IF, idx, i)
            out.add(NHDP_2HOP_TIME, idx, two_hop_time)
            out.add(NHDP_2HOP_LOST, idx, FALSE)
            out.add(OLSRV2_2HOP_IN_METRIC, idx, sym_of.get(other, {}).get(nb.name, metric))
            out.add(OLSRV2_2HOP_OUT_METRIC, idx, metric)


def _hellos(net: ManetNetwork, name: str, neighbor: str, which: int, ctx: NodeContext) -> int:
    return net.hello_counts(name, neighbor)[which] % 2**32


def _olsrv2(out: _Rows, view: NodeView) -> None:
    me = view.node
    out.scalar(OLSRV2_ADMIN_STATUS, 1)
    out.scalar(OLSRV2_ORIG_ADDR_TYPE, 1)
    out.scalar(OLSRV2_ORIG_ADDR, _addr(me.address))
    out.scalar(OLSRV2_ANSN, view.counters.ansn % 65536)
    out.scalar(OLSRV2_ROUTE_RECALCS, view.counters.route_recalcs % 2**32)
    out.scalar(OLSRV2_MPR_RECALCS, view.counters.mpr_recalcs % 2**32)
    for nb in view.neighbors:
        i = nb.index
        truth = TRUE if nb.symmetric else FALSE
        neighbor_metric = nb.metric if nb.symmetric else MAX_METRIC
        link = (IF_INDEX, i)
        out.add(OLSRV2_LINK_IN_METRIC, link, nb.metric)
        out.add(OLSRV2_LINK_OUT_METRIC, link, nb.metric)
        out.add(OLSRV2_LINK_MPR_SELECTOR, link, truth)
        out.add(OLSRV2_NIB_ADDR_TYPE, (i,), 1)
        out.add(OLSRV2_NIB_ADDR, (i,), _addr(nb.address))
        out.add(OLSRV2_NIB_IN_METRIC, (i,), neighbor_metric)
        out.add(OLSRV2_NIB_OUT_METRIC, (i,), neighbor_metric)
        out.add(OLSRV2_NIB_WILL_FLOODING, (i,), WILL_DEFAULT)
        out.add(OLSRV2_NIB_WILL_ROUTING, (i,), WILL_DEFAULT)
        out.add(OLSRV2_NIB_FLOODING_MPR, (i,), truth)
        out.add(OLSRV2_NIB_ROUTING_MPR, (i,), truth)
        out.add(OLSRV2_NIB_MPR_SELECTOR, (i,), truth)
        out.add(OLSRV2_NIB_ADVERTISED, (i,), truth)
    index = {n.name: n for n in view.known_nodes}
    advertisers = {a for a, _, _ in view.topology} - {me.name}
    for name in advertisers:
        idx = inet_index(index[name].address)
        out.add(OLSRV2_REMOTE_SEQNO, idx, view.ansn.get(name, 0) % 65536)
        out.add(OLSRV2_REMOTE_EXPIRE, idx, _tc_expire)
    for dest, route in view.routes.items():
        hop = index[route.next_hop]
        idx = inet_index(index[dest].address) + (32,)
        out.add(OLSRV2_ROUTE_NEXT_TYPE, idx, 1)
        out.add(OLSRV2_ROUTE_NEXT, idx, _addr(hop.address))
        out.add(OLSRV2_ROUTE_LOCAL_TYPE, idx, 1)
        out.add(OLSRV2_ROUTE_LOCAL, idx, _addr(me.address))
        out.add(OLSRV2_ROUTE_DIST, idx, min(255, route.hops))
        out.add(OLSRV2_ROUTE_METRIC, idx, min(4294901760, round(route.cost)))


def _ip_forward(out: _Rows, view: NodeView) -> None:
    index = {n.name: n for n in view.known_nodes}
    out.scalar(INET_CIDR_ROUTE_NUMBER, len(view.routes))
    out.scalar(INET_CIDR_ROUTE_DISCARDS, 0)   # the simulated router never discards a valid route
    age = functools.partial(_route_age, view.counters.routes_at)
    for dest, route in view.routes.items():
        local = route.hops == 1  # the next hop is the destination itself
        next_hop: tuple[int, ...] = (0, 0) if local else inet_index(index[route.next_hop].address)
        idx = inet_index(index[dest].address) + (32, len(ZERO_DOT_ZERO)) + ZERO_DOT_ZERO + next_hop
        out.add(CIDR_IF_INDEX, idx, IF_INDEX)
        out.add(CIDR_TYPE, idx, ROUTE_LOCAL if local else ROUTE_REMOTE)
        out.add(CIDR_PROTO, idx, PROTO_OTHER)
        out.add(CIDR_AGE, idx, age)
        out.add(CIDR_NEXT_HOP_AS, idx, 0)
        out.add(CIDR_METRIC1, idx, min(INT32[1], round(route.cost)))
        for col in (CIDR_METRIC2, CIDR_METRIC3, CIDR_METRIC4, CIDR_METRIC5):
            out.add(col, idx, -1)
        out.add(CIDR_STATUS, idx, ROW_ACTIVE)


def _route_age(routes_at: float, ctx: NodeContext) -> int:
    return min(UINT32_MAX, int(max(0.0, ctx.now() - routes_at)))


def parse_position_write(current: tuple[float, float, float],
                         writes: dict[str, int]) -> tuple[float, float, float]:
    """Apply SET values (mm, mm, centidegrees) to the current (x m, y m, heading deg)."""
    x, y, heading = current
    if "x" in writes:
        x = writes["x"] / 1000.0
    if "y" in writes:
        y = writes["y"] / 1000.0
    if "heading" in writes:
        heading = writes["heading"] / 100.0
    return x, y, heading


def names(oids: Iterable[OID]) -> list[str]:
    """`module::name.index` of each OID (for messages and tests)."""
    found = []
    for oid in oids:
        obj = object_of(oid)
        found.append(f"{obj.module}::{obj.name}" + "".join(f".{a}" for a in oid[len(obj.oid):])
                     if obj else ".".join(map(str, oid)))
    return found
