"""Paper 003, Table I: the basic response test, motor command to the first odometry showing motion.

A motion command is given to a robot standing still and the time is taken until the first
odometry reading that shows it moving; the robot is then halted and rests before the next
iteration. The paths are interleaved, iteration by iteration, as in the paper, and the
simulated robots (`erni robot-sim`, its own process, over TCP) report odometry every 10 ms,
the 100 Hz of the paper's Sparrow-99 board:

- raw: the device layer directly: an `ArcosDriver` sends VEL and waits for the SIP;
- poll: a robot agent's blackboard (motion plugin, behaviour stack and Pose publishing at
  100 Hz): a BotMotion velocity task is committed, then the caller actively polls the
  blackboard's Pose until it shows motion (the paper's method interface, actively waiting);
- notify: the same task, and a plugin subscribed to the Pose is woken by the change that shows
  motion (the paper's event-triggered interface);
- remote notify: a client in another process (as the paper's CORBA tests were separate tasks)
  sends the task through the transport to a robot agent process and is pushed its Poses
  (a watch) until one shows motion.
"""

from __future__ import annotations

import os
import random
import secrets
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from erni.blackboard import Plugin, Pose, Task
from erni.sim.experiments import Experiment, Progress, Result
from erni.sim.experiments.plots import color
from erni.sim.scenario import Scenario, ScenarioError

PAPER_MS = {"raw": (12.519, 20.807), "poll": (13.476, 15.660), "notify": (14.115, 15.091)}  # two runs' means
PAPER_ROWS = {"raw": [(4.789, 12.519, 20.722, 1.878), (14.613, 20.807, 27.164, 4.543)],
              "poll": [(5.459, 13.476, 21.257, 6.208), (10.176, 15.660, 22.634, 5.321)],
              "notify": [(8.372, 14.115, 21.661, 5.060), (8.511, 15.091, 21.917, 6.350)]}  # min mean max var (ms)
MOTION = {"rate_hz": 100.0, "pose_rate_hz": 100.0, "avoid_distance": 0.0}


class MotionSeen(Plugin):
    """Records when a Pose of its agent's robot first shows motion after `arm()` (event-triggered)."""

    def setup(self) -> None:
        self.poses = self.subscribe(Pose)
        self.armed = False
        self.seen = threading.Event()
        self.at = 0.0

    def arm(self) -> None:
        """Wait for the next Pose showing motion."""
        self.seen.clear()
        self.armed = True

    def execute(self) -> None:
        if not self.armed:
            return
        for pose in self.poses.added + self.poses.changed:
            if abs(pose.v) > 1e-4:
                self.at = time.monotonic()
                self.armed = False
                self.seen.set()
                return


def run(scenario: Scenario, progress: Progress, *, experiment: Experiment, mode: str, **_: Any) -> Result:
    """Run the interleaved response tests; return figure and table."""
    s = scenario.strategy
    iterations = int(s.get("iterations", 50))
    runs = int(s.get("runs", 2))
    period = float(s.get("sip_period", 0.01))
    rest = float(s.get("rest", 0.3))
    if iterations < 1 or runs < 1:
        raise ScenarioError("strategy.iterations and strategy.runs: expected at least 1")
    data = _measure(iterations, runs, period, rest, scenario.seed, progress)
    return _result(experiment, mode, data, iterations, period)


def _await_remote(client: Any, port: int, remote: subprocess.Popen[bytes], run_dir: Path,
                  remote_poses: list[tuple[float, float]], lock: threading.Lock) -> None:
    """Lease a watch from the robot agent process until it streams a Pose (ScenarioError when it exits
    or sends none within 20 s)."""
    from erni.blackboard.schemas import WatchRequest

    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:  # the remote agent is up when its watch streams a Pose
        if remote.poll() is not None:  # it exited: say why, from its own log, at once
            said = (run_dir / "robot.log").read_text(encoding="utf-8", errors="replace").strip().splitlines()
            raise ScenarioError(f"the robot agent process exited with status {remote.returncode}: "
                                f"{said[-1] if said else '(nothing logged)'}; log in {run_dir}")
        client.send(("127.0.0.1", port), "watch.request", WatchRequest(lease=15.0), reliable=False)
        time.sleep(0.5)
        with lock:
            if remote_poses:
                return
    raise ScenarioError(f"the robot agent process sent no Pose through the transport; log in {run_dir}")


