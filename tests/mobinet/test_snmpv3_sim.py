"""The simulated network node with v3 users: net-snmp's tools read and write it over SNMPv3 authPriv,
v1/v2c and wrong keys are refused, MobiNet reads it over v3 exactly as over v2c, and `erni net-sim
--v3-user` serves it. MobiNet warns once when a v2c write community goes to a non-loopback address."""

from __future__ import annotations

import asyncio
import logging
import os
import random
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator

import pytest

from erni.blackboard import Agent, NetInfo, Pose, Position, Task
from erni.blackboard.testing import wait_until
from erni.plugins.mobinet.resource import PARTS, SourceError
from erni.plugins.mobinet.snmp import SnmpSource
from erni.plugins.mobinet.usm import UsmUser
from erni.sim.snmp_agent import ManetSnmpAgent
from tests.mobinet.conftest import line_network

TOOLS = shutil.which("snmpget") is not None
needs_tools = pytest.mark.skipif(not TOOLS, reason="Debian package 'snmp' (net-snmp's tools) not installed")
USER = UsmUser("erni", "erni auth passphrase", "erni priv passphrase")
USER512 = UsmUser("erni512", "another auth passphrase", "another priv passphrase", auth_protocol="SHA-512")
NODE_NAME = "1.3.6.1.4.1.32473.1.1.1.0"
POS_X = "1.3.6.1.4.1.32473.1.1.4.0"


def tool(name: str, port: int, *args: str, user: UsmUser = USER, auth: str | None = None, priv: str | None = None,
         level: str = "authPriv") -> str:
    """A net-snmp tool run as an SNMPv3 user (its keys unless `auth`/`priv` say otherwise)."""
    keys = ["-a", user.auth_protocol, "-A", auth or user.auth_key]
    if level == "authPriv":
        keys += ["-x", "AES", "-X", priv or user.priv_key]
    res = subprocess.run([name, "-v3", "-l", level, "-u", user.name, *keys, "-On", "-m", "", "-t", "1", "-r", "0",
                          f"udp:127.0.0.1:{port}", *args], capture_output=True, text=True, timeout=30)
    return (res.stdout + res.stderr).strip()


def v2c(name: str, port: int, *args: str, version: str = "2c", community: str = "public") -> str:
    res = subprocess.run([name, f"-v{version}", "-c", community, "-On", "-m", "", "-t", "0.3", "-r", "0",
                          f"udp:127.0.0.1:{port}", *args], capture_output=True, text=True, timeout=30)
    return (res.stdout + res.stderr).strip()


@pytest.fixture(scope="module")
def v3_node() -> Iterator[tuple[ManetSnmpAgent, int]]:
    agent = ManetSnmpAgent(line_network(), write_community="w-v2c", v3_users=[USER, USER512]).start()
    try:
        yield agent, agent.serve("robot2")[1]
    finally:
        agent.close()


@needs_tools
def test_net_snmp_reads_and_writes_the_simulated_node_over_snmpv3(v3_node):
    agent, port = v3_node
    assert tool("snmpget", port, NODE_NAME) == f'.{NODE_NAME} = STRING: "robot2"'
    walked = tool("snmpwalk", port, "1.3.6.1.4.1.32473.1.2.1.1.2", user=USER512)
    assert walked.splitlines() == [f'.1.3.6.1.4.1.32473.1.2.1.1.2.{i} = STRING: "robot{i}"' for i in range(1, 6)]
    assert tool("snmpset", port, POS_X, "i", "61500") == f".{POS_X} = INTEGER: 61500"
    assert agent.network.known_position("robot2", "robot2").x == 61.5
    assert "getbulk" in agent.node_stats("robot2") or "getnext" in agent.node_stats("robot2")


@needs_tools
def test_a_v3_only_node_refuses_v1_v2c_and_wrong_keys(v3_node):
    agent, port = v3_node
    stats = agent.node_stats("robot2")
    before = dict(stats)
    for version in ("1", "2c"):
        for community in ("public", "w-v2c"):
            assert v2c("snmpget", port, NODE_NAME, version=version, community=community).startswith("Timeout")
    assert stats["snmpInBadCommunityNames"] - before.get("snmpInBadCommunityNames", 0) == 4
    assert "Authentication failure" in tool("snmpget", port, NODE_NAME, auth="not the auth passphrase")
    assert "Decryption error" in tool("snmpget", port, NODE_NAME, priv="not the priv passphrase")
    assert "Unsupported security level" in tool("snmpget", port, NODE_NAME, level="authNoPriv")
    assert "Unknown user name" in tool("snmpget", port, NODE_NAME,
                                       user=UsmUser("nobody", USER.auth_key, USER.priv_key))
    assert "Authentication failure" in tool("snmpset", port, POS_X, "i", "1", auth="not the auth passphrase")
    for counter in ("usmStatsWrongDigests", "usmStatsDecryptionErrors", "usmStatsUnsupportedSecLevels",
                    "usmStatsUnknownUserNames"):
        assert stats[counter] > before.get(counter, 0), counter
    assert agent.network.known_position("robot2", "robot2").x != 1.0   # no refused SET was applied


