"""Authorization, a collaborator of the transport plugin: whether a verified message's sender may
send it (`policy.py`, every kind, default deny), and what a refusal does (counted, logged at most
once per sender, kind and rule every 10 s, a refused task's requester told).

The policy's facts about tasks and statuses (who gave a task, who performs it, who holds a status
uid, the role of the agent a task is relayed to) are asked of the collaborators that keep them.
"""

from __future__ import annotations

import math

from erni.blackboard import AllocationResult, BBObject, Plugin, Task, TaskState
from erni.blackboard.schemas import ResultUpdate
from erni.transport.endpoint import Endpoint
from erni.transport.policy import OPERATORS, Refusal, check_relay, check_status, check_task, check_watch
from erni.transport.presence import Presence
from erni.transport.replication import StatusReplication
from erni.transport.settings import TransportSettings
from erni.transport.tasking import Relayed, Tasking
from erni.transport.wire import Message


class Authorization:
    """The role policy applied to every message a run handles, and the refusals it makes."""

    def __init__(self, plugin: Plugin[TransportSettings], endpoint: Endpoint, tasking: Tasking, presence: Presence,
                 replication: StatusReplication) -> None:
        self.endpoint, self.tasking, self.presence, self.replication = endpoint, tasking, presence, replication
        self.log, self.clock, self.me = plugin.log, plugin.clock, plugin.agent_name
        self._refused_at: dict[tuple[str, str, str], float] = {}  # (sender, kind, rule) -> last logged (monotonic)
        self._refused_more: dict[tuple[str, str, str], int] = {}  # ... refusals since, not logged

    def check(self, msg: Message) -> None:
        """Raise Refusal unless the policy lets `msg`'s sender send it (every kind, default deny)."""
        kind, body, sender, role = msg.kind, msg.body, msg.sender, msg.role
        if kind in ("task.add", "task.relay"):
            self._check_task(msg)
        elif kind in ("task.cancel", "task.rescind", "task.result", "task.query"):
            self._check_about_task(kind, getattr(body, "uid", ""), sender, role)
        elif kind == "status":
            if not isinstance(body, BBObject):
                raise Refusal("status", "a status that is no blackboard object")
            check_status(sender, role, body)
            self.replication.check_holder(sender, body.uid)
        elif kind in ("status.fresh", "status.remove"):
            self.replication.check_holder(sender, getattr(body, "uid", ""))
        elif kind in ("watch.request", "peers.request"):
            check_watch(role)
        elif kind not in ("beacon", "status.resend"):
            raise Refusal("kind", f"no rule lets anyone send {kind[:64]!r}")

    def _check_task(self, msg: Message) -> None:
        """A task given (`task.add`) or relayed (`task.relay`): may its originator give it, to this
        agent or, relayed on, to its destination, and may the relay relay for its originator?"""
        kind, body, sender, role = msg.kind, msg.body, msg.sender, msg.role
        me = self.endpoint.role
        task, origin_role = (body, role) if isinstance(body, Task) else (body.task, body.role) \
            if isinstance(body, Relayed) else (None, "")
        if task is None:
            raise Refusal("kind", f"a {kind} without a task")
        if kind == "task.relay":
            if not task.source or task.source == sender:
                raise Refusal("relay", "a relayed task must name its originator as its source")
            check_relay(role, origin_role)
        dest = task.destination
        if dest in (None, "", self.me):
            check_task(origin_role, me, task.verb, task.preposition)
        else:  # we are asked to relay it on: may we, for its originator, and may it task that agent?
            check_relay(me, origin_role)
            check_task(origin_role, self.presence.role_of(dest), task.verb, task.preposition)

    def _check_about_task(self, kind: str, uid: str, sender: str, role: str) -> None:
        """A message about task `uid`: a cancel or rescind from its requester (a cancel from an operating
        role too), a result from its performer, a query from either (or an operating role)."""
        if kind in ("task.cancel", "task.rescind"):
            requester = self.tasking.requester(uid)
            if requester is not None and requester != sender and (kind == "task.rescind" or role not in OPERATORS):
                raise Refusal("requester", f"task {uid[:64]} was given by {requester}, not {sender}")
        elif kind == "task.result":
            performer = self.tasking.performer(uid)
            if performer is not None and performer != sender:
                raise Refusal("performer", f"task {uid[:64]} is performed by {performer}, not {sender}")
        elif role not in OPERATORS and sender not in (self.tasking.requester(uid), self.tasking.performer(uid)):
            raise Refusal("query", f"role {role or '(none)'} may query only its own tasks")

    def refused(self, msg: Message, refusal: Refusal) -> None:
        """Count a refusal; log it once per sender, kind and rule every 10 s; tell a task's sender."""
        self.endpoint.count(f"refused.{refusal.rule}")
        key = (msg.sender, msg.kind, refusal.rule)
        mono = self.clock()
        if mono - self._refused_at.get(key, -math.inf) >= 10.0:
            more = self._refused_more.pop(key, 0)
            self._refused_at[key] = mono
            if len(self._refused_at) > 4096:  # bounded: forget the oldest
                del self._refused_at[next(iter(self._refused_at))]
            self.log.warning("refused %s from %s (role %s): rule %s: %s%s", msg.kind, msg.sender[:64],
                             msg.role[:32] or "(none)", refusal.rule, refusal,
                             f" (+{more} more since)" if more else "")
        elif len(self._refused_more) < 4096 or key in self._refused_more:
            self._refused_more[key] = self._refused_more.get(key, 0) + 1
        task = msg.body.task if isinstance(msg.body, Relayed) else msg.body
        if msg.kind in ("task.add", "task.relay") and isinstance(task, Task):  # its requester must not wait
            result = AllocationResult(state=TaskState.FAILED,
                                      message=f"refused by {self.me}: not authorized: {refusal}")
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=task.uid, result=result),
                               reliable=True, to=msg.sender)
