"""The `erni` command as a user runs it: `erni agent`, `erni tasks`, exit codes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from erni.blackboard.tasks import PREPOSITIONS

ROOT = Path(__file__).resolve().parents[2]


def erni(*args: str, **kw):
    return subprocess.run([sys.executable, "-m", "erni", *args], capture_output=True, text=True,
                          timeout=60, cwd=ROOT, **kw)


def test_tasks_prints_the_language():
    out = erni("tasks")
    assert out.returncode == 0
    assert out.stdout.count("\n| ") == len(PREPOSITIONS)  # one row each after the header


def test_no_command_prints_help_and_exits_2():
    out = erni()
    assert out.returncode == 2 and "COMMAND" in out.stderr


def test_bad_config_is_one_line_without_traceback(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[agent]\nname = 'r1'\nspeed = 3\n")
    out = erni("agent", str(path))
    assert out.returncode == 2
    assert out.stderr.strip() == f"{path}: agent: unknown key 'speed'"
    assert "Traceback" not in out.stderr


def test_check_validates_without_running():
    out = erni("agent", "examples/robot.toml", "--check")
    assert out.returncode == 0 and "ok (agent robot1" in out.stdout


def test_agent_runs_until_sigterm_and_stops_cleanly():
    proc = subprocess.Popen([sys.executable, "-m", "erni", "agent", "examples/robot.toml"],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        lines = [proc.stderr.readline() for _ in range(3)]
        assert any("erni.robot1: agent robot1 started with 2 plugin(s)" in ln for ln in lines), lines
        assert any("WITHOUT authentication" in ln for ln in lines), "insecure mode is warned about"
        time.sleep(0.2)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rest = proc.stderr.read()
        assert proc.wait(timeout=10) == 0
        assert time.monotonic() - t0 < 3.0
        assert "agent robot1 stopped" in rest and "Traceback" not in rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
