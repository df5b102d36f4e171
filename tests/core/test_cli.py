"""The `erni` command as a user runs it: `erni agent`, `erni tasks`, exit codes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from erni.blackboard import heap
from erni.blackboard.tasks import PREPOSITIONS
from erni.blackboard.testing import wait_until

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


def catches(pid: int, signum: int) -> bool:
    """Whether process `pid` has a handler of its own for `signum` (its SigCgt mask in /proc)."""
    status = Path(f"/proc/{pid}/status").read_text()
    caught = int(status.split("SigCgt:")[1].split()[0], 16)
    return bool(caught >> (signum - 1) & 1)


def test_agent_runs_until_sigterm_and_stops_cleanly():
    proc = subprocess.Popen([sys.executable, "-m", "erni", "agent", "examples/robot.toml"],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        lines = [proc.stderr.readline() for _ in range(3)]
        assert any("erni.robot1: agent robot1 started with 2 plugin(s)" in ln for ln in lines), lines
        assert any("WITHOUT authentication" in ln for ln in lines), "insecure mode is warned about"
        wait_until(lambda: catches(proc.pid, signal.SIGTERM), timeout=30)  # its handler is in place
        proc.send_signal(signal.SIGTERM)
        rest = proc.stderr.read()
        # 0, not the 3 of the stop watchdog, which ends a stop still busy 5 s (--stop-grace) after
        # the signal: the clean stop finished within its grace (a bound the agent keeps, so none
        # is timed here)
        assert proc.wait(timeout=60) == 0, rest
        assert "did not stop within" not in rest
        assert "agent robot1 stopped" in rest and "Traceback" not in rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


SECOND_SIGNAL = '''
import os, signal, sys, threading
from erni.cli import main
original = threading.Event.set
armed: list = []

def set_with_a_second_signal_inside(self):
    if not (armed and threading.current_thread() is threading.main_thread()):
        return original(self)
    armed.clear()
    # the second SIGTERM of a burst, arriving while the first handler holds the event's lock
    with self._cond:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):
            pass   # bytecodes: the interpreter runs the pending handler here
        self._flag = True
        self._cond.notify_all()

threading.Event.set = set_with_a_second_signal_inside
from erni.blackboard import heap
trim = heap.trim

def trim_then_arm():
    # start-up's last step: the agent's signal handlers are in place, so the burst comes after it (a
    # signal before running was set abandons the start: the same handler, the same exit 0)
    threading.Timer(0.5, lambda: (armed.append(1), os.kill(os.getpid(), signal.SIGTERM))).start()
    return trim()

heap.trim = trim_then_arm
sys.exit(main(["agent", "examples/robot.toml", "--log-level", "WARNING"]))
'''


FROZEN_HEAP = """
import gc, os, signal, sys, threading
from erni.blackboard import heap
from erni.cli import main

trimmed = []
trim = heap.trim

def trim_then_report():
    # start-up's last step (after the freeze): report, then stop the agent, whose handlers are in place
    trimmed.append(trim())
    print(gc.get_freeze_count(), len(gc.get_objects()), len(trimmed), flush=True)
    os.kill(os.getpid(), signal.SIGTERM)
    return trimmed[-1]

heap.trim = trim_then_report
sys.exit(main(["agent", "examples/robot.toml", "--log-level", "ERROR"]))
"""


def test_a_started_agent_keeps_its_start_up_heap_out_of_full_collections():
    """Every agent of a team starts at once; were their start-up heaps scanned, their full
    collections would come at once too, and the machine would stall for every robot. What start-up
    dropped goes back to the system, once."""
    out = subprocess.run([sys.executable, "-c", FROZEN_HEAP], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    frozen, scanned, trims = map(int, out.stdout.split())
    assert frozen > 10_000 and scanned < frozen / 10, (frozen, scanned)
    assert trims == 1


FREED_HEAP = """
import sys
from erni.blackboard import heap
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 >> 20
freed = [bytes(3000) for _ in range(20_000)]   # 60 MB from malloc's heap, not from mmap: 3 kB each
pin = bytes(3000)   # above them: the heap's top cannot shrink when they go
before = rss()
del freed
after_free = rss()
if sys.argv[1] == "trim":
    assert heap.trim()
