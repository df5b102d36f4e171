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
        tasks, out, err = two_tasks_recorded(control, robot, rec, warmup=0.8, timeout=20)  # warm-up: the watch leased
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
