"""The transactional blackboard: objects by uid, atomic commits, subscriptions with deltas.

Changes are staged in a `Transaction` and applied at commit, all at once and in publish
order. Each `Subscription` receives the committed events in an inbox; its owner's view
(members and `added` / `changed` / `removed`) moves forward only when the owner opens its
next run, so a plugin's view is frozen while it executes.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar, overload

from erni.blackboard.errors import TransactionError, UsageError
from erni.blackboard.objects import BBObject

if TYPE_CHECKING:
    from erni.blackboard.plugin import Plugin

T = TypeVar("T", bound=BBObject)

Predicate = Callable[[BBObject], bool]
"""A test an object must pass to belong to a subscription or a query."""

ADD, CHANGE, REMOVE = "add", "change", "remove"

Op = tuple[str, BBObject, tuple[Any, ...]]
"""One staged publication: (kind, object, change reports)."""


class Query(Protocol):
    """`query(Type, where=...)` -> `list[Type]`, or `query(predicate)` -> `list[BBObject]`: a snapshot
    of the committed objects that match."""

    @overload
    def __call__(self, kind: type[T], where: Callable[[T], bool] | None = None) -> list[T]: ...

    @overload
    def __call__(self, kind: Predicate | None = None) -> list[BBObject]: ...


class Subscription(Generic[T]):
    """The objects matching a predicate, with the deltas since the owner's last run."""

    def __init__(self, owner: Plugin[Any] | None, kind: type[T] | None, where: Callable[[T], bool] | None,
                 ignore: frozenset[str] = frozenset()):
        self._owner = owner
        self._kind = kind
        self._where = where
        self._ignore = ignore              # fields whose changes alone do not concern the owner
        self._routed_test: Callable[[BBObject], bool] | None = (  # what a routed object must still pass
            self._safe_match if kind is None or where is not None else None)  # routing checked the type
        self._delivered: dict[str, BBObject] = {}  # with `ignore`: the last version put in the inbox
        self._committed: set[str] = set()  # membership as of the latest commit (under bb lock)
        self._inbox: list[tuple[str, BBObject, tuple[Any, ...]]] = []  # under bb lock
        self._members: dict[str, T] = {}  # the owner's view
        self.added: list[T] = []
        self.changed: list[T] = []
        self.removed: list[T] = []
        self._reports: dict[str, list[Any]] = {}
        self.wakes = True
        """False: changes are collected for the owner's next run but do not cause one (a view
        needed only now and then, e.g. while somebody watches)."""

    # -- the owner's view -----------------------------------------------------------------

    def __iter__(self) -> Iterator[T]:
        return iter(list(self._members.values()))

    def __len__(self) -> int:
        return len(self._members)

    def __contains__(self, obj: object) -> bool:
        uid = obj.uid if isinstance(obj, BBObject) else obj
        return uid in self._members

    def get(self, uid: str) -> T | None:
        """Return the member with this uid as the owner sees it, or None."""
        return self._members.get(uid)

    def reports(self, obj: BBObject | str) -> list[Any]:
        """Return the change reports attached to this object's changes since the last run."""
        uid = obj.uid if isinstance(obj, BBObject) else obj
        return list(self._reports.get(uid, ()))

    @property
    def has_changes(self) -> bool:
        """True when the current view carries any delta."""
        return bool(self.added or self.changed or self.removed)

    # -- the blackboard's side ------------------------------------------------------------

    def matches(self, obj: BBObject) -> bool:
        """Return True when the object belongs to this subscription."""
        if self._kind is not None and not isinstance(obj, self._kind):
            return False
        return self._where is None or bool(self._where(obj))  # type: ignore[arg-type]  # of type T once _kind passed

    def _offer(self, kind: str, obj: BBObject, reports: tuple[Any, ...]) -> bool:
        """Record a committed event for an object the blackboard routed here by its type (a type
        subscription is offered only objects of its type); return True when it concerns this
        subscription."""
        uid = obj.uid
        was = uid in self._committed
        test = self._routed_test
        now = kind != REMOVE and (test is None or test(obj))
        if now and not was:
            self._committed.add(uid)
            self._inbox.append((ADD, obj, ()))
        elif now and was:
            if self._ignore:
                last = self._delivered.get(uid)
                if last is not None and _same_except(last, obj, self._ignore):
                    return False   # only ignored fields moved: the owner keeps the version it has
            self._inbox.append((CHANGE, obj, reports))
        elif was and not now:
            self._committed.discard(uid)
            self._delivered.pop(uid, None)
            self._inbox.append((REMOVE, obj, ()))
            return True
        else:
            return False
        if self._ignore:
            self._delivered[uid] = obj
        return True

    def _safe_match(self, obj: BBObject) -> bool:
        try:
            return self.matches(obj)
        except Exception:  # a predicate that raises simply does not match
            return False

    def _open(self, inbox: list[tuple[str, BBObject, tuple[Any, ...]]]) -> bool:
        """Fold the events committed since the last run into the view and its net deltas; return
        True when the view carries a delta."""
        if not inbox:  # nothing since the last run, whose `_close` left no deltas: a plugin with several
            return False  # subscriptions is run for one of them (a control node's transport, for each status)
        if len(inbox) == 1:  # one event (a plugin keeping up): it is the net delta
            kind, event, reps = inbox[0]
            one: T = event  # type: ignore[assignment]  # of type T: the blackboard routed it here by type
            uid = one.uid
            if kind == ADD:
                self._members[uid] = one
                self.added, self.changed, self.removed, self._reports = [one], [], [], {}
            elif kind == CHANGE:
                self._members[uid] = one
                self.added, self.changed, self.removed, self._reports = [], [one], [], {uid: list(reps)}
            else:
                self._members.pop(uid, None)
                self.added, self.changed, self.removed, self._reports = [], [], [one], {}
            return True
        added: dict[str, T] = {}
        changed: dict[str, T] = {}
        removed: dict[str, T] = {}
        reports: dict[str, list[Any]] = {}
        members = self._members
        for kind, obj, reps in inbox:
            uid = obj.uid
            if kind == ADD:
                if uid in removed:  # left and came back within one window: a change
                    del removed[uid]
                    changed[uid] = obj  # type: ignore[assignment]
                else:
                    added[uid] = obj  # type: ignore[assignment]
                members[uid] = obj  # type: ignore[assignment]
            elif kind == CHANGE:
                if uid in added:
                    added[uid] = obj  # type: ignore[assignment]
                else:
                    changed[uid] = obj  # type: ignore[assignment]
                    reports.setdefault(uid, []).extend(reps)
                members[uid] = obj  # type: ignore[assignment]
            else:
                if uid in added:
                    del added[uid]
                else:
                    changed.pop(uid, None)
                    reports.pop(uid, None)
                    removed[uid] = obj  # type: ignore[assignment]
                members.pop(uid, None)
        self.added = list(added.values())
        self.changed = list(changed.values())
        self.removed = list(removed.values())
        self._reports = reports
        return bool(added or changed or removed)

    def _close(self) -> None:
        self.added, self.changed, self.removed = [], [], []
        self._reports = {}


