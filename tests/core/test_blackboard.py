"""Transactions and subscriptions: atomic commits, frozen views, net deltas, change reports."""

from __future__ import annotations

import threading

import pytest

from erni.blackboard import Agent, Plugin, Task, TransactionError
from erni.blackboard.testing import wait_until
from tests.core.helpers import Item, Recorder, scheduler_idle


@pytest.fixture
def agent():
    a = Agent("t", workers=2)
    yield a
    a.stop()


def test_commit_makes_all_changes_visible_at_once_in_order(agent):
    rec = agent.add_plugin(Recorder)
    agent.start()
    items = [Item(value=i) for i in range(5)]
    with agent.transaction() as tx:
        for item in items:
            tx.add(item)
        assert agent.query(Item) == []  # nothing visible before commit
    wait_until(lambda: len(rec.all("added")) == 5)
    assert len(rec.views) == 1, "the commit arrived as one view"
    assert [o.value for o in rec.views[0]["added"]] == [0, 1, 2, 3, 4]


def test_exception_in_transaction_publishes_nothing(agent):
    agent.start()
    with pytest.raises(RuntimeError):
        with agent.transaction() as tx:
            tx.add(Item(value=1))
            raise RuntimeError("boom")
    assert agent.query(Item) == []


def test_publishing_outside_a_transaction_is_an_error(agent):
    plugin = agent.add_plugin(Recorder)
    agent.start()
    with pytest.raises(TransactionError, match="add\\(\\) outside a transaction"):
        plugin.add(Item())
    with plugin.transaction():
        plugin.add(Item())
    assert len(agent.query(Item)) == 1


def test_current_reads_what_the_open_transaction_staged_and_the_committed_object_outside(agent):
    plugin = agent.add_plugin(Recorder)
    agent.start()
    item, other = Item(value=1), Item(value=5)
    with agent.transaction() as tx:
        tx.add(item)
        tx.add(other)
    with plugin.transaction():
        assert plugin.current(item.uid) == item
        newer = plugin.change(item.model_copy(update={"value": 2}))
        plugin.remove(other)
        assert plugin.current(item.uid) is newer  # a change built now starts from the staged version
        assert plugin.get(item.uid) == item  # the committed one is unchanged until the commit
        assert plugin.current(other.uid) is None  # staged for removal
        assert plugin.current("nothing") is None
    assert plugin.current(item.uid) is newer and plugin.get(item.uid) is newer
    assert plugin.current(other.uid) is None


def test_add_change_remove_are_checked(agent):
    agent.start()
    item = Item()
    with pytest.raises(TransactionError, match="not on the blackboard"):
        with agent.transaction() as tx:
            tx.change(item)
    with agent.transaction() as tx:
        tx.add(item)
    with pytest.raises(TransactionError, match="already on the blackboard"):
        with agent.transaction() as tx:
            tx.add(item)
    with pytest.raises(TransactionError, match="expected a BBObject"):
        with agent.transaction() as tx:
            tx.add({"uid": "x"})  # type: ignore[arg-type]
    with agent.transaction() as tx:
        tx.remove(item)
    assert agent.query(Item) == []


def test_conflicting_commits_publish_nothing():
    agent = Agent("c")
    item = Item()
    tx1, tx2 = agent.blackboard.transaction(), agent.blackboard.transaction()
    tx1.add(item)
    tx2.add(Item(value=7))
    tx2.add(item)  # valid when staged, conflicts at commit
    tx1.commit()
    with pytest.raises(TransactionError, match="added by another transaction"):
        tx2.commit()
    assert [o.value for o in agent.query(Item)] == [0]


def test_view_is_frozen_while_execute_runs():
    started, release = threading.Event(), threading.Event()
    seen = {}

    class Slow(Plugin):
        def setup(self):
            self.sub = self.subscribe(Item)

        def execute(self):
            before = {o.uid: o.value for o in self.sub}
            started.set()
            release.wait(5)
            seen.setdefault("before", before)
            seen.setdefault("after", {o.uid: o.value for o in self.sub})
            seen.setdefault("added_after", [o.value for o in self.sub.added])

    agent = Agent("f", workers=2)
    agent.add_plugin(Slow)
    agent.start()
    try:
        item = Item(value=1)
        with agent.transaction() as tx:
            tx.add(item)
        started.wait(5)
        with agent.transaction() as tx:
            tx.change(item.evolve(value=2))
            tx.add(Item(value=3))
        release.set()
        wait_until(lambda: "added_after" in seen)
        assert seen["before"] == seen["after"] == {item.uid: 1}
        assert seen["added_after"] == [1]
    finally:
        release.set()
        agent.stop()