def test_mobinet_reads_a_v3_node_as_it_reads_a_v2c_node_and_writes_its_position():
    net = line_network()
    agent = ManetSnmpAgent(net).start()
    try:
        plain = agent.serve("robot3")[1]
        secure = agent.serve("robot2", v3_users=[USER])[1]
        agent.serve("robot4", v3_users=[USER512])

        async def go() -> tuple[object, object, object]:
            v2 = SnmpSource("127.0.0.1", plain, timeout=2.0)
            v3 = SnmpSource("127.0.0.1", secure, timeout=2.0, usm=USER)
            wrong = SnmpSource("127.0.0.1", secure, timeout=2.0, usm=UsmUser("erni", USER.auth_key, "not the priv key"))
            try:
                await v3.write_position(Position(x=12.5, y=-3.25, heading=90.0))
                views = await v2.read(PARTS), await v3.read(PARTS)
                try:
                    await wrong.read(PARTS)
                    refused: object = None
                except SourceError as err:
                    refused = err
                return views[0], views[1], refused
            finally:
                for src in (v2, v3, wrong):
                    await src.aclose()
        over_v2c, over_v3, refused = asyncio.run(go())
    finally:
        agent.close()
    assert net.known_position("robot2", "robot2").x == 12.5
    assert over_v3.node == "robot2" and over_v2c.node == "robot3"
    assert over_v3.positions == over_v2c.positions and over_v3.positions["robot2"].y == -3.25
    assert sorted(n.name for n in over_v3.neighbors) == ["robot1", "robot3"]
    assert {r.destination for r in over_v3.routes} == {"robot1", "robot3", "robot4", "robot5"}
    assert {(l.a, l.b) for l in over_v3.links} == {(l.a, l.b) for l in over_v2c.links}
    assert over_v3.missing == {} and over_v3.dropped == []
    assert str(refused) == (f"SNMPv3 GET to 127.0.0.1:{secure} as 'erni': the agent could not decrypt the request "
                            "(usmStatsDecryptionErrors): wrong priv key or priv protocol for user 'erni'")


def test_a_node_refuses_duplicate_v3_users():
    agent = ManetSnmpAgent(line_network())
    with pytest.raises(ValueError, match="SNMPv3 user names must differ"):
        agent.serve("robot1", v3_users=[USER, USER])
    agent.close()


ADDR_RE = re.compile(r"^\s+(\S+)\s+(\d+\.\d+\.\d+\.\d+)\s+snmp udp:([\d.]+):(\d+)$")