def _measure(iterations: int, runs: int, period: float, rest: float, seed: int, progress: Progress
             ) -> dict[str, list[list[float]]]:
    from erni.blackboard import Agent
    from erni.blackboard.schemas import WatchEvent, WatchRequest
    from erni.blackboard.testing import wait_until
    from erni.plugins.motion import ArcosDriver, RobotMotionControl
    from erni.sim.team import agent_toml, free_port
    from erni.transport.client import Client

    rng = random.Random(seed)
    run_dir = Path(tempfile.mkdtemp(prefix="erni-response-"))
    sim = subprocess.Popen([sys.executable, "-m", "erni", "robot-sim", "--port", "0", "--robots", "3",
                            "--sip-period", str(period), "--log-level", "WARNING"],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert sim.stdout is not None
    urls = [sim.stdout.readline().split()[1] for _ in range(3)]
    key = secrets.token_hex(16)
    port = free_port("127.0.0.1")
    config = run_dir / "robot.toml"
    config.write_text(agent_toml("robot", [
        ("transport", {"listen": f"127.0.0.1:{port}", "discovery_port": 0, "role": "robot"}),
        ("motion", {"url": urls[2], **MOTION})], workers=2), encoding="utf-8")
    env = {**os.environ, "ERNI_TEAM_KEY": key, "ERNI_RESPONSE_KEY": key}
    remote = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(config), "--log-level", "WARNING"],
                              stdout=open(run_dir / "robot.log", "ab"), stderr=subprocess.STDOUT, env=env)
    agent = Agent("local", workers=2)
    agent.add_plugin(RobotMotionControl, name="motion", settings={"url": urls[1], **MOTION})
    agent.add_plugin(MotionSeen, name="seen")
    raw = ArcosDriver(urls[0], name="raw", sync_timeout=0.5)
    os.environ["ERNI_RESPONSE_KEY"] = key
    client = Client(("127.0.0.1", port), key_env="ERNI_RESPONSE_KEY")
    out: dict[str, list[list[float]]] = {k: [[] for _ in range(runs)] for k in ("raw", "poll", "notify", "remote")}
    try:
        agent.start()
        wait_until(lambda: agent.query(Pose), timeout=15, message="the local agent published no Pose")
        raw.open()
        client.endpoint.start()
        seen = next(p for p in agent.plugins if isinstance(p, MotionSeen))
        motion = next(p for p in agent.plugins if isinstance(p, RobotMotionControl))
        remote_poses: list[tuple[float, float]] = []  # (arrival, v)
        lock = threading.Lock()

        def on_message(msg: Any) -> None:
            if msg.kind == "watch.event" and isinstance(msg.body, WatchEvent) and msg.body.type == "Pose":
                with lock:
                    remote_poses.append((time.monotonic(), float(msg.body.data.get("v") or 0.0)))

        client.endpoint.on_message = on_message
        _await_remote(client, port, remote, run_dir, remote_poses, lock)
        lease = time.monotonic()
        total = iterations * runs
        done = 0
        for r in range(runs):
            for _ in range(iterations):
                if time.monotonic() - lease > 5.0:
                    client.send(("127.0.0.1", port), "watch.request", WatchRequest(lease=15.0), reliable=False)
                    lease = time.monotonic()
                order = ["raw", "poll", "notify", "remote"]
                rng.shuffle(order)
                for path in order:
                    time.sleep(rng.uniform(0.0, period))  # the command lands at a random phase of the odometry
                    if path == "raw":
                        out[path][r].append(_raw(raw))
                    elif path == "remote":
                        out[path][r].append(_remote(client, port, remote_poses, lock))
                    else:
                        out[path][r].append(_local(agent, motion.resource.driver, seen, polling=path == "poll"))
                time.sleep(rest)
                done += 1
                progress(f"run {r + 1} of {runs}: response tests", done, total)
    finally:
        client.endpoint.stop()
        raw.close()
        agent.stop()
        remote.terminate()
        try:
            remote.wait(10)
        except subprocess.TimeoutExpired:
            remote.kill()
        sim.terminate()
        sim.wait(10)
    shutil.rmtree(run_dir, ignore_errors=True)  # kept when the run raised: its error names the log
    return out


