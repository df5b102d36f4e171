"""`Peer`: an agent as the transport knows it, published on every blackboard (the UI, the mission
and `erni peers` read it). `erni.blackboard.schemas` re-exports it."""

from __future__ import annotations

from pydantic import Field

from erni.blackboard.objects import BBObject
from erni.blackboard.text import Name

__all__ = ["Peer"]


class Peer(BBObject):
    """An agent known to this one: where it is, what it is, whether it is heard."""

    name: Name
    address: str = ""
    role: str = ""
    capabilities: list[str] = Field(default_factory=list)
    last_heard: float = 0.0
    up: bool = False
    epoch: int = Field(0, description="this agent's count of the peer's instances (a restart adds one)")
    degraded: str = Field("", description="why the peer cannot take new tasks ('' when it can)")
