"""Text that a peer sends is printed as text: `erni task --wait` and `erni watch` against a real
agent (its own identity, real sockets) whose performer answers with terminal escapes and a newline
that forges a line of its own, and whose network information is named with them.

Each command's output must hold no character that acts on a terminal (ESC, BEL, CR, DEL, C1, ...),
and one line per event: the forged `succeeded 100% arrived` never starts a line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import unicodedata
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from erni.blackboard import Agent, NetInfo, Plugin, Task, TaskState
from tests.transport.helpers import free_port, identity, make_agent

ROOT = Path(__file__).resolve().parents[2]
ESCAPES = "\x1b]0;owned\x07\x1b[2J\x1b[H\r\x7f\x9b31m\u202e"
FORGED = "robot9 t-forged BotMotion forward succeeded 100% arrived"
HOSTILE = f"{ESCAPES}working\n{FORGED}"


class HostilePerformer(Plugin):
    """Answers every BotMotion task with a running and a final result whose messages are hostile,
    and publishes a NetInfo whose kind and message are, changed ten times a second (a live stream)."""

    def setup(self) -> None:
        self.tasks = self.subscribe(Task, where=lambda t: t.verb == "BotMotion" and t.destination == self.agent_name)
        self.info = NetInfo(node=self.agent_name, kind=f"topology{ESCAPES}", message=HOSTILE)
        self.beats = 0
        with self.transaction():
            self.add(self.info)
        self.wake_every(0.1)

    def execute(self) -> None:
        self.beats += 1
        self.info = self.info.evolve(stamp=float(self.beats))
        self.change(self.info)
        for task in self.tasks.added:
            self.change(task.with_result(TaskState.RUNNING, progress=0.5, message=HOSTILE,
                                         values={f"left{ESCAPES}": f"1\n{FORGED}"}))
        for task in self.tasks.changed:
            if task.state == TaskState.RUNNING:
                self.change(task.with_result(TaskState.SUCCEEDED, progress=1.0, message=HOSTILE))


@pytest.fixture(scope="module")
def performer() -> Iterator[dict[str, Any]]:
    agent: Agent = make_agent("robot1", free_port(), echo=False, start=False, listen="127.0.0.1:0")
    agent.add_plugin(HostilePerformer, name="hostile")
    agent.start()
    host, port = agent.plugin("transport").address  # type: ignore[attr-defined]
    env = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli"), "PYTHONUNBUFFERED": "1"}
    try:
        yield {"via": f"{host}:{port}", "env": env, "agent": agent}
    finally:
        agent.stop()


def cli(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "erni", *args], capture_output=True, text=True, timeout=60,
                          cwd=ROOT, env=env)


def acting(text: str) -> list[str]:
    """The characters of printed output that act instead of showing (a newline between lines aside)."""
    return [repr(ch) for ch in text if ch != "\n" and unicodedata.category(ch) in ("Cc", "Cf", "Zl", "Zp")]


def test_task_wait_prints_a_performers_escapes_and_newlines_escaped_one_line_per_update(performer):
    out = cli(performer["env"], "task", "--via", performer["via"], "robot1", "BotMotion", "forward",
              "distance=1", "--wait")
    assert out.returncode == 0, out.stderr
    assert acting(out.stdout) == [] and acting(out.stderr) == []
    lines = out.stdout.splitlines()
    assert 1 <= len(lines) <= 2, lines  # (running,) succeeded: one line each, however many newlines they hold
    assert not any(line.startswith(FORGED) for line in lines)
    assert all("\\x1b]0;owned\\x07\\x1b[2J" in line and "\\n" + FORGED in line for line in lines)
    assert "succeeded" in lines[-1]


def test_task_json_lines_stay_json_with_the_text_intact(performer):
    out = cli(performer["env"], "task", "--via", performer["via"], "robot1", "BotMotion", "forward",
              "distance=1", "--wait", "--json")
    assert out.returncode == 0, out.stderr
    assert acting(out.stdout) == []
    last = json.loads(out.stdout.splitlines()[-1])
    assert last["message"] == HOSTILE  # escaped by JSON, read back whole


def test_watch_prints_peers_text_escaped(performer):
    done = cli(performer["env"], "task", "--via", performer["via"], "robot1", "BotMotion", "forward", "distance=1",
               "--wait")
    assert done.returncode == 0
    out = cli(performer["env"], "watch", "--via", performer["via"], "--count", "3", "--seconds", "20")
    assert out.returncode == 0, out.stderr
    assert acting(out.stdout) == [], out.stdout
    assert "topology\\x1b]0;owned\\x07" in out.stdout


def test_watch_into_a_pipe_closed_early_ends_quietly(performer):
    """`erni watch | head -1`: the reader leaves after one line; watch ends without a traceback."""
    command = (f"{sys.executable} -m erni watch --via {performer['via']} --seconds 20 | head -1; "
               "echo \"status ${PIPESTATUS[0]}\" >&2")
    out = subprocess.run(["bash", "-c", command], capture_output=True, text=True, timeout=60, cwd=ROOT,
                         env=performer["env"])
    assert "Traceback" not in out.stderr and "BrokenPipeError" not in out.stderr, out.stderr
    assert len(out.stdout.splitlines()) == 1, out.stdout
    assert out.stderr.strip().splitlines()[-1] == "status 141", out.stderr  # 128 + SIGPIPE, as `yes | head -1`
