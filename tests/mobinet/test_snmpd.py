"""MobiNet against Debian's net-snmp agent (`snmpd`), which serves the host's real routing table
in IP-FORWARD-MIB and neither NHDP-MIB nor OLSRv2-MIB; and snmpd as the reference for how an
SNMP agent answers the requests the simulated agent must answer the same way."""

from __future__ import annotations

import asyncio
import ipaddress
import os
import shutil
import socket
import struct
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from pyasn1.codec.ber import encoder
from pysnmp.proto.api import v2c

from erni.blackboard import Agent, NetInfo, Task
from erni.blackboard.testing import wait_until
from erni.plugins.mobinet.resource import PARTS
from erni.plugins.mobinet.snmp import SnmpSource
from erni.sim.snmp_agent import ManetSnmpAgent
from tests.mobinet.conftest import line_network

SNMPD = shutil.which("snmpd") or ("/usr/sbin/snmpd" if os.path.exists("/usr/sbin/snmpd") else None)
pytestmark = [pytest.mark.skipif(SNMPD is None or shutil.which("snmpget") is None,
                                 reason="Debian packages 'snmpd' and 'snmp' not installed"),
              pytest.mark.host_routes]  # snmpd serves the host's routes, which a real-mesh team changes
HOSTNAME = "erni-snmpd-test"


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def snmp(tool: str, port: int, *args: str, community: str = "public", version: str = "2c") -> str:
    res = subprocess.run([tool, f"-v{version}", "-c", community, "-On", "-m", "", "-t", "1", "-r", "1",
                          f"udp:127.0.0.1:{port}", *args], capture_output=True, text=True, timeout=30)
    return res.stdout + res.stderr


@pytest.fixture(scope="module")
def snmpd(tmp_path_factory) -> Iterator[int]:
    """Debian's snmpd on a loopback port with its own config, state and log in a temp dir."""
    work = tmp_path_factory.mktemp("snmpd")
    port = _free_udp_port()
    (work / "snmpd.conf").write_text(f"rocommunity public 127.0.0.1\nsysName {HOSTNAME}\n"
                                     "sysLocation test rack\nsysContact root\n")
    (work / "state").mkdir()   # snmpd rewrites <persistent dir>/snmpd.conf on exit: not our config
    env = {**os.environ, "MIBS": "", "SNMP_PERSISTENT_DIR": str(work / "state"), "SNMPCONFPATH": str(work)}
    proc = subprocess.Popen([SNMPD, "-f", "-C", "-c", str(work / "snmpd.conf"), "-Lf", str(work / "log"),
                             "-p", str(work / "pid"), "-I", "-smux", f"udp:127.0.0.1:{port}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: HOSTNAME in snmp("snmpget", port, "1.3.6.1.2.1.1.5.0") or proc.poll() is not None,
                   timeout=20)
        if proc.poll() is not None:
            pytest.fail(f"snmpd exited: {(work / 'log').read_text(errors='replace')}")
        yield port
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


def kernel_routes() -> set[tuple[str, str, float]]:
    """The host's IPv4 routes from /proc/net/route: (destination, next hop, metric)."""
    routes = set()
    for line in Path("/proc/net/route").read_text().splitlines()[1:]:
        fields = line.split()
        dest, gateway, flags, metric, mask = fields[1], fields[2], int(fields[3], 16), int(fields[6]), fields[7]
        if not flags & 0x1 or flags & 0x200:   # not up, or a reject route
            continue

        def addr(hex_le: str) -> str:
            return socket.inet_ntoa(struct.pack("<I", int(hex_le, 16)))

        prefix = bin(int(mask, 16)).count("1")
        target = addr(dest) if prefix == 32 else f"{addr(dest)}/{prefix}"
        hop = addr(gateway) if flags & 0x2 else (target if prefix == 32 else "")
        routes.add((target, hop, float(metric)))
    return routes


def test_the_client_reads_routes_from_debian_snmpd_and_names_what_is_missing(snmpd):
    async def go():
        src = SnmpSource("127.0.0.1", snmpd, timeout=2.0, retries=1)
        try:
            return await src.read(PARTS)
        finally:
            await src.aclose()
    view = asyncio.run(go())
    assert (view.node, view.address) == (HOSTNAME, "")
    assert view.sources["node"] == f"snmp 127.0.0.1:{snmpd} SNMPv2-MIB sysName"
    assert "IP-FORWARD-MIB inetCidrRouteTable" in view.sources["routes"]
    assert view.missing == {"neighbors": f"NHDP-MIB not served by 127.0.0.1:{snmpd}",
                            "topology": f"OLSRv2-MIB not served by 127.0.0.1:{snmpd}",
                            "positions": f"ERNI-MOBINET-MIB not served by 127.0.0.1:{snmpd}"}
    ipv4 = {(r.destination, r.next_hop, r.cost) for r in view.routes if ":" not in r.destination}
    assert ipv4 == kernel_routes()
    assert ipv4, "the host has no IPv4 route at all"
    assert view.dropped == []   # a real agent's real table: nothing implausible
    for r in view.routes:   # every destination is an address or a prefix, IPv4 or IPv6
        assert ipaddress.ip_network(r.destination)


def test_mobinet_against_snmpd_reports_routes_and_degrades_what_snmpd_lacks(snmpd):
    agent = Agent("host", workers=2)
    agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"host": "127.0.0.1", "port": snmpd, "timeout": 2.0, "retries": 1})
    agent.start()
    try:
        tasks = {kind: Task(verb="NetWatch", preposition=kind, params={"rate_hz": 5}, source="test")
                 for kind in ("path_cost", "neighbor_list")}
        with agent.transaction() as tx:
            for task in tasks.values():
                tx.add(task)

        def info(kind: str) -> NetInfo | None:
            found = [i for i in agent.query(NetInfo) if i.task == tasks[kind].uid and i.provenance]
            return found[0] if found else None

        paths = wait_until(lambda: info("path_cost"), timeout=15)
        nbrs = wait_until(lambda: info("neighbor_list"), timeout=15)
    finally:
        agent.stop()
    assert not paths.degraded and paths.node == HOSTNAME
    assert {(r.destination, r.next_hop, r.cost) for r in paths.routes if ":" not in r.destination} \
        == kernel_routes()
    assert paths.provenance["routes"].startswith(f"snmp 127.0.0.1:{snmpd} IP-FORWARD-MIB inetCidrRouteTable")
    assert nbrs.degraded and nbrs.neighbors == []
    assert nbrs.message == f"NHDP-MIB not served by 127.0.0.1:{snmpd}"
    assert nbrs.provenance["neighbors"] == f"missing: NHDP-MIB not served by 127.0.0.1:{snmpd}"


