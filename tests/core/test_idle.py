"""An idle agent sleeps: lazy imports at start, threads that wait on events rather than poll."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from erni.blackboard import Agent, Plugin
from erni.blackboard.testing import wait_until
from tests.core.helpers import Item

ROOT = Path(__file__).resolve().parents[2]

# A robot agent as the examples configure it (transport, motion, mobinet, mission), its robot and
# network subsystem unreachable: every plugin's setup runs and its threads start.
START_ROBOT_AGENT = """
import sys
from erni.blackboard.config import build_agent, read_config
from erni.blackboard.agent import Agent
from erni.blackboard.testing import wait_until
from tests.core.helpers import scheduler_idle
path = sys.argv[1]
config = read_config(path)
agent = build_agent(config, path)
agent.start()
# at work: the driver has tried the robot, the SNMP thread has made its source, every plugin is idle
wait_until(lambda: agent.plugin("motion").resource.driver.last_error, timeout=30)
wait_until(lambda: agent.plugin("mobinet").resource.source is not None, timeout=30)
wait_until(lambda: all(scheduler_idle(p) for p in agent.plugins), timeout=30)
heavy = sorted(m for m in ("numpy", "aiohttp", "scipy", "pysnmp", "pyasn1", "erni.sim", "erni.strategies.potential")
               if m in sys.modules)
agent.stop()
print("loaded:", " ".join(heavy))
"""


def test_a_robot_agent_starts_without_numpy_aiohttp_pysnmp_or_the_simulator(tmp_path):
    config = (ROOT / "examples/robot-mission.toml").read_text()
    config = config.replace('url = "simrobot://"', 'url = "socket://127.0.0.1:9"')   # nobody listens there
    assert 'socket://127.0.0.1:9' in config
    path = tmp_path / "robot.toml"
    path.write_text(config)
    out = subprocess.run([sys.executable, "-c", START_ROBOT_AGENT, str(path)], capture_output=True, text=True,
                         timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert "loaded: \n" in out.stdout, out.stdout


def test_deployment_imports_numpy_when_first_needed():
    out = subprocess.run([sys.executable, "-c",
                          "import sys, erni.plugins.mission.plugin as m\n"
                          "before = 'numpy' in sys.modules\n"
                          "from erni.plugins.mission.deploy import RUNNERS\n"
                          "print(before, 'numpy' in sys.modules, sorted(RUNNERS))"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    before, after, _ = out.stdout.split(" ", 2)
    assert (before, after) == ("False", "True")


def switches(tid: int) -> int:
    """Voluntary context switches of one thread of this process so far: one per wake-up (going back
    to sleep); preemptions by a loaded machine are not counted."""
    with open(f"/proc/self/task/{tid}/status") as f:
        return sum(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))


class Quiet(Plugin):
    def setup(self) -> None:
        self.items = self.subscribe(Item)

    def execute(self) -> None:
        pass


def test_an_idle_agents_timer_and_worker_threads_sleep():
    from tests.core.helpers import Probe, timers_caught_up

    agent = Agent("idle", workers=2, slow_plugin_seconds=1.0)
    agent.add_plugin(Quiet, name="quiet")
    probe = agent.add_plugin(Probe, name="probe")
    agent.start()
    try:
        # started: its first runs over, the timer thread gone round (and the slow-run watch looked) since
        timers_caught_up(probe)
        mine = {t.native_id: t.name for t in threading.enumerate()
                if t.name.startswith("erni-idle-") and t.native_id is not None}
        assert any(n.endswith("timers") for n in mine.values()) and len(mine) >= 3, mine
        before = {tid: switches(tid) for tid in mine}
        time.sleep(2.0)  # what is measured: the wake-ups of threads left alone for 2 s of real time
        woke = {mine[tid]: switches(tid) - n for tid, n in before.items()}
    finally:
        agent.stop()
    # the slow-plugin watch looks once per limit (1 s) while nothing runs: 2 or 3 wake-ups in 2 s
    # (it used to look every 0.25 s: 8); workers wait on their queue
    assert sum(woke.values()) <= 5, woke


def test_a_slow_plugin_is_still_reported_at_its_limit(caplog):
    """The watch waits a whole limit while nothing runs; a run that starts in the middle of that wait
    is still reported within a limit of its start (here 0.7 s into it, at the watch's next look)."""
    import logging

    from erni.testing import ManualClock
    from tests.core.helpers import Probe, timers_caught_up

    caplog.set_level(logging.WARNING)
    started, release = threading.Event(), threading.Event()

    class Slow(Plugin):
        def setup(self) -> None:
            self.items = self.subscribe(Item)

        def execute(self) -> None:
            started.set()
            release.wait(10)

    clock = ManualClock()
    agent = Agent("slowidle", workers=1, slow_plugin_seconds=0.6, clock=clock)
    agent.add_plugin(Slow, name="slow")
    probe = agent.add_plugin(Probe, name="probe")
    agent.start()
    try:
        clock.advance(0.9)
        timers_caught_up(probe)  # the watch looked at 0.9 s with nothing running: its next look is a limit on
        with agent.transaction() as tx:
            tx.add(Item(value=1))  # the run starts in the middle of the watch's wait
        assert started.wait(5)
        clock.advance(0.7)  # past the run's limit (0.6 s) and the watch's next look (a limit after 0.9 s)
        wait_until(lambda: any("has been running" in r.getMessage() for r in caplog.records), timeout=5)
    finally:
        release.set()
        agent.stop()
    assert any("plugin slow of agent slowidle has been running for 0.7 s" in r.getMessage() for r in caplog.records)


def test_erni_agent_stops_at_once_on_sigterm(tmp_path):
    path = tmp_path / "a.toml"
    path.write_text('[agent]\nname = "a"\nworkers = 1\n\n[[plugin]]\nclass = "echo"\n')
    log = tmp_path / "agent.log"
    with log.open("w") as out:
        p = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(path)], cwd=ROOT,
                             stdout=out, stderr=subprocess.STDOUT, text=True)
    try:
        # counted from the agent's own "started" (a loaded machine takes seconds to import it)
        wait_until(lambda: "agent a started" in log.read_text() or p.poll() is not None, timeout=60)
        assert p.poll() is None, log.read_text()
        time.sleep(1.0)  # then it freezes and trims the heap, and waits (it says nothing of it: real time passes)
        main_tid = p.pid
        with open(f"/proc/{p.pid}/task/{main_tid}/status") as f:
            a = sum(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))
        time.sleep(1.5)  # what is measured: the main thread's wake-ups in 1.5 s of real time
        with open(f"/proc/{p.pid}/task/{main_tid}/status") as f:
            b = sum(int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches"))
        os.kill(p.pid, 15)
        assert p.wait(10) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert b - a <= 1, "the main thread of erni agent woke while waiting for a signal"
