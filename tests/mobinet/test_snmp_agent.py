"""The simulated MANET's SNMP agent over real UDP: RFC 3416 operations and errors checked with
net-snmp's command-line tools (numeric OIDs, no MIB loaded), RFC 3412/3418 drops and counters,
read/write communities, and the fast BER encoder against pyasn1."""

from __future__ import annotations

import os
import re
import shutil
import socket
import struct
import subprocess

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyasn1.codec.ber import decoder, encoder
from pysnmp.proto.api import v1 as pv1
from pysnmp.proto.api import v2c

import erni.plugins.mobinet.snmp as client_mib
import erni.sim.manet_mib as agent_mib
from erni.blackboard.testing import wait_until
from erni.sim.manet import link_metric
from erni.sim.snmp_agent import ManetSnmpAgent
from tests.mobinet.conftest import WRITE, line_network

pytestmark = pytest.mark.skipif(shutil.which("snmpget") is None,
                                reason="net-snmp tools (Debian package 'snmp') not installed")

LINE_RE = re.compile(r"^(\.[\d.]+) = (?:([\w-]+): )?(.*)$")
ERNI = "1.3.6.1.4.1.32473.1"
SNMP_GROUP = "1.3.6.1.2.1.11"
UNKNOWN_PDU_HANDLERS = "1.3.6.1.6.3.11.2.1.3.0"


