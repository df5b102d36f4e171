"""A SQLite journal of durable blackboard objects, for rehydration after a crash.

Objects whose class sets `durable = True` (tasks, mission state) are written by a journal
thread, never by the committing thread: a commit only appends its operations to a queue.
Each batch is one SQLite transaction (WAL mode), so a crash mid-write leaves the journal as
it was before or after the batch, never in between. On start the agent loads the journal
back onto the blackboard before any plugin is set up.

A batch that cannot be written (a full disk, an I/O error) is kept in memory and retried
every second; meanwhile `failed` says why, and the agent reports itself degraded and refuses
new tasks. A file system with less than `RESERVE` bytes free counts as full before a write
fails (`problem()`), so a task is refused rather than acknowledged into a write that would fail. A journal that cannot be read at start (corrupted, or an empty file where a
journal was) raises `JournalError` with one line; `move_aside` makes room for an empty one.

A journal never loses committed writes without saying so. Each batch counts itself in the
journal (`meta.writes`, in the batch's own SQLite transaction) and, once committed, leaves the
count and how many objects the journal then holds in a small file beside it (`NAME-seal`, written
after the commit, so it never runs ahead of what is on disk). At start the two must agree: a
journal that holds fewer writes than its seal (a damaged write-ahead log, which SQLite's recovery
silently cuts at the first bad frame once its `-shm` index is gone) or, at the same write,
fewer objects, raises `JournalError` naming the file and what is missing.
"""

from __future__ import annotations

import logging
import os
import queue
import re
import sqlite3
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeAlias

from erni.blackboard.blackboard import CHANGE, REMOVE, Op
from erni.blackboard.clock import SYSTEM, Clock, monotonic
from erni.blackboard.errors import ConfigError
from erni.blackboard.objects import BBObject

SCHEMA = """
CREATE TABLE IF NOT EXISTS objects (
    uid TEXT PRIMARY KEY,
    type TEXT NOT NULL,
    data TEXT NOT NULL,
    updated REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


def durable_types() -> dict[str, type[BBObject]]:
    """Return every loaded BBObject subclass marked durable, by class name."""
    found: dict[str, type[BBObject]] = {}
    pending = [BBObject]
    while pending:
        cls = pending.pop()
        for sub in cls.__subclasses__():
            pending.append(sub)
            if getattr(sub, "durable", False):
                found[sub.__name__] = sub
    return found


class JournalError(ConfigError):
    """The journal cannot be opened or read: `FILE: what is wrong; what to do`."""


RESERVE = 1024 * 1024
"""Bytes that must stay free on the journal's file system for the agent to take new tasks."""

RECOVERY = ("move it aside to start empty (`erni agent CONFIG --reset-journal` does, keeping the file), "
            "or restore it from a copy")


SEAL = "-seal"
"""The suffix of the file beside a journal that says how many writes and objects it holds."""

_SEAL_LINE = re.compile(rb"erni-journal-seal 1 writes (\d{20}) objects (\d{20})\n")


def move_aside(path: str | Path) -> Path:
    """Rename a journal (and its -wal, -shm and -seal files) to `NAME.bad-N`; return the new path."""
    path = Path(path)
    n = 1
    while path.with_name(f"{path.name}.bad-{n}").exists():
        n += 1
    target = path.with_name(f"{path.name}.bad-{n}")
    for suffix in ("", "-wal", "-shm", SEAL):
        src = path.with_name(path.name + suffix)
        if src.exists():
            os.replace(src, target.with_name(target.name + suffix))
    return target


def _urgent(ops: list[Op]) -> bool:
    """Whether a commit's durable operations must reach the disk at once: anything but changes of
    objects still running (a new task, a final state, a removal)."""
    return any(kind != CHANGE or getattr(obj, "done", True) for kind, obj, _ in ops)


Item: TypeAlias = "list[Op] | Callable[[], Any] | None"
"""What the journal thread takes from its queue: a commit's durable operations, a flush marker
([]), a call to make once everything before it is on disk (`when_durable`), or the stop (None)."""


def _urgent_item(item: Item) -> bool:
    """Whether a queued item ends the batch's lingering: the stop (None), a flush marker ([]), a
    call waiting for the disk or an urgent commit."""
    return item is None or not isinstance(item, list) or not item or _urgent(item)


