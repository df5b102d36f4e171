"""One stop: every front end halts every motion of every robot, on `erni sim`'s real agent processes.

A team of four runs as a user starts it (`erni sim`, the default RemoteBotMotion tier). For each
front end — the spoken "everybody stop" streamed as audio through the page's microphone path,
the page's typed line and its Stop button, `erni console`, `erni task ... RemoteBotMotion cancel`,
`erni task ... BotMotion stop` and `erni stop` in either tier — the robots are first set moving the way an operator does
(typed commands that the dialogue sends as BotMotion straight to the robot, RemoteBotMotion
tasks that MissionControl expands, a Deploy spread it runs), one robot left idle, then stopped. Each case checks what the
operator sees from the control node: every robot stands within a second or two, stays standing,
and every motion task ends `cancelled` naming who stopped it, never `succeeded`.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from erni.blackboard.testing import wait_until
from tests.sim.test_sim_cli import ROOT, SimProcess

ROBOTS = ("robot1", "robot2", "robot3", "robot4")
MOVING_V, MOVING_W = 0.05, 0.1     # m/s, rad/s: a robot doing something
HALTED_V, HALTED_W = 0.01, 0.02    # m/s, rad/s: a robot standing
STOP_LATENCY: dict[str, list[float]] = {}


@dataclass
class Watched:
    """What the control node's blackboard shows, read from `erni watch --json`."""

    poses: dict[str, dict[str, Any]] = field(default_factory=dict)
    history: dict[str, list[tuple[float, bool]]] = field(default_factory=dict)  # robot -> (when read, halted)
    tasks: dict[str, dict[str, Any]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def feed(self, line: str) -> None:
        try:
            ev = json.loads(line)
        except ValueError:
            return
        if not isinstance(ev, dict) or "data" not in ev:
            return
        with self.lock:
            if ev.get("type") == "Pose":
                d = ev["data"]
                self.poses[d["robot"]] = d
                halted = abs(d["v"]) < HALTED_V and abs(d["w"]) < HALTED_W
                self.history.setdefault(d["robot"], []).append((time.monotonic(), halted))
            elif ev.get("type") == "Task":
                self.tasks[ev["data"]["uid"]] = ev["data"]

    def pose(self, robot: str) -> dict[str, Any]:
        with self.lock:
            return dict(self.poses.get(robot) or {})

    def halted(self, robot: str) -> bool:
        p = self.pose(robot)
        return bool(p) and abs(p["v"]) < HALTED_V and abs(p["w"]) < HALTED_W

    def halted_since(self, robot: str, after: float) -> float | None:
        """When the robot stopped for good after `after`: the first of the readings since then that
        are all halted (None while the newest reading shows it moving)."""
        with self.lock:
            readings = [(t, h) for t, h in self.history.get(robot, []) if t >= after]
        since = None
        for t, h in readings:
            since = (since if since is not None else t) if h else None
        return since

    def moving(self, robot: str) -> bool:
        p = self.pose(robot)
        return bool(p) and (abs(p["v"]) > MOVING_V or abs(p["w"]) > MOVING_W)

    def moved_since(self, robot: str, after: float) -> bool:
        """Whether a reading since `after` (monotonic) showed the robot moving."""
        with self.lock:
            return any(not h for t, h in self.history.get(robot, []) if t >= after)

    def stop_done(self, robot: str, since: float) -> float | None:
        """When the robot's performer finished the first stop, cancel or clear made after `since`
        (the stamp of its result), None while none has been seen done."""
        with self.lock:
            done = [t["result"]["stamp"] for t in self.tasks.values() if t.get("destination") == robot
                    and t["created"] >= since and t["preposition"] in ("stop", "cancel", "clear")
                    and (t.get("result") or {}).get("state") in ("succeeded", "failed", "cancelled")]
        return min(done, default=None)

    def motion_tasks(self, robot: str, since: float) -> list[dict[str, Any]]:
        """Motion tasks to `robot` created after `since` (stops and cancels are not motions)."""
        with self.lock:
            return [t for t in self.tasks.values() if t.get("destination") == robot and t["created"] >= since
                    and t["preposition"] not in ("stop", "cancel", "clear", "say", "avoid_obstacles", "teleport")]


@dataclass
class Team:
    sim: SimProcess
    via: str
    ws: str
    origin: str
    env: dict[str, str]
    watched: Watched
    watcher: subprocess.Popen[str]

    def close(self) -> None:
        self.watcher.kill()
        self.watcher.wait(10)
        self.sim.cleanup()

    def cli(self, *args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "erni", *args[:1], "--via", self.via, *args[1:]], cwd=ROOT,
                              env=self.env, capture_output=True, text=True, timeout=timeout)