def snmp(tool: str, address: tuple[str, int], *args: str, version: str = "2c",
         community: str = "public") -> subprocess.CompletedProcess:
    host, port = address
    cmd = [tool, f"-v{version}", "-c", community, "-On", "-Ot", "-m", "", "-t", "1", "-r", "0",
           f"udp:{host}:{port}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=20)


def parse(out: str) -> dict[str, tuple[str, str]]:
    rows = {}
    for line in out.splitlines():
        m = LINE_RE.match(line.strip())
        if m:
            rows[m.group(1).lstrip(".")] = (m.group(2) or "", m.group(3).strip().strip('"'))
    return rows


def counter(address: tuple[str, int], oid: str) -> int:
    return int(parse(snmp("snmpget", address, oid).stdout)[oid][1])


def test_client_and_agent_agree_on_every_oid():
    for name in ("ERNI", "ERNI_NODE_NAME", "ERNI_NODE_ADDRESS", "ERNI_POS_X", "ERNI_POS_Y",
                 "ERNI_POS_HEADING", "ERNI_TOPOLOGY_VERSION", "ERNI_STATE_VERSION", "NHDP", "OLSRV2",
                 "NHDP_DISC_IF_INDEX", "NHDP_DISC_ROUTER_INDEX", "NHDP_DISC_IF_ADDR_TYPE", "NHDP_DISC_IF_ADDR",
                 "NHDP_NIB_SYMMETRIC", "NHDP_PERF_RECVD", "NHDP_PERF_EXPECTED", "NHDP_UP_TIME",
                 "OLSRV2_ORIG_ADDR", "OLSRV2_ORIG_ADDR_TYPE", "OLSRV2_ANSN", "OLSRV2_NIB_ADDR",
                 "OLSRV2_NIB_IN_METRIC", "OLSRV2_NIB_OUT_METRIC", "OLSRV2_TOPO_METRIC",
                 "OLSRV2_ROUTE_NEXT_TYPE", "OLSRV2_ROUTE_NEXT", "OLSRV2_ROUTE_DIST", "OLSRV2_ROUTE_METRIC",
                 "INET_CIDR_ROUTE_NUMBER", "ERNI_NODES_NAME", "ERNI_NODES_ADDRESS", "ERNI_POSITION_X",
                 "ERNI_POSITION_Y", "ERNI_POSITION_HEADING", "ERNI_LINK_QUALITY", "SYS_NAME"):
        client, agent = getattr(client_mib, name), getattr(agent_mib, name)
        scalar = agent in agent_mib.OBJECTS and agent_mib.OBJECTS[agent].scalar
        assert client == (agent + (0,) if scalar else agent), name
    assert client_mib.INET_CIDR_TYPE == agent_mib.CIDR_TYPE
    assert client_mib.INET_CIDR_METRIC1 == agent_mib.CIDR_METRIC1
    assert client_mib.INET_CIDR_STATUS == agent_mib.CIDR_STATUS
    assert client_mib.METRIC_UNIT == 1024


def test_snmpget_scalars(served, net):
    res = snmp("snmpget", served["robot2"], f"{ERNI}.1.1.0", f"{ERNI}.1.2.0", f"{ERNI}.1.3.0",
               f"{ERNI}.1.4.0", f"{ERNI}.1.8.0", "1.3.6.1.2.1.1.5.0", "1.3.6.1.2.1.1.2.0",
               "1.3.6.1.2.1.4.24.6.0")
    assert res.returncode == 0, res.stderr
    rows = parse(res.stdout)
    assert rows[f"{ERNI}.1.1.0"] == ("STRING", "robot2")
    assert rows[f"{ERNI}.1.2.0"] == ("INTEGER", "2")
    assert rows[f"{ERNI}.1.3.0"] == ("IpAddress", "10.0.0.2")
    assert rows[f"{ERNI}.1.4.0"] == ("INTEGER", "60000")
    assert rows[f"{ERNI}.1.8.0"] == ("INTEGER", "100000")
    assert rows["1.3.6.1.2.1.1.5.0"] == ("STRING", "robot2")                 # sysName
    assert rows["1.3.6.1.2.1.1.2.0"] == ("OID", f".{ERNI}.4.1")              # sysObjectID
    assert rows["1.3.6.1.2.1.4.24.6.0"] == ("Gauge32", "4")                  # inetCidrRouteNumber


def test_sysuptime_counts_from_when_the_node_was_served(snmp_agent):
    address = snmp_agent.addresses()["robot1"]
    first = counter(address, "1.3.6.1.2.1.1.3.0")
    second = wait_until(lambda: (c := counter(address, "1.3.6.1.2.1.1.3.0")) > first and c, timeout=5, interval=0.05)
    assert 0 <= first < second < first + 1000


def test_routes_in_the_documented_index_layouts(served, net):
    rows = parse(snmp("snmpwalk", served["robot1"], "1.3.6.1.2.1.219.1.2.11").stdout)
    # olsrv2TibRoutingSetMetricValue to 10.0.0.5/32: { ipv4(1), 4 octets, prefix 32 }
    assert rows["1.3.6.1.2.1.219.1.2.11.1.9.1.4.10.0.0.5.32"] == ("Gauge32", str(4 * link_metric(0.8)))
    assert rows["1.3.6.1.2.1.219.1.2.11.1.8.1.4.10.0.0.5.32"] == ("Gauge32", "4")
    assert rows["1.3.6.1.2.1.219.1.2.11.1.4.1.4.10.0.0.5.32"] == ("INTEGER", "1")   # NextIfIpAddrType ipv4
    assert rows["1.3.6.1.2.1.219.1.2.11.1.5.1.4.10.0.0.5.32"][1].split() == ["0A", "00", "00", "02"]
    assert rows["1.3.6.1.2.1.219.1.2.11.1.7.1.4.10.0.0.5.32"][1].split() == ["0A", "00", "00", "01"]
    assert not any(k.startswith("1.3.6.1.2.1.219.1.2.11.1.1.") for k in rows)   # index columns: not-accessible
    assert len([k for k in rows if k.startswith("1.3.6.1.2.1.219.1.2.11.1.9.")]) == 4
    cidr = parse(snmp("snmpbulkwalk", served["robot1"], "1.3.6.1.2.1.4.24.7.1").stdout)
    remote = "1.4.10.0.0.3.32.2.0.0.1.4.10.0.0.2"   # dest, prefix, zeroDotZero, next hop
    local = "1.4.10.0.0.2.32.2.0.0.0.0"             # a neighbour: next hop unknown(0), ""
    assert {c for c in range(1, 18) if any(k.startswith(f"1.3.6.1.2.1.4.24.7.1.{c}.") for k in cidr)} \
        == set(range(7, 18))                         # every accessible column, no index column
    assert cidr[f"1.3.6.1.2.1.4.24.7.1.12.{remote}"] == ("INTEGER", str(2 * link_metric(0.8)))
    assert cidr[f"1.3.6.1.2.1.4.24.7.1.8.{remote}"] == ("INTEGER", "4")     # remote
    assert cidr[f"1.3.6.1.2.1.4.24.7.1.8.{local}"] == ("INTEGER", "3")      # local
    assert cidr[f"1.3.6.1.2.1.4.24.7.1.13.{local}"] == ("INTEGER", "-1")    # Metric2: not used
    assert cidr[f"1.3.6.1.2.1.4.24.7.1.17.{local}"] == ("INTEGER", "1")     # active


def test_neighbour_tables_follow_the_rfc_layouts(served, net):
    rows = parse(snmp("snmpwalk", served["robot3"], "1.3.6.1.2.1.213.1").stdout)
    for n in (2, 4):   # nhdpDiscIfSetTable: IfIndex, RouterIndex Unsigned32, type, address, prefix
        assert rows[f"1.3.6.1.2.1.213.1.2.3.1.2.{n}"] == ("Gauge32", str(n))
        assert rows[f"1.3.6.1.2.1.213.1.2.3.1.3.{n}"] == ("Gauge32", str(n))
        assert rows[f"1.3.6.1.2.1.213.1.2.3.1.4.{n}"] == ("INTEGER", "1")
        assert rows[f"1.3.6.1.2.1.213.1.2.3.1.5.{n}"][1].split() == ["0A", "00", "00", f"0{n}"]
        assert rows[f"1.3.6.1.2.1.213.1.2.3.1.6.{n}"] == ("Gauge32", "32")
        assert rows[f"1.3.6.1.2.1.213.1.2.6.1.1.{n}"] == ("INTEGER", "1")   # N_symmetric
        assert rows[f"1.3.6.1.2.1.213.1.2.4.1.4.1.{n}"] == ("INTEGER", "2")  # link set (ifIndex 1): not lost
    assert "1.3.6.1.2.1.213.1.2.6.1.1.1" not in rows                         # robot1 out of range
    # the 2-hop set: robot1 through robot2, robot5 through robot4
    assert rows["1.3.6.1.2.1.213.1.2.5.1.4.1.2.1.4.10.0.0.1"] == ("Gauge32", "2")
    assert rows["1.3.6.1.2.1.213.1.2.5.1.4.1.4.1.4.10.0.0.5"] == ("Gauge32", "4")
    assert rows["1.3.6.1.2.1.213.1.3.2.1.1.4"][0] == "Counter32"
    topo = parse(snmp("snmpbulkwalk", served["robot3"], "1.3.6.1.2.1.219.1.2.8.1.6").stdout)
    # four links, both directions, less the two robot3 advertises itself
    assert len(topo) == 6
    assert topo["1.3.6.1.2.1.219.1.2.8.1.6.1.4.10.0.0.4.1.4.10.0.0.5"] == ("Gauge32", str(link_metric(0.8)))
    assert not any(k.startswith("1.3.6.1.2.1.219.1.2.8.1.6.1.4.10.0.0.3.") for k in topo)
    erni = parse(snmp("snmpwalk", served["robot3"], f"{ERNI}.3").stdout)
    assert erni[f"{ERNI}.3.1.1.3.2"] == ("Gauge32", "800")
    assert erni[f"{ERNI}.3.1.1.2.4"] == ("IpAddress", "10.0.0.4")
    nodes = parse(snmp("snmpwalk", served["robot3"], f"{ERNI}.2.1.1.2").stdout)
    assert sorted(v for _, v in nodes.values()) == [f"robot{i}" for i in range(1, 6)]


def test_snmpset_with_the_write_community_reports_the_position(served, net):
    res = snmp("snmpset", served["robot2"], f"{ERNI}.1.4.0", "i", "61500", f"{ERNI}.1.5.0", "i", "-2500",
               f"{ERNI}.1.6.0", "i", "9000", community=WRITE)
    assert res.returncode == 0, res.stderr
    known = net.view("robot5").positions["robot2"]
    assert (known.x, known.y, known.heading) == (61.5, -2.5, 90.0)
    rows = parse(snmp("snmpget", served["robot4"], f"{ERNI}.2.2.1.1.2", f"{ERNI}.2.2.1.2.2").stdout)
    assert rows[f"{ERNI}.2.2.1.1.2"] == ("INTEGER", "61500")
    assert rows[f"{ERNI}.2.2.1.2.2"] == ("INTEGER", "-2500")


def test_the_read_community_cannot_set(snmp_agent, net):
    address = snmp_agent.addresses()["robot2"]
    res = snmp("snmpset", address, f"{ERNI}.1.4.0", "i", "1")
    assert res.returncode != 0 and "noAccess" in res.stdout + res.stderr
    res = snmp("snmpset", address, f"{ERNI}.1.4.0", "i", "1", version="1")
    assert res.returncode != 0 and "noSuchName" in res.stdout + res.stderr
    assert net.view("robot2").positions["robot2"].x == 60.0
    assert counter(address, f"{SNMP_GROUP}.5.0") == 2                  # snmpInBadCommunityUses
    agent = ManetSnmpAgent(net).start()                                # no write community at all
    try:
        res = snmp("snmpset", agent.serve("robot1"), f"{ERNI}.1.4.0", "i", "1")
        assert "noAccess" in res.stdout + res.stderr
    finally:
        agent.close()
    with pytest.raises(ValueError, match="write community must be non-empty and differ"):
        ManetSnmpAgent(net, read_community="same", write_community="same")


def test_snmpset_errors_are_reported_and_change_nothing(served, net):
    address = served["robot2"]

    def set_(*args: str, version: str = "2c") -> str:
        res = snmp("snmpset", address, *args, community=WRITE, version=version)
        assert res.returncode != 0
        return res.stdout + res.stderr

    assert "wrongType" in set_(f"{ERNI}.1.4.0", "s", "far")
    assert "notWritable" in set_(f"{ERNI}.1.1.0", "s", "evil")                    # read-only scalar
    assert "notWritable" in set_("1.3.6.1.2.1.1.5.0", "s", "evil")                # sysName: not writable here
    assert "notWritable" in set_(f"{ERNI}.1.99.0", "i", "1")                      # no such object
    assert "noCreation" in set_(f"{ERNI}.1.4.1", "i", "1")                        # no such instance
    assert "wrongValue" in set_(f"{ERNI}.1.6.0", "i", "18001")                    # heading out of range
    assert "badValue" in set_(f"{ERNI}.1.6.0", "i", "-18001", version="1")
    assert "noSuchName" in set_(f"{ERNI}.1.1.0", "s", "evil", version="1")
    out = set_(f"{ERNI}.1.4.0", "i", "1", f"{ERNI}.1.5.0", "s", "x")             # atomic: nothing applied
    assert "Failed object: .1.3.6.1.4.1.32473.1.1.5.0" in out
    assert net.view("robot2").positions["robot2"].x == 60.0
    assert net.view("robot2").position_updates == 0


def test_snmpv1_and_missing_objects(served, net):
    res = snmp("snmpget", served["robot1"], f"{ERNI}.1.1.0", version="1")
    assert parse(res.stdout)[f"{ERNI}.1.1.0"] == ("STRING", "robot1")
    res = snmp("snmpget", served["robot1"], f"{ERNI}.1.99.0", version="1")
    assert "noSuchName" in res.stdout + res.stderr
    missing = {
        f"{ERNI}.1.99.0": "No Such Object",                                   # no such object type
        f"{ERNI}.2.1.1.2.77": "No Such Instance",                             # erniNodesName: no row 77
        "1.3.6.1.2.1.213.1.2.5.1.5.1.2.1.4.10.9.9.9": "No Such Instance",     # nhdpIib2HopSetN2Time
        "1.3.6.1.2.1.4.24.7.1.7.1.4.10.0.0.9.32.2.0.0.0.0": "No Such Instance",  # inetCidrRouteIfIndex
        "1.3.6.1.2.1.4.24.7.1.1.1.4.10.0.0.2.32.2.0.0.0.0": "No Such Object",    # not-accessible index
        "1.3.6.1.2.1.1.3": "No Such Instance",                                # sysUpTime without .0
        "1.3.6.1.2.1.1.3.0.1": "No Such Instance",
    }
    res = snmp("snmpget", served["robot1"], *missing)
    for oid, what in missing.items():
        assert re.search(rf"^\.{re.escape(oid)} = {what}", res.stdout, re.M), (oid, res.stdout)


def test_a_served_column_without_rows_gives_no_such_instance(net):
    net.move("robot5", 1000.0, 0.0)            # robot5 alone: no neighbour, no route
    with ManetSnmpAgent(net) as agent:
        address = agent.serve("robot5")
        res = snmp("snmpget", address, "1.3.6.1.2.1.213.1.2.6.1.1.4",
                   "1.3.6.1.2.1.219.1.2.11.1.9.1.4.10.0.0.4.32", "1.3.6.1.2.1.4.24.6.0")
    rows = parse(res.stdout)
    assert "No Such Instance" in rows[".1.3.6.1.2.1.213.1.2.6.1.1.4".lstrip(".")][1] + res.stdout
    assert re.search(r"^\.1\.3\.6\.1\.2\.1\.219\.1\.2\.11\.1\.9\.1\.4\.10\.0\.0\.4\.32 = No Such Instance",
                     res.stdout, re.M)
    assert rows["1.3.6.1.2.1.4.24.6.0"] == ("Gauge32", "0")


def test_snmpbulkwalk_serves_the_same_rows_as_snmpwalk(served):
    """A GETBULK's repeaters walk on from where they stand (no search per row): net-snmp's bulk
    walk, with repetitions that end inside and across the node's row sets, reads what GETNEXT reads."""
    plain = snmp("snmpwalk", served["robot3"], "1.3")
    assert plain.returncode == 0, plain.stderr
    names = list(parse(plain.stdout))
    for reps in ("-Cr7", "-Cr50"):
        bulk = snmp("snmpbulkwalk", served["robot3"], reps, "1.3")
        assert bulk.returncode == 0, bulk.stderr
        assert "not increasing" not in bulk.stderr
        assert list(parse(bulk.stdout)) == names and len(names) > 200  # values: some are clocks and counters


def test_a_table_walked_place_by_place_is_every_served_oid_in_order():
    net = line_network()
    table = ManetSnmpAgent(net).table("robot3")

    def key_at(at: tuple[int, int]) -> tuple[int, ...]:
        return table.segments[at[0]][0].keys[at[1]]

    at, walked = table.locate((0,)), []
    while at is not None:
        walked.append(key_at(at))
        at = table.after(at)
    assert walked == table.keys and len(walked) > 200
    for k, following in zip(walked, walked[1:]):  # a search from any served OID agrees
        assert key_at(table.locate(k)) == following
    assert table.locate(walked[-1]) is None


def test_getbulk_past_the_end_names_the_last_name_reached(served):
    last = UNKNOWN_PDU_HANDLERS          # the last object this agent serves
    before = "1.3.6.1.6.3.11.2.1.2.0"
    res = snmp("snmpbulkget", served["robot1"], "-Cn0", "-Cr4", before)
    lines = [line for line in res.stdout.splitlines() if line.strip()]
    assert lines[0].startswith(f".{last} = Counter32")
    assert lines[1:] == [f".{last} = No more variables left in this MIB View "
                         "(It is past the end of the MIB tree)"]
    # two repeaters: the ended one keeps naming its last name while the other goes on
    res = snmp("snmpbulkget", served["robot1"], "-Cn1", "-Cr3", f"{ERNI}.1.1.0", before, "1.3.6.1.2.1.1.1.0")
    names = [line.split(" = ")[0] for line in res.stdout.splitlines() if line.strip()]
    assert names == [f".{ERNI}.1.2.0",                               # the non-repeater
                     f".{last}", ".1.3.6.1.2.1.1.2.0",
                     f".{last}", ".1.3.6.1.2.1.1.3.0",
                     f".{last}", ".1.3.6.1.2.1.1.4.0"]
    assert res.stdout.count("No more variables left") == 2


def test_wrong_community_is_dropped_and_counted(snmp_agent):
    address = snmp_agent.addresses()["robot1"]
    res = snmp("snmpget", address, f"{ERNI}.1.1.0", community="guess")
    assert res.returncode != 0 and "Timeout" in res.stdout + res.stderr
    assert counter(address, f"{SNMP_GROUP}.4.0") == 1                   # snmpInBadCommunityNames
    assert snmp_agent.stats["snmpInBadCommunityNames"] == 1


def test_garbage_datagrams_are_counted_and_the_agent_keeps_answering(snmp_agent):
    address = snmp_agent.addresses()["robot1"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for junk in (b"", b"\x30", b"hello", bytes(range(256))):
            s.sendto(junk, address)
        s.sendto(b"\x30\x03\x02\x01\x05", address)                                     # version 5
        s.sendto(_message(v2c, v2c.GetRequestPDU(), "public", version=3), address)   # SNMPv3 header
    res = snmp("snmpget", address, f"{ERNI}.1.1.0", f"{SNMP_GROUP}.6.0", f"{SNMP_GROUP}.3.0",
               f"{SNMP_GROUP}.1.0")
    rows = parse(res.stdout)
    assert rows[f"{ERNI}.1.1.0"] == ("STRING", "robot1")
    assert rows[f"{SNMP_GROUP}.6.0"] == ("Counter32", "4")                # snmpInASNParseErrs
    assert rows[f"{SNMP_GROUP}.3.0"] == ("Counter32", "2")                # snmpInBadVersions
    assert rows[f"{SNMP_GROUP}.1.0"] == ("Counter32", "7")                # snmpInPkts, this one too


def _message(p_mod, pdu, community: str, oid=agent_mib.ERNI_NODE_NAME + (0,), version: int | None = None) -> bytes:
    msg = p_mod.Message()
    p_mod.apiMessage.set_defaults(msg)
    if version is not None:
        msg.setComponentByPosition(0, version)
    p_mod.apiMessage.set_community(msg, community)
    if isinstance(pdu, pv1.TrapPDU):
        pv1.apiTrapPDU.set_defaults(pdu)
    else:
        p_mod.apiPDU.set_defaults(pdu)
        p_mod.apiPDU.set_varbinds(pdu, [(oid, p_mod.null)])
    p_mod.apiMessage.set_pdu(msg, pdu)
    return encoder.encode(msg)


RESPONSE_CLASS = [
    ("GetResponse", v2c, v2c.ResponsePDU), ("SNMPv2-Trap", v2c, v2c.SNMPv2TrapPDU),
    ("Report", v2c, v2c.ReportPDU), ("InformRequest", v2c, v2c.InformRequestPDU),
    ("v1 GetResponse", pv1, pv1.GetResponsePDU), ("v1 Trap", pv1, pv1.TrapPDU),
]


def test_response_and_notification_pdus_are_dropped_and_counted(snmp_agent):
    address = snmp_agent.addresses()["robot1"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(0.5)
        for _, p_mod, pdu in RESPONSE_CLASS:
            s.sendto(_message(p_mod, pdu(), "public"), address)
        with pytest.raises(TimeoutError):
            s.recvfrom(65535)
    assert counter(address, UNKNOWN_PDU_HANDLERS) == len(RESPONSE_CLASS)
    assert snmp_agent.stats["answered"] == 1                               # only the GET just made


def test_no_pdu_makes_two_agents_answer_each_other(snmp_agent):
    """Feed every answer of one node to the other, as a spoofed source address would: the
    exchange stops after at most one answer, whatever the first datagram."""
    for _, p_mod, pdu in RESPONSE_CLASS + [("GetRequest", v2c, v2c.GetRequestPDU)]:
        datagram: bytes | None = _message(p_mod, pdu(), "public")
        hops = 0
        while datagram is not None and hops < 10:
            datagram = snmp_agent.handle("robot1" if hops % 2 == 0 else "robot2", datagram)
            hops += 1
        assert hops <= 2


def _spoofed_udp(src: tuple[str, int], dst: tuple[str, int], payload: bytes) -> bytes:
    """An IPv4 + UDP packet from `src` to `dst` (checksum 0: none, allowed for UDP over IPv4)."""
    udp = struct.pack("!HHHH", src[1], dst[1], 8 + len(payload), 0) + payload
    header = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0, 64, socket.IPPROTO_UDP, 0,
                         socket.inet_aton(src[0]), socket.inet_aton(dst[0]))
    return header + udp


@pytest.mark.skipif(os.geteuid() != 0, reason="spoofing a source address needs a raw socket (root)")
@pytest.mark.parametrize("kind", ["GetResponse", "GetRequest"])
def test_a_spoofed_pdu_between_two_nodes_gets_at_most_one_answer(snmp_agent, kind):
    """The loop of a spoofed GetResponse (or GetRequest) whose source is another node's endpoint."""
    a, b = snmp_agent.addresses()["robot1"], snmp_agent.addresses()["robot2"]
    pdu = v2c.ResponsePDU() if kind == "GetResponse" else v2c.GetRequestPDU()
    with socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW) as raw:
        raw.sendto(_spoofed_udp(b, a, _message(v2c, pdu, "public")), (a[0], 0))
    wait_until(lambda: snmp_agent.node_stats("robot1")["snmpInPkts"] >= 1, timeout=10)
    # a GetRequest of the test's own to each node, twice, answered: whatever the nodes sent each other
    # before it was handled before it (one loop serves both, each socket in order)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as own:
        own.settimeout(10)
        for _ in range(2):
            for node in (a, b):
                own.sendto(_message(v2c, v2c.GetRequestPDU(), "public"), node)
                own.recvfrom(65535)
    stats_a, stats_b = snmp_agent.node_stats("robot1"), snmp_agent.node_stats("robot2")
    probes = 2
    assert stats_a["snmpInPkts"] == 1 + probes
    if kind == "GetResponse":   # dropped at once
        assert (stats_a["snmpUnknownPDUHandlers"], stats_b["snmpInPkts"]) == (1, probes)
    else:                       # answered once; the answer is dropped by the other node
        assert (stats_a["answered"], stats_b["snmpInPkts"], stats_b["snmpUnknownPDUHandlers"]) == (1 + probes,
                                                                                                    1 + probes, 1)
        assert stats_b["answered"] == probes


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.binary(max_size=200),
                 st.builds(lambda cut, flip: (cut, flip), st.integers(0, 60), st.integers(0, 255))))
