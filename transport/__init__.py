"""Message transport between agents: framing, authentication, TCP/UDP endpoint, the transport
plugin that carries tasks and results between blackboards, discovery, and a mock network."""

from erni.blackboard.schemas import Peer
from erni.transport.endpoint import Endpoint, parse_address, team_key
from erni.transport.mock import MockEndpoint, MockNetwork
from erni.transport.plugin import TransportPlugin
from erni.transport.settings import TransportSettings
from erni.transport.wire import FrameError, Message, register_type

__all__ = ["Endpoint", "FrameError", "Message", "MockEndpoint", "MockNetwork", "Peer",
           "TransportPlugin", "TransportSettings", "parse_address", "register_type", "team_key"]