def test_deltas_are_net_since_the_last_run_with_reports(agent):
    rec = agent.add_plugin(Recorder)
    keep, gone, brief = Item(value=1), Item(value=2), Item(value=3)
    with agent.transaction() as tx:
        tx.add(keep)
        tx.add(gone)
    agent.start()  # objects already present arrive as the first `added`
    wait_until(lambda: rec.views)
    assert {o.uid for o in rec.views[0]["added"]} == {keep.uid, gone.uid}
    # between two runs: change keep twice, remove gone, add then remove brief
    with agent.transaction() as tx:
        tx.change(keep.evolve(value=10), reports="first")
        tx.change(keep.evolve(value=11), reports=["second", "third"])
        tx.remove(gone)
        tx.add(brief)
        tx.remove(brief)
    wait_until(lambda: len(rec.views) >= 2)
    view = rec.views[1]
    assert [o.value for o in view["changed"]] == [11]
    assert view["reports"][keep.uid] == ["first", "second", "third"]
    assert [o.uid for o in view["removed"]] == [gone.uid]
    assert view["added"] == []
    assert set(view["members"]) == {keep.uid}


def test_predicate_subscriptions_follow_membership_changes(agent):
    class Big(Recorder):
        where = staticmethod(lambda o: o.value >= 10)

    rec = agent.add_plugin(Big)
    agent.start()
    item = Item(value=1)
    with agent.transaction() as tx:
        tx.add(item)
    with agent.transaction() as tx:
        tx.change(item.evolve(value=20))  # starts matching: an add
    wait_until(lambda: rec.all("added"))
    with agent.transaction() as tx:
        tx.change(item.evolve(value=5))  # stops matching: a remove
    wait_until(lambda: rec.all("removed"))
    assert [o.value for o in rec.all("added")] == [20]
    assert [o.value for o in rec.all("removed")] == [5]


def test_callable_subscription_and_query(agent):
    class Tasks(Recorder):
        kind = staticmethod(lambda o: isinstance(o, Task) and o.verb == "BotMotion")

    rec = agent.add_plugin(Tasks)
    agent.start()
    with agent.transaction() as tx:
        tx.add(Task(verb="BotMotion", preposition="stop"))
        tx.add(Task(verb="NetWatch", preposition="neighbor_list"))
        tx.add(Item())
    wait_until(lambda: rec.all("added"))
    assert [t.verb for t in rec.all("added")] == ["BotMotion"]
    assert len(agent.query(Task)) == 2
    assert len(agent.query(Task, where=lambda t: t.verb == "NetWatch")) == 1


def test_subscribe_outside_setup_is_refused(agent):
    plugin = agent.add_plugin(Recorder)
    agent.start()
    with pytest.raises(TransactionError, match="only allowed in setup"):
        plugin.subscribe(Item)


def test_listeners_see_every_commit_in_order(agent):
    seen = []
    agent.blackboard.add_listener(lambda ops: seen.append([(k, o.value) for k, o, _ in ops]))
    agent.start()
    item = Item(value=1)
    with agent.transaction() as tx:
        tx.add(item)
    with agent.transaction() as tx:
        tx.change(item.evolve(value=2))
        tx.remove(item)
    assert seen == [[("add", 1)], [("change", 2), ("remove", 2)]]


def test_change_or_removal_of_an_object_removed_meanwhile_is_moot_not_fatal():
    agent = Agent("m")
    task, other = Item(value=1), Item(value=2)
    with agent.transaction() as tx:
        tx.add(task)
    canceller, performer = agent.blackboard.transaction(), agent.blackboard.transaction()
    canceller.remove(task)
    performer.change(task.evolve(value=5))  # valid when staged ...
    performer.remove(task)
    performer.add(other)
    canceller.commit()
    performer.commit()  # ... moot at commit: dropped, and the rest of the run still lands
    assert [o.value for o in agent.query(Item)] == [2]
    assert agent.blackboard.moot == 2