def test_any_bytes_never_crash_the_handler(snmp_agent_unstarted, data):
    agent = snmp_agent_unstarted
    if isinstance(data, tuple):   # a truncated or corrupted valid request
        cut, flip = data
        raw = bytearray(_message(v2c, v2c.GetRequestPDU(), "public"))
        raw = raw[: max(1, len(raw) - cut)]
        raw[flip % len(raw)] ^= 0x5A
        data = bytes(raw)
    before = agent.stats["snmpInPkts"]
    reply = agent.handle("robot1", data)
    assert reply is None or isinstance(reply, bytes)
    assert agent.stats["snmpInPkts"] == before + 1
    if reply is not None:
        msg, rest = decoder.decode(reply, asn1Spec=v2c.Message())
        assert rest == b"" and v2c.apiMessage.get_pdu(msg).isSameTypeWith(v2c.ResponsePDU())


@pytest.fixture(scope="module")
def snmp_agent_unstarted():
    return ManetSnmpAgent(line_network())


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 2**32), min_size=2, max_size=20).map(
           lambda a: (1, 3) + tuple(a[2:]) if a else (1, 3)),
       st.integers(-(2**31), 2**31 - 1), st.integers(0, 2**32 - 1), st.binary(max_size=300))
def test_fast_ber_encoder_agrees_with_pyasn1(arcs, number, unsigned, octets):
    from pyasn1.type import univ as u

    from erni.sim import snmp_ber as ber
    assert tuple(decoder.decode(ber.oid(arcs), asn1Spec=u.ObjectIdentifier())[0]) == arcs
    assert tuple(decoder.decode(ber.value("oid", arcs), asn1Spec=u.ObjectIdentifier())[0]) == arcs
    assert int(decoder.decode(ber.value("int", number), asn1Spec=u.Integer())[0]) == number
    assert int(decoder.decode(ber.value("counter", unsigned), asn1Spec=v2c.Counter32())[0]) == unsigned
    assert int(decoder.decode(ber.value("gauge", unsigned), asn1Spec=v2c.Gauge32())[0]) == unsigned
    assert int(decoder.decode(ber.value("ticks", unsigned), asn1Spec=v2c.TimeTicks())[0]) == unsigned
    assert bytes(decoder.decode(ber.value("str", octets), asn1Spec=u.OctetString())[0]) == octets
    msg = ber.response(1, b"public", number, 0, 0,
                       [ber.varbind(ber.oid(arcs), ber.value("uns", unsigned))])
    decoded, rest = decoder.decode(msg, asn1Spec=v2c.Message())
    assert rest == b""
    pdu = v2c.apiMessage.get_pdu(decoded)
    assert int(v2c.apiPDU.get_request_id(pdu)) == number
    [(oid, val)] = v2c.apiPDU.get_varbinds(pdu)
    assert tuple(oid) == arcs and int(val) == unsigned


