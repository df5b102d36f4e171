"""A SQLite journal of durable blackboard objects, for rehydration after a crash.

Objects whose class sets `durable = True` (tasks, mission state) are written by a journal
thread, never by the committing thread: a commit only appends its operations to a queue.
Each batch is one SQLite transaction (WAL mode), so a crash mid-write leaves the journal as
it was before or after the batch, never in between. On start the agent loads the journal
back onto the blackboard before any plugin is set up.
"""

from __future__ import annotations

import logging
import queue
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

from erni.blackboard.blackboard import REMOVE, Op
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


class Journal:
    """Journal durable objects of one blackboard to a SQLite file."""

    def __init__(self, path: str | Path, agent: str = "agent"):
        self.path = Path(path)
        self.log = logging.getLogger(f"erni.{agent}.journal")
        self._queue: queue.SimpleQueue[list[Op] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._flushed = threading.Condition()
        self._enqueued = 0
        self._written = 0
        self.batches = 0
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(SCHEMA)
            self._db.execute("PRAGMA quick_check").fetchone()
        except sqlite3.DatabaseError as err:
            raise ConfigError(f"{self.path}: cannot open the journal: {err}") from None

    # -- reading back ---------------------------------------------------------------------

    def load(self) -> tuple[list[BBObject], list[str]]:
        """Return the journaled objects, and one problem line per row that could not be read."""
        types = durable_types()
        objects: list[BBObject] = []
        problems: list[str] = []
        for uid, type_name, data in self._db.execute("SELECT uid, type, data FROM objects ORDER BY rowid"):
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
        """Blackboard commit listener: queue the durable operations (no I/O here)."""
        durable = [op for op in ops if getattr(op[1], "durable", False)]
        if durable:
            self._enqueued += 1
            self._queue.put(durable)

    def start(self) -> None:
        """Start the journal thread."""
        self._thread = threading.Thread(target=self._run, name=f"{self.log.name}-writer", daemon=True)
        self._thread.start()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until everything queued so far is on disk; return False on timeout."""
        target = self._enqueued
        deadline = time.monotonic() + timeout
        with self._flushed:
            while self._written < target:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._flushed.wait(left)
        return True

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

    def _run(self) -> None:
        while True:
            batch = [self._queue.get()]
            while True:  # take whatever else is waiting: one SQLite transaction for all of it
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            stop = None in batch
            ops = [op for item in batch if item for op in item]
            if ops:
                self._write(ops)
            with self._flushed:
                self._written += sum(1 for item in batch if item)
                self._flushed.notify_all()
            if stop:
                return

    def _write(self, ops: list[Op]) -> None:
        now = time.time()
        rows: dict[str, Any] = {}
        for kind, obj, _ in ops:  # later operations on the same uid win
            rows[obj.uid] = None if kind == REMOVE else (type(obj).__name__, obj.model_dump_json())
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
            self._db.execute("COMMIT")
            self.batches += 1
        except sqlite3.Error as err:
            try:
                self._db.execute("ROLLBACK")
            except sqlite3.Error:
                pass
            self.log.error("journal write failed (%d object(s) not saved): %s", len(rows), err)
