"""The agent host: a blackboard, a worker pool that runs plugins, timers, start and stop."""

from __future__ import annotations

import functools
import heapq
import importlib
import itertools
import logging
import queue
import threading
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, TypeVar, overload

from pydantic import BaseModel, ValidationError

from erni.blackboard.blackboard import Blackboard, Query, Transaction
from erni.blackboard.clock import SYSTEM, Clock, as_clock, monotonic
from erni.blackboard.errors import ConfigError, PluginError, UsageError, describe_validation
from erni.blackboard.plugin import NoSettings, Plugin

P = TypeVar("P", bound=Plugin[Any])

ENTRY_POINT_GROUP = "erni.plugins"


class Scheduler:
    """Runs plugins on a pool of worker threads; one plugin never runs concurrently with itself."""

    def __init__(self, agent: Agent, workers: int, slow_seconds: float):
        self.agent = agent
        self.workers = workers
        self.slow_seconds = slow_seconds
        self._queue: queue.SimpleQueue[Plugin[Any] | None] = queue.SimpleQueue()
        self._threads: list[threading.Thread] = []
        self._accepting = False
        self._log = logging.getLogger(f"erni.{agent.name}")

    def start(self) -> None:
        """Start the worker threads."""
        self._accepting = True
        for i in range(self.workers):
            t = threading.Thread(target=self._work, name=f"erni-{self.agent.name}-worker-{i}",
                                 daemon=True)
            t.start()
            self._threads.append(t)

    def signal(self, plugin: Plugin[Any]) -> None:
        """Ask for a run of `plugin`; signals coalesce, and one during a run causes one more."""
        with plugin._sched_lock:
            if not self._accepting or plugin._disabled:
                return
            if plugin._running:
                plugin._dirty = True
            elif not plugin._scheduled:
                plugin._scheduled = True
                self._queue.put(plugin)

    def stop(self, deadline: float) -> list[str]:
        """Stop accepting work, let running plugins finish, join workers; return laggards."""
        self._accepting = False
        for _ in self._threads:
            self._queue.put(None)
        late = []
        for t in self._threads:
            t.join(max(0.0, deadline - monotonic()))
            if t.is_alive():
                late.append(t.name)
        self._threads = []
        return late

    def _work(self) -> None:
        while True:
            plugin: Plugin[Any] | None = self._queue.get()
            if plugin is None:
                return
            while plugin is not None:
                plugin = self._run_once(plugin)

    def _run_once(self, plugin: Plugin[Any]) -> Plugin[Any] | None:
        """Run `plugin` once; return it when it was signalled meanwhile (this worker runs it again
        at once: putting it back in the queue would wake another worker for it, and this one would
        wait for work), else None."""
        if not self._accepting:  # stopping: queued runs are dropped
            with plugin._sched_lock:
                plugin._scheduled = False
            return None
        started = self.agent.clock()
        with plugin._sched_lock:
            plugin._scheduled = False
            plugin._running = True
            plugin._dirty = False
            plugin._run_started = started
            plugin._slow_reported = False
        try:
            self._run(plugin)
        finally:
            with plugin._sched_lock:
                plugin._running = False
                again = plugin._dirty and self._accepting and not plugin._disabled
                plugin._dirty = False
                if again:
                    plugin._scheduled = True  # taken by this worker: a signal meanwhile adds nothing
        return plugin if again else None

    def _run(self, plugin: Plugin[Any]) -> None:
        """One run: the view moves to the latest commit, then execute() inside a transaction."""
        board = self.agent.blackboard
        subs = plugin._subs
        deltas = False
        for sub, inbox in zip(subs, board._drain(subs)):
            if sub._open(inbox):
                deltas = True
        woken, plugin._woken = plugin._woken, False
        laters = []
        pending = plugin._later
        while pending:
            laters.append(pending.popleft())
        if not (deltas or woken or laters):
            return
        plugin.runs += 1
        tx = Transaction(board, plugin.name)
        plugin._local.tx = tx
        try:
            for fn in laters:  # each hand-off fails alone: its publications are dropped
                mark = tx.savepoint()
                try:
                    fn()
                except Exception:
                    tx.rollback_to(mark)
                    plugin.failures += 1
                    plugin.log.exception("work handed to agent %s, plugin %s with later() failed; "
                                         "it published nothing, the run goes on", self.agent.name, plugin.name)
            plugin.execute()
            tx.commit()
        except Exception:
            tx.abort()
            plugin.failures += 1
            plugin.log.exception("execute() failed in agent %s, plugin %s; its transaction "
                                 "published nothing", self.agent.name, plugin.name)
        finally:
            plugin._local.tx = None
            for sub in subs:
                sub.added, sub.changed, sub.removed, sub._reports = [], [], [], {}  # the deltas were this run's

    def check_slow(self) -> float:
        """Report each plugin run that exceeded the slow limit (once per run); return when to look again.

        A run that starts after this check is over the limit no earlier than one limit from now, so
        with nothing running the next look is one limit away, else at the earliest running one's limit.
        """
        now = self.agent.clock()
        nxt = now + self.slow_seconds
        for plugin in list(self.agent.plugins):
            if not plugin._running or plugin._slow_reported:
                continue
            elapsed = now - plugin._run_started
            if elapsed > self.slow_seconds:
                plugin._slow_reported = True
                plugin.log.warning("plugin %s of agent %s has been running for %.1f s (limit %.1f s)",
                                   plugin.name, self.agent.name, elapsed, self.slow_seconds)
            else:
                nxt = min(nxt, plugin._run_started + self.slow_seconds + 0.001)
        return nxt