class Journal:
    """Journal durable objects of one blackboard to a SQLite file."""

    def __init__(self, path: str | Path, agent: str = "agent", linger: float = 1.0, *, clock: Clock = SYSTEM):
        self.path = Path(path)
        self.clock = clock  # the agent's: its wall reading stamps each row's last write (`updated`)
        # a batch of progress changes only waits this long for more (s): a walking robot's running tasks
        # change a few times a second, and each write is an fsync and a dozen wake-ups of this thread
        self.linger = linger
        self.log = logging.getLogger(f"erni.{agent}.journal")
        self._queue: queue.SimpleQueue[Item] = queue.SimpleQueue()
        self._hold_lock = threading.Lock()
        self._lingering = False  # the journal thread waits out a batch's linger (`listener` holds commits)
        self._held: list[Item] = []  # commits made during the linger, in commit order
        self._durable_calls: list[Callable[[], Any]] = []  # `when_durable` calls waiting for a write that succeeds
        self._thread: threading.Thread | None = None
        self._flushed = threading.Condition()
        self._enqueued = 0
        self._written = 0
        self._pending: dict[str, tuple[str, str] | None] = {}  # rows not written yet, retried
        self.failed = ""  # why the last write failed ('' when writes succeed)
        self.batches = 0
        self.writes = 0  # batches this journal holds, over its whole life (`meta.writes`)
        self._seal_path = self.path.with_name(self.path.name + SEAL)
        self._seal_fd: int | None = None
        existed = self.path.exists()
        self.written_at: dict[str, float] = {}  # uid -> when `load` found its row last written (wall clock)
        try:
            if self.path.exists() and self.path.stat().st_size == 0:
                raise JournalError(f"{self.path}: the journal is an empty file (0 bytes), not a journal: it "
                                   f"was truncated or is not ERNI's; {RECOVERY}")
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        except OSError as err:
            raise JournalError(f"{self.path}: cannot open the journal: {err.strerror or err}") from None
        except sqlite3.Error as err:
            raise JournalError(f"{self.path}: cannot open the journal: {err}") from None
        try:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(SCHEMA)
            problems = [row[0] for row in self._db.execute("PRAGMA quick_check")]
            if problems != ["ok"]:
                raise sqlite3.DatabaseError(f"{len(problems)} problem(s), first: {str(problems[0])[:120]}")
            row = self._db.execute("SELECT value FROM meta WHERE key = 'writes'").fetchone()
            self.writes = int(row[0]) if row is not None and str(row[0]).isdigit() else 0
            held = int(self._db.execute("SELECT COUNT(*) FROM objects").fetchone()[0])
        except sqlite3.Error as err:
            self._db.close()
            raise JournalError(f"{self.path}: the journal is unreadable ({str(err).splitlines()[0]}); "
                               f"{RECOVERY}") from None
        try:
            self._check_seal(existed, held)
        except JournalError:
            self._db.close()
            raise

    def _check_seal(self, existed: bool, held: int) -> None:
        """Compare what the journal holds with its seal (JournalError when it lost writes), then
        open the seal for this run's writes."""
        try:
            sealed = self._seal_path.read_bytes()
        except FileNotFoundError:
            sealed = None
        except OSError as err:
            raise JournalError(f"{self._seal_path}: cannot read the journal's seal: {err.strerror or err}") from None
        if sealed is not None:
            match = _SEAL_LINE.fullmatch(sealed)
            if match is None:
                self.log.warning("%s: the journal's seal is unreadable (%d bytes): what the journal holds is not "
                                 "checked this time", self._seal_path, len(sealed))
            elif not existed:
                self.log.warning("%s: no journal, but its seal says it held %d object(s) after %d write(s): "
                                 "starting a new, empty journal", self.path, int(match[2]), int(match[1]))
            else:
                writes, objects = int(match[1]), int(match[2])
                if writes > self.writes or (writes == self.writes and held < objects):
                    raise JournalError(
                        f"{self.path}: the journal lost committed writes: it holds {held} object(s) after "
                        f"{self.writes} write(s), but after write {writes} it held {objects}: {writes - self.writes} "
                        f"write(s) missing (a damaged or lost {self.path.name}-wal?); {RECOVERY} (with its {SEAL} "
                        "file, or without one)")
        try:
            self._seal_fd = os.open(self._seal_path, os.O_WRONLY | os.O_CREAT, 0o600)
        except OSError as err:
            raise JournalError(f"{self._seal_path}: cannot write the journal's seal: {err.strerror or err}") from None
        self._seal(held)

    def _seal(self, held: int) -> None:
        """Leave the writes and objects the journal holds now in its seal (after a commit: the seal
        never says more than is on disk; a crash may leave it a write behind, never ahead)."""
        if self._seal_fd is None:
            return
        line = b"erni-journal-seal 1 writes %020d objects %020d\n" % (self.writes, held)
        try:
            os.pwrite(self._seal_fd, line, 0)
        except OSError as err:
            self.log.warning("%s: cannot write the journal's seal: %s", self._seal_path, err.strerror or err)

    def problem(self) -> str:
        """Why this journal cannot keep new objects now ('' when it can): a full disk, a failed write
        (both when both: a write fails on a full disk before the disk's check sees it)."""
        failed = f"journal write failed: {self.failed}" if self.failed else ""
        try:
            stat = os.statvfs(self.path.parent)
        except OSError as err:
            return failed or f"journal file system unreadable: {err.strerror or err}"
        free = stat.f_bavail * stat.f_frsize
        if free < RESERVE:
            full = f"disk full: {free // 1024} KiB free for the journal {self.path.name} (needs {RESERVE // 1024} KiB)"
            return f"{full}; {failed}" if failed else full
        return failed

    # -- reading back ---------------------------------------------------------------------

    def load(self) -> tuple[list[BBObject], list[str]]:
        """Return the journaled objects, and one problem line per row that could not be read; when
        each row was last written (wall clock) is left in `written_at`."""
        types = durable_types()
        objects: list[BBObject] = []
        problems: list[str] = []
        try:
            rows = self._db.execute("SELECT uid, type, data, updated FROM objects ORDER BY rowid").fetchall()
        except sqlite3.Error as err:
            self._db.close()
            raise JournalError(f"{self.path}: the journal is unreadable ({str(err).splitlines()[0]}); "
                               f"{RECOVERY}") from None
        for uid, type_name, data, updated in rows:
            self.written_at[uid] = updated
            cls = types.get(type_name)
            if cls is None:
                problems.append(f"{self.path}: object {uid}: unknown type {type_name!r} (plugin not loaded?)")
                continue
            try:
                objects.append(cls.model_validate_json(data))
            except Exception as err:  # a row we cannot read is reported and kept, never fatal
                problems.append(f"{self.path}: object {uid}: {str(err).splitlines()[0]}")
        return objects, problems

    # -- writing --------------------------------------------------------------------------

    def listener(self, ops: list[Op]) -> None:
        """Blackboard commit listener: queue the durable operations (no I/O here). While a batch
        lingers they join it without waking the journal thread, unless they end the linger."""
        durable = [op for op in ops if getattr(op[1], "durable", False)]
        if durable:
            self._enqueued += 1
            with self._hold_lock:  # (commits come in order: the blackboard calls its listeners under its lock)
                if not self._lingering:
                    self._queue.put(durable)
                    return
                self._held.append(durable)
                if _urgent(durable):
                    self._queue.put([])  # ends the linger: the batch, this commit in it, goes now

    def when_durable(self, fn: Callable[[], Any]) -> None:
        """Call `fn` on the journal thread once every commit queued before this call is on disk (at
        once after a batch's write: a group commit acknowledges all of its batch; while writes fail,
        after the first that succeeds). No I/O here."""
        self._queue.put(fn)

    def start(self) -> None:
        """Start the journal thread."""
        self._thread = threading.Thread(target=self._run, name=f"{self.log.name}-writer", daemon=True)
        self._thread.start()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until everything queued so far was tried; return True if it is on disk."""
        target = self._enqueued
        deadline = monotonic() + timeout
        self._queue.put([])  # the flush marker: ends a lingering batch, and the batch it is in does not linger
        with self._flushed:
            while self._written < target:
                left = deadline - monotonic()
                if left <= 0:
                    return False
                self._flushed.wait(left)
        return not self.failed

    def stop(self, timeout: float = 1.0) -> None:
        """Write what is queued, stop the thread and close the file."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout)
            self._thread = None
        try:
            self._db.close()
        except sqlite3.Error:
            pass
        if self._seal_fd is not None:
            os.close(self._seal_fd)
            self._seal_fd = None

    def _run(self) -> None:
        while True:
            try:  # with rows waiting for a failed disk, retry every second
                batch = [self._queue.get(timeout=1.0 if self._pending else None)]
            except queue.Empty:
                self._write([])
                self._durable([])
                continue
            # take whatever else is waiting: one SQLite transaction (one fsync) for all of it; a batch
            # of changes that are not news (a running task's progress: a control node gets two a
            # second from every robot) waits up to `linger` for more; a new, final or removed
            # object, a flush or the stop is written at once; the commits of a lingering batch are held
            # beside the queue (`listener`): only what ends the linger wakes this thread
            until = monotonic() + self.linger
            urgent = _urgent_item(batch[0])
            if not urgent:
                with self._hold_lock:
                    self._lingering = True
                while not urgent:
                    left = until - monotonic()
                    if left <= 0:
                        break
                    try:
                        item = self._queue.get(timeout=left)
                    except queue.Empty:
                        break
                    batch.append(item)
                    urgent = _urgent_item(item)
                batch += self._taken()  # commits queued before the linger began, calls, flush markers
                with self._hold_lock:  # commits queued from now on come after the held ones
                    self._lingering = False
                    batch += self._held
                    self._held = []
            batch += self._taken()
            stop = None in batch
            ops = [op for item in batch if isinstance(item, list) for op in item]
            if ops:
                self._write(ops)
            with self._flushed:
                self._written += sum(1 for item in batch if isinstance(item, list) and item)
                self._flushed.notify_all()
            self._durable([item for item in batch if item is not None and not isinstance(item, list)])
            if stop:
                return

    def _taken(self) -> list[Item]:
        """Everything the queue holds now."""
        items = []
        while True:
            try:
                items.append(self._queue.get_nowait())
            except queue.Empty:
                return items

    def _durable(self, calls: list[Callable[[], Any]]) -> None:
        """Make the calls waiting for the disk, once nothing waits to be written (a failed write's
        rows are retried first: their calls wait with them)."""
        self._durable_calls += calls
        if self.failed or self._pending or not self._durable_calls:
            return
        calls, self._durable_calls = self._durable_calls, []
        for fn in calls:
            try:
                fn()
            except Exception:
                self.log.exception("a call waiting for the journal's write failed")

    def _write(self, ops: list[Op]) -> None:
        now = self.clock.wall()
        rows: dict[str, Any] = dict(self._pending)  # rows a failed write left behind come first
        for kind, obj, _ in ops:  # later operations on the same uid win
            rows.pop(obj.uid, None)
            rows[obj.uid] = None if kind == REMOVE else (type(obj).__name__, obj.model_dump_json())
        if not rows:
            return
        try:
            self._db.execute("BEGIN IMMEDIATE")
            for uid, row in rows.items():
                if row is None:
                    self._db.execute("DELETE FROM objects WHERE uid = ?", (uid,))
                else:
                    self._db.execute(
                        "INSERT INTO objects (uid, type, data, updated) VALUES (?, ?, ?, ?) "
                        "ON CONFLICT(uid) DO UPDATE SET type = excluded.type, data = excluded.data, "
                        "updated = excluded.updated", (uid, row[0], row[1], now))
            self._db.execute("INSERT INTO meta (key, value) VALUES ('writes', ?) ON CONFLICT(key) DO UPDATE "
                             "SET value = excluded.value", (str(self.writes + 1),))
            held = int(self._db.execute("SELECT COUNT(*) FROM objects").fetchone()[0])
            self._db.execute("COMMIT")
            self.writes += 1
            self._seal(held)
            self.batches += 1
        except sqlite3.Error as err:
            try:
                self._db.execute("ROLLBACK")
            except sqlite3.Error:
                pass
            self._pending = rows
            if not self.failed:  # one line when it starts failing, one when it recovers
                self.log.error("journal write failed (%d object(s) kept in memory, retried every second; "
                               "new tasks are refused meanwhile): %s", len(rows), err)
            self.failed = str(err).splitlines()[0] if str(err) else type(err).__name__
            return
        self._pending = {}
        if self.failed:
            self.log.warning("journal writes again (%d object(s) saved)", len(rows))
            self.failed = ""
