"""The transport plugin's collaborators alone: presence, tasking, status replication, watchers and
authorization, each built on a board kept in a dict and an endpoint that records what it is given,
their time a ManualClock's (nothing here waits)."""

from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Any

import pytest

from erni.blackboard import BBObject, Pose, Task, TaskState
from erni.blackboard.schemas import Beacon, Peer, ResultUpdate, WatchRequest
from erni.testing import ManualClock
from erni.transport.authorization import Authorization
from erni.transport.bounds import SenderBounds
from erni.transport.policy import Refusal
from erni.transport.presence import Presence
from erni.transport.replication import StatusReplication
from erni.transport.settings import TransportSettings
from erni.transport.tasking import Tasking
from erni.transport.watchers import Watchers
from erni.transport.wire import Message


class Board:
    """What the collaborators use of their plugin: settings, log, clock, name and the blackboard."""

    def __init__(self, clock: ManualClock, **settings: Any) -> None:
        self.settings = TransportSettings(insecure=True, discovery_port=0, **settings)
        self.log = logging.getLogger("erni.test.collaborators")
        self.clock, self.agent_name = clock, "me"
        self.objects: dict[str, BBObject] = {}
        self.reports: list[tuple[str, list[str]]] = []
        self.subscriptions: list[SimpleNamespace] = []

    def add(self, obj: BBObject) -> BBObject:
        self.objects[obj.uid] = obj
        return obj

    def change(self, obj: BBObject, reports: Any = ()) -> BBObject:
        self.objects[obj.uid] = obj
        self.reports.append((obj.uid, list(reports)))
        return obj

    def remove(self, obj: BBObject | str) -> None:
        self.objects.pop(obj if isinstance(obj, str) else obj.uid, None)

    def get(self, uid: str) -> BBObject | None:
        return self.objects.get(uid)

    current = get

    def query(self, where: Any) -> list[BBObject]:
        return [o for o in self.objects.values() if where(o)]

    def rehydrated(self, obj: Any) -> bool:
        return False

    def subscribe(self, where: Any) -> SimpleNamespace:
        sub = SimpleNamespace(where=where, added=[], changed=[], removed=[], wakes=True)
        self.subscriptions.append(sub)
        return sub


class Wire:
    """An endpoint that keeps what it is asked to send."""

    role, wire = "robot", "udp"

    def __init__(self) -> None:
        self.sent: list[tuple[Any, str, Any, bool, str | None]] = []
        self.announced: list[tuple[Any, str]] = []
        self.counters: dict[str, int] = {}

    def send(self, addr: Any, kind: str, body: Any = None, *, reliable: bool, to: str | None = None, **kw: Any) -> str:
        self.sent.append((addr, kind, body, reliable, to))
        return f"m{len(self.sent)}"

    def announce(self, addr: Any, kind: str, body: Any) -> None:
        self.announced.append((addr, kind))

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def kinds(self) -> list[str]:
        return [s[1] for s in self.sent]


def parts(**settings: Any) -> SimpleNamespace:
    clock = ManualClock()
    board, wire = Board(clock, **settings), Wire()
    bounds = SenderBounds(board.settings, wire.count, board.log, clock)
    presence = Presence(board, wire, bounds, degraded=lambda: "", count=wire.count)  # type: ignore[arg-type]
    tasking = Tasking(board, wire, presence, bounds, degraded=lambda: "", keep=lambda msg: None,  # type: ignore[arg-type]
                      count=wire.count)
    replication = StatusReplication(board, wire, presence, bounds)  # type: ignore[arg-type]
    watchers = Watchers(board, wire)  # type: ignore[arg-type]
    authorization = Authorization(board, wire, tasking, presence, replication)  # type: ignore[arg-type]
    presence.add_static()
    return SimpleNamespace(clock=clock, board=board, wire=wire, presence=presence, tasking=tasking,
                           replication=replication, watchers=watchers, authorization=authorization)


def message(sender: str, kind: str, body: Any, *, seq: int = 1, epoch: int = 1, role: str = "robot") -> Message:
    return Message(sender, role, ("127.0.0.1", 4000), epoch, seq, f"m{seq}", kind, body)


