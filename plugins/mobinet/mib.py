"""OIDs MobiNet reads and writes: NHDP-MIB, OLSRv2-MIB, IP-FORWARD-MIB subsets and the ERNI subtree.

Numeric OIDs only (pysnmp ships none of these MIBs). Units of the ERNI subtree: positions in
millimetres, headings in centidegrees, link quality in thousandths; OLSRv2 link metrics are
ETX scaled by `METRIC_UNIT` (a loss-free link costs 1024).
"""

from __future__ import annotations

OID = tuple[int, ...]

METRIC_UNIT = 1024

NHDP = (1, 3, 6, 1, 2, 1, 213, 1)
NHDP_DISC_IF_ADDR = NHDP + (2, 3, 1, 4)          # .<nbr>  OCTET STRING (4): neighbour address
NHDP_NIB_SYMMETRIC = NHDP + (2, 6, 1, 1)         # .<nbr>  TruthValue: symmetric neighbour
NHDP_PERF_RECVD = NHDP + (3, 2, 1, 1)            # .<nbr>  Counter32: HELLOs received
NHDP_PERF_EXPECTED = NHDP + (3, 2, 1, 2)         # .<nbr>  Counter32: HELLOs expected
OLSRV2 = (1, 3, 6, 1, 2, 1, 219, 1)
OLSRV2_LINK_IN_METRIC = OLSRV2 + (2, 1, 1, 1)    # .<ifIndex>.<nbr>  Unsigned32
OLSRV2_TOPO_FROM = OLSRV2 + (2, 8, 1, 2)         # .<from>.<to>  OCTET STRING (4)
OLSRV2_TOPO_TO = OLSRV2 + (2, 8, 1, 4)           # .<from>.<to>  OCTET STRING (4)
OLSRV2_TOPO_METRIC = OLSRV2 + (2, 8, 1, 6)       # .<from>.<to>  Unsigned32
OLSRV2_ROUTE_NEXT_HOP = OLSRV2 + (2, 11, 1, 5)   # .1.4.<a.b.c.d>.32  OCTET STRING (4)
OLSRV2_ROUTE_DIST = OLSRV2 + (2, 11, 1, 8)       # .1.4.<a.b.c.d>.32  Unsigned32 hops
OLSRV2_ROUTE_METRIC = OLSRV2 + (2, 11, 1, 9)     # .1.4.<a.b.c.d>.32  Unsigned32 path cost
INET_CIDR_METRIC1 = (1, 3, 6, 1, 2, 1, 4, 24, 7, 1, 12)  # Integer32 path cost (fallback)

ERNI = (1, 3, 6, 1, 4, 1, 32473, 1)
ERNI_NODE_NAME = ERNI + (1, 1, 0)                # OCTET STRING
ERNI_NODE_ADDRESS = ERNI + (1, 3, 0)             # IpAddress
ERNI_POS_X = ERNI + (1, 4, 0)                    # Integer32 mm, read-write
ERNI_POS_Y = ERNI + (1, 5, 0)                    # Integer32 mm, read-write
ERNI_POS_HEADING = ERNI + (1, 6, 0)              # Integer32 centidegrees, read-write
ERNI_TOPOLOGY_VERSION = ERNI + (1, 9, 0)         # Counter32: changes when links/routes may have
ERNI_STATE_VERSION = ERNI + (1, 10, 0)           # Counter32: changes when anything may have
ERNI_NODES_NAME = ERNI + (2, 1, 2)               # .<node>  OCTET STRING
ERNI_NODES_ADDRESS = ERNI + (2, 1, 3)            # .<node>  IpAddress
ERNI_NODES_X = ERNI + (2, 1, 4)                  # .<node>  Integer32 mm
ERNI_NODES_Y = ERNI + (2, 1, 5)                  # .<node>  Integer32 mm
ERNI_NODES_HEADING = ERNI + (2, 1, 6)            # .<node>  Integer32 centidegrees
ERNI_LINK_QUALITY = ERNI + (3, 1, 3)             # .<nbr>  Gauge32 thousandths

NAMES: dict[OID, str] = {
    NHDP_DISC_IF_ADDR: "nhdpDiscIfSetIpAddr", NHDP_NIB_SYMMETRIC: "nhdpNibNeighborSetSymmetric",
    NHDP_PERF_RECVD: "nhdpDiscIfRecvdPackets", NHDP_PERF_EXPECTED: "nhdpDiscIfExpectedPackets",
    OLSRV2_LINK_IN_METRIC: "olsrv2IibLinkSetInMetric", OLSRV2_TOPO_FROM: "olsrv2TibRouterTopologySetFromOrigAddr",
    OLSRV2_TOPO_TO: "olsrv2TibRouterTopologySetToOrigAddr",
    OLSRV2_TOPO_METRIC: "olsrv2TibRouterTopologySetMetricValue",
    OLSRV2_ROUTE_NEXT_HOP: "olsrv2TibRoutingSetNextIfAddr", OLSRV2_ROUTE_DIST: "olsrv2TibRoutingSetDist",
    OLSRV2_ROUTE_METRIC: "olsrv2TibRoutingSetMetricValue", INET_CIDR_METRIC1: "inetCidrRouteMetric1",
    ERNI_NODE_NAME: "erniNodeName", ERNI_NODE_ADDRESS: "erniNodeAddress", ERNI_POS_X: "erniPosX",
    ERNI_POS_Y: "erniPosY", ERNI_POS_HEADING: "erniPosHeading",
    ERNI_TOPOLOGY_VERSION: "erniTopologyVersion", ERNI_STATE_VERSION: "erniStateVersion", ERNI_NODES_NAME: "erniNodesName",
    ERNI_NODES_ADDRESS: "erniNodesAddress", ERNI_NODES_X: "erniNodesX", ERNI_NODES_Y: "erniNodesY",
    ERNI_NODES_HEADING: "erniNodesHeading", ERNI_LINK_QUALITY: "erniLinkQuality",
}


def label(oid: OID) -> str:
    """`name.index` for a known column or scalar, else the dotted OID."""
    for n in range(len(oid), 0, -1):
        name = NAMES.get(oid[:n])
        if name:
            rest = ".".join(map(str, oid[n:]))
            return f"{name}.{rest}" if rest else name
    return ".".join(map(str, oid))


def dotted(oid: OID) -> str:
    """The OID as `1.3.6...`."""
    return ".".join(map(str, oid))
