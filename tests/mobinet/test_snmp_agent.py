"""The simulated MANET's SNMP agent, checked with net-snmp's command-line tools over real UDP."""

from __future__ import annotations

import re
import shutil
import socket
import subprocess

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyasn1.codec.ber import encoder
from pysnmp.proto.api import v2c

import erni.plugins.mobinet.snmp as client_mib
import erni.sim.manet_mib as agent_mib
from erni.sim.manet import link_metric

pytestmark = pytest.mark.skipif(shutil.which("snmpget") is None,
                                reason="net-snmp tools (Debian package 'snmp') not installed")

LINE_RE = re.compile(r"^(\.[\d.]+) = (?:([\w-]+): )?(.*)$")


def snmp(tool: str, address: tuple[str, int], *args: str, version: str = "2c",
         community: str = "public") -> subprocess.CompletedProcess:
    host, port = address
    cmd = [tool, f"-v{version}", "-c", community, "-On", "-m", "", "-t", "1", "-r", "0",
           f"udp:{host}:{port}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=20)


def parse(out: str) -> dict[str, tuple[str, str]]:
    rows = {}
    for line in out.splitlines():
        m = LINE_RE.match(line.strip())
        if m:
            rows[m.group(1).lstrip(".")] = (m.group(2) or "", m.group(3).strip().strip('"'))
    return rows


def test_client_and_agent_agree_on_every_oid():
    pairs = {"ERNI": "ERNI", "ERNI_NODE_NAME": "ERNI_NODE_NAME", "ERNI_POS_X": "ERNI_POS_X",
             "ERNI_POS_Y": "ERNI_POS_Y", "ERNI_POS_HEADING": "ERNI_POS_HEADING",
             "ERNI_NODE_ADDRESS": "ERNI_NODE_ADDRESS", "NHDP": "NHDP", "OLSRV2": "OLSRV2"}
    for c, a in pairs.items():
        assert getattr(client_mib, c) == getattr(agent_mib, a), c
    assert client_mib.NHDP_DISC_IF_ADDR == agent_mib.NHDP_DISC_IF + (4,)
    assert client_mib.NHDP_NIB_SYMMETRIC == agent_mib.NHDP_NIB_NEIGHBOR + (1,)
    assert client_mib.OLSRV2_TOPO_METRIC == agent_mib.OLSRV2_TOPOLOGY + (6,)
    assert client_mib.OLSRV2_ROUTE_METRIC == agent_mib.OLSRV2_ROUTING + (9,)
    assert client_mib.INET_CIDR_METRIC1 == agent_mib.INET_CIDR_ROUTE + (12,)
    assert client_mib.ERNI_NODES_X == agent_mib.ERNI_NODE_TABLE + (4,)
    assert client_mib.ERNI_LINK_QUALITY == agent_mib.ERNI_LINK_TABLE + (3,)
    assert client_mib.METRIC_UNIT == agent_mib.__dict__.get("METRIC_UNIT", 1024)


def test_snmpget_scalars(served, net):
    res = snmp("snmpget", served["robot2"], "1.3.6.1.4.1.32473.1.1.1.0", "1.3.6.1.4.1.32473.1.1.2.0",
               "1.3.6.1.4.1.32473.1.1.3.0", "1.3.6.1.4.1.32473.1.1.4.0",
               "1.3.6.1.4.1.32473.1.1.8.0")
    assert res.returncode == 0, res.stderr
    rows = parse(res.stdout)
    assert rows["1.3.6.1.4.1.32473.1.1.1.0"] == ("STRING", "robot2")
    assert rows["1.3.6.1.4.1.32473.1.1.2.0"] == ("INTEGER", "2")
    assert rows["1.3.6.1.4.1.32473.1.1.3.0"] == ("IpAddress", "10.0.0.2")
    assert rows["1.3.6.1.4.1.32473.1.1.4.0"] == ("INTEGER", "60000")
    assert rows["1.3.6.1.4.1.32473.1.1.8.0"] == ("INTEGER", "100000")


def test_snmpwalk_routes_match_the_documented_index(served, net):
    res = snmp("snmpwalk", served["robot1"], "1.3.6.1.2.1.219.1.2.11")
    assert res.returncode == 0, res.stderr
    rows = parse(res.stdout)
    # the reference's example: route metric to 10.0.0.5/32
    assert rows["1.3.6.1.2.1.219.1.2.11.1.9.1.4.10.0.0.5.32"] == ("Gauge32", str(4 * link_metric(0.8)))
    assert rows["1.3.6.1.2.1.219.1.2.11.1.8.1.4.10.0.0.5.32"] == ("Gauge32", "4")
    assert rows["1.3.6.1.2.1.219.1.2.11.1.5.1.4.10.0.0.5.32"][1].split() == ["0A", "00", "00", "02"]
    assert len([k for k in rows if k.startswith("1.3.6.1.2.1.219.1.2.11.1.9.")]) == 4
    cidr = parse(snmp("snmpbulkwalk", served["robot1"], "1.3.6.1.2.1.4.24.7.1.12").stdout)
    key = "1.3.6.1.2.1.4.24.7.1.12.1.4.10.0.0.3.32.2.0.0.1.4.10.0.0.2"
    assert cidr[key] == ("INTEGER", str(2 * link_metric(0.8)))


def test_snmpwalk_neighbours_links_and_topology(served, net):
    rows = parse(snmp("snmpwalk", served["robot3"], "1.3.6.1.2.1.213.1").stdout)
    assert rows["1.3.6.1.2.1.213.1.2.6.1.1.2"] == ("INTEGER", "1")      # robot2 symmetric
    assert rows["1.3.6.1.2.1.213.1.2.6.1.1.4"] == ("INTEGER", "1")      # robot4 symmetric
    assert "1.3.6.1.2.1.213.1.2.6.1.1.1" not in rows                    # robot1 out of range
    assert rows["1.3.6.1.2.1.213.1.3.2.1.1.4"] == ("Counter32", "800")
    assert rows["1.3.6.1.2.1.213.1.3.2.1.2.4"] == ("Counter32", "1000")
    erni = parse(snmp("snmpwalk", served["robot3"], "1.3.6.1.4.1.32473.1.3").stdout)
    assert erni["1.3.6.1.4.1.32473.1.3.1.3.2"] == ("Gauge32", "800")
    assert erni["1.3.6.1.4.1.32473.1.3.1.2.4"] == ("IpAddress", "10.0.0.4")
    topo = parse(snmp("snmpbulkwalk", served["robot3"], "1.3.6.1.2.1.219.1.2.8.1.6").stdout)
    # four undirected links, both directions
    assert len(topo) == 8
    assert topo["1.3.6.1.2.1.219.1.2.8.1.6.4.5"] == ("Gauge32", str(link_metric(0.8)))
    nodes = parse(snmp("snmpwalk", served["robot3"], "1.3.6.1.4.1.32473.1.2.1.2").stdout)
    assert sorted(v for _, v in nodes.values()) == [f"robot{i}" for i in range(1, 6)]


def test_snmpset_writes_the_position_and_the_network_spreads_it(served, net):
    res = snmp("snmpset", served["robot2"], "1.3.6.1.4.1.32473.1.1.4.0", "i", "61500",
               "1.3.6.1.4.1.32473.1.1.5.0", "i", "-2500", "1.3.6.1.4.1.32473.1.1.6.0", "i", "9000")
    assert res.returncode == 0, res.stderr
    known = net.view("robot5").positions["robot2"]
    assert (known.x, known.y, known.heading) == (61.5, -2.5, 90.0)
    rows = parse(snmp("snmpget", served["robot4"], "1.3.6.1.4.1.32473.1.2.1.4.2",
                      "1.3.6.1.4.1.32473.1.2.1.5.2").stdout)
    assert rows["1.3.6.1.4.1.32473.1.2.1.4.2"] == ("INTEGER", "61500")
    assert rows["1.3.6.1.4.1.32473.1.2.1.5.2"] == ("INTEGER", "-2500")


def test_snmpset_errors_are_reported_and_change_nothing(served, net):
    res = snmp("snmpset", served["robot2"], "1.3.6.1.4.1.32473.1.1.4.0", "s", "far")
    assert res.returncode != 0 and "wrongType" in res.stdout + res.stderr
    res = snmp("snmpset", served["robot2"], "1.3.6.1.4.1.32473.1.1.1.0", "s", "evil")
    assert res.returncode != 0 and "notWritable" in res.stdout + res.stderr
    res = snmp("snmpset", served["robot2"], "1.3.6.1.4.1.32473.1.1.4.0", "i", "1",
               "1.3.6.1.4.1.32473.1.1.5.0", "s", "x")
    assert res.returncode != 0
    assert net.view("robot2").positions["robot2"].x == 60.0   # nothing applied
    assert net.view("robot2").position_updates == 0


def test_snmpv1_and_missing_objects(served):
    res = snmp("snmpget", served["robot1"], "1.3.6.1.4.1.32473.1.1.1.0", version="1")
    assert parse(res.stdout)["1.3.6.1.4.1.32473.1.1.1.0"] == ("STRING", "robot1")
    res = snmp("snmpget", served["robot1"], "1.3.6.1.4.1.32473.1.1.99.0", version="1")
    assert "noSuchName" in res.stdout + res.stderr
    res = snmp("snmpget", served["robot1"], "1.3.6.1.4.1.32473.1.1.99.0")
    assert "No Such Object" in res.stdout
    res = snmp("snmpget", served["robot1"], "1.3.6.1.4.1.32473.1.2.1.2.77")
    assert "No Such Instance" in res.stdout


def test_wrong_community_is_dropped_and_counted(snmp_agent):
    address = snmp_agent.addresses()["robot1"]
    res = snmp("snmpget", address, "1.3.6.1.4.1.32473.1.1.1.0", community="guess")
    assert res.returncode != 0 and "Timeout" in res.stdout + res.stderr
    assert snmp_agent.stats["bad_community"] == 1


def test_garbage_datagrams_are_counted_and_the_agent_keeps_answering(snmp_agent):
    address = snmp_agent.addresses()["robot1"]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for junk in (b"", b"\x30", b"\x30\x03\x02\x01\x05", b"hello", bytes(range(256))):
            s.sendto(junk, address)
    res = snmp("snmpget", address, "1.3.6.1.4.1.32473.1.1.1.0")
    assert parse(res.stdout)["1.3.6.1.4.1.32473.1.1.1.0"] == ("STRING", "robot1")
    assert snmp_agent.stats["malformed"] + snmp_agent.stats["bad_version"] == 5


def _request(oid: tuple[int, ...]) -> bytes:
    msg = v2c.Message()
    v2c.apiMessage.set_defaults(msg)
    v2c.apiMessage.set_community(msg, "public")
    pdu = v2c.GetRequestPDU()
    v2c.apiPDU.set_defaults(pdu)
    v2c.apiPDU.set_varbinds(pdu, [(oid, v2c.null)])
    v2c.apiMessage.set_pdu(msg, pdu)
    return encoder.encode(msg)


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.binary(max_size=200),
                 st.builds(lambda cut, flip: (cut, flip), st.integers(0, 60), st.integers(0, 255))))