def task_for(dest: str) -> Task:
    return Task(verb="BotMotion", preposition="forward", params={"distance": 1.0}, source="me", destination=dest)


# -- presence ------------------------------------------------------------------------------


def test_a_peer_heard_in_a_session_is_up_and_goes_down_when_silent_past_its_limit() -> None:
    p = parts(beacon_period=0.5, peer_timeout=2.0)
    p.presence.heard("robot1", ("127.0.0.1", 4000), 1, Beacon(role="robot"), "robot")
    peer = p.board.get("peer:robot1")
    assert isinstance(peer, Peer) and peer.up and peer.address == "127.0.0.1:4000" and peer.role == "robot"
    p.clock.advance(1.9)
    p.presence.beacon_and_liveness()
    assert p.board.get("peer:robot1").up  # type: ignore[union-attr]
    p.clock.advance(0.2)  # 2.1 s silent: past peer_timeout
    p.presence.beacon_and_liveness()
    assert not p.board.get("peer:robot1").up  # type: ignore[union-attr]
    assert ("peer:robot1", ["down"]) in p.board.reports


def test_a_broadcast_beacon_only_hints_at_a_peer_and_is_answered_with_a_beacon() -> None:
    p = parts()
    msg = Message("robot2", "robot", ("10.0.0.2", 5000), 1, 0, "h1", "beacon", Beacon(role="robot"), hint=True)
    assert p.presence.hint_wanted("robot2")
    p.presence.hinted(msg)
    peer = p.board.get("peer:robot2")
    assert isinstance(peer, Peer) and not peer.up and peer.address == "10.0.0.2:5000"
    assert p.wire.kinds() == ["beacon"]  # starts a session
    p.presence.gone("robot2")  # known only from the hint: forgotten
    assert p.board.get("peer:robot2") is None and "robot2" not in p.presence.directory


def test_static_peers_are_in_the_directory_before_they_are_heard() -> None:
    p = parts(peers=["robot1@127.0.0.1:4000"])
    assert p.presence.address_of("robot1") == ("127.0.0.1", 4000)
    assert p.presence.heard_at("robot1") == 0.0 and p.presence.role_of("robot1") == ""


# -- tasking -------------------------------------------------------------------------------


def test_a_task_for_an_agent_never_discovered_fails_after_its_time_to_live() -> None:
    p = parts(task_ttl=5.0)
    task = p.board.add(task_for("robot9"))
    p.tasking.published([task], [])
    assert p.wire.sent == [] and p.tasking.tasks_out[task.uid].pending is not None
    p.clock.advance(4.0)
    p.tasking.retry_pending()
    assert p.board.get(task.uid).result is None  # type: ignore[union-attr]
    p.clock.advance(2.0)
    p.tasking.retry_pending()
    failed = p.board.get(task.uid)
    assert isinstance(failed, Task) and failed.result is not None and failed.result.state is TaskState.FAILED
    assert "never discovered" in failed.result.message


def test_a_task_sent_to_a_known_peer_is_pending_and_fails_when_its_performer_falls_silent() -> None:
    p = parts(peers=["robot1@127.0.0.1:4000"], link_deadline=10.0)
    task = p.board.add(task_for("robot1"))
    p.tasking.published([task], [])
    assert p.wire.kinds() == ["task.add"] and p.wire.sent[0][3]  # reliably
    sent = p.board.get(task.uid)
    assert isinstance(sent, Task) and sent.result is not None and sent.result.state is TaskState.PENDING
    p.clock.advance(10.5)
    p.tasking.check_links()
    lost = p.board.get(task.uid)
    assert isinstance(lost, Task) and lost.result is not None and lost.result.state is TaskState.FAILED
    assert lost.result.message.startswith("link lost: robot1")
    assert p.wire.kinds()[-1] == "task.cancel"