def wait_for(check: Callable[[], Any], timeout: float, what: str) -> Any:
    return wait_until(check, timeout, interval=0.02, message=f"{what} within {timeout} s")


def open_team(sim: SimProcess, run: Path) -> Team:
    """Wait for a starting `erni sim` with its GUI, and watch its control node."""
    sim.wait_for("Ctrl-C stops the team", timeout=120)
    via = sim.wait_for("erni peers --via", timeout=1).split("--via")[1].strip()
    url = sim.gui_url()
    assert url.startswith("http://"), url
    base, token = url.split("/?token=")
    env = {**os.environ, "ERNI_IDENTITY": str(run / "keys" / "cli.pem"), "PYTHONUNBUFFERED": "1"}
    watched = Watched()
    watcher = subprocess.Popen([sys.executable, "-m", "erni", "watch", "--via", via, "--json"], cwd=ROOT, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)

    def read() -> None:
        assert watcher.stdout is not None
        for line in watcher.stdout:
            watched.feed(line)

    threading.Thread(target=read, name="stop-matrix-watch", daemon=True).start()
    team = Team(sim, via, base.replace("http://", "ws://") + f"/ws?token={token}", base, env, watched, watcher)
    try:
        wait_for(lambda: all(watched.pose(r) for r in ROBOTS), 30, "the watch did not show every robot's Pose")
    except BaseException:
        team.close()
        raise
    return team


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Team]:
    run = tmp_path_factory.mktemp("stop") / "run"
    sim = SimProcess(run, "--robots", "4", "--control-port", "0", "--gui-listen", "127.0.0.1:0", headless=False)
    try:
        team = open_team(sim, run)
    except BaseException:
        sim.cleanup()
        raise
    yield team
    team.close()
    if STOP_LATENCY:
        print("\nstop latency, command complete -> every moving robot standing (s):")
        for name, lat in STOP_LATENCY.items():
            print(f"  {name:<20} median {sorted(lat)[len(lat) // 2]:.2f}  max {max(lat):.2f}  ({len(lat)} robots)")


async def _page(team: Team, sends: list[Any], *, pace: float = 0.0, marks: dict[str, float] | None = None,
                mark: int = -1) -> list[dict[str, Any]]:
    """Open the page's WebSocket as the browser does, send each message (pacing binary frames in
    real time) while reading what comes back, and return the first reply (within 20 s of the last
    send). `marks["sent"]` is when message number `mark` went (the last by default)."""
    got: list[dict[str, Any]] = []
    async with aiohttp.ClientSession() as s, s.ws_connect(team.ws, headers={"Origin": team.origin}) as ws:

        async def read() -> None:  # reading answers the server's heartbeat pings, as a browser does
            async for msg in ws:
                if msg.type == aiohttp.WSMsgType.TEXT and (data := json.loads(msg.data)).get("type") == "reply":
                    got.append(data)
                    return

        reader = asyncio.create_task(read())
        for i, m in enumerate(sends):
            if marks is not None and i == (mark % len(sends)):
                marks["sent"] = time.monotonic()
            if isinstance(m, bytes):
                await ws.send_bytes(m)
                await asyncio.sleep(pace)
            else:
                await ws.send_str(json.dumps(m))
        try:
            await asyncio.wait_for(reader, 20.0)  # a recogniser at load 12 took over 8 s
        except TimeoutError:
            pass
    return got


def page(team: Team, *sends: Any, pace: float = 0.0, marks: dict[str, float] | None = None,
         mark: int = -1) -> list[dict[str, Any]]:
    return asyncio.run(_page(team, list(sends), pace=pace, marks=marks, mark=mark))


TRAILING = 8  # 100 ms frames of silence after an utterance: the recogniser's end of speech


def spoken(text: str, tmp: Path) -> list[bytes]:
    """`text` spoken by espeak-ng, as the page's microphone sends it: 100 ms frames of 16 kHz int16."""
    from erni.plugins.ui.speech import wav_frames

    wav = tmp / "utterance.wav"
    subprocess.run(["espeak-ng", "-v", "en-us", "-s", "150", "-w", str(wav), text], check=True, timeout=30)
    silence = b"\0\0" * 1600
    return [silence] * 3 + list(wav_frames(wav)) + [silence] * TRAILING


# -- front ends: each stops the whole team and returns when the command was complete ---------