def _still(driver: Any) -> None:
    if driver.wait_for(lambda st: st.left == 0 and st.right == 0, 5.0) is None:
        raise ScenarioError("a robot did not come to rest between iterations")


def _raw(driver: Any) -> float:
    _still(driver)
    t0 = time.monotonic()
    driver.vel(0.2)
    st = driver.wait_for(lambda st: st.stamp >= t0 and (st.left != 0 or st.right != 0), 3.0)
    driver.stop()
    if st is None:
        raise ScenarioError("raw: no SIP showed the wheels turning")
    return float(st.stamp - t0) * 1000.0


def _local(agent: Any, driver: Any, seen: MotionSeen, polling: bool) -> float:
    _still(driver)
    while any(abs(p.v) > 1e-4 for p in agent.query(Pose)):
        time.sleep(0.002)
    task = Task(verb="BotMotion", preposition="velocity", params={"v": 0.2}, source="response")
    if not polling:
        seen.arm()
    t0 = time.monotonic()
    with agent.transaction() as tx:
        tx.add(task)
    at = None
    if polling:
        end = t0 + 3.0
        while time.monotonic() < end:
            if any(abs(p.v) > 1e-4 for p in agent.query(Pose)):
                at = time.monotonic()
                break
            time.sleep(0.0005)
    elif seen.seen.wait(3.0):
        at = seen.at
    with agent.transaction() as tx:
        tx.remove(task.uid)
    if at is None:
        raise ScenarioError(f"{'poll' if polling else 'notify'}: no Pose showed motion within 3 s")
    return (at - t0) * 1000.0


def _remote(client: Any, port: int, poses: list[tuple[float, float]], lock: threading.Lock) -> float:
    from erni.blackboard.schemas import Cancel

    end = time.monotonic() + 5.0
    while time.monotonic() < end:  # at rest, as the watch last said
        with lock:
            if poses and abs(poses[-1][1]) < 1e-4:
                break
        time.sleep(0.01)
    task = Task(verb="BotMotion", preposition="velocity", params={"v": 0.2}, source=client.endpoint.name,
                destination="robot")
    t0 = time.monotonic()
    client.send(("127.0.0.1", port), "task.add", task)
    at = None
    while time.monotonic() < t0 + 3.0:
        with lock:
            moving = [a for a, v in poses if a >= t0 and abs(v) > 1e-4]
        if moving:
            at = moving[0]
            break
        time.sleep(0.0005)
    client.send(("127.0.0.1", port), "task.cancel", Cancel(uid=task.uid))
    if at is None:
        raise ScenarioError("remote: no Pose showing motion came through the transport within 3 s")
    return (at - t0) * 1000.0