print(before, after_free, rss())
"""


def test_trim_gives_pages_freed_inside_mallocs_heap_back_to_the_system():
    """Freed blocks below a live one stay in the process (malloc trims only the heap's top) until
    `trim()`: without it their pages count in the RSS for as long as the agent runs."""
    run = lambda how: subprocess.run([sys.executable, "-c", FREED_HEAP, how], cwd=ROOT,  # noqa: E731
                                     capture_output=True, text=True, timeout=60)
    kept, trimmed = run("keep"), run("trim")
    assert kept.returncode == 0 and trimmed.returncode == 0, kept.stderr + trimmed.stderr
    before, after_free, end = map(int, kept.stdout.split())
    assert end > before - 10, kept.stdout            # freed, and still held
    before, after_free, end = map(int, trimmed.stdout.split())
    assert end < before - 40, trimmed.stdout         # freed, and given back


BUSY_THREADS = """
import sys, threading
from erni.blackboard import heap
if sys.argv[1] == "capped":
    assert heap.cap_arenas()
start, keep = threading.Barrier(6), []
def allocate():
    start.wait()  # all at once: each finds the arenas' locks taken
    keep.append([bytes(3000) for _ in range(2000)])
threads = [threading.Thread(target=allocate) for _ in range(6)]
[t.start() for t in threads]
[t.join() for t in threads]
print(heap.thread_arenas())
"""


def test_an_agents_threads_share_one_malloc_arena():
    """Each thread that allocates while another holds malloc's lock gets an arena of its own, and
    an agent's twenty threads then keep pages in several (0.6-1.5 MB of a robot agent's RSS)."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    run = lambda *argv: subprocess.run([sys.executable, "-c", *argv], cwd=ROOT, capture_output=True,  # noqa: E731
                                       text=True, timeout=60, env=env)
    free, capped = run(BUSY_THREADS, "free"), run(BUSY_THREADS, "capped")
    assert free.returncode == 0 and capped.returncode == 0, free.stderr + capped.stderr
    assert int(free.stdout) >= 1 and int(capped.stdout) == 0, (free.stdout, capped.stdout)  # the count sees arenas
    agent = subprocess.Popen([sys.executable, "-m", "erni", "agent", "examples/robot.toml", "--log-level", "ERROR"],
                             cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True)
    try:
        threads = lambda: int(Path(f"/proc/{agent.pid}/status").read_text().split("Threads:")[1].split()[0])  # noqa: E731
        wait_until(lambda: agent.poll() is not None or threads() >= 10, timeout=30)
        assert agent.poll() is None, agent.communicate()[1]
        time.sleep(1.0)  # the started agent's threads at work: a soak in real time (nothing to wait for)
        assert heap.thread_arenas(agent.pid) == 0
    finally:
        agent.terminate()
        agent.wait(10)


def test_a_second_signal_inside_the_first_ones_handler_does_not_hang_the_agent():
    """A killed launcher's death signal can come again while the agent's handler is stopping it
    (once for each of the launcher's threads that exits). The nested handler must not wait for
    the lock the first one holds: the agent stops and exits 0."""
    out = subprocess.run([sys.executable, "-c", SECOND_SIGNAL], cwd=ROOT, capture_output=True, text=True,
                         timeout=20)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "Traceback" not in out.stderr


HANGING = '''
import threading
from erni import Plugin

class HangsInSetup(Plugin):
    def setup(self):
        print("setting up", flush=True)
        threading.Event().wait()      # waits for a peer that never answers

class HangsInTeardown(Plugin):
    def setup(self):
        print("set up", flush=True)
    def teardown(self):
        threading.Event().wait()
'''


def _hanging_agent(tmp_path: Path, cls: str, *extra: str) -> subprocess.Popen[str]:
    (tmp_path / "hanging.py").write_text(HANGING)
    path = tmp_path / "a.toml"
    path.write_text(f'[agent]\nname = "stuck"\nworkers = 1\n\n[[plugin]]\nclass = "hanging:{cls}"\n')
    return subprocess.Popen([sys.executable, "-m", "erni", "agent", str(path), *extra], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(tmp_path), "PYTHONUNBUFFERED": "1"})


def test_a_signal_during_a_start_that_never_ends_stops_the_agent(tmp_path):
    """A launcher that dies while an agent is still starting (its SIGTERM through PDEATHSIG)
    must not leave the agent running: the start is abandoned and the agent stopped."""
    proc = _hanging_agent(tmp_path, "HangsInSetup")
    try:
        assert proc.stdout.readline().strip() == "setting up"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
        assert "Traceback" not in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_stop_that_never_ends_is_cut_after_the_grace(tmp_path):
    proc = _hanging_agent(tmp_path, "HangsInTeardown", "--stop-grace", "1")
    try:
        assert proc.stdout.readline().strip() == "set up"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 3
        err = proc.stderr.read()
        assert "agent stuck: did not stop within 1 s of the signal; exiting now" in err, err
        assert "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