class Transaction:
    """Publications staged by one thread; applied atomically by `commit()`."""

    __slots__ = ("_board", "label", "ops", "_staged", "closed", "_after")

    def __init__(self, board: Blackboard, label: str = ""):
        self._board = board
        self.label = label
        self.ops: list[Op] = []
        self._staged: dict[str, BBObject | None] = {}  # uid -> latest staged version (None = removed)
        self.closed = False
        self._after: list[Callable[[], Any]] | None = None  # `after_commit`, in order

    def after_commit(self, fn: Callable[[], Any]) -> None:
        """Call `fn` once this transaction has committed (after the commit listeners, such as the
        journal's queue, have seen it); never when it aborts or what was staged before is rolled back."""
        self._check_open()
        if self._after is None:
            self._after = []
        self._after.append(fn)

    def _run_after(self) -> None:
        after, self._after = self._after, None
        for fn in after or ():
            try:
                fn()
            except Exception:
                logging.getLogger("erni.blackboard").exception("a hook after the commit of %s failed", self.label)

    def current(self, uid: str) -> BBObject | None:
        """The object with this uid as this transaction would leave it: what it staged, else the
        committed one (None when absent or staged for removal)."""
        if uid in self._staged:
            return self._staged[uid]
        return self._board.get(uid)

    def _exists(self, uid: str) -> bool:
        if uid in self._staged:
            return self._staged[uid] is not None
        return self._board.contains(uid)

    def _check_open(self) -> None:
        if self.closed:
            raise TransactionError(f"transaction {self.label!r} is closed; publish inside an open one")

    def add(self, obj: T) -> T:
        """Stage a new object; its uid must not be on the blackboard yet."""
        if self.closed:
            self._check_open()
        if not isinstance(obj, BBObject):
            raise TransactionError(f"add: expected a BBObject, got {type(obj).__name__}")
        uid = obj.uid
        staged = self._staged
        if staged[uid] is not None if uid in staged else uid in self._board._objects:
            raise TransactionError(f"add: {type(obj).__name__} {uid} is already on the blackboard")
        self.ops.append((ADD, obj, ()))
        staged[uid] = obj
        return obj

    def change(self, obj: T, reports: Any = ()) -> T:
        """Stage a new version of an object already on the blackboard."""
        self._check_open()
        if not isinstance(obj, BBObject):
            raise TransactionError(f"change: expected a BBObject, got {type(obj).__name__}")
        if not self._exists(obj.uid):
            raise TransactionError(f"change: {type(obj).__name__} {obj.uid} is not on the blackboard")
        reps = (reports,) if isinstance(reports, str) else tuple(reports)
        self.ops.append((CHANGE, obj, reps))
        self._staged[obj.uid] = obj
        return obj

    def remove(self, obj: BBObject | str) -> None:
        """Stage the removal of an object (or uid) that is on the blackboard."""
        self._check_open()
        uid = obj if isinstance(obj, str) else obj.uid
        if not self._exists(uid):
            raise TransactionError(f"remove: {uid} is not on the blackboard")
        current = self._staged.get(uid) or self._board.get(uid)
        assert current is not None
        self.ops.append((REMOVE, current, ()))
        self._staged[uid] = None

    def savepoint(self) -> tuple[int, dict[str, BBObject | None], int]:
        """Return a mark that `rollback_to` can return to (drops what was staged after it)."""
        return len(self.ops), dict(self._staged), len(self._after or ())

    def rollback_to(self, mark: tuple[int, dict[str, BBObject | None], int]) -> None:
        """Drop every publication (and `after_commit` hook) staged since `mark`."""
        count, staged, hooks = mark
        del self.ops[count:]
        self._staged = dict(staged)
        if self._after is not None:
            del self._after[hooks:]

    def commit(self) -> None:
        """Apply every staged publication at once, in order, and wake the subscribers."""
        if self.closed:
            self._check_open()
        self.closed = True
        if self.ops:
            self._board._commit(self.ops)
        if self._after is not None:
            self._run_after()

    def abort(self) -> None:
        """Drop everything staged."""
        self.closed = True
        self.ops = []
        self._after = None

    def __enter__(self) -> Transaction:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self.abort()
            return
        if self.closed:
            self._check_open()
        self.closed = True
        if self.ops:
            self._board._commit(self.ops)
        if self._after is not None:
            self._run_after()


