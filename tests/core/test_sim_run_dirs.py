"""`erni sim`'s run directories: one per run in the temporary directory, the newest finished ones kept."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from erni.commands.sim import KEEP_RUNS, OWNER_FILE, UNMARKED_AGE, prune_run_dirs


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _run_dir(tmp: Path, name: str, age: float, pid: int | None) -> Path:
    run = tmp / f"erni-sim-{name}"
    (run / "agents").mkdir(parents=True)
    (run / "logs").mkdir()
    if pid is not None:
        (run / OWNER_FILE).write_text(f"{pid}\n")
    when = time.time() - age
    os.utime(run, (when, when))
    return run


def test_a_run_removes_finished_run_directories_but_the_newest_three(tmp_path: Path) -> None:
    dead = _dead_pid()
    finished = [_run_dir(tmp_path, f"old{i}", age=60.0 * (i + 1), pid=dead) for i in range(5)]
    running = _run_dir(tmp_path, "running", age=3600.0, pid=os.getpid())
    unmarked_recent = _run_dir(tmp_path, "unmarked-recent", age=60.0, pid=None)
    unmarked_old = _run_dir(tmp_path, "unmarked-old", age=UNMARKED_AGE + 60.0, pid=None)
    not_a_run = tmp_path / "erni-sim-notes"
    not_a_run.mkdir()
    other = tmp_path / "something-else"
    (other / "logs").mkdir(parents=True)

    removed = prune_run_dirs(tmp_path)

    assert KEEP_RUNS == 3
    assert sorted(removed) == sorted(finished[3:] + [unmarked_old])
    for kept in finished[:3] + [running, unmarked_recent, not_a_run, other]:
        assert kept.is_dir(), kept
    assert prune_run_dirs(tmp_path) == [], "a second run finds nothing more to remove"


def test_the_rule_is_documented_where_users_read_it() -> None:
    root = Path(__file__).resolve().parents[2]
    page = " ".join((root / "docs" / "explanation" / "simulator.md").read_text(encoding="utf-8").split())
    assert "removes the finished runs' directories but the newest three" in page
    help_text = subprocess.run([sys.executable, "-m", "erni", "sim", "--help"], capture_output=True, text=True,
                               timeout=60).stdout
    assert f"newest {KEEP_RUNS} of finished runs are kept" in " ".join(help_text.split())
