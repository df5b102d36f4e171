"""The file a running `erni sim` names its team in for the other commands: this user's only, and a run
that no longer runs is not found (its file goes)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from erni.commands import _team_file
from erni.commands._team_file import announce, running_sim, runtime_dir, started, withdraw


def test_a_running_team_is_found_and_withdrawn(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    path = announce(("127.0.1.250", 47100), 47001, tmp_path / "cli.pem", tmp_path / "run")
    assert path is not None and path.parent == runtime_dir() == tmp_path / "erni"
    assert path.parent.stat().st_mode & 0o777 == 0o700 and path.stat().st_mode & 0o777 == 0o600
    team = running_sim()
    assert team is not None and team["via"] == "127.0.1.250:47100" and team["pid"] == os.getpid()
    withdraw(path)
    assert running_sim() is None and not path.exists()


def test_the_file_of_a_run_that_no_longer_runs_is_not_found_and_removed(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    folder = tmp_path / "erni"
    folder.mkdir(mode=0o700)
    stale = folder / f"sim-{dead.stdout.strip()}.json"
    stale.write_text(json.dumps({"pid": int(dead.stdout), "via": "127.0.1.250:1", "identity": "x"}))
    stale.chmod(0o600)
    assert running_sim() is None and not stale.exists()


def test_a_file_or_directory_others_may_write_is_not_trusted(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    path = announce(("127.0.1.250", 47100), 47001, "cli.pem", "run")
    assert path is not None
    path.chmod(0o644)
    assert running_sim() is None
    path.chmod(0o600)
    assert running_sim() is not None
    path.parent.chmod(0o777)
    assert running_sim() is None
    assert announce(("127.0.1.250", 47100), 47001, "cli.pem", "run") is None  # nor written to
    path.parent.chmod(0o700)


def test_without_xdg_runtime_dir_it_is_in_the_temporary_directory(monkeypatch):
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    assert runtime_dir().name == f"erni-{os.getuid()}"
    assert _team_file.PREFIX == "sim-"


def test_a_pid_another_program_took_is_not_a_running_sim(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    other = subprocess.Popen(["sleep", "30"])  # runs, but is no erni
    try:
        folder = tmp_path / "erni"
        folder.mkdir(mode=0o700)
        taken = folder / f"sim-{other.pid}.json"
        mine = json.loads(announce(("127.0.1.250", 1), 1, "x", "run").read_text())  # type: ignore[union-attr]
        assert mine["started"] and mine["started"] != started(other.pid)
        taken.write_text(json.dumps({**mine, "pid": other.pid}))  # the PID of a run, taken by another process
        taken.chmod(0o600)
        withdraw(folder / f"sim-{os.getpid()}.json")
        assert running_sim() is None and not taken.exists()
    finally:
        other.kill()
        other.wait()
