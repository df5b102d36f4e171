"""`erni console`: typed commands in the speech grammar reach a running team through its control
node, with the same feedback, and the results of the tasks it sent are printed."""

from __future__ import annotations

import json
import math
import os
import pty
import re
import select
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.ui.team import KEY, Team, start_team

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def team() -> Iterator[Team]:
    team = start_team(2)
    yield team
    team.stop()


def console(team: Team, lines: str, *args: str, key: str = KEY) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ERNI_TEAM_KEY": key}
    return subprocess.run([sys.executable, "-m", "erni", "console", "--via", team.via, "--verb", "BotMotion",
                           "--timeout", "15", *args], input=lines, text=True, capture_output=True, env=env,
                          cwd=ROOT, timeout=60)


def test_typed_commands_task_the_team_and_print_feedback_and_results(team):
    p0 = team.pose("robot1")
    out = console(team, "robot 1 go forward 2 feet\nrobot 9 turn left\n# a comment\nturn left 90 degrees\nyes\n")
    lines = out.stdout.splitlines()
    assert "Roger: robot 1, go forward 0.61 metres" in lines and "I don't know robot 9; I know robots 1 and 2" in lines
    # robot 1 was named before the refused line: the turn that names no robot is asked first
    assert ("Robot 1: turn left 90 degrees? No robot named; robot 1 was named 2 commands ago \u2014 "
            "type yes to confirm, or name the robots") in lines
    assert "Roger: robot 1, turn left 90 degrees" in lines  # on "yes" the turn went to the last target
    assert "robot1: turn succeeded" in out.stdout
    assert out.returncode == 1  # a piped command was refused
    assert "robot1: forward succeeded" not in out.stdout  # superseded by the turn: cancelled on the robot
    assert "robot1: forward cancelled \u2014 superseded by turn" in out.stdout  # and its end is printed
    p1 = team.pose("robot1")
    assert math.hypot(p1.x - p0.x, p1.y - p0.y) < 0.6096 - 0.05
    assert math.degrees(abs(math.remainder(p1.theta - p0.theta, 2 * math.pi))) == pytest.approx(90, abs=4)


def test_all_accepted_and_succeeded_exits_zero(team):
    p0 = team.pose("robot2")
    out = console(team, "attention\nrobot 2 go forward 0.5 metres\n")
    assert out.returncode == 0, out.stdout + out.stderr
    # the task's updates (timestamped lines) stream in beside the replies and may come before "Roger"
    replies = [ln for ln in out.stdout.splitlines() if not re.match(r"\d\d:\d\d:\d\d\.\d+ ", ln)]
    assert replies[:4] == ["> attention", "Listening", "> robot 2 go forward 0.5 metres",
                           "Roger: robot 2, go forward 0.5 metres"]
    assert "robot2: forward succeeded" in out.stdout
    p1 = team.pose("robot2")
    assert math.hypot(p1.x - p0.x, p1.y - p0.y) == pytest.approx(0.5, abs=0.08)


def test_json_lines(team):
    out = console(team, "robot 1 turn left 30 degrees\nrobot 7 stop\n", "--json")
    rows = [json.loads(line) for line in out.stdout.splitlines()]
    replies = [r for r in rows if "heard" in r]  # task updates may interleave with the replies
    assert replies[0]["say"] == "Roger: robot 1, turn left 30 degrees" and replies[0]["targets"] == ["robot1"]
    assert len(replies[0]["tasks"]) == 1
    assert replies[1] == {"heard": "robot 7 stop", "say": "I don't know robot 7", "accepted": False, "targets": [],
                          "tasks": []}  # a stop to no known robot sends nothing
    assert len(replies) == 2 and all("uid" in r for r in rows if "heard" not in r)
    final = [r for r in rows if r.get("uid") == replies[0]["tasks"][0] and r["state"] == "succeeded"]
    assert final and final[0]["agent"] == "robot1"


def test_bad_arguments_exit_two_with_one_line(team):
    out = console(team, "", "--robot-names", "robot")
    assert out.returncode == 2 and out.stderr.strip().startswith("erni console: robot naming 'robot': expected")
    out = subprocess.run([sys.executable, "-m", "erni", "console", "--via", "localhost"], input="", text=True,
                         capture_output=True, cwd=ROOT, timeout=60)
    assert out.returncode == 2 and "erni console: --via 'localhost': expected HOST:PORT" in out.stderr


def test_after_sleep_everyone_stop_stops_every_moving_robot_and_every_task_ends_with_a_line(team):
    out = console(team, "everyone random walk\ngo to sleep\nrobot 1 turn left\neveryone stop\nrobot 2 status\n"
                  "how many robots\n")
    lines = out.stdout.splitlines()
    assert "Roger: everyone, random walk" in lines and "Standing by" in lines
    assert "(standing by: say 'attention')" in lines  # the turn was ignored while standing by ...
    assert "Roger: everyone, stop" in lines  # ... the stop was not
    for robot in ("robot1", "robot2"):
        assert any(f"{robot}: randomwalk cancelled" in line for line in lines), out.stdout
        pose = team.pose(robot)
        assert pose is not None and abs(pose.v) < 0.05
    assert not any("turn" in line and "robot1:" in line for line in lines)