def test_any_bytes_never_crash_the_handler(snmp_agent_unstarted, data):
    agent = snmp_agent_unstarted
    if isinstance(data, tuple):   # a truncated or corrupted valid request
        cut, flip = data
        raw = bytearray(_request(agent_mib.ERNI_NODE_NAME))
        raw = raw[: max(1, len(raw) - cut)]
        raw[flip % len(raw)] ^= 0x5A
        data = bytes(raw)
    before = sum(agent.stats.values())
    reply = agent.handle("robot1", data)
    assert reply is None or isinstance(reply, bytes)
    assert sum(agent.stats.values()) == before + 1 or reply is not None


@pytest.fixture(scope="module")
def snmp_agent_unstarted():
    from erni.sim.snmp_agent import ManetSnmpAgent
    from tests.mobinet.conftest import line_network
    return ManetSnmpAgent(line_network())


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 2**32), min_size=2, max_size=20).map(
           lambda a: (1, 3) + tuple(a[2:]) if a else (1, 3)),
       st.integers(-(2**31), 2**31 - 1), st.integers(0, 2**32 - 1), st.binary(max_size=300))
def test_fast_ber_encoder_agrees_with_pyasn1(arcs, number, unsigned, octets):
    from pyasn1.codec.ber import decoder
    from pyasn1.type import univ as u

    from erni.sim import snmp_ber as ber
    assert tuple(decoder.decode(ber.oid(arcs), asn1Spec=u.ObjectIdentifier())[0]) == arcs
    assert int(decoder.decode(ber.value("int", number), asn1Spec=u.Integer())[0]) == number
    assert int(decoder.decode(ber.value("counter", unsigned), asn1Spec=v2c.Counter32())[0]) == unsigned
    assert int(decoder.decode(ber.value("gauge", unsigned), asn1Spec=v2c.Gauge32())[0]) == unsigned
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
    rows = parse(snmp("snmpget", served["robot1"], "1.3.6.1.4.1.32473.1.1.9.0",
                      "1.3.6.1.4.1.32473.1.1.10.0").stdout)
    topo = int(rows["1.3.6.1.4.1.32473.1.1.9.0"][1])
    state = int(rows["1.3.6.1.4.1.32473.1.1.10.0"][1])
    assert rows["1.3.6.1.4.1.32473.1.1.9.0"][0] == "Counter32"
    net.set_position("robot4", 1.0, 2.0)      # a report: state changes, topology does not
    rows = parse(snmp("snmpget", served["robot1"], "1.3.6.1.4.1.32473.1.1.9.0",
                      "1.3.6.1.4.1.32473.1.1.10.0").stdout)
    assert int(rows["1.3.6.1.4.1.32473.1.1.9.0"][1]) == topo
    assert int(rows["1.3.6.1.4.1.32473.1.1.10.0"][1]) > state
    net.move("robot4", 170.0, 0.0)
    rows = parse(snmp("snmpget", served["robot1"], "1.3.6.1.4.1.32473.1.1.9.0").stdout)
    assert int(rows["1.3.6.1.4.1.32473.1.1.9.0"][1]) > topo


def test_tables_with_the_shared_topology_block_are_complete_and_ordered():
    from erni.sim.manet_mib import build_table
    from erni.sim.snmp_agent import ManetSnmpAgent
    from tests.mobinet.conftest import line_network
    net = line_network()
    agent = ManetSnmpAgent(net)
    for step in range(3):
        for name in net.names():
            table = agent.table(name)
            full = build_table(net.view(name), net.radio.comm_range)
            assert table.keys == [k for k, _ in full]
            assert all(a < b for a, b in zip(table.keys, table.keys[1:]))
        net.move("robot5", 150.0 + step * 30, 40.0)


def test_walking_the_whole_tree_is_strictly_increasing(served, net):
    res = snmp("snmpwalk", served["robot3"], "1.3")
    assert res.returncode == 0, res.stderr
    assert "not increasing" not in res.stderr
    rows = parse(res.stdout)
    assert len(rows) > 100
    assert any(k.startswith("1.3.6.1.2.1.219.1.2.8.1.6.") for k in rows)
