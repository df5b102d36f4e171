"""The SQLite journal: durable objects survive a restart and a kill -9; non-durable ones do not."""

from __future__ import annotations

import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from erni.blackboard import Agent, Pose, Task, TaskState
from erni.blackboard.journal import Journal
from erni.blackboard.testing import wait_until
from tests.core.helpers import Recorder

ROOT = Path(__file__).resolve().parents[2]


def test_durable_objects_come_back_and_plugins_see_them_as_rehydrated(tmp_path):
    path = tmp_path / "robot.sqlite"
    agent = Agent("r1", journal=path)
    agent.start()
    keep = Task(verb="BotMotion", preposition="goto", params={"x": 1, "y": 2}, source="control")
    gone = Task(verb="BotMotion", preposition="stop", source="control")
    with agent.transaction() as tx:
        tx.add(keep)
        tx.add(gone)
        tx.add(Pose(robot="r1", x=3.0))  # not durable
    with agent.transaction() as tx:
        tx.change(keep.with_result(TaskState.RUNNING, progress=0.4, values={"remaining": 1.2}))
        tx.remove(gone)
    agent.stop()

    again = Agent("r1", journal=path)

    class Seer(Recorder):
        kind = Task

        def execute(self):
            super().execute()
            self.flags = [self.rehydrated(t) for t in self.sub.added]

    seer = again.add_plugin(Seer)
    again.start()
    try:
        wait_until(lambda: seer.views)
        (task,) = seer.views[0]["added"]
        assert task.uid == keep.uid and task.params == keep.params and task.source == "control"
        assert task.result.values == {"remaining": 1.2} and task.state is TaskState.RUNNING
        assert seer.flags == [True]
        assert again.query(Pose) == []
        fresh = Task(verb="BotMotion", preposition="stop")
        with again.transaction() as tx:
            tx.add(fresh)
        wait_until(lambda: len(seer.views) == 2)
        assert not seer.rehydrated(fresh)
    finally:
        again.stop()


def test_unreadable_rows_are_reported_not_fatal(tmp_path, caplog):
    path = tmp_path / "j.sqlite"
    j = Journal(path)
    j._db.execute("INSERT INTO objects VALUES ('a', 'Task', '{not json', 0)")
    j._db.execute("INSERT INTO objects VALUES ('b', 'Rocket', '{}', 0)")
    objects, problems = j.load()
    j.stop()
    assert objects == []
    assert any("object a:" in p for p in problems)
    assert any("object b: unknown type 'Rocket'" in p for p in problems)
    agent = Agent("r1", journal=path)
    agent.start()
    agent.stop()
    assert "unknown type 'Rocket'" in caplog.text


def _start(config, *args):
    return subprocess.run([sys.executable, "-m", "erni", "agent", str(config), *args], capture_output=True,
                          text=True, timeout=30, cwd=ROOT)


def _journal_with_rows(path: Path, rows: int = 300) -> None:
    agent = Agent("r1", journal=path)
    agent.start()
    with agent.transaction() as tx:
        for i in range(rows):
            tx.add(Task(verb="BotMotion", preposition="forward", params={"distance": 1 + i}, source="c"))
    assert agent.journal.flush()
    agent.stop()


def test_an_unreadable_journal_is_one_line_with_its_recovery(tmp_path):
    bad = tmp_path / "bad.sqlite"
    bad.write_bytes(b"this is not sqlite" * 100)
    config = tmp_path / "a.toml"
    config.write_text(f"[agent]\nname='r1'\njournal='{bad}'\n")
    out = _start(config)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    (line,) = out.stderr.strip().splitlines()
    assert "the journal is unreadable" in line and "--reset-journal" in line


def test_a_corrupted_page_stops_the_start_and_reset_moves_the_journal_aside(tmp_path):
    path = tmp_path / "r1.sqlite"
    _journal_with_rows(path)
    assert path.stat().st_size > 5 * 4096
    with path.open("r+b") as f:  # a page in the middle turns to noise (a bad sector, a torn copy)
        f.seek(3 * 4096)
        f.write(os.urandom(4096))
    config = tmp_path / "a.toml"
    config.write_text(f"[agent]\nname='r1'\njournal='{path}'\nlog_level='WARNING'\n")
    out = _start(config, "--check")
    assert out.returncode == 0  # the config is fine; the journal is checked when the agent starts
    proc = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(config)], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    err = proc.stderr.read()
    assert proc.wait(30) == 2 and "Traceback" not in err
    (line,) = err.strip().splitlines()
    assert "unreadable" in line and str(path) in line
    assert path.exists(), "nothing is moved unless asked"
    proc = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(config), "--reset-journal"], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stderr.readline()
        assert "moved to" in first and "bad-1" in first and "starting with an empty journal" in first
        wait_until(lambda: path.exists() and (tmp_path / "r1.sqlite.bad-1").exists())
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(10)
        proc.stderr.close()
    journal = Journal(path)
    assert journal.load() == ([], [])
    journal.stop()


