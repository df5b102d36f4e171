"""The messages the transport exchanges with command-line clients and other agents besides tasks.

`Beacon`, `ResultUpdate`, `Fresh`, `PeerList`, `WatchRequest`, `WatchEvent`, and one type for each
message that names a task or a shared object by its uid (`Cancel`, `TaskRescind`, `TaskQuery`,
`TaskUnknown`, `StatusResend`, `StatusRemoved`): the kind and its body say the same thing, so a body
of the wrong type is never acted on. `erni.blackboard.schemas` re-exports each of them.
"""

from __future__ import annotations

from pydantic import ConfigDict, Field

from erni.blackboard.objects import FiniteAny, Model
from erni.blackboard.peer import Peer
from erni.blackboard.tasks import AllocationResult
from erni.blackboard.text import Name

__all__ = ["Beacon", "Cancel", "Fresh", "PeerList", "ResultUpdate", "StatusRemoved", "StatusResend", "TaskQuery",
           "TaskRescind", "TaskUnknown", "WatchEvent", "WatchRequest"]


class _Message(Model):
    model_config = ConfigDict(extra="forbid")


class Beacon(_Message):
    """What an agent announces about itself."""

    role: str = ""
    capabilities: list[str] = Field(default_factory=list)
    degraded: str = Field("", description="why this agent refuses new tasks ('' when it takes them)")
    interval: float = Field(0.0, ge=0.0, le=3600.0, description="the longest the sender waits before its "
                            "next beacon to this receiver (s); 0: not said (the receiver's own timings)")
    seq: int = Field(0, ge=0, description="the number of this in-session beacon among those the sender "
                     "sent this receiver (from 1); 0: not counted (a broadcast, a session's first)")


class ResultUpdate(_Message):
    """A performer's new result for a task."""

    uid: str
    result: AllocationResult


class _ByUid(_Message):
    """A message that names a task or a shared object by its uid (one subclass per meaning)."""

    uid: str


class Cancel(_ByUid):
    """`task.cancel`: end a task: its requester removed it, or an operator cancels it."""


class TaskRescind(_ByUid):
    """`task.rescind`: the requester no longer holds a task it gave (its performer drops it)."""


class TaskQuery(_ByUid):
    """`task.query`: what is this task's result? Answered by `task.result`, or by `task.unknown`."""


class TaskUnknown(_ByUid):
    """`task.unknown`: the agent asked (`TaskQuery`) holds no task under this uid."""


class StatusResend(_ByUid):
    """`status.resend`: send this shared object whole at its next change (the asker missed the
    whole version a `Fresh` was based on)."""


class StatusRemoved(_ByUid):
    """`status.remove`: a shared object was removed by the agent that shared it."""


class Fresh(_Message):
    """A shared object still holds as sent whole when its stamp was `base`; only its stamp is now `stamp`."""

    uid: str
    base: float
    stamp: float


class PeerList(_Message):
    """The directory of an agent, sent to a client: in `parts` messages when one would not fit in a
    frame, each with some of the peers (`erni.transport.client.PeerListParts` puts them together)."""

    agent: Name
    peers: list[Peer]
    request: str = Field("", max_length=128, description="the id of the `peers.request` this answers")
    part: int = Field(0, ge=0, lt=10_000, description="which part of the answer this is, from 0")
    parts: int = Field(1, ge=1, le=10_000, description="how many parts the answer has")
    down_after: dict[str, float] = Field(default_factory=dict, description="peer -> the silence (s) that "
                                         "marks it down now: peer_timeout, scaled and stretched for a lossy link")
    beacons: dict[str, float] = Field(default_factory=dict, description="peer -> the share of its recent "
                                      "numbered beacons that arrived (only peers whose beacons were counted)")


class WatchRequest(_Message):
    """A client asks for blackboard changes for `lease` seconds."""

    lease: float = Field(10.0, gt=0, le=3600)


class WatchEvent(_Message):
    """One blackboard change sent to a watcher."""

    agent: Name
    op: str
    type: str
    data: dict[str, FiniteAny]