def test_a_command_naming_no_robot_long_after_one_was_named_is_asked_and_not_sent(team):
    out = console(team, "robot 2 turn left 10 degrees\nhow many robots\nclear\nrobot 1 go forward 100 metres\n"
                  "no\n", "--json")
    replies = [json.loads(line) for line in out.stdout.splitlines()]
    replies = [r for r in replies if "heard" in r]
    assert [r["heard"] for r in replies] == ["robot 2 turn left 10 degrees", "how many robots", "clear",
                                             "robot 1 go forward 100 metres", "no"]
    clear, far, no = replies[2:]
    assert clear["say"].startswith("Robot 2: clear your behaviours? No robot named") and clear["tasks"] == []
    assert far["say"].endswith("more than 10 metres; type yes to confirm") and far["tasks"] == []
    assert no["say"] == "Not sent: robot 1, go forward 100 metres" and no["tasks"] == []
    assert out.returncode == 0, out.stdout + out.stderr


def test_status_questions_are_answered_from_the_streamed_poses_and_the_directory(team):
    out = console(team, "robot 2 status\nwhere is robot 1\nhow many robots\n")
    lines = out.stdout.splitlines()
    p1 = team.pose("robot1")
    assert p1 is not None
    status = next(line for line in lines if line.startswith("Robot 2: "))
    assert "at x " in status and "battery " in status and status.endswith("link up")
    assert f"Robot 1 is at x {p1.x:.1f}, y {p1.y:.1f}" in out.stdout
    assert "2 robots, 2 up" in lines


ESCAPES = re.compile(r"\x1b(\[[0-?]*[ -/]*[@-~]|\][^\x07]*\x07|[()][0-9A-Za-z]|[=>78])")


class Terminal:
    """`erni console` on a pseudo-terminal, as a person types into it: what it draws is read as it comes."""

    def __init__(self, team: Team, tmp: Path) -> None:
        self.fd, child = pty.openpty()
        env = {**os.environ, "ERNI_TEAM_KEY": KEY, "TERM": "xterm", "COLUMNS": "120", "LINES": "40",
               "PROMPT_TOOLKIT_NO_CPR": "1"}  # a terminal that does not answer where its cursor is
        self.proc = subprocess.Popen([sys.executable, "-m", "erni", "console", "--via", team.via, "--verb",
                                      "BotMotion", "--history-file", str(tmp / "history")],
                                     stdin=child, stdout=child, stderr=child, env=env, cwd=ROOT,
                                     start_new_session=True)
        os.close(child)
        self.raw = b""

    def read(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            ready, _, _ = select.select([self.fd], [], [], left)
            if ready:
                try:
                    self.raw += os.read(self.fd, 65536)
                except OSError:  # the console exited
                    return

    def wait_for(self, text: str, seconds: float) -> None:
        end = time.monotonic() + seconds
        while text not in self.text and time.monotonic() < end:
            self.read(0.1)
        assert text in self.text, f"no {text!r} within {seconds} s:\n{self.text}"

    @property
    def text(self) -> str:
        """What was drawn, without the terminal's control sequences."""
        return ESCAPES.sub("", self.raw.decode(errors="replace")).replace("\r", "")

    def type(self, keys: str) -> None:
        os.write(self.fd, keys.encode())

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)
        os.close(self.fd)


def test_an_event_line_arriving_while_a_line_is_typed_leaves_the_typed_line_intact(team, tmp_path):
    term = Terminal(team, tmp_path)
    try:
        term.wait_for("erni>", 30)
        term.type("robot 1 go forward 0.4 metres\r")
        term.wait_for("Roger: robot 1, go forward 0.4 metres", 15)
        term.type("robot 2 tu")  # half a line, not sent
        term.wait_for("robot1: forward succeeded", 20)  # an event line comes while it is typed
        term.read(1.0)
        after = term.text.rsplit("robot1: forward succeeded", 1)[1]
        # below the event line the prompt is drawn again with the half line, and nothing follows it
        assert after.splitlines()[-1].strip() == "erni> robot 2 tu", term.text
        term.type("rn left 10 degrees\r")  # the line goes on where it was left, and is carried out
        term.wait_for("Roger: robot 2, turn left 10 degrees", 15)
        term.type("quit\r")
        assert term.proc.wait(15) == 0
        assert (tmp_path / "history").read_text().splitlines() == [
            "robot 1 go forward 0.4 metres", "robot 2 turn left 10 degrees", "quit"]  # one line per command
    finally:
        term.close()


def test_the_history_file_reads_one_command_per_line_newest_first(tmp_path):
    from erni.commands.console import HISTORY_LENGTH, _history

    path = tmp_path / "history"
    path.write_text("robot 1 go to 2 3\n\neveryone stop\n")  # as readline wrote it
    history = _history(str(path))
    assert list(history.load_history_strings()) == ["everyone stop", "robot 1 go to 2 3"]
    history.store_string("how many robots")
    assert path.read_text().splitlines()[-1] == "how many robots"
    path.write_text("".join(f"line {i}\n" for i in range(2 * HISTORY_LENGTH + 1)))
    kept = list(_history(str(path)).load_history_strings())
    assert len(kept) == HISTORY_LENGTH and kept[0] == f"line {2 * HISTORY_LENGTH}"
    assert len(path.read_text().splitlines()) == HISTORY_LENGTH  # the file is trimmed too
