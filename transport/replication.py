"""Status replication, a collaborator of the transport plugin: this agent's shared objects (`share`,
`share_with`: Poses, network information ...) sent to the peers of the roles that receive them, and
the statuses of peers held here.

A change of nothing but an object's `stamp` goes as a `Fresh` note to the peers that hold its whole
version (the whole object again at least every `status_refresh`); a receiver that lost that version
asks for it whole (`status.resend`). A status uid is held by the one sender that sent it until that
sender removes it; an older status never overwrites a newer one, and a peer's never overwrites an
object of our own. What one sender may make us hold is bounded (`SenderBounds`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from pydantic import BaseModel

from erni.blackboard import BBObject, Plugin
from erni.blackboard.errors import ConfigError
from erni.blackboard.objects import only_stamp_differs
from erni.blackboard.schemas import Fresh, StatusRemoved, StatusResend
from erni.transport.bounds import SenderBounds
from erni.transport.endpoint import Address, Endpoint, parse_address
from erni.transport.policy import STATUS, Refusal
from erni.transport.presence import Presence
from erni.transport.settings import TransportSettings
from erni.transport.wire import Message


class StatusReplication:
    """Statuses out to the peers that receive them, and in from the peers that hold them."""

    def __init__(self, plugin: Plugin[TransportSettings], endpoint: Endpoint, presence: Presence,
                 bounds: SenderBounds) -> None:
        self.plugin, self.endpoint, self.presence, self.bounds = plugin, endpoint, presence, bounds
        self.settings, self.clock = plugin.settings, plugin.clock
        self.status_in: dict[str, tuple[int, int]] = {}  # uid of a status received -> (epoch, seq) of its owner
        self.status_owner: dict[str, str] = {}  # uid of a status received -> the one sender that holds it
        self.status_base: dict[str, float] = {}  # uid of a status received -> stamp of the whole version held
        self.whole_sent: dict[str, Sent] = {}  # uid of a shared object of ours -> its last whole version sent
        self._resend_asked: dict[str, float] = {}  # uid of a status received -> when we last asked for it whole
        self._targets: dict[str, tuple[int, list[Target], frozenset[tuple[str, int]]]] = {}  # `_status_targets`
        shared = set(self.settings.share) | set(self.settings.share_with)
        # our own shared objects: a status received from a peer (status_in) is committed by us and
        # must not run us again (a control node receives ten Poses a second from every robot)
        self.shared = plugin.subscribe(lambda o: type(o).__name__ in shared and o.uid not in self.status_in)

    def on_resend(self, msg: Message, body: StatusResend) -> None:
        """A peer lost the whole version of one of ours: its next change goes whole again."""
        sent = self.whole_sent.get(body.uid)
        if sent is not None:  # its next change goes whole again
            sent.holders = frozenset(h for h in sent.holders if h[0] != msg.sender)

    def on_removed(self, msg: Message, body: StatusRemoved) -> None:
        """A peer removed a status of its own: forgotten here, and off the blackboard."""
        self.bounds.status_gone(body.uid)
        self.status_base.pop(body.uid, None)
        self._resend_asked.pop(body.uid, None)
        self.status_owner.pop(body.uid, None)
        if self.status_in.pop(body.uid, None) is not None and self.plugin.get(body.uid) is not None:
            self.plugin.remove(body.uid)

    def check_holder(self, sender: str, uid: str) -> None:
        """A status uid is held by one sender (until it removes it): no other may change or remove it."""
        holder = self.status_owner.get(uid)
        if holder is not None and holder != sender:
            raise Refusal("status", f"{uid[:64]} is held by {holder}, not {sender}")

    def share(self) -> None:
        """Send this agent's own shared objects (poses, network info) to the status peers.

        A change of nothing but an object's `stamp` (a keep-alive: a standing robot's Pose, a
        network reading that did not change) goes as a `Fresh` note to peers that were sent the
        whole object, unless `status_refresh` has passed since: a control node hears of every
        robot's network topology each second, and the whole of it only when it changed."""
        objs = self.shared.added + self.shared.changed
        gone = self.shared.removed
        if not objs and not gone:
            return
        s = self.settings
        mono = self.clock()
        for obj in objs:
            targets, holders = self._status_targets(type(obj).__name__)
            if not targets:
                continue
            sent = self.whole_sent.get(obj.uid)
            if sent is not None and holders <= sent.holders and mono - sent.at < s.status_refresh \
                    and only_stamp_differs(sent.obj, obj):
                self._send_status(targets, "status.fresh", Fresh(uid=obj.uid, base=sent.obj.stamp,  # type: ignore[attr-defined]
                                                                 stamp=obj.stamp), False, mono)  # type: ignore[attr-defined]
                continue
            self._send_status(targets, "status", obj, False, mono)
            if isinstance(getattr(obj, "stamp", None), float):
                self.whole_sent[obj.uid] = Sent(obj, mono, holders)
        for obj in gone:  # removals reliably: a stale object would stay forever
            self.whole_sent.pop(obj.uid, None)
            self._send_status(self._status_targets(type(obj).__name__)[0], "status.remove", StatusRemoved(uid=obj.uid),
                              True, mono)

    def _status_targets(self, type_name: str) -> tuple[list[Target], frozenset[tuple[str, int]]]:
        """The peers (name, address, epoch) that an object of `type_name` is shared with, and the set
        of their (name, epoch): worked out again only when the directory changed who is up where
        (a robot shares ten Poses a second; its peers' liveness alone changes nothing here)."""
        cached = self._targets.get(type_name)
        if cached is not None and cached[0] == self.presence.directory.gen:
            return cached[1], cached[2]
        s = self.settings
        roles = s.share_with.get(type_name, s.share_with_roles)
        targets = []
        for p in self.presence.directory.values():
            if p.up and p.address and p.role in roles:
                try:
                    targets.append(Target(p.name, parse_address(p.address), p.epoch))
                except ConfigError:
                    continue
        holders = frozenset((t.name, t.epoch) for t in targets)
        self._targets[type_name] = (self.presence.directory.gen, targets, holders)
        return targets, holders

    def _send_status(self, targets: list[Target], kind: str, body: BaseModel, reliable: bool, mono: float) -> None:
        """Send a status to its peers: a fast one as one burst (encoded once, sealed per peer, the
        datagrams handed to the socket back to back), a reliable one to each peer's queue."""
        fanout = getattr(self.endpoint, "send_fanout", None)  # a test's in-memory endpoint has none
        if reliable or len(targets) < 2 or fanout is None:
            for t in targets:
                self.endpoint.send(t.address, kind, body, reliable=reliable, to=t.name)
        else:
            fanout([(t.address, t.name) for t in targets], kind, body)
        for t in targets:
            self.presence.sent_to(t.name, mono)

    def apply_status(self, msg: Message, obj: BBObject) -> None:
        """A peer's status: on the blackboard unless older than the one held, or beyond its bounds."""
        stamp = (msg.epoch, msg.seq)
        if stamp <= self.status_in.get(obj.uid, (0, 0)):
            return  # an older status never overwrites a newer one
        first = obj.uid not in self.status_in  # (two statuses of a new object may come in one run)
        if first and self.plugin.get(obj.uid) is not None:
            return  # never overwrite an object of our own with a peer's
        why = self._hold_status(msg.sender, obj)
        if why:
            self.bounds.refuse("refused.status_bound", msg.sender, f"status {type(obj).__name__}", why)
            return
        self.status_in[obj.uid] = stamp
        self.status_owner[obj.uid] = msg.sender
        base = getattr(obj, "stamp", None)
        if isinstance(base, float):
            self.status_base[obj.uid] = base
        if first:
            self.plugin.add(obj)
        else:
            self.plugin.change(obj, reports=[f"status from {msg.sender}"])

    def _hold_status(self, sender: str, obj: BBObject) -> str:
        """'' when `sender`'s status `obj` fits its bounds (held from now on), else why not. A type whose
        uid the policy fixes (one per sender: a Pose, a Peer) is not counted: its one object is at most
        a frame."""
        name = type(obj).__name__
        rule = STATUS.get(name)
        if rule is not None and rule.uid:
            return ""
        return self.bounds.status(sender, name, obj.uid, len(obj.model_dump_json()))

    def apply_fresh(self, msg: Message, note: Fresh) -> None:
        """A peer's shared object is unchanged but for its stamp: if we hold the version it was
        sent whole as, take the new stamp; else (that version was lost) ask for it whole."""
        stamp = (msg.epoch, msg.seq)
        if stamp <= self.status_in.get(note.uid, (0, 0)):
            return
        held = self.plugin.get(note.uid) if note.uid in self.status_in else None
        if held is None or self.status_base.get(note.uid) != note.base:
            now = self.clock()
            if now - self._resend_asked.get(note.uid, -math.inf) >= 1.0:
                if len(self._resend_asked) >= 4096 and note.uid not in self._resend_asked:
                    del self._resend_asked[next(iter(self._resend_asked))]  # bounded: the oldest asked goes
                self._resend_asked[note.uid] = now
                self.endpoint.send(msg.reply, "status.resend", StatusResend(uid=note.uid), reliable=False, to=msg.sender)
            return
        self.status_in[note.uid] = stamp
        self.plugin.change(held.model_copy(update={"stamp": note.stamp}), reports=[f"status from {msg.sender}"])


class Target(NamedTuple):
    """A peer a status goes to: its name, its address parsed, and its epoch (the `holders` key)."""

    name: str
    address: Address
    epoch: int


class Sent:
    """The last whole version of a shared object sent, when, and to which peers (name, epoch)."""

    __slots__ = ("obj", "at", "holders")

    def __init__(self, obj: BBObject, at: float, holders: frozenset[tuple[str, int]]):
        self.obj, self.at, self.holders = obj, at, holders
