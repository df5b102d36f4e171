"""`erni record` a live team, `erni replay` it: `erni watch` sees the same objects in the same order."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from erni.blackboard import Pose, Task, TaskState
from erni.blackboard.testing import wait_until
from erni.replay import LogError, read_log
from erni.transport import Peer
from tests.transport.helpers import free_port, identity, make_agent, two_tasks_recorded

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "ERNI_IDENTITY": identity("cli", "cli"), "PYTHONUNBUFFERED": "1"}


def erni(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "erni", *args], cwd=ROOT, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_record_then_replay_looks_live(tmp_path):
    disc = free_port()
    port = free_port()
    control = make_agent("control", disc, echo=False, role="control", listen=f"127.0.0.1:{port}")
    robot = make_agent("robot1", disc)
    log = tmp_path / "team.jsonl"
    try:
        wait_until(lambda: any(p.up and p.role == "control" for p in robot.query(Peer)))
        rec = erni("record", "--via", f"127.0.0.1:{port}", "--seconds", "3", str(log))
        tasks, out, err = two_tasks_recorded(control, robot, rec, timeout=20)
    finally:
        control.stop()
        robot.stop()

    header, events, problems = read_log(log)
    assert problems == [] and header["via"] == f"127.0.0.1:{port}"
    recorded_tasks = [(e.obj.uid, e.obj.state) for e in events if isinstance(e.obj, Task)]
    assert (tasks[1].uid, TaskState.SUCCEEDED) in recorded_tasks
    assert any(isinstance(e.obj, Pose) and e.obj.x == 2.0 for e in events)

    replay_port = free_port()
    replay = erni("replay", str(log), "--speed", "2", "--listen", f"127.0.0.1:{replay_port}", "--no-gui",
                  "--identity", identity("control", "control"))
    try:
        watch = subprocess.run([sys.executable, "-m", "erni", "watch", "--via", f"127.0.0.1:{replay_port}",
                                "--json", "--seconds", "4"], cwd=ROOT, env=ENV, capture_output=True,
                               text=True, timeout=30)
        replay.communicate(timeout=20)
    finally:
        if replay.poll() is None:
            replay.kill()
            replay.wait()
    seen = [json.loads(line) for line in watch.stdout.splitlines()]
    replayed_tasks = [(e["data"]["uid"], (e["data"].get("result") or {}).get("state", "pending"))
                      for e in seen if e["type"] == "Task"]
    # the final state of every recorded task, and task states in recorded order
    assert (tasks[0].uid, "succeeded") in replayed_tasks and (tasks[1].uid, "succeeded") in replayed_tasks
    order = [uid for uid, state in replayed_tasks if state == "succeeded"]
    assert order.index(tasks[0].uid) < order.index(tasks[1].uid)
    poses = [e["data"]["x"] for e in seen if e["type"] == "Pose"]
    assert poses and poses[-1] == 2.0 and poses == sorted(poses)
    assert all(e["agent"] == "control" for e in seen), "the replay node speaks as the control node"


def test_bad_logs_are_clear_errors(tmp_path):
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    with pytest.raises(LogError, match="empty"):
        read_log(empty)
    wrong = tmp_path / "wrong.jsonl"
    wrong.write_text('{"hello": 1}\n')
    with pytest.raises(LogError, match="not an ERNI record"):
        read_log(wrong)
    mixed = tmp_path / "mixed.jsonl"
    good = {"t": 0.5, "agent": "c", "op": "add", "type": "Pose", "data": Pose(robot="r").model_dump(mode="json")}
    mixed.write_text("\n".join([json.dumps({"erni_record": 1, "via": "x"}), "{broken", json.dumps(good),
                                json.dumps({**good, "type": "Rocket"}), json.dumps({**good, "op": "explode"})]))
    _, events, problems = read_log(mixed)
    assert len(events) == 1 and len(problems) == 3
    assert problems[0].startswith(f"{mixed}:2:") and "Rocket" in problems[1] and "explode" in problems[2]
    out = subprocess.run([sys.executable, "-m", "erni", "replay", str(wrong)], capture_output=True, text=True,
                         timeout=30, cwd=ROOT)
    assert out.returncode == 2 and "not an ERNI record" in out.stderr and "Traceback" not in out.stderr


def test_log_times_must_be_finite_and_nesting_is_bounded(tmp_path):
    """A log line at t = NaN or infinity, or nested a hundred thousand deep, is one skipped line."""
    log = tmp_path / "odd.jsonl"
    good = {"t": 0.1, "agent": "c", "op": "add", "type": "Pose", "data": Pose(robot="r").model_dump(mode="json")}
    lines = [json.dumps({"erni_record": 1, "via": "x"}), json.dumps(good)]
    lines += [json.dumps(good).replace('"t": 0.1', f'"t": {bad}') for bad in ("NaN", "Infinity", "-1", "true", '"1"')]
    lines.append("[" * 100_000 + "]" * 100_000)
    log.write_text("\n".join(lines))
    _, events, problems = read_log(log)
    assert len(events) == 1 and len(problems) == 6
    assert "t: expected a finite number of seconds >= 0, got nan" in problems[0]
    assert "got inf" in problems[1] and "got True" in problems[3]
    assert "nested deeper than 64 levels" in problems[5]
    out = subprocess.run([sys.executable, "-m", "erni", "replay", str(log), "--no-gui", "--insecure",
                          "--listen", f"127.0.0.1:{free_port()}", "--speed", "nan"],
                         capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert out.returncode == 2 and "--speed: expected a finite number > 0, got nan" in out.stderr
    out = subprocess.run([sys.executable, "-m", "erni", "replay", str(log), "--no-gui", "--insecure",
                          "--listen", f"127.0.0.1:{free_port()}", "--speed", "50"],
                         capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert out.returncode == 0 and "replay finished (1 events)" in out.stderr
    assert out.stderr.count("skipping") == 6 and "Traceback" not in out.stderr


# -- logs handed to the operator that hold hostile values ------------------------------------------

def _line(type_name: str, data: dict, agent: str = "control", t: float = 0.1) -> str:
    return json.dumps({"t": t, "agent": agent, "op": "change", "type": type_name, "data": data})


def test_a_log_line_with_nan_or_infinity_anywhere_is_skipped_and_named_and_the_rest_replays(tmp_path):
    """json writes NaN and Infinity, and json reads them back: a recorded Pose, NetInfo or result
    that holds one is one skipped line naming the field, never an object on the blackboard."""
    from erni.blackboard import NetInfo

    good = Pose(robot="robot1", x=1.0).model_dump(mode="json")
    net = NetInfo(node="robot1", kind="network_topology").model_dump(mode="json")
    task = Task(verb="BotMotion", preposition="forward", params={"distance": 1.0}, source="control",
                destination="robot1").with_result(TaskState.RUNNING, values={"left": 0.5}).model_dump(mode="json")
    lines = [json.dumps({"erni_record": 1, "via": "x"}), _line("Pose", good),
             _line("Pose", {**good, "x": float("nan"), "y": float("inf")}),
             _line("Pose", {**good, "sonar": [0.5, float("-inf")]}),
             _line("NetInfo", {**net, "links": [{"a": "robot1", "b": "robot2", "quality": float("nan")}]}),
             _line("Task", {**task, "result": {**task["result"], "values": {"left": float("nan")}}}),
             _line("Pose", {**good, "x": 2.0}, t=0.2)]
    log = tmp_path / "nan.jsonl"
    log.write_text("\n".join(lines) + "\n")
    _, events, problems = read_log(log)
    assert [e.obj.x for e in events] == [1.0, 2.0]  # type: ignore[attr-defined]
    assert [p.split(": ", 1)[1] for p in problems] == [
        "data.x: Input should be a finite number (got nan); data.y: Input should be a finite number (got inf)",
        "data.sonar[1]: Input should be a finite number (got -inf)",
        "data.links[0].quality: Input should be a finite number (got nan)",
        "data: forward: result.values.left.float: Input should be a finite number (got nan)"]
    assert [p.split(": ", 1)[0] for p in problems] == [f"{log}:{n}" for n in (3, 4, 5, 6)]


def test_long_lines_odd_bytes_and_names_cost_one_line_each_and_lose_nothing_else(tmp_path):
    from erni.replay import MAX_LINE, MAX_PROBLEMS

    good = Pose(robot="robot1", x=1.0).model_dump(mode="json")
    log = tmp_path / "odd.jsonl"
    with log.open("wb") as f:
        f.write(json.dumps({"erni_record": 1, "via": "x"}).encode() + b"\n")
        f.write(_line("Pose", good).encode() + b"\n")
        f.write(b'{"t": 0.1, "pad": "' + b"x" * (MAX_LINE + 10) + b'"}\n')  # longer than a line may be
        f.write(b"\xff\xfe not UTF-8\n")
        f.write(_line("Pose", good, agent="ctl\x1b[2J").encode() + b"\n")
        f.write(_line("Pose", {**good, "robot": "r\x1b]0;x\x07"}).encode() + b"\n")
        f.write(_line("Pose", {**good, "x": 2.0}, t=0.2).encode() + b"\n")
        f.write(b"{broken\n" * (MAX_PROBLEMS + 5))
    _, events, problems = read_log(log)
    assert [e.obj.x for e in events] == [1.0, 2.0]  # type: ignore[attr-defined]
    assert f"a line longer than {MAX_LINE} bytes" in problems[0] and problems[0].startswith(f"{log}:3: ")
    assert "codec can't decode" in problems[1] and problems[1].startswith(f"{log}:4: ")
    assert "agent 'ctl\\x1b[2J': expected a name" in problems[2]
    assert "data.robot: expected a name of letters" in problems[3]
    assert len(problems) == MAX_PROBLEMS + 1 and problems[-1] == f"{log}: 9 more lines skipped"
    assert all(len(p) < 500 and "\x1b" not in p for p in problems)


def test_replaying_a_log_with_a_100_mb_line_holds_no_such_line(tmp_path):
    """The line is skipped as it is read, a block at a time: the replay's memory stays far below it."""
    log = tmp_path / "huge.jsonl"
    with log.open("wb") as f:
        f.write(json.dumps({"erni_record": 1, "via": "x"}).encode() + b"\n")
        f.write(b'{"t": 0.1, "pad": "')
        for _ in range(100):
            f.write(b"x" * (1 << 20))
        f.write(b'"}\n')
        f.write(_line("Pose", Pose(robot="robot1", x=1.0).model_dump(mode="json")).encode() + b"\n")
    out, grown = replay_memory(log)
    assert out.returncode == 0 and "replay finished (1 events)" in out.stderr, out.stderr[-2000:]
    assert sum("skipping" in line for line in out.stderr.splitlines()) == 1
    assert grown < 40 * 1024, f"the replay grew by {grown} KiB beyond what its imports took, for a 100 MB line"


def replay_memory(path: Path) -> tuple[subprocess.CompletedProcess[str], int]:
    """`erni replay PATH` in a process of its own, and how far its peak memory (KiB) rose above what
    importing what it runs took (compiling sources without cached bytecode costs memory of its own)."""
    code = ("import resource, sys\nfrom erni.cli import main\nimport erni.commands.replay, erni.replay\n"
            "try:\n    import erni.plugins.ros2.bags\nexcept ImportError:\n    pass\n"
            "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
            f"rc = main(['replay', {str(path)!r}, '--no-gui', '--insecure', '--listen', '127.0.0.1:{free_port()}',"
            " '--speed', '1000'])\n"
            "print('grown', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before, file=sys.stderr)\n"
            "sys.exit(rc)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, cwd=ROOT)
    last = out.stderr.strip().splitlines()[-1] if out.stderr.strip() else ""
    return out, int(last.split()[1]) if last.startswith("grown ") else -1