class _IgnoresTags(Recorder):
    def setup(self) -> None:
        self.sub = self.subscribe(Item, ignore=("tag",))
        self.views = []
        self.lock = threading.Lock()
        self.runs = 0

    def execute(self) -> None:
        self.runs += 1
        super().execute()


def test_a_change_of_ignored_fields_alone_neither_wakes_nor_is_delivered(agent):
    """A transport refreshes each peer's last_heard every second: plugins that only want a
    peer's address or role subscribe with ignore=("last_heard",) and are not run for it."""
    rec = agent.add_plugin(_IgnoresTags)
    agent.start()
    item = Item(value=1, tag="a")
    with agent.transaction() as tx:
        tx.add(item)
    wait_until(lambda: any(v["added"] for v in rec.views))
    wait_until(lambda: scheduler_idle(rec))
    runs = rec.runs
    for tag in "bcd":
        with agent.transaction() as tx:
            tx.change(agent.blackboard.get(item.uid).evolve(tag=tag))
    wait_until(lambda: scheduler_idle(rec))  # a wake-up would have queued it at the commit
    assert rec.runs == runs                                    # not woken
    with agent.transaction() as tx:   # a change the plugin cares about comes through
        tx.add(Item(value=9))
    wait_until(lambda: any(o.value == 9 for v in rec.views for o in v["added"]))
    assert all(not v["changed"] for v in rec.views)            # the tag changes were never delivered
    assert rec.views[-1]["members"][item.uid].tag == "a"       # it keeps the version it was given
    with agent.transaction() as tx:
        tx.change(agent.blackboard.get(item.uid).evolve(value=2, tag="e"))
    wait_until(lambda: rec.views[-1]["changed"])
    assert [(o.value, o.tag) for o in rec.views[-1]["changed"]] == [(2, "e")]   # the newest version
    with agent.transaction() as tx:
        tx.change(agent.blackboard.get(item.uid).evolve(tag="f"))
    with agent.transaction() as tx:
        tx.remove(item.uid)
    wait_until(lambda: rec.views[-1]["removed"])
    assert [o.uid for o in rec.views[-1]["removed"]] == [item.uid] and not rec.views[-1]["changed"]


def test_ignore_names_fields_of_the_type(agent):
    from erni.blackboard.errors import UsageError
    with pytest.raises(UsageError, match="subscribe\\(Item, ignore=...\\): no field 'colour'; fields: uid, value, tag"):
        agent.blackboard.subscribe(None, Item, ignore=("colour",))
    with pytest.raises(UsageError, match="needs an object type"):
        agent.blackboard.subscribe(None, lambda o: True, ignore=("tag",))


class _Quiet(Recorder):
    def setup(self) -> None:
        self.quiet = self.subscribe(Item)
        self.quiet.wakes = False
        self.views = []
        self.lock = threading.Lock()
        self.runs = 0
        self.seen: list[list[int]] = []

    def execute(self) -> None:
        self.runs += 1
        self.seen.append(sorted(o.value for o in self.quiet.added))


def test_a_subscription_that_does_not_wake_is_delivered_at_the_next_run(agent):
    """`sub.wakes = False`: its changes wait for a run the plugin has for another reason."""
    rec = agent.add_plugin(_Quiet)
    agent.start()
    wait_until(lambda: rec.runs >= 0 and rec._setup_ran)
    wait_until(lambda: scheduler_idle(rec))
    runs = rec.runs
    for v in (1, 2, 3):
        with agent.transaction() as tx:
            tx.add(Item(value=v))
    wait_until(lambda: scheduler_idle(rec))  # a wake-up would have queued it at the commit
    assert rec.runs == runs                      # not woken by them
    rec.wake()
    wait_until(lambda: rec.runs > runs)
    assert rec.seen[-1] == [1, 2, 3]             # but all there, in one delta, at the next run
    rec.quiet.wakes = True
    with agent.transaction() as tx:
        tx.add(Item(value=4))
    wait_until(lambda: rec.seen[-1] == [4])      # waking again


