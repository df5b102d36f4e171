"""The transport plugin's former module: `TransportPlugin` lives in `plugin.py`, its settings in
`settings.py`, its collaborators in `tasking.py`, `presence.py`, `replication.py`, `watchers.py` and
`authorization.py`. The names stay importable from here (the `transport` entry point, older imports)."""

from __future__ import annotations

from erni.blackboard.schemas import (
    Beacon,
    Cancel,
    Fresh,
    Peer,
    PeerList,
    ResultUpdate,
    StatusRemoved,
    StatusResend,
    TaskQuery,
    TaskRescind,
    TaskUnknown,
    WatchEvent,
    WatchRequest,
)
from erni.transport.plugin import TransportPlugin
from erni.transport.presence import Directory as _Directory
from erni.transport.settings import TransportSettings
from erni.transport.tasking import Received, Relayed
from erni.transport.watchers import WATCHED

__all__ = ["WATCHED", "Beacon", "Cancel", "Fresh", "Peer", "PeerList", "Received", "Relayed", "ResultUpdate",
           "StatusRemoved", "StatusResend", "TaskQuery", "TaskRescind", "TaskUnknown", "TransportPlugin",
           "TransportSettings", "WatchEvent", "WatchRequest", "_Directory"]
