"""Remote tasking, a collaborator of the transport plugin: tasks sent to their performers and tasks
given to this agent by a requester (or relayed through it).

- A task whose `destination` is another agent is sent (reliably) when it is published and
  cancelled there when it is removed here; one whose performer is not discovered yet waits for it
  up to `task_ttl`. If its performer is not heard for `link_deadline` seconds the task fails with
  `link lost: ...` (a performer back in time goes on as if nothing happened; one back later is
  told to cancel the task).
- A task received from a peer appears on this blackboard as a task from that source; its result
  changes travel back to the peer it came from (UDP; a final state once, over TCP). An agent that
  cannot keep tasks (its journal cannot write) refuses new ones with the reason.

What it knows of each task is its own (`tasks_out`, `tasks_in`); where a peer is and when it was
last heard it asks `Presence`; what it changes goes on the blackboard through the plugin.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from pydantic import ConfigDict, Field

from erni.blackboard import AllocationResult, BBObject, Plugin, Task, TaskState
from erni.blackboard.errors import ConfigError
from erni.blackboard.objects import Model
from erni.blackboard.schemas import Cancel, ResultUpdate, TaskQuery, TaskRescind, TaskUnknown
from erni.transport.bounds import SenderBounds
from erni.transport.endpoint import Address, Endpoint, parse_address
from erni.transport.presence import Presence
from erni.transport.settings import TransportSettings
from erni.transport.wire import Message, register_type


class Received(BBObject):
    """Durable note of which peer gave this agent a task, so results find their way after a restart."""

    durable: ClassVar[bool] = True

    task: str
    sender: str
    address: str = Field("", description="the sender's reply address, HOST:PORT")
    role: str = Field("", description="the role of the task's originator (the relay's statement for a "
                      "relayed task)")


class Relayed(Model):
    """A task forwarded by a relay (`task.relay`): the relay states the role of its originator
    (`task.source`), and the receiver checks that the relay may relay for that role and that the
    originator may give the task."""

    model_config = ConfigDict(extra="forbid")

    task: Task
    role: str = Field(max_length=32)


for _cls in (Received, Relayed):  # the transport's own wire types (the blackboard's are the wire's)
    register_type(_cls)


class Tasking:
    """Tasks out to their performers and in from their requesters, for one transport plugin."""

    def __init__(self, plugin: Plugin[TransportSettings], endpoint: Endpoint, presence: Presence,
                 bounds: SenderBounds, *, degraded: Callable[[], str], keep: Callable[[Message], None],
                 count: Callable[[str], None]) -> None:
        self.plugin, self.endpoint, self.presence, self.bounds = plugin, endpoint, presence, bounds
        self.settings, self.log, self.clock, self.me = plugin.settings, plugin.log, plugin.clock, plugin.agent_name
        self.degraded, self.keep, self._count = degraded, keep, count
        self.tasks_out: dict[str, TaskOut] = {}  # task uid -> what we know of a task we sent to its performer
        self.tasks_in: dict[str, TaskIn] = {}  # task uid -> what we know of a task given to us (or relayed)
        self._waiting = 0  # records of tasks_out whose performer is not discovered yet (`retry_pending`)

    # -- what the blackboard brings (each run) ---------------------------------------------

    def restore(self, receipts: Sequence[Received]) -> None:
        """After a restart: who gave us which task, and where (the durable `Received` notes)."""
        for receipt in receipts:
            self.bounds.task(receipt.sender, receipt.task)
            given = self.task_in(receipt.task)
            if given.sender is None:
                given.sender = receipt.sender
            if receipt.role and given.origin_role is None:
                given.origin_role = receipt.role
            if receipt.address:
                try:
                    addr = parse_address(receipt.address)
                except ConfigError:
                    continue
                if given.reply_to is None:
                    given.reply_to = addr
                self.presence.reply_known(receipt.sender, addr)

    def published(self, added: Sequence[Task], changed: Sequence[Task]) -> None:
        """Tasks added here (sent to their performers, re-sent after a restart) and results of tasks
        given to us (sent back to their requesters)."""
        me = self.me
        for task in added:
            if self.plugin.rehydrated(task):
                self.reconcile(task)
            elif (task.destination not in (None, "", me) and self.settings.forward_tasks
                  and self.requester(task.uid) != task.destination):
                self.send_task(task)
        for task in [*added, *changed]:  # added and changed in one window: added
            origin = self.requester(task.uid)
            if origin and task.result is not None:
                self.send_result(origin, task)

    def removed(self, tasks: Sequence[Task]) -> None:
        """Tasks gone from the blackboard: cancelled at their performer, their records forgotten."""
        for task in tasks:
            self.bounds.task_gone(task.uid)
            sent = self.tasks_out.pop(task.uid, None)
            if sent is not None and sent.pending is not None:
                self._waiting -= 1
            if sent is not None and sent.dest:
                self.send_to_peer(sent.dest, "task.cancel", Cancel(uid=task.uid), reliable=True)
            received = self.tasks_in.pop(task.uid, None)
            if received is not None and received.sender and self.plugin.get(f"received:{task.uid}") is not None:
                self.plugin.remove(f"received:{task.uid}")

    # -- what is known of each task --------------------------------------------------------

    def task_in(self, uid: str) -> TaskIn:
        """The record of task `uid` given to us, made when first written."""
        given = self.tasks_in.get(uid)
        if given is None:
            given = self.tasks_in[uid] = TaskIn()
        return given

    def requester(self, uid: str) -> str | None:
        """The peer task `uid` came from (None: not given to us)."""
        given = self.tasks_in.get(uid)
        return given.sender if given is not None else None

    def performer(self, uid: str) -> str | None:
        """The peer task `uid` was sent to (None: not sent by us)."""
        sent = self.tasks_out.get(uid)
        return sent.dest if sent is not None else None

    def _stop_waiting(self, record: TaskOut) -> None:
        record.pending = None
        self._waiting -= 1

    def address_of(self, name: str, uid: str | None = None) -> Address | None:
        addr = self.presence.address_of(name)
        if addr is not None:
            return addr
        given = self.tasks_in.get(uid) if uid is not None else None
        if given is not None and given.reply_to is not None:  # a client: the address its task came from
            return given.reply_to
        return self.presence.reply_address(name)

    def send_to_peer(self, name: str, kind: str, body: Any, *, reliable: bool, uid: str | None = None) -> bool:
        addr = self.address_of(name, uid)
        if addr is None:
            return False
        self.endpoint.send(addr, kind, body, reliable=reliable, to=name)
        self.presence.sent_to(name, self.clock())
        return True

    def send_task(self, task: Task) -> None:
        dest = task.destination
        assert dest is not None
        record = self.tasks_out.get(task.uid)
        if record is None:
            record = self.tasks_out[task.uid] = TaskOut(dest, self.clock())
        else:
            record.dest, record.sent_at = dest, self.clock()
        given = self.tasks_in.get(task.uid)
        if given is not None and given.sender:  # relayed: the receiver checks that we may relay for its originator
            sent = self.send_to_peer(dest, "task.relay", Relayed(task=task, role=given.origin_role or ""),
                                      reliable=True)
        else:
            sent = self.send_to_peer(dest, "task.add", task, reliable=True)
        if not sent:
            if record.pending is None:
                self._waiting += 1
            record.pending = (dest, self.clock() + self.settings.task_ttl)
            self.log.info("task %s waits for agent %s to be discovered", task.uid, dest)
            return
        latest = self._task_now(task.uid)  # this run may have applied its performer's result already
        if latest is not None and not latest.result:
            self.plugin.change(latest.with_result(TaskState.PENDING, message=f"sent to {dest}"))

    def _task_now(self, uid: str) -> Task | None:
        """The task as this run leaves it so far: a change is built on it, never on an older version."""
        task = self.plugin.current(uid)
        return task if isinstance(task, Task) else None

    def reconcile(self, task: Task) -> None:
        """After a restart: re-send unfinished tasks we pass on; report on tasks we were given."""
        me = self.me
        if task.destination not in (None, "", me) and self.settings.forward_tasks:
            if not task.done:  # ours or relayed: the receiver de-duplicates by uid
                self.log.info("re-sending task %s to %s after restart", task.uid, task.destination)
                self.send_task(task)
        origin = self.requester(task.uid)
        if origin and task.result is not None and task.destination in (None, "", me):
            self.task_in(task.uid).final_sent = False  # the requester may have missed it while we were away
            self.send_result(origin, task)

    def retry_pending(self) -> None:
        if not self._waiting:  # O(tasks sent) only while some wait
            return
        mono = self.clock()
        for uid, record in list(self.tasks_out.items()):
            if record.pending is None:
                continue
            dest, deadline = record.pending
            task = self._task_now(uid)
            if task is None or task.done:
                self._stop_waiting(record)
            elif self.address_of(dest) is not None:
                self._stop_waiting(record)
                self.send_task(task)
            elif mono > deadline:
                self._stop_waiting(record)
                self.plugin.change(task.with_result(TaskState.FAILED, message=f"unknown agent {dest}: "
                                             "never discovered"))

    def check_links(self) -> None:
        """Fail tasks whose performer has not been heard for `link_deadline` seconds."""
        deadline = self.settings.link_deadline
        mono = self.clock()
        for uid, record in list(self.tasks_out.items()):
            if record.lost or record.pending is not None:
                continue
            dest = record.dest
            since = max(self.presence.heard_at(dest), record.sent_at)
            if mono - since <= deadline:
                continue
            task = self._task_now(uid)
            if task is None or task.done:
                continue
            record.lost = True
            self.log.warning("task %s: link lost: %s not heard for %.0f s", uid, dest, mono - since)
            self.plugin.change(task.with_result(TaskState.FAILED, message=f"link lost: {dest} not heard for "
                                         f"{mono - since:.0f} s (link_deadline {deadline:g} s)"))
            self.send_to_peer(dest, "task.cancel", Cancel(uid=uid), reliable=True)

    def send_result(self, origin: str, task: Task) -> None:
        if task.result is None:
            return
        update = ResultUpdate(uid=task.uid, result=task.result)
        if not task.done:
            self.send_to_peer(origin, "task.result", update, reliable=False, uid=task.uid)
        elif not (given := self.task_in(task.uid)).final_sent:  # a final state once, and reliably
            given.final_sent = True
            self.send_to_peer(origin, "task.result", update, reliable=True, uid=task.uid)

    def undeliverable(self, addr: Address, kind: str, body: Any) -> None:
        if kind == "task.relay" and isinstance(body, Relayed):
            kind, body = "task.add", body.task
        if kind == "task.add" and isinstance(body, Task):
            task = self._task_now(body.uid)
            if task is not None and not task.done:
                self.plugin.change(task.with_result(
                    TaskState.FAILED, message=f"link lost: could not deliver to {task.destination} "
                    f"at {addr[0]}:{addr[1]}"))

    def on_rescind(self, msg: Message, body: TaskRescind) -> None:
        if self.requester(body.uid) == msg.sender and self.plugin.get(body.uid) is not None:
            self.log.info("task %s was rescinded by %s (it no longer has it)", body.uid, msg.sender)
            self.plugin.remove(body.uid)

    def on_cancel(self, msg: Message, body: Cancel) -> None:
        requester = self.requester(body.uid)
        if requester is not None and requester != msg.sender:  # an operator's (`_authorized`)
            self.cancelled_by_operator(msg, body.uid, requester)
        elif requester == msg.sender and self.plugin.get(body.uid) is not None:
            self.plugin.remove(body.uid)

    def on_query(self, msg: Message, body: TaskQuery) -> None:
        known = self.plugin.get(body.uid)
        if isinstance(known, Task):
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=known.uid, result=known.result
                                                                      or AllocationResult()),
                               reliable=False, to=msg.sender)
        else:
            self.endpoint.send(msg.reply, "task.unknown", TaskUnknown(uid=body.uid), reliable=False, to=msg.sender)

    def cancelled_by_operator(self, msg: Message, uid: str, requester: str) -> None:
        """An operating role cancels a task another agent gave: its requester gets the final state
        (`cancelled by NAME`), then the task leaves, as at its requester's own cancel."""
        task = self._task_now(uid)
        if task is None:
            return
        self.log.info("task %s of %s cancelled by %s (role %s)", uid, requester, msg.sender, msg.role)
        given = self.tasks_in.get(uid)
        if not task.done and not (given is not None and given.final_sent):
            self.task_in(uid).final_sent = True
            update = ResultUpdate(uid=uid, result=AllocationResult(
                state=TaskState.CANCELLED, message=f"cancelled by {msg.sender} ({msg.role})"))
            self.send_to_peer(requester, "task.result", update, reliable=True, uid=uid)
        self.plugin.remove(uid)

    def task_added(self, msg: Message, body: Task, origin: str, role: str) -> None:
        """A task from `msg.sender`, given by `origin` of `role` (the sender itself, or the originator
        a relay named)."""
        if body.source != origin:
            body = body.evolve(source=origin)  # the source is who asked, as authenticated or relayed
        known = self.plugin.current(body.uid)
        if known is not None:  # the requester restarted and re-sent it: tell it where we are
            self.keep(msg)  # (its journal write may still be on its way)
            if self.requester(body.uid) in (None, msg.sender) and isinstance(known, Task):
                given = self.task_in(body.uid)
                given.sender, given.reply_to = msg.sender, msg.reply
                if known.result is not None:
                    given.final_sent = False
                    self.send_result(msg.sender, known)
            return
        reason = self.degraded()
        if reason:  # never acknowledge what this agent cannot keep
            self.log.warning("refused task %s from %s: %s", body.uid, msg.sender, reason)
            refusal = AllocationResult(state=TaskState.FAILED, message=f"refused by {self.me}: {reason}")
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=body.uid, result=refusal),
                               reliable=True, to=msg.sender)
            return
        if self.bounds.task_full(msg.sender) and not self._make_room(msg.sender):
            s = self.settings
            why = (f"{msg.sender} has {s.tasks_per_requester} unfinished tasks here (tasks_per_requester = "
                   f"{s.tasks_per_requester})")
            self.bounds.refuse("refused.task_bound", msg.sender, "tasks", f"task {body.uid[:64]} refused: {why}")
            refusal = AllocationResult(state=TaskState.FAILED, message=f"refused by {self.me}: {why}")
            self.endpoint.send(msg.reply, "task.result", ResultUpdate(uid=body.uid, result=refusal),
                               reliable=True, to=msg.sender)
            return
        given = self.task_in(body.uid)
        given.sender, given.reply_to, given.origin_role = msg.sender, msg.reply, role
        self.bounds.task(msg.sender, body.uid)
        self.plugin.add(body)
        self.plugin.add(Received(uid=f"received:{body.uid}", task=body.uid, sender=msg.sender,
                          address=f"{msg.reply[0]}:{msg.reply[1]}", role=role))
        self.keep(msg)

    def _make_room(self, requester: str) -> bool:
        """At `requester`'s bound of tasks: its oldest finished task leaves now instead of after the
        retention (its performer is told, as at retention); False when none of them is finished."""
        for uid in self.bounds.tasks_of(requester):
            task = self._task_now(uid)
            if task is None or task.done:
                self.bounds.task_gone(uid)
                if task is not None:
                    self.plugin.remove(uid)
                    self._count("evicted.task_bound")
                return True
        return False

    def apply_result(self, msg: Message, update: ResultUpdate) -> None:
        task = self.plugin.current(update.uid)
        if task is None:  # a result for a task we no longer have: stale, rescind it there
            self.endpoint.send(msg.reply, "task.rescind", TaskRescind(uid=update.uid), reliable=True, to=msg.sender)
            return
        sent = self.tasks_out.get(update.uid)
        if sent is None or sent.dest != msg.sender:
            return
        if not isinstance(task, Task) or task.done or sent.final_seen:  # a final state is
            if sent.lost and not update.result.state.done:  # never overwritten; back too late:
                self.endpoint.send(msg.reply, "task.cancel", Cancel(uid=update.uid), reliable=True, to=msg.sender)
            return  # stop it there
        stamp = (msg.epoch, msg.seq)
        final = update.result.state.done  # the last word, whatever its number: a status sent before it
        applied = sent.last_result or (0, 0)
        if stamp <= applied and not final:  # may be numbered after it
            return  # an older update never overwrites a newer one
        sent.last_result = max(stamp, applied)
        if final:
            sent.final_seen = True
        self.plugin.change(task.evolve(result=update.result), reports=[f"result from {msg.sender}"])


@dataclass(slots=True)
class TaskOut:
    """A task this agent sent to its performer (`send_task`), until the task leaves the board."""

    dest: str  # the peer it was sent to
    sent_at: float  # when it was sent (monotonic)
    pending: tuple[str, float] | None = None  # (destination, deadline) while the destination is not discovered
    lost: bool = False  # failed because its performer was not heard in time
    last_result: tuple[int, int] | None = None  # (epoch, seq) of the performer's result applied
    final_seen: bool = False  # the performer's final result was applied


@dataclass(slots=True)
class TaskIn:
    """A task given to this agent (to perform or to relay), until the task leaves the board."""

    sender: str | None = None  # the peer it came from
    origin_role: str | None = None  # role of its originator (relayed: as its relay stated)
    reply_to: Address | None = None  # address of the agent or client it came from
    final_sent: bool = False  # its final state went back to its requester