def test_change_counters_are_served(served, net):
    rows = parse(snmp("snmpget", served["robot1"], f"{ERNI}.1.9.0", f"{ERNI}.1.10.0").stdout)
    topo = int(rows[f"{ERNI}.1.9.0"][1])
    state = int(rows[f"{ERNI}.1.10.0"][1])
    assert rows[f"{ERNI}.1.9.0"][0] == "Counter32"
    net.set_position("robot4", 1.0, 2.0)      # a report: state changes, topology does not
    rows = parse(snmp("snmpget", served["robot1"], f"{ERNI}.1.9.0", f"{ERNI}.1.10.0").stdout)
    assert int(rows[f"{ERNI}.1.9.0"][1]) == topo
    assert int(rows[f"{ERNI}.1.10.0"][1]) > state
    net.move("robot4", 170.0, 0.0)
    rows = parse(snmp("snmpget", served["robot1"], f"{ERNI}.1.9.0").stdout)
    assert int(rows[f"{ERNI}.1.9.0"][1]) > topo


def test_tables_with_the_shared_topology_block_are_complete_and_ordered():
    from erni.sim.manet_mib import build_table
    net = line_network()
    agent = ManetSnmpAgent(net)
    for step in range(3):
        for name in net.names():
            table = agent.table(name)
            full = build_table(net.view(name), net)
            assert table.keys == [k for k, _, _ in full]
            assert all(a < b for a, b in zip(table.keys, table.keys[1:]))
        net.move("robot5", 150.0 + step * 30, 40.0)