@needs_tools
def test_net_sim_with_a_v3_user_serves_snmpv3_only(tmp_path):
    scenario = tmp_path / "two.toml"
    scenario.write_text('comm_range = 100.0\nlossless_range = 50.0\nbase_port = 0\nwrite_community = "w-all"\n'
                        'nodes = [{name = "a", x = 0, y = 0}, {name = "b", x = 60, y = 0}]\n')
    keyfile = tmp_path / "priv.key"
    keyfile.write_text(USER.priv_key + "\n")
    keyfile.chmod(0o600)
    env = {**os.environ, "ERNI_SNMP_AUTH_KEY": USER.auth_key}
    proc = subprocess.Popen([sys.executable, "-m", "erni", "net-sim", str(scenario), "--v3-user", "erni",
                             "--v3-auth", "SHA-256", "--v3-priv", "AES", "--v3-priv-key-file", str(keyfile)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        lines, ports = [], {}
        while "serving; Ctrl-C to stop" not in lines[-1:]:
            line = proc.stdout.readline()
            assert line, f"net-sim exited early: {proc.stderr.read()}"
            lines.append(line.rstrip("\n"))
            m = ADDR_RE.match(lines[-1])
            if m:
                ports[m.group(1)] = int(m.group(4))
        assert "SNMPv3 only: user 'erni', authPriv SHA-256/AES" in lines[0]
        assert tool("snmpget", ports["b"], NODE_NAME) == f'.{NODE_NAME} = STRING: "b"'
        assert v2c("snmpget", ports["b"], NODE_NAME).startswith("Timeout")
        assert v2c("snmpset", ports["b"], POS_X, "i", "5", community="w-all").startswith("Timeout")
        assert "Authentication failure" in tool("snmpget", ports["a"], NODE_NAME, auth="not the auth passphrase")
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "1 refused by USM" in out


def test_net_sim_refuses_a_v3_user_without_keys_in_one_line(tmp_path):
    scenario = tmp_path / "one.toml"
    scenario.write_text('comm_range = 10\nlossless_range = 5\nnodes = [{name = "a", x = 0, y = 0}]\n')
    env = {k: v for k, v in os.environ.items() if k not in ("ERNI_SNMP_AUTH_KEY", "ERNI_SNMP_PRIV_KEY")}
    res = subprocess.run([sys.executable, "-m", "erni", "net-sim", str(scenario), "--v3-user", "erni"],
                         capture_output=True, text=True, timeout=30, env=env)
    assert res.returncode == 2
    assert res.stderr.strip() == ("erni net-sim: SNMPv3 auth key: environment variable ERNI_SNMP_AUTH_KEY is not "
                                  "set or empty")


@pytest.mark.parametrize(("host", "warned"), [("127.0.0.1", False), ("localhost", False), ("::1", False),
                                              ("192.0.2.7", True), ("robot2.local", True)])
def test_a_write_community_to_a_non_loopback_address_is_warned_about_once(caplog, host, warned):
    agent = Agent("robot2", workers=1)
    agent.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"host": host, "port": 9, "timeout": 0.05, "write_community": "w-robot2",
                               "write_interval": 0.0, "log_interval": 60.0})
    with caplog.at_level(logging.WARNING, logger="erni"):
        agent.start()
        try:
            with agent.transaction() as tx:
                tx.add(Pose(robot="robot2", x=1.0, y=0.0))
            for x in (2.0, 3.0):   # more writes: still one warning
                with agent.transaction() as tx:
                    tx.change(agent.query(Pose)[0].evolve(x=x))
        finally:
            agent.stop()
    found = [r.getMessage() for r in caplog.records if "travels in clear" in r.getMessage()]
    assert len(found) == (1 if warned else 0), found
    if warned:
        assert found[0].startswith(f"the SNMPv2c write community travels in clear to {host}:9")
        assert "w-robot2" not in found[0]


def test_mobinet_writes_its_robots_pose_to_a_v3_node_and_watches_it():
    net = line_network()
    agent = ManetSnmpAgent(net, v3_users=[USER]).start()
    port = agent.serve("robot2")[1]
    robot = Agent("robot2", workers=2)
    robot.add_plugin("erni.plugins.mobinet:MobiNetControl", name="mobinet",
                     settings={"port": port, "timeout": 1.0, "v3_user": USER.name, "auth_key": USER.auth_key,
                               "priv_key": USER.priv_key, "write_interval": 0.0})
    try:
        robot.start()
        task = Task(verb="NetWatch", preposition="node_position", params={"rate_hz": 10}, source="test")
        with robot.transaction() as tx:
            tx.add(Pose(robot="robot2", x=7.25, y=-1.5))
            tx.add(task)
        info = wait_until(lambda: next((i for i in robot.query(NetInfo) if i.task == task.uid and not i.degraded
                                        and i.positions.get("robot2", Position(x=0, y=0)).x == 7.25), None),
                          timeout=15)
    finally:
        robot.stop()
        agent.close()
    assert (info.positions["robot2"].x, info.positions["robot2"].y) == (7.25, -1.5)
    assert info.provenance["positions"] == f"snmp 127.0.0.1:{port} ERNI-MOBINET-MIB erniPositionTable"
    assert net.known_position("robot2", "robot2").x == 7.25


def test_malformed_snmpv3_datagrams_are_dropped_and_the_node_keeps_answering(v3_node):
    agent, port = v3_node
    good = None

    class Catch(asyncio.DatagramProtocol):
        def datagram_received(self, data: bytes, addr: object) -> None:
            nonlocal good
            good = data

    async def go() -> None:
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(Catch, remote_addr=("127.0.0.1", port))
        src = SnmpSource("127.0.0.1", port, timeout=1.0, usm=USER)
        try:
            await src.get([(1, 3, 6, 1, 4, 1, 32473, 1, 1, 1, 0)])
            header = b"\x30\x82\x00\x40\x02\x01\x03"   # a SEQUENCE claiming 64 bytes, version 3
            rng = random.Random(38)
            for n in range(300):
                body = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 80)))
                transport.sendto(header + body if n % 2 else b"\x30" + bytes([len(body) + 3]) + b"\x02\x01\x03" + body)
            await asyncio.sleep(0.2)
            assert (await src.get([(1, 3, 6, 1, 4, 1, 32473, 1, 1, 1, 0)]))
        finally:
            transport.close()
            await src.aclose()
    asyncio.run(go())
    assert good is None or len(good) < 200   # nothing it sent back was more than a Report