def by_voice(team: Team, tmp: Path) -> float:
    frames = spoken("everybody stop", tmp)
    marks: dict[str, float] = {}
    # the command is complete when its last word has been said: the first frame of trailing silence
    replies = page(team, {"type": "mic", "on": True, "rate": 16000}, *frames, {"type": "mic", "on": False},
                   pace=0.1, marks=marks, mark=-1 - TRAILING)
    assert replies and "stop" in replies[0]["text"].lower(), replies
    return marks["sent"]


def by_page_button(team: Team, tmp: Path) -> float:
    marks: dict[str, float] = {}
    replies = page(team, {"type": "command", "robots": [], "action": "stop", "params": {}}, marks=marks)
    assert replies and "stop" in replies[0]["text"], replies
    return marks["sent"]


def by_page_typing(team: Team, tmp: Path) -> float:
    marks: dict[str, float] = {}
    replies = page(team, {"type": "say", "text": "everybody stop", "selection": []}, marks=marks)
    assert replies and "stop" in replies[0]["text"], replies
    return marks["sent"]


def by_console(team: Team, tmp: Path) -> float:
    proc = subprocess.Popen([sys.executable, "-m", "erni", "console", "--via", team.via], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT, env=team.env, text=True)
    assert proc.stdin is not None and proc.stdout is not None
    try:
        proc.stdin.write("everybody stop\n")
        proc.stdin.close()
        echo = proc.stdout.readline()  # printed as the console takes the line, once it has found the team
        sent = time.monotonic()
        assert echo.strip() == "> everybody stop", echo
        out = echo + proc.stdout.read()
        proc.wait(30)
    finally:
        proc.kill()
    assert "stop" in out, out
    return sent