class Timer:
    """A pending wake-up; `cancel()` stops it."""

    def __init__(self, plugin: Plugin[Any], when: float, period: float | None):
        self.plugin = plugin
        self.when = when
        self.period = period
        self.cancelled = False

    def cancel(self) -> None:
        """Do not fire again."""
        self.cancelled = True


class Timers:
    """One thread that fires plugin wake-ups and watches for slow plugins."""

    def __init__(self, agent: Agent):
        self.agent = agent
        self._heap: list[tuple[float, int, Timer]] = []
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._stopping = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the timer thread."""
        self._stopping = False
        self._thread = threading.Thread(target=self._loop, name=f"erni-{self.agent.name}-timers",
                                        daemon=True)
        self._thread.start()

    def schedule(self, plugin: Plugin[Any], delay: float, period: float | None) -> Timer:
        """Wake `plugin` after `delay` seconds, then every `period` seconds if given."""
        timer = Timer(plugin, self.agent.clock() + max(0.0, delay), period)
        with self._cond:
            heapq.heappush(self._heap, (timer.when, next(self._seq), timer))
            self._cond.notify()
        return timer

    def poke(self) -> None:
        """Look at the clock again now (a test's clock moved: see `erni.testing.ManualClock`)."""
        with self._cond:
            self._cond.notify()

    def stop(self, deadline: float) -> bool:
        """Stop the thread; return True when it was joined in time."""
        with self._cond:
            self._stopping = True
            self._heap.clear()
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(max(0.0, deadline - monotonic()))
            alive = self._thread.is_alive()
            self._thread = None
            return not alive
        return True

    def _loop(self) -> None:
        look = 0.0   # when the slow-plugin watch must look next
        while True:
            due: list[Timer] = []
            with self._cond:
                if self._stopping:
                    return
                now = self.agent.clock()
                while self._heap and self._heap[0][0] <= now:
                    _, _, timer = heapq.heappop(self._heap)
                    if timer.cancelled:
                        continue
                    due.append(timer)
                    if timer.period:
                        timer.when = max(timer.when + timer.period, now)
                        heapq.heappush(self._heap, (timer.when, next(self._seq), timer))
                wait = look - now
                if self._heap:
                    wait = min(wait, self._heap[0][0] - now)
                if not due:
                    self._cond.wait(max(0.0, wait))
            for timer in due:
                timer.plugin.wake()
            if self.agent.clock() >= look:
                look = self.agent.scheduler.check_slow()


class Agent:
    """One agent: a named blackboard with its plugins, run by a worker pool."""

    def __init__(self, name: str, *, workers: int = 4, slow_plugin_seconds: float = 1.0,
                 journal: str | Path | None = None, retention: float | None = 600.0, reset_journal: bool = False,
                 clock: Clock | Callable[[], float] = SYSTEM):
        if workers < 1:
            raise UsageError(f"workers: expected at least 1, got {workers}")
        self.name = name
        self.clock: Clock = as_clock(clock)
        """The agent's clock (erni.blackboard.clock): called, monotonic seconds (when plugins' wake-ups are
        due, how long a run has taken, when a final task is old enough to go); `wall()`, the stamps it
        makes. A test may give its own (`erni.testing.ManualClock`); a bare callable is its monotonic
        reading, with the process's wall clock beside it."""
        self.blackboard = Blackboard(name)
        self.scheduler = Scheduler(self, workers, slow_plugin_seconds)
        self.timers = Timers(self)
        watch = getattr(self.clock, "on_advance", None)
        if callable(watch):  # a test's clock says when it moves: timers and slow-run watch look again
            watch(self.timers.poke)
        self.blackboard.signal = self.scheduler.signal
        self.plugins: list[Plugin[Any]] = []
        self.log = logging.getLogger(f"erni.{name}")
        self.started = False
        self.components: list[Any] = []  # non-plugin parts with start()/stop()
        self._offers: dict[str, Any] = {}  # what plugins offer each other beside the blackboard (`provide`)
        self._offers_lock = threading.Lock()
        self.journal_path = Path(journal) if journal else None
        self.journal: Any = None
        self.reset_journal = reset_journal  # a journal unreadable at start is moved aside, not fatal
        self.rehydrated: set[str] = set()
        self.retention: Any = None
        if retention is not None:
            if not retention > 0:
                raise UsageError(f"retention: expected a positive number of seconds, got {retention}")
            from erni.blackboard.retention import Retention

            self.retention = Retention(self, retention)
            from erni.blackboard.tasks import Task

            self.blackboard.add_listener(self.retention.listener, Task)
            self.components.append(self.retention)

    @classmethod
    def from_config(cls, path: str | Path) -> Agent:
        """Build an agent from a TOML config file (raises ConfigError)."""
        from erni.blackboard.config import load_agent

        return load_agent(path)

    # -- plugins --------------------------------------------------------------------------

    def provide(self, name: str, thing: Any) -> None:
        """Offer `thing` to the agent's plugins under `name`: the agent-level facility for what one
        plugin gives another that cannot travel on the blackboard (a live session, a hardware
        description read from a driver). Plugins never reach into each other's attributes; the
        names offered are listed in the architecture's documentation. A second offer replaces the first."""
        with self._offers_lock:
            self._offers[name] = thing

    def provided(self, name: str) -> Any | None:
        """What a plugin offered under `name` (`provide`), None when nothing was."""
        with self._offers_lock:
            return self._offers.get(name)

    @overload
    def add_plugin(self, plugin: type[P] | P, settings: dict[str, Any] | BaseModel | None = None,
                   name: str | None = None) -> P: ...

    @overload
    def add_plugin(self, plugin: str, settings: dict[str, Any] | BaseModel | None = None,
                   name: str | None = None) -> Plugin[Any]: ...

    def add_plugin(self, plugin: type[Plugin[Any]] | Plugin[Any] | str,
                   settings: dict[str, Any] | BaseModel | None = None, name: str | None = None) -> Plugin[Any]:
        """Add a plugin (class, instance, `module:Class` path or entry point name)."""
        cls = resolve_plugin(plugin) if not isinstance(plugin, Plugin) else type(plugin)
        instance = plugin if isinstance(plugin, Plugin) else cls()
        name = name or cls.__name__
        if any(p.name == name for p in self.plugins):
            raise PluginError(f"agent {self.name}: a plugin named {name!r} is already loaded")
        try:
            valid = validate_settings(cls, settings)
        except ValidationError as err:
            raise ConfigError(describe_validation(err, f"agent {self.name}, plugin {name}", "settings")) from None
        instance._bind(self, name, valid)
        self.plugins.append(instance)
        if self.started:
            self._setup(instance)
        return instance

    def plugin(self, name: str) -> Plugin[Any]:
        """Return the plugin with this name."""
        for p in self.plugins:
            if p.name == name:
                return p
        raise PluginError(f"agent {self.name}: no plugin named {name!r}")

    @property
    def degraded(self) -> str:
        """Why this agent cannot keep new work ('' when it can): its journal cannot write."""
        return self.journal.problem() if self.journal is not None else ""

    def when_durable(self, fn: Callable[[], Any]) -> None:
        """Call `fn` once everything committed so far would survive a kill -9: after the journal's
        next write (on its thread; with writes failing, after the first that succeeds), at once
        for an agent without a journal. An acknowledgement of a task waits for this."""
        if self.journal is not None:
            self.journal.when_durable(fn)
        else:
            fn()

    def _setup(self, plugin: Plugin[Any]) -> None:
        """Run setup() as the plugin's first run: signals meanwhile cause one run after it."""
        with plugin._sched_lock:
            plugin._running = True
            plugin._run_started = self.clock()  # a setup is a run: timed like one
            plugin._slow_reported = False
        plugin._in_setup = True
        plugin._setup_ran = True
        try:
            with plugin.transaction():
                plugin.setup()
        except Exception as err:
            plugin._disabled = True
            plugin.failures += 1
            plugin._setup_error = err
            if not plugin.essential:  # an essential plugin's failure stops the start, with one line
                plugin.log.exception("setup() failed in agent %s, plugin %s; the plugin is disabled, "
                                     "the agent goes on", self.name, plugin.name)
        finally:
            plugin._in_setup = False
            with plugin._sched_lock:
                plugin._running = False
                again, plugin._dirty = plugin._dirty, False
            if again:
                self.scheduler.signal(plugin)

    # -- life cycle -----------------------------------------------------------------------

    def start(self) -> Agent:
        """Start workers and timers, then set up every plugin."""
        if self.started:
            return self
        if self.journal_path is not None:
            self._rehydrate()
        self.scheduler.start()
        self.timers.start()
        self.started = True
        for plugin in list(self.plugins):
            self._setup(plugin)
            if plugin.essential and plugin._setup_error is not None:
                err = plugin._setup_error
                self.stop(announce=False)
                detail = str(err).splitlines()[0] if str(err) else type(err).__name__
                raise PluginError(f"plugin {plugin.name} could not start: {detail}")
        for component in self.components:
            component.start()
        self.log.info("agent %s started with %d plugin(s)", self.name, len(self.plugins))
        return self

    def stop(self, timeout: float = 1.0, *, announce: bool = True) -> None:
        """Stop plugins, components, workers and timers; returns within `timeout` for
        well-behaved plugins, with every thread of the agent joined."""
        if not self.started:
            return
        deadline = monotonic() + timeout  # thread joins keep real time, whatever the agent's clock
        self.started = False
        late = self.scheduler.stop(deadline)
        for plugin in self.plugins:
            if not plugin._setup_ran:
                continue  # never set up (an essential plugin before it failed): nothing to tear down
            try:
                plugin.teardown()
            except Exception:
                plugin.log.exception("teardown() failed in agent %s, plugin %s", self.name, plugin.name)
        for component in reversed(self.components):
            try:
                component.stop()
            except Exception:
                self.log.exception("stopping %s failed", type(component).__name__)
        if not self.timers.stop(deadline):
            late.append("timers")
        if self.journal is not None:
            self.journal.stop()
            self.journal = None
        if late:
            self.log.warning("agent %s: threads still busy at stop: %s", self.name, ", ".join(late))
        if announce:
            self.log.info("agent %s stopped", self.name)

    def _rehydrate(self) -> None:
        """Open the journal, put its objects back on the blackboard, then journal every commit.

        An unreadable journal raises JournalError (one line, with the recovery), unless
        `reset_journal` asks to move it aside and start empty.
        """
        from erni.blackboard.journal import Journal, JournalError, move_aside

        assert self.journal_path is not None
        try:
            self.journal = Journal(self.journal_path, self.name, clock=self.clock)
            objects, problems = self.journal.load()
        except JournalError as err:
            if not self.reset_journal:
                raise
            aside = move_aside(self.journal_path)
            self.log.warning("%s; moved to %s, starting with an empty journal", str(err).split(";")[0], aside)
            self.journal = Journal(self.journal_path, self.name, clock=self.clock)
            objects, problems = [], []
        for line in problems:
            self.log.warning("%s", line)
        if objects:
            with self.blackboard.transaction("rehydrate") as tx:
                for obj in objects:
                    if not self.blackboard.contains(obj.uid):
                        tx.add(obj)
            self.rehydrated = {obj.uid for obj in objects}
            if self.retention is not None:  # a final task leaves `retention` after it ended, not after the restart
                wall = self.clock.wall()
                for obj in objects:
                    written = self.journal.written_at.get(obj.uid)
                    if getattr(obj, "done", False) and written is not None:
                        self.retention.ended(obj.uid, wall - written)
            self.log.info("agent %s rehydrated %d object(s) from %s", self.name, len(objects),
                          self.journal_path)
        self.blackboard.add_listener(self.journal.listener)
        self.journal.start()

    def __enter__(self) -> Agent:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    # -- access from outside threads ------------------------------------------------------

    def transaction(self, label: str = "outside") -> Transaction:
        """Open a transaction for code outside any plugin (`with`: commit on success)."""
        return Transaction(self.blackboard, label)

    @property
    def query(self) -> Query:
        """`query(Type, where=...)`: a snapshot of the committed objects matching a type and/or predicate."""
        return self.blackboard.query


@overload
def resolve_plugin(spec: type[P]) -> type[P]: ...


@overload
def resolve_plugin(spec: str) -> type[Plugin[Any]]: ...


def resolve_plugin(spec: type[Plugin[Any]] | str) -> type[Plugin[Any]]:
    """Return the plugin class named by a class, a `module:Class` path or an entry point name."""
    if isinstance(spec, type):
        if not issubclass(spec, Plugin):
            raise PluginError(f"{spec.__qualname__} is not a Plugin subclass")
        return spec
    if not isinstance(spec, str) or not spec.strip():
        raise PluginError(f"expected a plugin class, 'module:Class' or an entry point name, got {spec!r}")
    if ":" not in spec and "." not in spec:
        found = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == spec]
        if not found:
            known = sorted(ep.name for ep in entry_points(group=ENTRY_POINT_GROUP))
            raise PluginError(f"unknown plugin {spec!r}; known entry points: {', '.join(known) or 'none'}; "
                              "or give 'module:Class'")
        try:
            obj = found[0].load()
        except Exception as err:
            raise PluginError(f"cannot load plugin {spec!r} ({found[0].value}): {err}") from None
    else:
        module_name, _, attr = spec.partition(":") if ":" in spec else spec.rpartition(".")
        try:
            module = importlib.import_module(module_name)
        except Exception as err:
            raise PluginError(f"cannot import {spec!r}: {err}") from None
        obj = getattr(module, attr, None)
        if obj is None:
            raise PluginError(f"cannot import {spec!r}: module {module_name!r} has no {attr!r}")
    if not isinstance(obj, type) or not issubclass(obj, Plugin):
        raise PluginError(f"{spec!r} is not a Plugin subclass")
    return obj


def validate_settings(cls: type[Plugin[Any]], settings: dict[str, Any] | BaseModel | None) -> BaseModel:
    """Validate a plugin's settings against its `Settings` model (raises ValidationError).

    Unknown keys are refused even when the model itself would ignore them: a typo in a
    config must not pass silently.
    """
    model = getattr(cls, "Settings", NoSettings) or NoSettings
    if isinstance(settings, model):
        return settings
    if isinstance(settings, BaseModel):
        settings = settings.model_dump()
    return _strict(model).model_validate(settings or {})


@functools.cache
def _strict(model: type[BaseModel]) -> type[BaseModel]:
    """`model`, or a subclass of it that refuses unknown keys and non-finite numbers where `model`
    itself does not say (a plugin from outside ERNI may not derive its settings from `Model`)."""
    config = model.model_config
    if config.get("extra") is not None and config.get("allow_inf_nan") is False:
        return model
    strict = {**config, "extra": config.get("extra") or "forbid", "allow_inf_nan": False}
    return type(model.__name__, (model,), {"model_config": strict, "__module__": model.__module__})


__all__ = ["Agent", "ENTRY_POINT_GROUP", "Scheduler", "Timers", "ValidationError", "resolve_plugin"]
