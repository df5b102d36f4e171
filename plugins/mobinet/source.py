"""The one interface MobiNet reads the network through, and the view it returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from blackboard import Link, Neighbor, Position, Route

# what a read may ask for
NEIGHBORS = "neighbors"
TOPOLOGY = "topology"
ROUTES = "routes"
POSITIONS = "positions"
PARTS = frozenset({NEIGHBORS, TOPOLOGY, ROUTES, POSITIONS})


class SourceError(Exception):
    """The network subsystem could not be read or written; the message says why, in one line."""


@dataclass
class NetView:
    """One reading of the network subsystem (only the requested parts are filled)."""

    node: str
    address: str
    names: dict[str, str] = field(default_factory=dict)   # address -> node name
    neighbors: list[Neighbor] = field(default_factory=list)
    links: list[Link] = field(default_factory=list)
    routes: list[Route] = field(default_factory=list)
    positions: dict[str, Position] = field(default_factory=dict)


@runtime_checkable
class NetworkSource(Protocol):
    """Reads and writes the network subsystem; methods run on MobiNet's asyncio thread.

    Implementations raise `SourceError` (one clear line) for timeouts, error answers and
    malformed or mistyped data. The SNMP implementation is `SnmpSource`; another (for
    example an olsrd2 JSON reader) only has to provide these three coroutines.
    """

    async def read(self, parts: frozenset[str]) -> NetView:
        """Return a view with the requested parts (a subset of PARTS)."""
        ...

    async def write_position(self, position: Position) -> None:
        """Tell the network subsystem where this node is (x, y in m, heading in deg)."""
        ...

    async def aclose(self) -> None:
        """Release sockets and engines."""
        ...