def test_an_older_result_never_overwrites_a_newer_one() -> None:
    p = parts(peers=["robot1@127.0.0.1:4000"])
    task = p.board.add(task_for("robot1"))
    p.tasking.published([task], [])
    running = ResultUpdate(uid=task.uid, result=task.with_result(TaskState.RUNNING, message="second").result)
    older = ResultUpdate(uid=task.uid, result=task.with_result(TaskState.RUNNING, message="first").result)
    p.tasking.apply_result(message("robot1", "task.result", running, seq=5), running)
    p.tasking.apply_result(message("robot1", "task.result", older, seq=4), older)
    assert p.board.get(task.uid).result.message == "second"  # type: ignore[union-attr]


# -- authorization -------------------------------------------------------------------------


def test_a_result_from_another_than_the_performer_is_refused_and_logged_once_in_ten_seconds(caplog) -> None:
    p = parts(peers=["robot1@127.0.0.1:4000"])
    task = p.board.add(task_for("robot1"))
    p.tasking.published([task], [])
    update = ResultUpdate(uid=task.uid, result=task.with_result(TaskState.SUCCEEDED).result)
    p.authorization.check(message("robot1", "task.result", update))  # its performer may
    forged = message("mallory", "task.result", update)
    with pytest.raises(Refusal) as refused:
        p.authorization.check(forged)
    assert refused.value.rule == "performer"
    with caplog.at_level(logging.WARNING, logger="erni.test.collaborators"):
        for _ in range(3):
            p.authorization.refused(forged, refused.value)
        p.clock.advance(10.0)
        p.authorization.refused(forged, refused.value)
    logged = [r.getMessage() for r in caplog.records if r.getMessage().startswith("refused task.result")]
    assert len(logged) == 2 and logged[1].endswith("(+2 more since)")
    assert p.wire.counters["refused.performer"] == 4


def test_no_rule_lets_anyone_send_an_unknown_kind() -> None:
    p = parts()
    with pytest.raises(Refusal) as refused:
        p.authorization.check(message("robot1", "made.up", None))
    assert refused.value.rule == "kind"


# -- status replication --------------------------------------------------------------------


def test_a_status_is_held_by_its_sender_and_an_older_one_never_overwrites_it() -> None:
    p = parts()
    newer = Pose(robot="robot1", x=2.0, y=0.0, stamp=2.0)
    p.replication.apply_status(message("robot1", "status", newer, seq=7), newer)
    older = Pose(robot="robot1", x=1.0, y=0.0, stamp=1.0)
    p.replication.apply_status(message("robot1", "status", older, seq=6), older)
    assert p.board.get("pose:robot1").x == 2.0  # type: ignore[union-attr]
    p.replication.check_holder("robot1", "pose:robot1")
    with pytest.raises(Refusal):
        p.replication.check_holder("robot2", "pose:robot1")


def test_our_pose_goes_to_the_peers_of_the_roles_that_receive_it() -> None:
    p = parts()
    p.presence.heard("control", ("127.0.0.1", 4001), 1, Beacon(role="control"), "control")
    p.presence.heard("robot2", ("127.0.0.1", 4002), 1, Beacon(role="robot"), "robot")
    shared = p.replication.shared
    pose = Pose(robot="me", x=1.0, y=1.0, stamp=p.clock.wall())
    assert shared.where(pose)
    shared.added = [pose]
    p.replication.share()
    assert [(s[1], s[4]) for s in p.wire.sent] == [("status", "control")]  # share_with_roles: control


# -- watchers ------------------------------------------------------------------------------


def test_a_watcher_gets_the_current_state_then_changes_until_its_lease_ends() -> None:
    p = parts()
    p.board.add(Pose(robot="me", x=0.0, y=0.0))
    p.watchers.on_request(message("cli", "watch.request", None, role="cli"), WatchRequest(lease=5.0))
    assert p.wire.kinds() == ["watch.event"] and p.watchers.watched.wakes
    p.watchers.watched.changed = [Pose(robot="me", x=1.0, y=0.0)]
    p.watchers.forward()
    assert p.wire.kinds() == ["watch.event", "watch.event"]
    p.clock.advance(5.5)
    p.watchers.forward()
    assert not p.watchers.watchers and not p.watchers.watched.wakes
    assert len(p.wire.sent) == 2
