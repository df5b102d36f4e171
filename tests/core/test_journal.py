"""The SQLite journal: durable objects survive a restart and a kill -9; non-durable ones do not."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

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


def test_a_file_that_is_not_a_journal_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.sqlite"
    bad.write_bytes(b"this is not sqlite" * 100)
    config = tmp_path / "a.toml"
    config.write_text(f"[agent]\nname='r1'\njournal='{bad}'\n")
    out = subprocess.run([sys.executable, "-m", "erni", "agent", str(config)], capture_output=True,
                         text=True, timeout=30, cwd=ROOT)
    assert out.returncode == 2
    assert "cannot open the journal" in out.stderr and "Traceback" not in out.stderr


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
    for round_ in range(3):
        proc = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(config)], cwd=ROOT,
                                stderr=subprocess.PIPE, text=True)
        line = proc.stderr.readline()
        while "started" not in line:
            line = proc.stderr.readline()
        wait_until(lambda: path.exists() and path.stat().st_size > 0, timeout=10)
        time.sleep(0.3 + 0.2 * round_)
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
