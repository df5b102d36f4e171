"""Message transport between agents: framing, authentication, TCP/UDP endpoint, the transport
plugin that carries tasks and results between blackboards, discovery, and a mock network.

Importing one module of the transport (`erni.transport.client`, as a command line sending a
stop does) imports this package first, and with it none of the others: each name below is
imported from its module when first asked for.
"""

import importlib as _importlib
from typing import TYPE_CHECKING, Any

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
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = ["Endpoint", "FrameError", "Message", "MockEndpoint", "MockNetwork", "Peer",
           "TransportPlugin", "TransportSettings", "parse_address", "register_type", "team_key"]


def __getattr__(name: str) -> Any:
    """A name of `__all__`, imported from its module when first asked for; or a module of the package
    not imported yet (`erni.transport.wire`)."""
    module = _HOME_OF.get(name)
    if module is not None:
        value = getattr(_importlib.import_module(module), name)
        globals()[name] = value
        return value
    if not name.startswith("__"):
        try:
            return _importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as err:
            if err.name != f"{__name__}.{name}":
                raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOME_OF))