def test_an_empty_journal_file_is_not_taken_for_a_new_one(tmp_path):
    path = tmp_path / "r1.sqlite"
    path.write_bytes(b"")  # a journal truncated to nothing: its tasks are gone, and that must be said
    config = tmp_path / "a.toml"
    config.write_text(f"[agent]\nname='r1'\njournal='{path}'\n")
    out = _start(config)
    assert out.returncode == 2
    (line,) = out.stderr.strip().splitlines()
    assert "empty file (0 bytes)" in line and "--reset-journal" in line
    fresh = tmp_path / "new.sqlite"  # a journal that does not exist yet is simply created
    agent = Agent("r1", journal=fresh)
    agent.start()
    agent.stop()
    assert fresh.stat().st_size > 0


FLOOD_UID = re.compile(r"(\w{6})-(\d{8})")  # tests.core.crashy:Flood's tasks: its run's prefix, a number


def test_kill_9_mid_write_never_corrupts_the_journal(tmp_path):
    path = tmp_path / "flood.sqlite"
    config = tmp_path / "flood.toml"
    config.write_text(f"""
[agent]
name = "flood"
journal = "{path}"
[[plugin]]
class = "tests.core.crashy:Flood"
""")
    before: set[str] = set()  # the Flood's uid prefixes of the rounds before: one per run

    def flooded(at_least: int) -> bool:  # this run's Flood has written its task number `at_least`
        if not path.exists() or path.stat().st_size == 0:
            return False
        db = sqlite3.connect(path, timeout=10)
        try:
            found = [FLOOD_UID.fullmatch(uid) for (uid,) in db.execute("SELECT uid FROM objects")]
        except sqlite3.OperationalError:  # the table is not made yet
            return False
        finally:
            db.close()
        return any(m is not None and m[1] not in before and int(m[2]) >= at_least for m in found)

    for round_ in range(3):
        proc = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(config)], cwd=ROOT,
                                stderr=subprocess.PIPE, text=True)
        line = proc.stderr.readline()
        while "started" not in line:
            line = proc.stderr.readline()
        wait_until(lambda round_=round_: flooded(100 * (round_ + 1)), timeout=30)  # killed later each round
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        proc.stderr.close()
        db = sqlite3.connect(path)
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        count = db.execute("SELECT count(*) FROM objects").fetchone()[0]
        db.close()
        assert count > 0
        journal = Journal(path)
        objects, problems = journal.load()
        journal.stop()
        assert problems == [] and len(objects) == count
        before.update(m[1] for o in objects if (m := FLOOD_UID.fullmatch(o.uid)))


def _reader(path: Path):
    reader = sqlite3.connect(path)

    def row(uid: str) -> str | None:
        found = reader.execute("SELECT data FROM objects WHERE uid = ?", (uid,)).fetchone()
        return found[0] if found else None

    return reader, row


def test_progress_changes_linger_for_one_write_while_new_final_and_removed_tasks_go_at_once(tmp_path):
    """A control node gets two progress results a second from every robot: each was one SQLite
    transaction and one fsync. Changes of running tasks now wait up to `linger` for more; a new
    task, a final state and a removal are written at once (and end the wait). The linger is long
    (300 s) so that "at once" and "after the linger" stay far apart on a loaded machine."""
    from erni.blackboard.blackboard import ADD, CHANGE, REMOVE

    path = tmp_path / "j.sqlite"
    journal = Journal(path, linger=300.0)
    journal.start()
    reader, row = _reader(path)
    try:
        task = Task(verb="BotMotion", preposition="randomwalk", source="control")
        t0 = time.monotonic()
        journal.listener([(ADD, task, ())])
        wait_until(lambda: row(task.uid) is not None, timeout=30)     # new: at once
        batches = journal.batches
        for i in range(20):                                           # progress: lingers
            task = task.with_result(TaskState.RUNNING, progress=i / 20)
            journal.listener([(CHANGE, task, ())])
        wait_until(journal._queue.empty, timeout=30)                 # all taken into the lingering batch
        assert '"progress":0.95' not in row(task.uid) and journal.batches == batches
        final = task.with_result(TaskState.SUCCEEDED, progress=1.0)
        journal.listener([(CHANGE, final, ())])                       # final: at once, with the changes before it
        wait_until(lambda: '"succeeded"' in row(task.uid), timeout=30)
        assert journal.batches == batches + 1                         # the 20 changes and the final: one write
        journal.listener([(CHANGE, task.with_result(TaskState.RUNNING, progress=0.5), ())])
        assert journal.flush(timeout=30)                               # a flush does not wait for the linger
        journal.listener([(REMOVE, final, ())])
        wait_until(lambda: row(task.uid) is None, timeout=30)
        assert time.monotonic() - t0 < 120                             # never waited out the 300 s linger
    finally:
        reader.close()
        journal.stop()


