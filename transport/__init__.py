"""Message transport between agents: framing, authentication, TCP/UDP endpoint, the transport
plugin that carries tasks and results between blackboards, discovery, and a mock network.

Importing one module of the transport (`erni.transport.client`, as a command line sending a
stop does) imports this package first, and with it none of the others: each name below is
imported from its module when first asked for.
"""

from typing import TYPE_CHECKING

from erni._lazy import lazy_names as _lazy_names

if TYPE_CHECKING:
    from erni.blackboard.schemas import Peer
    from erni.transport.endpoint import Endpoint, parse_address, team_key
    from erni.transport.mock import MockEndpoint, MockNetwork
    from erni.transport.plugin import TransportPlugin
    from erni.transport.settings import TransportSettings
    from erni.transport.wire import FrameError, Message, register_type

_HOMES = {
    "erni.blackboard.schemas": ("Peer",),
    "erni.transport.endpoint": ("Endpoint", "parse_address", "team_key"),
    "erni.transport.mock": ("MockEndpoint", "MockNetwork"),
    "erni.transport.plugin": ("TransportPlugin",),
    "erni.transport.settings": ("TransportSettings",),
    "erni.transport.wire": ("FrameError", "Message", "register_type"),
}

__all__ = ["Endpoint", "FrameError", "Message", "MockEndpoint", "MockNetwork", "Peer",
           "TransportPlugin", "TransportSettings", "parse_address", "register_type", "team_key"]


__getattr__, __dir__ = _lazy_names(__name__, _HOMES, globals())
