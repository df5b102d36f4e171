"""The transport plugin: remote tasking through the blackboard, discovery, peer liveness, watchers.

- A task whose `destination` is another agent is sent (reliably) when it is published and
  cancelled there when it is removed here. If its performer is not heard for `link_deadline`
  seconds the task fails with `link lost: ...` (a performer back in time goes on as if nothing
  happened; one back later is told to cancel the task).
- A task received from a peer appears on this blackboard as a task from that source; its
  result changes travel back to the peer it came from (UDP; a final state once, over TCP).
  An agent that cannot keep tasks (its journal cannot write) refuses new ones with the reason.
- Signed beacons go to the configured broadcast/unicast addresses and to addresses learned
  from MobiNet's `NetInfo` where no peer is up: they only tell that an agent may be there. While every known peer
  is up and nothing new is learned, these announcements back off (doubling up to
  `announce_backoff` beacon periods); a newcomer still announces every period and is answered
  at once. Known peers get beacons inside their session, but only the quiet ones (nothing else
  sent to them for a beacon period: any session frame tells they are alive), and at most
  `beacon_fanout` of them a period: with more, each gets one less often and the beacon says
  how often, so its receiver waits as many periods longer. Only session traffic (fresh by
  construction) marks a peer up (a peer not up shows when its signed beacon was last heard; an
  agent running insecure has no sessions, so there any beacon marks its sender up), and a peer silent for `peer_timeout` (scaled by its announced
  interval, and stretched by the share of its numbered beacons that arrive: `liveness`) is down.
  A beacon that says nothing new (its peer up, at the same address and epoch) costs no run: the
  receive thread marks the peer heard, the liveness pass updates `last_heard`.
- Clients (`erni watch`) may lease a stream of blackboard changes; `erni task --wait` asks
  for a task's state (`task.query`).
- With `wire = "zenoh"` the same messages travel over Zenoh (`zenoh_wire.py`): no broadcast
  beacons; an agent's liveliness token stands for them, and a peer whose token goes is down at
  once (`_gone`).

All network traffic is handed to the endpoint's sender pool; received messages are handed
to `execute()` with `later()`, so nothing here does I/O inside a transaction.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

from erni.blackboard import BBObject, NetInfo, Plugin, Task
from erni.blackboard.errors import ConfigError
from erni.blackboard.schemas import (
    Cancel,
    Fresh,
    ResultUpdate,
    StatusRemoved,
    StatusResend,
    TaskQuery,
    TaskRescind,
    WatchRequest,
)
from erni.transport.authorization import Authorization
from erni.transport.bounds import SenderBounds
from erni.transport.endpoint import CLIENT_ROLE, STREAM_BUFFER, Endpoint, InboundFilter
from erni.transport.identity import IdentityError
from erni.transport.policy import Refusal
from erni.transport.presence import Presence
from erni.transport.replication import StatusReplication
from erni.transport.settings import TransportSettings
from erni.transport.tasking import Received, Relayed, Tasking
from erni.transport.watchers import WATCHED, Watchers
from erni.transport.wire import Message

__all__ = ["WATCHED", "Received", "Relayed", "TransportPlugin", "TransportSettings"]


class TransportPlugin(Plugin[TransportSettings]):
    """Bridges this agent's blackboard to the other agents of the team: composed of its tasking,
    presence, status replication, watchers and authorization, which it hands what each run and each
    message brings."""

    essential: ClassVar[bool] = True  # an agent that cannot reach its team must not run deaf
    endpoint_factory: Any = None  # tests may inject a mock network endpoint
    inbound_filter: InboundFilter | None = None
    """Set before the agent starts: `(sender, role) -> bool` decides which verified frames are
    delivered (`erni sim` hands its simulated radio to the transport this way)."""

    def setup(self) -> None:
        s = self.settings
        # peers' silence, task deadlines, watch leases and status refreshes are timed by the agent's
        # clock (`self.clock`), as is what expires in the endpoint (a test's ManualClock moves them all)
        if self.endpoint_factory is not None:
            self.endpoint: Endpoint = self.endpoint_factory(self.agent_name)
            self.endpoint.inbound_filter = self.inbound_filter
            self.endpoint.role = s.role  # its frames carry the agent's role, as a real session's do
        else:
            try:
                self.endpoint = s.make_endpoint(self.agent_name, self.inbound_filter, self.clock)
            except IdentityError as err:
                raise ConfigError(str(err)) from None
        # what other plugins may use of the transport, through the agent (never this plugin's attributes):
        # the role its frames carry and, on the Zenoh wire, the session the ROS 2 edge shares
        self.provide("transport.role", s.role)
        if s.wire == "zenoh":
            from erni.transport.zenoh_wire import ZenohEndpoint  # imports zenoh: only on its wire

            endpoint = self.endpoint
            if isinstance(endpoint, ZenohEndpoint):  # (not a test's mock endpoint)
                self.provide("transport.zenoh_session", lambda: endpoint.session)
        if s.insecure:
            self.log.warning("transport of %s runs WITHOUT authentication (insecure = true): any "
                             "host on the network can task this agent", self.agent_name)
        elif s.identity is None:
            self.log.info("transport of %s authenticates with a shared team key: any holder of the key "
                          "can speak as any agent (give identities on a real team: erni keys)", self.agent_name)
        count: Callable[[str], None] = getattr(self.endpoint, "count", None) or (lambda name: None)  # (a test's
        self.bounds = SenderBounds(s, count, self.log, self.clock)  # in-memory endpoint counts nothing)  # per sender: what it may make us hold
        self.tasks = self.subscribe(Task)
        self.receipts = self.subscribe(Received)
        self.netinfo = self.subscribe(NetInfo)
        degraded = lambda: self._degraded()  # noqa: E731  # looked up at each call
        self.presence = Presence(self, self.endpoint, self.bounds, degraded=degraded, count=count)
        self.tasking = Tasking(self, self.endpoint, self.presence, self.bounds, degraded=degraded,
                               keep=self._keep, count=count)
        self.replication = StatusReplication(self, self.endpoint, self.presence, self.bounds)
        self.watchers = Watchers(self, self.endpoint)
        self.authorization = Authorization(self, self.endpoint, self.tasking, self.presence, self.replication)
        # the collaborators' tables under the names tools and tests read them by
        self.peers, self.directory, self.learned = self.presence.peers, self.presence.directory, self.presence.learned
        self.tasks_in, self.tasks_out = self.tasking.tasks_in, self.tasking.tasks_out
        self.status_owner, self.status_in = self.replication.status_owner, self.replication.status_in
        self.presence.add_static()
        self._next_liveness = 0.0  # beacons and silences are looked at a few times a period
        self._next_link_check = 0.0  # performers' silences are looked at a few times a period
        self._kinds = self._kind_table()
        # a task is acknowledged once this agent's journal holds it (it survives a kill -9): the
        # acknowledgement of a task.add or task.relay waits for the journal's next write (`_keep`)
        self.endpoint.held_kinds = frozenset({"task.add", "task.relay"})
        self.endpoint.on_message = self._received
        self.endpoint.hint_wanted = self.presence.hint_wanted
        self.endpoint.on_gone = lambda name: self.later(lambda: self.presence.gone(name))
        self.endpoint.on_undeliverable = lambda addr, mid, kind, body: self.later(
            lambda: self.tasking.undeliverable(addr, kind, body))
        self.endpoint.start()
        self.address = self.endpoint.address
        room = s.receive_buffer if s.receive_buffer is not None else (STREAM_BUFFER if s.role == "control" else 0)
        if room:  # a burst of Poses that arrives while the agent is held back waits here, not lost
            got = self.endpoint.receive_buffer(room)
            if got < room:
                self.log.info("UDP receive buffer: %d bytes granted of %d asked (net.core.rmem_max caps it "
                              "without root)", got, room)
        if s.wire == "zenoh":
            self.log.info("agent %s on Zenoh (%s, team %s%s)", self.agent_name, s.zenoh.mode, s.zenoh.team,
                          f", connect {' '.join(s.zenoh.connect)}" if s.zenoh.connect else "")
        else:
            self.log.info("agent %s listening on %s:%d (TCP+UDP), beacons on port %s", self.agent_name,
                          *self.address, s.discovery_port or "off")
        self.wake_every(s.beacon_period)
        self.wake()

    def teardown(self) -> None:
        self.endpoint.stop()

    def _degraded(self) -> str:
        """Why this agent cannot keep new tasks ('' when it can)."""
        return str(getattr(self._require_agent(), "degraded", "") or "")

    # -- each run -------------------------------------------------------------------------

    def execute(self) -> None:
        self.tasking.restore(self.receipts.added)
        self.tasking.published(self.tasks.added, self.tasks.changed)
        self.tasking.removed(self.tasks.removed)
        self.presence.learn_from(self.netinfo.added + self.netinfo.changed)
        self.replication.share()
        self.tasking.retry_pending()
        self.watchers.forward()
        mono = self.clock()
        if mono >= self._next_liveness:  # O(peers): not on every run of a busy agent
            self._next_liveness = mono + self.settings.beacon_period / 4
            self.presence.beacon_and_liveness()
        if mono >= self._next_link_check:  # O(tasks sent): a control node runs for every Pose it receives
            self._next_link_check = mono + min(self.settings.beacon_period, self.settings.link_deadline) / 4
            self._check_links()

    def _check_links(self) -> None:
        """Fail tasks whose performer has not been heard for `link_deadline` seconds."""
        self.tasking.check_links()

    # -- incoming -------------------------------------------------------------------------

    def _received(self, msg: Message) -> None:
        """Hand a message to a run, unless it is an in-session beacon that tells nothing new: then it
        only marks its peer heard (the liveness pass puts that on the board). Runs on the endpoint's
        receive thread; in a team of N each agent hears up to `beacon_fanout` of these a period."""
        if not self.presence.repeated(msg):
            self.later(lambda: self._handle(msg))

    def _handle(self, msg: Message) -> None:
        try:
            self._handle_message(msg)
        finally:
            ack, msg.ack = msg.ack, None
            if ack is not None:  # a held acknowledgement nothing durable waits for (refused, or no task)
                ack()

    def _keep(self, msg: Message) -> None:
        """Acknowledge `msg` once what this run publishes is durable: after the run's commit, at the
        journal's next write (group commit: the tasks of one write are acknowledged together)."""
        ack, msg.ack = msg.ack, None
        if ack is not None:
            agent = self._require_agent()
            self.after_commit(lambda: agent.when_durable(ack))

    def _handle_message(self, msg: Message) -> None:
        if msg.hint:  # a broadcast beacon: signed but replayable, so only a hint of presence
            if msg.kind == "beacon" and msg.role != CLIENT_ROLE:
                self.presence.hinted(msg)
            return
        self.presence.replied_from(msg.sender, msg.reply)
        if msg.role != CLIENT_ROLE:  # a command-line client is not a peer
            self.presence.heard(msg.sender, msg.reply, msg.epoch, msg.body if msg.kind == "beacon" else None, msg.role)
        try:
            self.authorization.check(msg)
        except Refusal as refusal:
            self.authorization.refused(msg, refusal)
            return
        handler = self._kinds.get(msg.kind)
        if handler is not None and isinstance(msg.body, handler[0]):
            handler[1](msg, msg.body)

    def _kind_table(self) -> dict[str, tuple[type | tuple[type, ...], Callable[[Message, Any], None]]]:
        """The handler of each kind of message, with the type its body must have (anything else is
        not acted on: the authorization has already let the sender send that kind)."""
        tasking, replication = self.tasking, self.replication
        return {
            "task.add": (Task, lambda msg, task: tasking.task_added(msg, task, msg.sender, msg.role)),
            "task.relay": (Relayed, lambda msg, relayed: tasking.task_added(msg, relayed.task, relayed.task.source,
                                                                            relayed.role)),
            "task.rescind": (TaskRescind, tasking.on_rescind),
            "task.cancel": (Cancel, tasking.on_cancel),
            "task.result": (ResultUpdate, tasking.apply_result),
            "task.query": (TaskQuery, tasking.on_query),
            "status": (BBObject, replication.apply_status),
            "status.fresh": (Fresh, replication.apply_fresh),
            "status.resend": (StatusResend, replication.on_resend),
            "status.remove": (StatusRemoved, replication.on_removed),
            "peers.request": (object, self.presence.on_peers_request),
            "watch.request": (WatchRequest, self.watchers.on_request),
        }
