"""`erni replay` refuses event times no recording has: each such line is one skipped line, never a wait."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from erni.blackboard import Pose
from erni.replay import MAX_SECONDS, read_log
from tests.transport.helpers import free_port

ROOT = Path(__file__).resolve().parents[2]


def test_absurd_times_are_refused_naming_the_line(tmp_path):
    log = tmp_path / "far.jsonl"
    good = {"t": 0.1, "agent": "c", "op": "add", "type": "Pose", "data": Pose(robot="r").model_dump(mode="json")}
    lines = [json.dumps({"erni_record": 1, "via": "x"}), json.dumps(good)]
    lines += [json.dumps({**good, "t": 1e300}), json.dumps({**good, "t": 10**400}),
              json.dumps({**good, "t": MAX_SECONDS + 1}), json.dumps({**good, "t": MAX_SECONDS})]
    log.write_text("\n".join(lines))
    _, events, problems = read_log(log)
    assert [e.t for e in events] == [0.1, MAX_SECONDS] and len(problems) == 3
    assert problems[0] == (f"{log}:3: t: expected seconds since the recording started, at most 2592000 (30 days), "
                           "got 1e+300")
    assert problems[1].startswith(f"{log}:4: t: expected seconds since the recording started") and "\n" not in problems[1]
    assert problems[2].startswith(f"{log}:5: t: expected") and "got 2592001.0" in problems[2]


def test_replay_of_a_log_with_an_event_at_1e300_ends(tmp_path):
    log = tmp_path / "far.jsonl"
    good = {"t": 0.1, "agent": "c", "op": "add", "type": "Pose", "data": Pose(robot="r").model_dump(mode="json")}
    log.write_text("\n".join([json.dumps({"erni_record": 1, "via": "x"}), json.dumps(good),
                              json.dumps({**good, "t": 1e300})]))
    out = subprocess.run([sys.executable, "-m", "erni", "replay", str(log), "--no-gui", "--insecure",
                          "--listen", f"127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=30, cwd=ROOT)
    assert out.returncode == 0 and "replay finished (1 events)" in out.stderr
    assert f"erni replay: skipping {log}:3: t: expected seconds since the recording started" in out.stderr
    assert "Traceback" not in out.stderr
