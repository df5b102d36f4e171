"""The plugin base class: subscriptions, publishing, wake-ups and hand-offs from other threads."""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, ClassVar, Generic, get_args, get_origin, overload

from pydantic import BaseModel, ConfigDict
from typing_extensions import TypeVar

from erni.blackboard.blackboard import Blackboard, Predicate, Query, Subscription, T, Transaction
from erni.blackboard.clock import SYSTEM, Clock
from erni.blackboard.errors import TransactionError, UsageError
from erni.blackboard.objects import BBObject, Model

if TYPE_CHECKING:
    from erni.blackboard.agent import Agent, Timer


class NoSettings(Model):
    """Settings of a plugin that takes none."""

    model_config = ConfigDict(extra="forbid")


SettingsT = TypeVar("SettingsT", bound=BaseModel, default=NoSettings)


class Plugin(Generic[SettingsT]):
    """Base of every plugin: override `setup()`, `execute()` and, if needed, `teardown()`.

    `class Motion(Plugin[MotionSettings])` makes `MotionSettings` the model that validates the
    plugin's `[plugin.settings]` and the type of `self.settings`; a plain `Plugin` takes none.
    `setup()` and `execute()` run inside a transaction opened by the agent; any other
    thread of the plugin publishes inside `with self.transaction():` or hands work over
    with `self.later(fn)`.
    """

    Settings: ClassVar[type[BaseModel]] = NoSettings
    essential: ClassVar[bool] = False
    """True: the agent does not start without this plugin (a failed `setup()` stops it, one line
    saying why); False: a failed setup disables the plugin and the agent goes on."""
    settings: SettingsT

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "Settings" in cls.__dict__:
            return
        for base in getattr(cls, "__orig_bases__", ()):
            origin, args = get_origin(base), get_args(base)
            if isinstance(origin, type) and issubclass(origin, Plugin) and args \
                    and isinstance(args[0], type) and issubclass(args[0], BaseModel):
                cls.Settings = args[0]
                return

    def __init__(self) -> None:
        self.name = type(self).__name__
        self.agent_name = ""
        self.log = logging.getLogger(f"erni.plugin.{self.name}")
        self._agent: Agent | None = None
        self._subs: list[Subscription[Any]] = []
        self._local = threading.local()
        self._later: deque[Callable[[], Any]] = deque()
        self._in_setup = False
        # scheduling state, guarded by _sched_lock (owned by the agent's scheduler)
        self._sched_lock = threading.Lock()
        self._scheduled = False
        self._running = False
        self._dirty = False
        self._woken = False
        self._disabled = False
        self._setup_error: BaseException | None = None
        self._setup_ran = False
        self._run_started = 0.0
        self._slow_reported = False
        self.runs = 0
        self.failures = 0

    # -- to override ----------------------------------------------------------------------

    def setup(self) -> None:
        """Make subscriptions and publish initial objects (inside a transaction)."""

    def execute(self) -> None:
        """React to subscription deltas and wake-ups (inside a transaction)."""

    def teardown(self) -> None:
        """Stop and join the plugin's own threads (outside any transaction)."""

    # -- subscriptions ----------------------------------------------------------------------

    @overload
    def subscribe(self, kind: type[T], where: Callable[[T], bool] | None = None, *,
                  ignore: Iterable[str] = ()) -> Subscription[T]: ...

    @overload
    def subscribe(self, kind: Predicate) -> Subscription[BBObject]: ...

    def subscribe(self, kind: type[Any] | Predicate,
                  where: Callable[[Any], bool] | None = None, *, ignore: Iterable[str] = ()) -> Subscription[Any]:
        """Subscribe to a type (members typed as it) and/or a predicate; only allowed in `setup()`.

        `ignore` names fields of the type whose changes alone do not concern this plugin: such a
        change is not delivered and does not wake it (its view keeps the version it has)."""
        if not self._in_setup:
            raise TransactionError(f"{self.name}: subscribe() is only allowed in setup()")
        sub = self._board.subscribe(self, kind, where, ignore)
        self._subs.append(sub)
        return sub

    def get(self, uid: str) -> BBObject | None:
        """Return the committed object with this uid, or None."""
        return self._board.get(uid)

    def current(self, uid: str) -> BBObject | None:
        """The object with this uid as this plugin's open transaction would leave it (what it staged
        earlier in the run, else the committed one); the committed one outside a transaction.

        Build a change on this, not on a subscription's member, when the run may already have
        changed the object: a change built on an older version undoes the newer one."""
        tx = self._open_tx()
        return self._board.get(uid) if tx is None else tx.current(uid)

    @property
    def clock(self) -> Clock:
        """The agent's clock: `self.clock()` monotonic seconds (durations, deadlines), `self.clock.wall()`
        seconds since the epoch (stamps). A test's agent may run on `erni.testing.ManualClock`; a plugin
        not yet part of an agent reads the process's clock."""
        return self._agent.clock if self._agent is not None else SYSTEM

    def provide(self, name: str, thing: Any) -> None:
        """Offer `thing` to this agent's other plugins under `name` (see `Agent.provide`)."""
        self._require_agent().provide(name, thing)

    def provided(self, name: str) -> Any | None:
        """What another plugin of this agent offered under `name`, None when nothing was (or no agent)."""
        return self._agent.provided(name) if self._agent is not None else None

    @property
    def query(self) -> Query:
        """`query(Type, where=...)`: a snapshot of the committed objects matching a type and/or predicate."""
        return self._board.query

    def rehydrated(self, obj: BBObject | str) -> bool:
        """True when this object came back from the journal after a restart (not new work)."""
        uid = obj if isinstance(obj, str) else obj.uid
        return self._agent is not None and uid in self._agent.rehydrated

    # -- publishing -----------------------------------------------------------------------

    def _open_tx(self) -> Transaction | None:
        """The transaction open on the calling thread, or None."""
        tx: Transaction | None = getattr(self._local, "tx", None)
        return None if tx is None or tx.closed else tx

    def _tx(self, verb: str) -> Transaction:
        tx = self._open_tx()
        if tx is None:
            raise TransactionError(
                f"{self.agent_name}/{self.name}: {verb}() outside a transaction; publish in "
                "setup()/execute() or inside `with self.transaction():`"
            )
        return tx

    def add(self, obj: T) -> T:
        """Publish a new object (visible to others when the transaction commits)."""
        return self._tx("add").add(obj)

    def change(self, obj: T, reports: Any = ()) -> T:
        """Publish a new version of an object, with optional change reports."""
        return self._tx("change").change(obj, reports)

    def remove(self, obj: BBObject | str) -> None:
        """Remove an object (for a task: cancel it)."""
        self._tx("remove").remove(obj)

    def after_commit(self, fn: Callable[[], Any]) -> None:
        """Call `fn` once the open transaction has committed (never when it publishes nothing because
        it failed); `fn` runs on the committing thread, outside the blackboard."""
        self._tx("after_commit").after_commit(fn)

    @contextmanager
    def transaction(self) -> Iterator[Transaction]:
        """Open a transaction on the calling thread; commit on success, publish nothing on error."""
        joined = self._open_tx()
        if joined is not None:
            yield joined  # already inside one on this thread: join it
            return
        tx = self._board.transaction(f"{self.agent_name}/{self.name}")
        self._local.tx = tx
        try:
            yield tx
        except BaseException:
            tx.abort()
            raise
        else:
            tx.commit()
        finally:
            self._local.tx = None

    # -- wake-ups and hand-offs -----------------------------------------------------------

    def wake(self) -> None:
        """Ask for one more run of `execute()` soon."""
        self._woken = True
        self._signal()

    def wake_in(self, seconds: float) -> Timer:
        """Run `execute()` once after `seconds`; returns a handle with `cancel()`."""
        return self._require_agent().timers.schedule(self, seconds, None)

    def wake_every(self, seconds: float) -> Timer:
        """Run `execute()` every `seconds`; returns a handle with `cancel()`."""
        if not seconds > 0:
            raise UsageError(f"wake_every: expected a period > 0 s, got {seconds}")
        return self._require_agent().timers.schedule(self, seconds, seconds)

    def later(self, fn: Callable[[], Any]) -> None:
        """Run `fn()` at the start of the next `execute()`, inside its transaction."""
        self._later.append(fn)
        self._signal()

    # -- internals ------------------------------------------------------------------------

    @property
    def _board(self) -> Blackboard:
        return self._require_agent().blackboard

    def _require_agent(self) -> Agent:
        if self._agent is None:
            raise TransactionError(f"{self.name}: plugin is not part of an agent yet")
        return self._agent

    def _signal(self) -> None:
        if self._agent is not None:
            self._agent.scheduler.signal(self)

    def _bind(self, agent: Agent, name: str, settings: SettingsT) -> None:
        self._agent = agent
        self.name = name
        self.agent_name = agent.name
        self.settings = settings
        self.log = logging.getLogger(f"erni.{agent.name}.{name}")
