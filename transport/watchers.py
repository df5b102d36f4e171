"""Watchers, a collaborator of the transport plugin: clients (`erni watch`) that lease a stream of
blackboard changes (tasks, poses, network information, peers) by `watch.request`; the stream
starts with the current state and ends when the lease does."""

from __future__ import annotations

from erni.blackboard import BBObject, NetInfo, Plugin, Pose, Task
from erni.blackboard.schemas import Peer, WatchEvent, WatchRequest
from erni.transport.endpoint import Address, Endpoint
from erni.transport.settings import TransportSettings
from erni.transport.wire import Message

WATCHED = (Task, Pose, NetInfo, Peer)


class Watchers:
    """The leases of the clients watching this agent, and their streams of changes."""

    def __init__(self, plugin: Plugin[TransportSettings], endpoint: Endpoint) -> None:
        self.plugin, self.endpoint, self.clock, self.me = plugin, endpoint, plugin.clock, plugin.agent_name
        self.watchers: dict[tuple[str, Address], float] = {}  # (client, its address) -> lease end
        self.watched = plugin.subscribe(lambda o: isinstance(o, WATCHED))
        self.watched.wakes = False  # only while a client watches: else every Pose or Peer change ran us again

    def on_request(self, msg: Message, body: WatchRequest) -> None:
        """A client's lease begins or is renewed (a new one gets the current state first)."""
        key = (msg.sender, msg.reply)
        new = key not in self.watchers
        self.watchers[key] = self.clock() + body.lease
        self.watched.wakes = True
        if new:  # start the stream with the current state
            for obj in self.plugin.query(lambda o: isinstance(o, WATCHED)):
                self._event(key, "add", obj)

    def forward(self) -> None:
        """Forget expired leases; send this run's changes to every watcher left."""
        mono = self.clock()
        for key, until in list(self.watchers.items()):
            if until < mono:
                del self.watchers[key]
        if not self.watchers:
            self.watched.wakes = False
            return
        for op, objs in (("add", self.watched.added), ("change", self.watched.changed),
                         ("remove", self.watched.removed)):
            for obj in objs:
                for key in self.watchers:
                    self._event(key, op, obj)

    def _event(self, watcher: tuple[str, Address], op: str, obj: BBObject) -> None:
        event = WatchEvent(agent=self.me, op=op, type=type(obj).__name__,
                           data=obj.model_dump(mode="json"))
        self.endpoint.send(watcher[1], "watch.event", event, reliable=False, to=watcher[0])
