"""The wire an endpoint's frames travel on: the interface every wire implements (`Wire`), and ERNI's
own (`UdpTcpWire`: datagrams on the endpoint's UDP socket, reliable messages over TCP connections,
`reliable.py`). Zenoh's is `zenoh_wire.ZenohWire`.

The endpoint seals, queues, batches and retries; its wire only carries frames: a datagram (a status,
a batch of them, a handshake, its answer, a hint, a beacon) best effort, and a reliable message until
its acknowledgement comes back.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from erni.transport.endpoint import Endpoint
    from erni.transport.outbox import Dest, Outgoing
    from erni.transport.session import Session

Address = tuple[str, int]


class Wire(Protocol):
    """How an endpoint's frames leave it."""

    name: str
    """The wire's name ('udp', 'zenoh'), as logs and `erni peers` show it."""
    batch_limit: int | None
    """Bytes of statuses a burst gathers into one frame (None: as many as a UDP datagram holds)."""

    def sendto(self, frame: bytes, addr: Address) -> None:
        """Send one frame to `addr` best effort, never waiting (OSError when it cannot go)."""

    def write_now(self, addr: Address, out: Outgoing) -> bool:
        """Try to write the reliable message `out` at once from the caller's thread; False: the
        sender pool delivers it (`deliver`)."""

    def deliver(self, dest: Dest, out: Outgoing, session: Session | None) -> bool:
        """Deliver `dest`'s first reliable message `out` (on a sender thread); True once it is
        acknowledged (or dropped for good), False to retry it later."""


class UdpTcpWire:
    """ERNI's own wire: datagrams on the endpoint's UDP socket, reliable messages on a TCP connection
    per destination, acknowledged on it (`ReliableDelivery`)."""

    name = "udp"
    batch_limit: int | None = None

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint

    def sendto(self, frame: bytes, addr: Address) -> None:
        self.endpoint.send_udp(frame, addr)

    def write_now(self, addr: Address, out: Outgoing) -> bool:
        return self.endpoint.reliable.write_now(addr, out)

    def deliver(self, dest: Dest, out: Outgoing, session: Session | None) -> bool:
        return self.endpoint.reliable.tcp_deliver(dest, out, session)