def test_walking_the_whole_tree_is_strictly_increasing(served, net):
    res = snmp("snmpwalk", served["robot3"], "1.3")
    assert res.returncode == 0, res.stderr
    assert "not increasing" not in res.stderr
    rows = parse(res.stdout)
    assert len(rows) > 200
    assert any(k.startswith("1.3.6.1.2.1.219.1.2.8.1.6.") for k in rows)


def test_a_position_report_changes_what_is_served_without_rebuilding_any_table(snmp_agent, net):
    """Robots report their positions twice a second each: a report changes values, never rows, so
    no node's table is rebuilt for it (a team of 20 spent most of the host's CPU rebuilding)."""
    served = snmp_agent.addresses()
    names = net.names()
    tables = {n: snmp_agent.table(n) for n in names}
    updates = int(parse(snmp("snmpget", served["robot2"], f"{ERNI}.1.7.0").stdout)[f"{ERNI}.1.7.0"][1])
    res = snmp("snmpset", served["robot2"], f"{ERNI}.1.4.0", "i", "61500", f"{ERNI}.1.5.0", "i", "-2500",
               f"{ERNI}.1.6.0", "i", "9000", community=WRITE)
    assert res.returncode == 0, res.stderr
    net.set_position("robot3", 1.25, 2.5, -45.0)
    assert all(snmp_agent.table(n) is tables[n] for n in names)
    own = parse(snmp("snmpget", served["robot2"], f"{ERNI}.1.4.0", f"{ERNI}.1.5.0", f"{ERNI}.1.6.0",
                     f"{ERNI}.1.7.0").stdout)
    assert [own[f"{ERNI}.1.{k}.0"][1] for k in (4, 5, 6)] == ["61500", "-2500", "9000"]
    assert int(own[f"{ERNI}.1.7.0"][1]) == updates + 1
    for name in names:   # every node serves what it knows now, as a table built afresh would
        rows = parse(snmp("snmpwalk", served[name], f"{ERNI}.2.2").stdout)
        known = net.view(name).positions
        for origin, pos in known.items():
            index = net.info(origin).index
            assert rows[f"{ERNI}.2.2.1.1.{index}"][1] == str(round(pos.x * 1000))
            assert rows[f"{ERNI}.2.2.1.2.{index}"][1] == str(round(pos.y * 1000))
            assert rows[f"{ERNI}.2.2.1.3.{index}"][1] == str(round(pos.heading * 100))
        assert len([k for k in rows if k.startswith(f"{ERNI}.2.2.1.1.")]) == len(known)


def test_a_node_learning_a_new_origin_serves_its_rows():
    from erni.sim.manet import ManetNetwork, RadioModel
    net = ManetNetwork(RadioModel(100.0, 50.0, 0.1))
    net.add_node("robot1", 0.0, 0.0)
    net.add_node("robot2", 300.0, 0.0)        # out of range: robot1 has no position of robot2
    agent = ManetSnmpAgent(net)
    before = agent.table("robot1")
    x_of_robot2 = agent_mib.ERNI_POSITION_X + (net.info("robot2").index,)
    assert before.get(x_of_robot2, agent.node("robot1")) is None
    net.move("robot2", 30.0, 0.0)              # in range: the position spreads to robot1
    after = agent.table("robot1")
    assert after is not before and after.get(x_of_robot2, agent.node("robot1")) is not None