class Blackboard:
    """Objects by uid, shared by the plugins of one agent."""

    def __init__(self, name: str = "agent"):
        self.name = name
        self._lock = threading.Lock()
        self._objects: dict[str, BBObject] = {}
        self._by_type: dict[type, list[Subscription[Any]]] = {}
        self._general: list[Subscription[Any]] = []
        self._listeners: list[tuple[Callable[[list[Op]], None], type[BBObject] | None]] = []
        self._route: dict[type, list[Subscription[Any]]] = {}  # type -> subscriptions, cached
        self.signal: Callable[[Plugin[Any]], None] = lambda plugin: None
        self.query: Query = self._query
        self.commits = 0
        self.moot = 0  # changes/removals dropped because another transaction removed the object

    def contains(self, uid: str) -> bool:
        """Return True when an object with this uid is on the blackboard."""
        return uid in self._objects

    def get(self, uid: str) -> BBObject | None:
        """Return the committed object with this uid, or None."""
        return self._objects.get(uid)

    def __len__(self) -> int:
        return len(self._objects)

    def _query(self, kind: type[Any] | Predicate | None = None,
               where: Callable[[Any], bool] | None = None) -> list[Any]:
        """Return a snapshot list of the committed objects matching a type and/or predicate."""
        sub: Subscription[Any] = _make_subscription(None, kind, where)
        with self._lock:
            objects = list(self._objects.values())
        return [o for o in objects if sub._safe_match(o)]

    def transaction(self, label: str = "") -> Transaction:
        """Open a transaction (use as a context manager: commit on success, nothing on error)."""
        return Transaction(self, label)

    def subscribe(self, owner: Plugin[Any] | None, kind: type[Any] | Predicate | None = None,
                  where: Callable[[Any], bool] | None = None, ignore: Iterable[str] = ()) -> Subscription[Any]:
        """Create a subscription; the objects already here arrive as its first `added`. A change
        that moves only `ignore`d fields of a member is not delivered (nor wakes the owner)."""
        sub: Subscription[Any] = _make_subscription(owner, kind, where, ignore)
        with self._lock:
            if sub._kind is not None:
                self._by_type.setdefault(sub._kind, []).append(sub)
            else:
                self._general.append(sub)
            self._route = {}
            for obj in self._objects.values():
                if sub._safe_match(obj):  # not routed: the type is checked here
                    sub._offer(ADD, obj, ())
            pending = bool(sub._inbox)
        if pending and owner is not None:
            self.signal(owner)
        return sub

    def unsubscribe(self, sub: Subscription[Any]) -> None:
        """Stop delivering events to a subscription."""
        with self._lock:
            subs = self._by_type.get(sub._kind, []) if sub._kind else self._general
            if sub in subs:
                subs.remove(sub)
            self._route = {}

    def add_listener(self, fn: Callable[[list[Op]], None], kind: type[BBObject] | None = None) -> None:
        """Call `fn(ops)` after every commit, in commit order (journals, recorders, transport); with
        `kind`, only after the commits that publish an object of that type (`ops` are still all of
        the commit's)."""
        self._listeners.append((fn, kind))

    def _subscriptions_for(self, obj: BBObject) -> list[Subscription[Any]]:
        """Return the subscriptions that may match this object's type (cached; under lock)."""
        kind = type(obj)
        subs = self._route.get(kind)
        if subs is None:
            subs = [s for cls in kind.__mro__ for s in self._by_type.get(cls, ())] + self._general
            self._route[kind] = subs
        return subs

    def _commit(self, ops: list[Op]) -> None:
        owners: dict[int, Plugin[Any]] = {}
        objects = self._objects
        with self._lock:
            route = self._route  # replaced (under this lock) when a subscription comes or goes
            ops = self._valid(ops)
            for kind, obj, reports in ops:
                if kind == REMOVE:
                    objects.pop(obj.uid, None)
                else:
                    objects[obj.uid] = obj
                subs = route.get(type(obj))
                if subs is None:
                    subs = self._subscriptions_for(obj)
                for sub in subs:
                    if sub._offer(kind, obj, reports) and sub.wakes:
                        owner = sub._owner
                        if owner is not None:
                            owners[id(owner)] = owner
            self.commits += 1
            if ops:
                self._tell_listeners(ops)
        if owners:
            signal = self.signal
            for owner in owners.values():
                signal(owner)

    def _valid(self, ops: list[Op]) -> list[Op]:
        """The operations of a commit that stand (under the lock): everything is validated first so a
        conflicting commit publishes nothing (TransactionError); a change or removal of an object another
        transaction removed meanwhile is moot and dropped."""
        objects = self._objects
        if len(ops) == 1:  # one publication (most commits): nothing staged before it to consult
            kind, obj, _ = ops[0]
            present = obj.uid in objects
            if kind == ADD and present:
                raise TransactionError(f"commit: {obj.uid} was added by another transaction")
            if kind != ADD and not present:
                self.moot += 1
                return []
            return ops
        state: dict[str, bool] = {}
        kept: list[Op] = []
        for op in ops:
            kind, obj, _ = op
            present = state.get(obj.uid, obj.uid in objects)
            if kind == ADD and present:
                raise TransactionError(f"commit: {obj.uid} was added by another transaction")
            if kind != ADD and not present:
                self.moot += 1
                continue
            state[obj.uid] = kind != REMOVE
            kept.append(op)
        return kept

    def _tell_listeners(self, ops: list[Op]) -> None:
        """Give a commit's operations to each listener concerned by one of them (under the lock)."""
        for listener, concerns in self._listeners:
            if concerns is not None:
                for op in ops:
                    if isinstance(op[1], concerns):
                        break
                else:
                    continue
            listener(ops)

    def _drain(self, subs: list[Subscription[Any]]) -> list[list[tuple[str, BBObject, tuple[Any, ...]]]]:
        """Take each subscription's inbox atomically (the start of its owner's run)."""
        empty: list[tuple[str, BBObject, tuple[Any, ...]]] = []  # shared by the empty ones: never kept by a subscription
        if len(subs) == 1:
            (sub,) = subs
            with self._lock:
                inbox = sub._inbox
                if inbox:
                    sub._inbox = []
            return [inbox or empty]
        with self._lock:
            inboxes = [s._inbox or empty for s in subs]
            for s in subs:
                if s._inbox:
                    s._inbox = []
        return inboxes