def test_evolve_validates_the_changes_and_keeps_the_rest_as_it_was():
    """evolve() checks what changes and runs the object's validators again, but takes the fields
    it keeps as they are (frozen, validated when the object was made), without a dump and reload."""
    from pydantic import ValidationError

    from erni.blackboard import Pose, TaskState

    task = Task(verb="BotMotion", preposition="goto", params={"x": 1, "y": "2"}, source="control")
    done = task.with_result(TaskState.SUCCEEDED, message="there")
    assert done.params is task.params and done.uid == task.uid and done.state is TaskState.SUCCEEDED
    with pytest.raises(ValidationError, match="goto: x"):
        task.evolve(params={"x": "east", "y": 0})
    with pytest.raises(ValidationError, match="verb"):
        task.evolve(verb="NoSuchVerb")
    pose = Pose(robot="r1", sonar=[1.0, 2.0])
    moved = pose.evolve(x=3.0)
    assert moved.uid == "pose:r1" and moved.x == 3.0 and moved.sonar == [1.0, 2.0]
    assert moved.sonar is not pose.sonar  # a list is copied by validation: no version shares a mutable value
    with pytest.raises(ValidationError):
        pose.evolve(x="far")


def test_plugins_offer_each_other_what_cannot_go_on_the_blackboard_by_name():
    """`provide`/`provided`: the agent-level facility instead of one plugin reading another's attributes."""
    from erni.blackboard import Agent, Plugin

    class Offering(Plugin):
        def setup(self) -> None:
            self.provide("example.session", lambda: "the live session")

    class Asking(Plugin):  # asks when it needs it: plugin order is unspecified, so never in setup()
        pass

    agent = Agent("a")
    asking = agent.add_plugin(Asking)
    agent.add_plugin(Offering)
    agent.start()
    try:
        got = asking.provided("example.session")
        assert got is not None and got() == "the live session" and asking.provided("example.other") is None
        assert agent.provided("example.session") is got
    finally:
        agent.stop()
    assert Asking().provided("example.session") is None  # a plugin outside an agent is offered nothing


def test_after_commit_hooks_run_once_committed_never_after_an_abort_or_a_rollback(agent):
    """What waits for a commit (a task's acknowledgement waits for the journal this way) runs after
    the commit listeners saw it, and never for publications that were dropped."""
    seen: list[str] = []
    agent.blackboard.add_listener(lambda ops: seen.append("listener"))
    with agent.transaction() as tx:
        tx.add(Item(uid="a", value=1))
        tx.after_commit(lambda: seen.append("hook"))
        assert seen == []
    assert seen == ["listener", "hook"]
    seen.clear()
    with pytest.raises(RuntimeError):
        with agent.transaction() as tx:
            tx.add(Item(uid="b", value=1))
            tx.after_commit(lambda: seen.append("aborted"))
            raise RuntimeError("boom")
    tx = agent.transaction()
    tx.add(Item(uid="c", value=1))
    tx.after_commit(lambda: seen.append("kept"))
    mark = tx.savepoint()
    tx.add(Item(uid="d", value=1))
    tx.after_commit(lambda: seen.append("rolled back"))
    tx.rollback_to(mark)
    tx.commit()
    assert seen == ["listener", "kept"]
    assert agent.blackboard.get("d") is None


def test_when_durable_waits_for_the_journal_write_of_what_was_committed_before(tmp_path):
    """`Agent.when_durable` calls back once the journal holds every commit made before the call."""
    import sqlite3


    agent = Agent("r1", journal=tmp_path / "j.sqlite").start()
    try:
        done = threading.Event()
        found: list[int] = []

        def check() -> None:
            db = sqlite3.connect(tmp_path / "j.sqlite")
            found.append(db.execute("SELECT COUNT(*) FROM objects WHERE uid = 'durable'").fetchone()[0])
            db.close()
            done.set()

        with agent.transaction() as tx:
            tx.add(Task(uid="durable", verb="BotMotion", preposition="stop"))
            tx.after_commit(lambda: agent.when_durable(check))
        assert done.wait(10)
        assert found == [1]
    finally:
        agent.stop()