def test_progress_changes_during_a_linger_do_not_wake_the_journal_thread(tmp_path):
    """A robot's running tasks change a few times a second: while a batch lingers, each such commit
    joins it without waking the journal thread (its voluntary context switches, from /proc, stay
    put while it sleeps through twenty of them); the final state still ends the linger at once."""
    from erni.blackboard.blackboard import ADD, CHANGE

    path = tmp_path / "j.sqlite"
    journal = Journal(path, linger=300.0)
    journal.start()
    assert journal._thread is not None and journal._thread.native_id is not None
    task_dir = f"/proc/self/task/{journal._thread.native_id}"
    reader, row = _reader(path)

    def asleep() -> bool:
        with open(f"{task_dir}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "S" and journal._queue.empty()

    def switches() -> int:
        with open(f"{task_dir}/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))

    try:
        task = Task(verb="BotMotion", preposition="randomwalk", source="robot1")
        journal.listener([(ADD, task, ())])
        wait_until(lambda: row(task.uid) is not None, timeout=30)
        task = task.with_result(TaskState.RUNNING, progress=0.0)
        journal.listener([(CHANGE, task, ())])  # the linger begins
        wait_until(asleep, timeout=30)
        before = switches()
        for i in range(1, 21):
            task = task.with_result(TaskState.RUNNING, progress=i / 40)
            journal.listener([(CHANGE, task, ())])
            wait_until(asleep, timeout=30)  # had it been woken, it took the commit and sleeps again
        assert switches() - before < 5
        journal.listener([(CHANGE, task.with_result(TaskState.SUCCEEDED, progress=1.0), ())])
        wait_until(lambda: '"succeeded"' in row(task.uid), timeout=30)
    finally:
        reader.close()
        journal.stop()


def test_lingering_progress_is_written_in_one_batch_when_the_linger_ends(tmp_path):
    from erni.blackboard.blackboard import ADD, CHANGE

    path = tmp_path / "j.sqlite"
    journal = Journal(path, linger=2.0)
    journal.start()
    reader, row = _reader(path)
    try:
        task = Task(verb="BotMotion", preposition="randomwalk", source="control")
        journal.listener([(ADD, task, ())])
        wait_until(lambda: row(task.uid) is not None, timeout=10)
        assert journal.flush(timeout=10)  # the write that put the row there is counted (after its commit)
        batches = journal.batches
        for i in range(20):
            task = task.with_result(TaskState.RUNNING, progress=i / 20)
            journal.listener([(CHANGE, task, ())])
        wait_until(lambda: '"progress":0.95' in row(task.uid), timeout=10)
        assert journal.batches == batches + 1
    finally:
        reader.close()
        journal.stop()


def test_a_finished_task_from_the_journal_leaves_retention_after_it_ended_not_after_the_restart(tmp_path):
    """A task that ended 500 s before a restart, with a retention of 600 s, goes 100 s after the
    restart (the journal's row says when it ended: its last write), not 600 s after."""
    import sqlite3
    import time

    from erni.blackboard import Agent, Task, TaskState
    from erni.blackboard.tasks import AllocationResult
    from erni.testing import ManualClock

    path = tmp_path / "journal.db"
    first = Agent("robot1", journal=path, retention=600.0).start()
    ended = Task(verb="BotMotion", preposition="stop", source="robot1",
                 result=AllocationResult(state=TaskState.SUCCEEDED))
    running = Task(verb="BotMotion", preposition="forward", params={"distance": 1.0}, source="robot1")
    with first.transaction() as tx:
        tx.add(ended)
        tx.add(running)
    assert first.journal.flush()
    first.stop()
    db = sqlite3.connect(path)  # as if the agent had ended the task 500 s ago, then stopped
    db.execute("UPDATE objects SET updated = ? WHERE uid = ?", (time.time() - 500.0, ended.uid))
    db.commit()
    db.close()

    clock = ManualClock()
    second = Agent("robot1", journal=path, retention=600.0, clock=clock).start()
    try:
        assert second.blackboard.get(ended.uid) is not None
        clock.advance(90.0)
        assert second.retention.sweep() == 0
        clock.advance(20.0)  # 610 s after it ended
        assert second.retention.sweep() == 1
        assert second.blackboard.get(ended.uid) is None and second.blackboard.get(running.uid) is not None
    finally:
        second.stop()


def _crashed_copy(journal, into):
    """The journal's files as a kill -9 leaves them (SQLite's -shm index is not copied: gone)."""
    import shutil

    into.mkdir()
    for suffix in ("", "-wal", "-seal"):
        src = journal.path.with_name(journal.path.name + suffix)
        if src.exists():
            shutil.copyfile(src, into / (journal.path.name + suffix))
    return into / journal.path.name


def _flip_wal_frame(path, frame):
    """Flip one byte in the page of committed WAL frame `frame` (its checksum no longer matches)."""
    wal = path.with_name(path.name + "-wal")
    data = bytearray(wal.read_bytes())
    page = int.from_bytes(data[8:12], "big")
    at = 32 + frame * (24 + page) + 24 + page // 2
    assert at < len(data), f"the WAL has fewer than {frame + 1} frames"
    data[at] ^= 0xFF
    wal.write_bytes(bytes(data))


@pytest.mark.parametrize("frame", [1, 40], ids=["early frame", "later frame"])
def test_a_damaged_write_ahead_log_is_never_silent_loss(tmp_path, frame):
    """80 tasks, each in its own journal write; a byte flipped in a committed WAL frame with the
    -shm index gone: SQLite's recovery stops at that frame and the journal looks whole but holds
    fewer objects. The agent refuses to start on it, with one line naming the file and what is
    missing; `--reset-journal` moves it aside and starts empty, as for any unreadable journal."""
    from erni.blackboard import Agent, Task
    from erni.blackboard.journal import Journal, JournalError

    first = Agent("robot1", journal=tmp_path / "journal.db", retention=None).start()
    try:
        for i in range(80):
            with first.transaction() as tx:
                tx.add(Task(uid=f"t{i:02d}", verb="BotMotion", preposition="stop", source="robot1"))
            assert first.journal.flush()
        copy = _crashed_copy(first.journal, tmp_path / "crashed")
    finally:
        first.stop()
    _flip_wal_frame(copy, frame)
    with pytest.raises(JournalError) as err:
        Agent("robot1", journal=copy, retention=None).start()
    line = str(err.value)
    assert "\n" not in line and str(copy) in line and "lost committed writes" in line
    assert "80 object(s)" not in line.split("but")[0] and "it held 80" in line and "--reset-journal" in line
    reset = Agent("robot1", journal=copy, retention=None, reset_journal=True).start()
    try:
        assert not reset.blackboard.query(Task)
        assert copy.with_name("journal.db.bad-1-seal").exists()
    finally:
        reset.stop()
    assert Journal(copy).load()[0] == []  # the new journal, with a seal of its own, opens clean


def test_a_journal_whose_seal_is_a_write_behind_opens(tmp_path):
    """A crash between a write's commit and its seal leaves the seal one write behind: that is no
    loss (what the seal says is on disk), and the journal opens."""
    from erni.blackboard import Agent, Task

    path = tmp_path / "journal.db"
    agent = Agent("robot1", journal=path, retention=None).start()
    try:
        with agent.transaction() as tx:
            tx.add(Task(uid="t0", verb="BotMotion", preposition="stop", source="robot1"))
        assert agent.journal.flush()
        seal = path.with_name("journal.db-seal").read_bytes()
        with agent.transaction() as tx:
            tx.add(Task(uid="t1", verb="BotMotion", preposition="stop", source="robot1"))
        assert agent.journal.flush()
    finally:
        agent.stop()
    path.with_name("journal.db-seal").write_bytes(seal)
    again = Agent("robot1", journal=path, retention=None).start()
    try:
        assert {t.uid for t in again.blackboard.query(Task)} == {"t0", "t1"}
    finally:
        again.stop()