def _same_except(a: BBObject, b: BBObject, ignore: frozenset[str]) -> bool:
    """True when two versions of an object differ at most in the `ignore`d fields."""
    return type(a) is type(b) and all(getattr(a, f) == getattr(b, f) for f in type(a).model_fields
                                      if f not in ignore)


def _make_subscription(owner: Plugin[Any] | None, kind: type[Any] | Predicate | None,
                       where: Callable[[Any], bool] | None, ignore: Iterable[str] = ()) -> Subscription[Any]:
    fields = frozenset(ignore)
    if fields:
        if not (isinstance(kind, type) and issubclass(kind, BBObject)):
            raise UsageError("subscribe(..., ignore=...) needs an object type whose fields it names")
        unknown = sorted(fields - set(kind.model_fields))
        if unknown:
            raise UsageError(f"subscribe({kind.__name__}, ignore=...): no field {', '.join(map(repr, unknown))}; "
                             f"fields: {', '.join(kind.model_fields)}")
    if kind is None or isinstance(kind, type):
        return Subscription(owner, kind, where, fields)
    if callable(kind):
        if where is not None:
            raise UsageError("subscribe(predicate) takes no `where`; combine the two predicates")
        return Subscription(owner, None, kind)
    raise UsageError(f"subscribe: expected a type or a predicate, got {kind!r}")