@pytest.fixture(scope="module")
def ours() -> Iterator[int]:
    agent = ManetSnmpAgent(line_network()).start()
    try:
        yield agent.serve("robot1")[1]
    finally:
        agent.close()


@pytest.mark.parametrize("request_args", [
    ("snmpget", "1.3.6.1.2.1.1.3"),                # an object type, no instance
    ("snmpget", "1.3.6.1.2.1.1.3.0.1"),            # an instance that cannot exist
    ("snmpget", "1.3.6.1.2.1.1.99.0"),             # no such object
    ("snmpget", "1.3.6.1.2.1.1.9.1.2.999"),        # a missing row of a served column
    ("snmpget", "1.3.6.1.2.1.1.5.0", "1.3.6.1.2.1.1.99.0"),
    ("snmpset", "1.3.6.1.2.1.1.5.0", "s", "x"),    # a SET with the read community
], ids=lambda a: " ".join(a))
@pytest.mark.parametrize("version", ["1", "2c"])
def test_the_agent_answers_like_snmpd(snmpd, ours, request_args, version):
    tool, *args = request_args

    def outcome(port: int) -> list[str]:
        text = snmp(tool, port, *args, version=version)
        kinds = ("No Such Instance", "No Such Object", "noAccess", "noSuchName", "Timeout", "STRING")
        return [next((k for k in kinds if k in line), line) for line in text.splitlines() if line.strip()
                and not line.startswith(("Error in packet", "Failed object"))]
    assert outcome(ours) == outcome(snmpd)


def test_neither_agent_answers_a_response_pdu(snmpd, ours):
    msg = v2c.Message()
    v2c.apiMessage.set_defaults(msg)
    v2c.apiMessage.set_community(msg, "public")
    pdu = v2c.ResponsePDU()
    v2c.apiPDU.set_defaults(pdu)
    v2c.apiPDU.set_varbinds(pdu, [((1, 3, 6, 1, 2, 1, 1, 5, 0), v2c.null)])
    v2c.apiMessage.set_pdu(msg, pdu)
    for port in (snmpd, ours):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.settimeout(0.5)
            s.sendto(encoder.encode(msg), ("127.0.0.1", port))
            t0 = time.monotonic()
            with pytest.raises(TimeoutError):
                s.recvfrom(65535)
            assert time.monotonic() - t0 >= 0.4


def kernel_choice(address: str, routes: set[tuple[str, str, float]]) -> set[tuple[str, str, float]]:
    """The kernel's routes of the longest prefix covering `address` (host routes are /32)."""
    target = int(ipaddress.IPv4Address(address))

    def covers(dest: str) -> int:   # the prefix length if `dest` covers the address, else -1
        net, _, length = dest.partition("/")
        bits = int(length or 32)
        mask = (0xFFFFFFFF << (32 - bits)) & 0xFFFFFFFF
        return bits if int(ipaddress.IPv4Address(net)) & mask == target & mask else -1
    longest = max(covers(r[0]) for r in routes)
    return {r for r in routes if covers(r[0]) == longest} if longest >= 0 else set()


def test_path_cost_to_an_address_inside_a_kernel_network_route_answers_its_longest_prefix(snmpd):
    """The kernel forwards to an address by the longest prefix that covers it; `path_cost` to an address
    no route names answers that route, read from the kernel's table through snmpd."""
    kernel = kernel_routes()
    networks = [ipaddress.IPv4Network(d) for d, _, _ in kernel if "/" in d]
    assert networks, "the host has no IPv4 network route"
    probes = sorted({"198.51.100.7" if n.prefixlen == 0 else str(n.network_address + 1)
                     for n in networks if n.prefixlen < 31})
    agent = Agent("host", workers=2)
    agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"host": "127.0.0.1", "port": snmpd, "timeout": 2.0, "retries": 1})
    agent.start()
    try:
        tasks = {probe: Task(verb="NetWatch", preposition="path_cost", source="test",
                             params={"rate_hz": 5, "destination": probe}) for probe in probes}
        with agent.transaction() as tx:
            for task in tasks.values():
                tx.add(task)

        def info(probe: str) -> NetInfo | None:
            found = [i for i in agent.query(NetInfo) if i.task == tasks[probe].uid and i.provenance]
            return found[0] if found else None

        answers = {probe: wait_until(lambda p=probe: info(p), timeout=15) for probe in probes}
    finally:
        agent.stop()
    for probe, answer in answers.items():
        expected = kernel_choice(probe, kernel)
        assert expected and all("/" in d for d, _, _ in expected), (probe, expected)
        assert not answer.degraded, (probe, answer.message)
        assert {(r.destination, r.next_hop, r.cost) for r in answer.routes} == expected, probe
