"""Type routing: a type subscription is offered only the objects of its type (and subclasses), a
view of one event is that event, and a listener for a type hears only the commits that carry one."""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from erni.blackboard import BBObject, Blackboard
from tests.core.helpers import Item


class Special(Item):
    """An Item of a kind of its own."""


class Other(BBObject):
    """Not an Item."""

    value: int = 0


def view(board: Blackboard, sub: Any) -> tuple[set[str], set[str], set[str]]:
    (inbox,) = board._drain([sub])
    sub._open(inbox)
    seen = ({o.uid for o in sub.added}, {o.uid for o in sub.changed}, {o.uid for o in sub.removed})
    sub._close()
    return seen


def view_of(board: Blackboard, kind: type[BBObject]) -> list[BBObject]:
    sub = board.subscribe(None, kind)
    (inbox,) = board._drain([sub])
    sub._open(inbox)
    return list(sub.added)


# each step: (verb, kind, index) with kind 0 = Item, 1 = Special, 2 = Other; "view" takes a view
steps = st.lists(st.one_of(st.tuples(st.sampled_from(["add", "change", "remove"]), st.integers(0, 2),
                                     st.integers(0, 20)),
                           st.just(("view", 0, 0))), max_size=50)


@settings(max_examples=300, deadline=None)
@given(steps=steps)
def test_a_type_subscription_sees_its_type_and_its_subclasses_only(steps):
    board = Blackboard("routing")
    items = board.subscribe(None, Item)
    specials = board.subscribe(None, Special)
    kinds = (Item, Special, Other)
    live: dict[str, BBObject] = {}
    counter = 0
    for verb, kind, index in steps:
        if verb == "view":
            for sub, cls in ((items, Item), (specials, Special)):
                view(board, sub)
                assert {o.uid for o in sub} == {u for u, o in live.items() if isinstance(o, cls)}
            continue
        with board.transaction() as tx:
            keys = sorted(live)
            if verb == "add" or not keys:
                counter += 1
                obj = kinds[kind](uid=f"o{counter}", value=index)
                tx.add(obj)
                live[obj.uid] = obj
            elif verb == "change":
                uid = keys[index % len(keys)]
                live[uid] = tx.change(live[uid].evolve(value=index), reports=f"to {index}")  # type: ignore[attr-defined]
            else:
                uid = keys[index % len(keys)]
                tx.remove(uid)
                del live[uid]
    for sub, cls in ((items, Item), (specials, Special)):
        view(board, sub)
        assert {o.uid for o in sub} == {u for u, o in live.items() if isinstance(o, cls)}


def test_one_event_is_the_view():
    board = Blackboard("one")
    sub = board.subscribe(None, Item)
    with board.transaction() as tx:
        first = tx.add(Item(value=1))
    assert view(board, sub) == ({first.uid}, set(), set())
    with board.transaction() as tx:
        tx.change(first.evolve(value=2), reports="up")
    (inbox,) = board._drain([sub])
    assert sub._open(inbox)
    assert (sub.changed, sub.reports(first)) == ([first.evolve(value=2)], ["up"])
    sub._close()
    with board.transaction() as tx:
        tx.remove(first)
    assert view(board, sub) == (set(), set(), {first.uid})
    assert len(sub) == 0
    (inbox,) = board._drain([sub])
    assert not sub._open(inbox)  # nothing since: no delta


def test_a_new_subscription_starts_with_its_own_type_only():
    board = Blackboard("late")
    with board.transaction() as tx:
        item, special, _ = tx.add(Item()), tx.add(Special()), tx.add(Other())
    assert {o.uid for o in view_of(board, Item)} == {item.uid, special.uid}
    assert {o.uid for o in view_of(board, Special)} == {special.uid}


def test_a_listener_for_a_type_hears_the_commits_that_carry_one_with_all_of_their_ops():
    board = Blackboard("listen")
    every: list[int] = []
    items: list[list[str]] = []
    board.add_listener(lambda ops: every.append(len(ops)))
    board.add_listener(lambda ops: items.append([type(op[1]).__name__ for op in ops]), Special)
    with board.transaction() as tx:
        tx.add(Other())
    with board.transaction() as tx:
        tx.add(Other())
        tx.add(Special())
    with board.transaction() as tx:
        tx.add(Item())  # an Item, not a Special
    assert every == [1, 2, 1]
    assert items == [["Other", "Special"]]
