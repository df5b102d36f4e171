"""Property: folding the deltas of every view into the previous view gives the blackboard."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from erni.blackboard import Blackboard
from tests.core.helpers import Item

# an action: ("add"|"change"|"remove", index into live objects, new value) or ("view",)
actions = st.lists(
    st.one_of(
        st.tuples(st.sampled_from(["add", "change", "remove"]), st.integers(0, 50), st.integers(0, 30)),
        st.just(("view",)),
        st.just(("commit",)),
    ),
    max_size=60,
)


@settings(max_examples=300, deadline=None)
@given(actions=actions, threshold=st.sampled_from([0, 0, 10, 20]))
def test_net_deltas_reconstruct_membership(actions, threshold):
    board = Blackboard("prop")
    sub = board.subscribe(None, Item, where=lambda o: o.value >= threshold)
    view: dict[str, Item] = {}  # what the subscriber believes
    live: dict[str, Item] = {}  # the truth, staged and committed
    pending_reports: dict[str, list[str]] = {}
    tx = board.transaction()
    counter = 0

    def take_view() -> None:
        nonlocal view
        (inbox,) = board._drain([sub])
        sub._open(inbox)
        prev = dict(view)
        added = {o.uid: o for o in sub.added}
        changed = {o.uid: o for o in sub.changed}
        removed = {o.uid for o in sub.removed}
        assert len(added) == len(sub.added) and len(changed) == len(sub.changed)
        assert not (added.keys() & prev.keys()), "added objects were not in the previous view"
        assert removed <= prev.keys(), "removed objects were in the previous view"
        assert changed.keys() <= prev.keys(), "changed objects were in the previous view"
        assert not (changed.keys() & removed)
        view = {k: v for k, v in prev.items() if k not in removed}
        view.update(changed)
        view.update(added)
        truth = {o.uid: o for o in board.query(Item) if o.value >= threshold}
        assert view == truth
        assert {o.uid: o for o in sub} == truth
        if threshold == 0:  # every object matches: each change's reports reach the view in order
            for uid in changed:
                assert sub.reports(uid) == pending_reports.get(uid, [])
        pending_reports.clear()
        sub._close()

    staged_reports: dict[str, list[str]] = {}
    for action in actions:
        kind = action[0]
        if kind == "view":
            take_view()
            continue
        if kind == "commit":
            tx.commit()
            for uid, reps in staged_reports.items():
                pending_reports.setdefault(uid, []).extend(reps)
            staged_reports.clear()
            tx = board.transaction()
            continue
        _, index, value = action
        keys = sorted(live)
        if kind == "add" or not keys:
            counter += 1
            obj = Item(uid=f"o{counter}", value=value)
            tx.add(obj)
            live[obj.uid] = obj
        elif kind == "change":
            uid = keys[index % len(keys)]
            obj = live[uid].evolve(value=value)
            report = f"r{counter}-{value}"
            counter += 1
            tx.change(obj, reports=report)
            live[uid] = obj
            staged_reports.setdefault(uid, []).append(report)
        else:
            uid = keys[index % len(keys)]
            tx.remove(uid)
            del live[uid]
            staged_reports.pop(uid, None)
    tx.commit()
    for uid, reps in staged_reports.items():
        pending_reports.setdefault(uid, []).extend(reps)
    take_view()


@settings(max_examples=200, deadline=None)
@given(actions=actions)
def test_current_is_the_board_the_transaction_would_leave(actions):
    """Whatever a transaction staged (adds, changes, removals, also of committed objects), `current`
    answers as the blackboard will after the commit, and `get` as it is before it."""
    board = Blackboard("prop")
    committed: dict[str, Item] = {}
    staged: dict[str, Item | None] = {}
    tx = board.transaction()
    uids: list[str] = []
    for action in actions:
        if action[0] == "commit":
            tx.commit()
            for uid, obj in staged.items():
                if obj is None:
                    committed.pop(uid, None)
                else:
                    committed[uid] = obj
            staged, tx = {}, board.transaction()
        elif action[0] == "view":
            continue
        else:
            verb, index, value = action
            live = {**committed, **staged}
            present = [u for u in uids if live.get(u) is not None]
            if verb == "add" or not present:
                obj = Item(value=value)
                tx.add(obj)
                uids.append(obj.uid)
                staged[obj.uid] = obj
            elif verb == "change":
                uid = present[index % len(present)]
                staged[uid] = tx.change(Item(uid=uid, value=value))
            else:
                uid = present[index % len(present)]
                tx.remove(uid)
                staged[uid] = None
        for uid in uids + ["absent"]:
            expected = staged[uid] if uid in staged else committed.get(uid)
            assert tx.current(uid) == expected
            assert board.get(uid) == committed.get(uid)
