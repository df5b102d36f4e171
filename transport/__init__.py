"""Message transport between agents: framing, authentication, TCP/UDP endpoint, the bridge
plugin that carries tasks and results between blackboards, discovery, and a mock network."""

from transport.bridge import Peer, TransportPlugin, TransportSettings
from transport.endpoint import Endpoint, parse_address, team_key
from transport.mock import MockEndpoint, MockNetwork
from transport.wire import FrameError, Message, register_type

__all__ = ["Endpoint", "FrameError", "Message", "MockEndpoint", "MockNetwork", "Peer",
           "TransportPlugin", "TransportSettings", "parse_address", "register_type", "team_key"]