def _each_robot(team: Team, *task: str) -> float:
    sent = time.monotonic()  # these include starting `erni task` itself, as a user types it
    procs = [subprocess.Popen([sys.executable, "-m", "erni", "task", "--via", team.via, r, *task], cwd=ROOT,
                              env=team.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for r in ROBOTS]
    for p in procs:
        out, _ = p.communicate(timeout=30)
        assert p.returncode == 0, out
    return sent


def by_task_cancel(team: Team, tmp: Path) -> float:
    return _each_robot(team, "RemoteBotMotion", "cancel")


def by_task_stop(team: Team, tmp: Path) -> float:
    return _each_robot(team, "BotMotion", "stop")


def _stop(team: Team, *options: str) -> float:
    sent = time.monotonic()  # this includes starting `erni stop` itself, as a user types it
    out = team.cli("stop", *options)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.startswith(f"stop taken by {len(ROBOTS)} of {len(ROBOTS)} robots"), out.stdout
    return sent


def by_stop(team: Team, tmp: Path) -> float:
    return _stop(team)


def by_stop_botmotion(team: Team, tmp: Path) -> float:
    return _stop(team, "--verb", "BotMotion")


FRONT_ENDS: dict[str, Callable[[Team, Path], float]] = {
    "voice": by_voice, "page button": by_page_button, "page typing": by_page_typing, "console": by_console,
    "task cancel": by_task_cancel, "task BotMotion stop": by_task_stop, "erni stop": by_stop,
    "erni stop BotMotion": by_stop_botmotion}

# Two sets of motions, as an operator starts them: typed lines go through the dialogue (turn and
# backward go as BotMotion straight to the robot, forward as RemoteBotMotion), the rest by `erni
# task` (a held velocity, a deployment that MissionControl runs, a remote random walk and goto).
# Robot 4 stays idle in the first set.
TYPED_A = ["robot 1 turn left 720 degrees", "robot 2 go back 2 meters"]
TASKS_A = [("robot3", "BotMotion", "velocity", "v=0.2", "w=20")]
TYPED_B = ["robot 1 go forward 3 meters"]
TASKS_B = [("robot2", "Deploy", "spread", "distance=6"), ("robot3", "RemoteBotMotion", "randomwalk", "speed=0.3"),
           ("robot4", "RemoteBotMotion", "goto", "x=0", "y=6")]


HOME = {"robot1": (-4.0, 3.0), "robot2": (-1.5, 3.0), "robot3": (1.5, 3.0), "robot4": (4.0, 3.0)}


def home(team: Team) -> None:
    """Put the team back at its start of each case (a simulator's teleport), well clear of walls and
    of each other, so every case starts the same."""
    procs = [subprocess.Popen([sys.executable, "-m", "erni", "task", "--via", team.via, r, "RemoteBotMotion",
                               "teleport", f"x={x}", f"y={y}", "heading=0", "--wait", "--timeout", "20"], cwd=ROOT,
                              env=team.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for r, (x, y) in HOME.items()]
    for p in procs:
        out, _ = p.communicate(timeout=40)
        assert p.returncode == 0, out


def start_motions(team: Team, typed: list[str], tasks: list[tuple[str, ...]]) -> list[str]:
    since, started = time.time(), time.monotonic()
    for line in typed:
        replies = page(team, {"type": "say", "text": line, "selection": []})
        assert replies and replies[0]["text"].startswith("Roger"), (line, replies)
    for robot, *task in tasks:
        out = team.cli("task", robot, *task)
        assert out.returncode == 0, out.stdout + out.stderr
    movers = sorted({f"robot{line.split()[1]}" for line in typed} | {t[0] for t in tasks})
    try:
        # each has started (on a loaded machine the first can finish a short motion before the last starts;
        # the case then still needs one motion that the stop ends, asserted below)
        wait_for(lambda: all(team.watched.moved_since(r, started) for r in movers), 10,
                 f"{movers} did not all start moving")
    except AssertionError as err:
        raise AssertionError(f"{err}: {[(r, team.watched.pose(r), team.watched.motion_tasks(r, since)) for r in movers]}") from None
    return movers


@pytest.mark.parametrize("front_end", list(FRONT_ENDS))
@pytest.mark.parametrize("motions", ["A", "B"])
def test_every_front_end_halts_every_motion_and_the_robots_stay_halted(team, tmp_path, front_end, motions):
    if front_end == "voice" and not shutil.which("espeak-ng"):
        pytest.fail("espeak-ng is needed to speak the stop (apt install espeak-ng)")
    wait_for(lambda: all(team.watched.halted(r) for r in ROBOTS), 10, "the team was not standing before the case")
    home(team)
    since = time.time()
    typed, tasks = (TYPED_A, TASKS_A) if motions == "A" else (TYPED_B, TASKS_B)
    movers = start_motions(team, typed, tasks)
    idle = [r for r in ROBOTS if r not in movers]
    time.sleep(1.0)  # well under way
    sent = FRONT_ENDS[front_end](team, tmp_path)
    sent_wall = time.time() - (time.monotonic() - sent)  # tasks' results are stamped by the wall clock
    wait_for(lambda: all(team.watched.halted(r) for r in ROBOTS), 5,
             f"{front_end}: not every robot halted ({[r for r in ROBOTS if not team.watched.halted(r)]} still moving)")
    for _ in range(20):  # and they stay halted: nothing resumes under the stop
        time.sleep(0.1)
        moving = [r for r in ROBOTS if not team.watched.halted(r)]
        assert not moving, f"{front_end}: {moving} moved again after the stop ({[team.watched.pose(r) for r in moving]})"
    # acted on: from the moment the operator's command was complete to the robot standing for good,
    # as the control node sees it (its Pose, 10 a second)
    STOP_LATENCY.setdefault(front_end, []).extend(max(0.0, (team.watched.halted_since(r, sent) or sent) - sent)
                                                  for r in movers)
    cancelled = 0
    for robot in movers:
        ends = wait_for(lambda r=robot: (ts := team.watched.motion_tasks(r, since)) and all(
            (t.get("result") or {}).get("state") in ("succeeded", "failed", "cancelled") for t in ts) and ts,
            10, f"{front_end}: the motion tasks of {robot} did not end")
        # a motion that ended by itself before the stop reached its robot was not the stop's to end: on
        # a loaded machine starting four `erni task` processes can outlast a 10 s forward, and a robot
        # backing towards its neighbour is stopped by its own obstacle guard ("blocked by an obstacle")
        stopped = team.watched.stop_done(robot, sent_wall - 1.0) or sent_wall
        for t in ends:
            r = t["result"]
            by_stop = "stopped by" in r["message"] or "cancelled by" in r["message"]
            if r["state"] in ("succeeded", "failed") and not by_stop and r["stamp"] < stopped:
                continue
            cancelled += 1
            assert r["state"] == "cancelled", (f"{front_end}: {robot}'s {t['verb']} {t['preposition']} ended "
                                               f"{r['state']}: {r['message']}")
            assert "stopped by" in r["message"] or "cancelled by" in r["message"], r["message"]
    assert cancelled, f"{front_end}: every motion had ended before the stop was sent: the case stopped nothing"
    for robot in idle:  # an idle robot stays where it was
        assert team.watched.halted(robot)