def _result(experiment: Experiment, mode: str, data: dict[str, list[list[float]]], iterations: int,
            period: float) -> Result:
    res = Result(experiment.name, experiment.title, mode)
    res.mode_note = (f"simulated robots in their own process over TCP, odometry every {period * 1000:g} ms; "
                     "poll and notify on a robot agent's blackboard; remote notify from another process through "
                     "the transport")
    labels = {"raw": "raw (device layer)", "poll": "poll (blackboard, active wait)",
              "notify": "notify (subscription)", "remote": "remote notify (transport, other process)"}
    for path, per_run in data.items():
        for r, xs in enumerate(per_run):
            a = np.array(xs)
            res.metrics[f"{labels[path]}, run {r + 1}: min / mean / max / std"] = (
                f"{a.min():.1f} / {a.mean():.1f} / {a.max():.1f} / {a.std():.1f}", "ms")
            res.series[f"{path}/run{r + 1}_ms"] = (list(range(len(xs))), xs, "ms")
    res.compare("odometry period", "10 ms (100 Hz, Sparrow-99 over CAN)", f"{period * 1000:g} ms (ARCOS SIP)", "",
                "the simulated robot's setting", "input")
    res.compare("iterations", "2 runs x 100", f"{len(next(iter(data.values())))} runs x {iterations}", "",
                "interleaved paths, random phase, rest between", "input")
    for path in ("raw", "poll", "notify", "remote"):
        means = [float(np.mean(xs)) for xs in data[path]]
        paper = PAPER_MS.get(path)
        res.compare(f"{labels[path]}: mean per run", f"{paper[0]:.1f} / {paper[1]:.1f}" if paper else "no such test",
                    " / ".join(f"{m:.1f}" for m in means), "ms",
                    "command issued to the first odometry showing motion")
    res.notes.append("paper 003: the response is dominated by the odometry cycle and the motors; the CORBA "
                     "overhead was not measurable. Ours: the same for the raw path; the agent's paths add its "
                     "100 Hz behaviour cycle and Pose publishing")
    res.draw = lambda fig: _draw(fig, data, labels, period)
    return res


def _draw(fig: Any, data: dict[str, list[list[float]]], labels: dict[str, str], period: float) -> None:
    gs = fig.add_gridspec(1, 2, width_ratios=[1.3, 1])
    ax = fig.add_subplot(gs[0, 0])
    paths = list(data)
    boxes = [x for path in paths for x in data[path]]
    pos = [i * 3 + r for i, path in enumerate(paths) for r in range(len(data[path]))]
    parts = ax.boxplot(boxes, positions=pos, widths=0.8, showfliers=True, patch_artist=True)
    for k, patch in enumerate(parts["boxes"]):
        patch.set_facecolor(color(pos[k] // 3))
        patch.set_alpha(0.5)
    ax.set_xticks([i * 3 + 0.5 for i in range(len(paths))], [labels[p].replace(" (", "\n(") for p in paths],
                  fontsize=8)
    ax.set_ylabel("command to first odometry showing motion (ms)")
    ax.set_title("Ours: each path, two runs\n(box: quartiles)", fontsize=10)
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    ax = fig.add_subplot(gs[0, 1])
    for i, path in enumerate(paths):
        means = [float(np.mean(xs)) for xs in data[path]]
        ax.scatter([i] * len(means), means, color=color(i), s=50, label="ours (run means)" if i == 0 else None,
                   zorder=3)
        for run in PAPER_ROWS.get(path, []):
            lo, mean, hi, _ = run
            ax.errorbar([i + 0.2], [mean], yerr=[[mean - lo], [hi - mean]], fmt="s", color="#444444", capsize=4,
                        label="paper 003 (min / mean / max)" if path == "raw" and run is PAPER_ROWS["raw"][0]
                        else None)
    ax.set_xticks(range(len(paths)), [p for p in paths])
    ax.set_ylabel("ms")
    ax.set_title(f"Means beside paper 003's Table I\n(odometry every {period * 1000:g} ms in both)", fontsize=10)
    ax.grid(True, axis="y", color="#e0e0e0", lw=0.6)
    ax.legend(fontsize=8)
    fig.suptitle("Paper 003, Table I: basic response test, motor command to odometry (agents mode)", fontsize=12)
