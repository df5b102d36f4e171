"""`erni task` without --wait waits for the agent's answer: exit 0 once it took the task, 1 on a refusal.

What "at once" means here is told apart from the command's waits by making those waits long, not
by timing the command: it runs with its answer wait (and, where a test says so, its discovery
wait) raised to `PATIENT` s, so a command that waited one out would take a minute, while one
that answers at once ends well within `PROGRESS` s even with Python's start-up on a loaded machine.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel

from erni.blackboard import Plugin, Task, TaskState
from erni.blackboard.testing import wait_until
from tests.transport.helpers import free_port, identity, make_agent

ROOT = Path(__file__).resolve().parents[2]
PATIENT = 60.0   # the command's answer wait (5 s) in these runs, and its discovery wait (4 s) where asked
PROGRESS = 30.0  # a generous bound on a whole run of the command that waits out none of its waits

# `python -m erni`, with the command's waits set from its first two arguments
COMMAND = """
import sys
import erni.commands.task as task
task.ANSWER_WAIT, task.DISCOVERY_WAIT = float(sys.argv.pop(1)), float(sys.argv.pop(1))
from erni.cli import main
raise SystemExit(main())
"""


class DockedSettings(BaseModel):
    """No settings."""


class Docked(Plugin[DockedSettings]):
    """A robot on its dock: refuses to turn, starts anything else."""

    def setup(self) -> None:
        self.tasks = self.subscribe(Task, where=lambda t: t.verb == "BotMotion" and t.destination == self.agent_name)

    def execute(self) -> None:
        for task in self.tasks.added:
            if task.preposition == "turn":
                self.change(task.with_result(TaskState.FAILED, message="refused: cannot turn\non the dock"))
            else:
                self.change(task.with_result(TaskState.RUNNING, message="started"))


@pytest.fixture(scope="module")
def via() -> Iterator[str]:
    disc, port = free_port(), free_port()
    control = make_agent("control", disc, echo=False, role="control", listen=f"127.0.0.1:{port}")
    robot = make_agent("robot1", disc, echo=False, start=False)
    robot.add_plugin(Docked, name="motion")
    robot.start()
    try:
        wait_until(lambda: any(p.name == "robot1" and p.up for p in control.blackboard.query(
            lambda o: type(o).__name__ == "Peer")), timeout=10)
        yield f"127.0.0.1:{port}"
    finally:
        robot.stop()
        control.stop()


def task(via: str, *args: str, discovery_wait: float = PATIENT) -> tuple[subprocess.CompletedProcess[str], float]:
    """Run `erni task --via VIA ARGS` with its answer wait raised to PATIENT s and its discovery
    wait to `discovery_wait` s; return what it did and the seconds it took."""
    env = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli")}
    start = time.monotonic()
    out = subprocess.run([sys.executable, "-c", COMMAND, str(PATIENT), str(discovery_wait), "task", "--via", via,
                          *args], capture_output=True, text=True, timeout=PATIENT + 30, cwd=ROOT, env=env)
    return out, time.monotonic() - start


def test_a_task_the_robot_refuses_exits_1_with_the_reason_on_one_line(via: Any) -> None:
    out, seconds = task(via, "robot1", "BotMotion", "turn", "angle=90")
    assert out.returncode == 1 and out.stdout == ""
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("erni task: robot1: task ")
    assert lines[0].endswith(" failed: refused: cannot turn on the dock")
    assert seconds < PROGRESS  # the answer, not the end of the (60 s) wait


def test_a_task_the_robot_takes_exits_0_once_it_runs(via: Any) -> None:
    out, seconds = task(via, "robot1", "BotMotion", "forward", "distance=1")
    assert out.returncode == 0, out.stderr
    assert out.stdout.rstrip().endswith("sent to robot1: BotMotion forward distance=1.0 speed=0.3 -> robot1 (running)")
    assert seconds < PROGRESS  # once it runs, not at the end of the (60 s) wait that would say "running" too


def test_an_agent_the_team_never_heard_of_fails_at_once(via: Any) -> None:
    out, seconds = task(via, "robot9", "BotMotion", "stop")
    assert out.returncode == 1
    assert out.stderr == "erni task: no agent robot9 in the team: control knows robot1 (`erni peers` lists them)\n"
    assert seconds < PROGRESS  # at the first directory that lists others, not after the (60 s) discovery wait


def test_an_agent_the_team_never_heard_of_fails_at_once_with_wait_too(via: Any) -> None:
    out, seconds = task(via, "robot9", "BotMotion", "goto", "x=1", "y=2", "--wait")
    assert out.returncode == 1 and out.stdout == ""
    assert out.stderr == "erni task: no agent robot9 in the team: control knows robot1 (`erni peers` lists them)\n"
    assert seconds < PROGRESS  # nor the (60 s) discovery wait, the control node's task_ttl or the link deadline


@pytest.mark.parametrize("wait", [False, True])
def test_through_an_agent_that_heard_of_nobody_yet_the_name_is_given_a_discovery_wait(wait: bool) -> None:
    """A control node just started knows nobody: the name is asked for again for DISCOVERY_WAIT s,
    and then fails with the reason (a robot that shows up in time is tasked)."""
    from erni.commands.task import DISCOVERY_WAIT

    disc, port = free_port(), free_port()
    control = make_agent("control", disc, echo=False, role="control", listen=f"127.0.0.1:{port}")
    try:
        out, seconds = task(f"127.0.0.1:{port}", "robot9", "BotMotion", "stop", *(["--wait"] if wait else []),
                            discovery_wait=DISCOVERY_WAIT)
    finally:
        control.stop()
    assert out.returncode == 1
    said = re.fullmatch(r"erni task: no agent robot9 in the team: control has heard of no other agent within "
                        r"(\d+) s \(is robot9 running, with the same discovery port\?\)\n", out.stderr)
    assert said, out.stderr
    # the command's own count of the wait (the last answer may come late on a loaded machine), and
    # the run: the discovery wait was waited out, and not the (60 s) answer wait
    assert int(said[1]) >= DISCOVERY_WAIT and seconds >= DISCOVERY_WAIT
    assert seconds < PROGRESS


def test_a_robot_that_starts_with_the_command_is_tasked() -> None:
    """`erni agent control.toml & erni agent robot.toml & erni task ...` at once: the robot is found
    while the control node's directory is still empty. (The discovery wait is raised to PATIENT s
    here: the robot's start must fall inside it, which a loaded machine could make 4 s miss.)"""
    disc, port = free_port(), free_port()
    control = make_agent("control", disc, echo=False, role="control", listen=f"127.0.0.1:{port}")
    env = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli")}
    counters = control.plugin("transport").endpoint.counters
    before = counters.get("received", 0)
    proc = subprocess.Popen([sys.executable, "-c", COMMAND, str(PATIENT), str(PATIENT), "task", "--via",
                             f"127.0.0.1:{port}", "robot1", "BotMotion", "forward", "distance=1", "--wait"],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    robot = None
    try:
        # the command has reached the control node (its directory still empty) before the robot starts
        wait_until(lambda: counters.get("received", 0) > before or proc.poll() is not None, timeout=PROGRESS)
        assert proc.poll() is None
        robot = make_agent("robot1", disc)
        out, err = proc.communicate(timeout=PATIENT + 30)
    finally:
        proc.kill()
        if robot is not None:
            robot.stop()
        control.stop()
    assert proc.returncode == 0, err
    assert "succeeded" in out
