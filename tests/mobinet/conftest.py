"""Fixtures for MobiNet tests: a simulated MANET served over real UDP, and misbehaving agents."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest
from pyasn1.codec.ber import decoder, encoder
from pysnmp.proto import api
from pysnmp.proto.api import v2c

from erni.sim.manet import ManetNetwork, RadioModel
from erni.sim.snmp_agent import ManetSnmpAgent

NAME = (1, 3, 6, 1, 4, 1, 32473, 1, 1, 1, 0)
ADDRESS = (1, 3, 6, 1, 4, 1, 32473, 1, 1, 3, 0)
SYS_NAME = (1, 3, 6, 1, 2, 1, 1, 5, 0)
WRITE = "test-writer"   # the write community of the agents the fixtures serve
LINE = [("robot1", 0.0, 0.0), ("robot2", 60.0, 0.0), ("robot3", 120.0, 0.0),
        ("robot4", 180.0, 0.0), ("robot5", 240.0, 0.0)]


def line_network() -> ManetNetwork:
    """Five nodes 60 m apart with R = 100 m, loss-free to 50 m: a chain of 0.8-quality links."""
    net = ManetNetwork(RadioModel(100.0, 50.0, 0.1))
    for name, x, y in LINE:
        net.add_node(name, x, y)
    return net


@pytest.fixture
def net() -> ManetNetwork:
    return line_network()


@pytest.fixture
def served(net: ManetNetwork) -> Iterator[dict[str, tuple[str, int]]]:
    agent = ManetSnmpAgent(net, write_community=WRITE).start()
    try:
        yield agent.serve_all()
    finally:
        agent.close()


@pytest.fixture
def snmp_agent(net: ManetNetwork) -> Iterator[ManetSnmpAgent]:
    agent = ManetSnmpAgent(net, write_community=WRITE).start()
    agent.serve_all()
    try:
        yield agent
    finally:
        agent.close()


class BadAgent:
    """A raw UDP 'agent': silent, garbage, wrong types (`wrongtype`), non-increasing OIDs (`loop`)
    or noSuchObject for everything (`nothing`)."""

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.address = self.sock.getsockname()
        self.received = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"bad-agent-{mode}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, peer = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            self.received += 1
            reply = self._reply(data)
            if reply is not None:
                self.sock.sendto(reply, peer)

    def _reply(self, data: bytes) -> bytes | None:
        if self.mode == "silent":
            return None
        if self.mode == "garbage":
            return b"\x30\x82\xff\xff not SNMP at all " + data[:5]
        # well-formed responses where every value is an Integer32 7; "wrongtype" walks
        # forward one level then ends, "loop" answers GETNEXT/GETBULK with the same OIDs
        p_mod = api.PROTOCOL_MODULES[int(api.decodeMessageVersion(data))]
        msg, _ = decoder.decode(data, asn1Spec=p_mod.Message())
        rsp_msg = p_mod.apiMessage.get_response(msg)
        rsp = p_mod.apiMessage.get_pdu(rsp_msg)
        req = p_mod.apiMessage.get_pdu(msg)
        binds = []
        walking = not req.isSameTypeWith(p_mod.GetRequestPDU())
        for oid, _ in p_mod.apiPDU.get_varbinds(req):
            oid = tuple(oid)
            if self.mode == "nothing":                 # an SNMP agent serving none of it
                binds.append((oid, v2c.NoSuchObject("")))
            elif not walking and self.mode == "loop":   # a valid identity, then looping walks
                binds.append((oid, {NAME: v2c.OctetString(b"loopy"), SYS_NAME: v2c.OctetString(b"loopy"),
                                    ADDRESS: v2c.IpAddress("10.9.9.9")}.get(oid, v2c.NoSuchObject(""))))
            elif walking and self.mode == "wrongtype":
                binds.append((oid + (1,), v2c.Integer32(7)) if len(oid) < 14
                             else (oid, v2c.EndOfMibView("")))
            else:
                binds.append((oid, v2c.Integer32(7)))
        p_mod.apiPDU.set_varbinds(rsp, binds)
        return encoder.encode(rsp_msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


@pytest.fixture
def bad_agent() -> Iterator[callable]:
    agents: list[BadAgent] = []

    def make(mode: str) -> BadAgent:
        agents.append(BadAgent(mode))
        return agents[-1]

    yield make
    for a in agents:
        a.close()
