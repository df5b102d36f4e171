"""What the real-mesh launcher starts dies with it (netns.die_with_parent): however the process
treats SIGTERM, and however early the launcher dies. Plain processes, no namespaces: no root needed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from erni.blackboard.testing import wait_until
from erni.sim import netns

ROOT = Path(__file__).resolve().parents[2]


def gone(pid: int) -> bool:
    """True once process `pid` has exited (reaped, or a zombie waiting for its new parent)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def launcher(code: str) -> subprocess.Popen[str]:
    """A stand-in launcher: this Python code, its output (and its children's) on a pipe."""
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], stdout=subprocess.PIPE, text=True,
                            cwd=ROOT, start_new_session=True)


def read_pid(proc: subprocess.Popen[str], word: str) -> int:
    assert proc.stdout is not None
    line = proc.stdout.readline().split()
    assert line[:1] == [word], line
    return int(line[1])


@pytest.fixture
def children():
    pids: list[int] = []
    yield pids
    for pid in pids:
        if not gone(pid):
            os.kill(pid, signal.SIGKILL)


def test_a_child_dies_with_its_killed_launcher_whatever_it_does_with_sigterm(children):
    # A launcher with threads: when it is killed the kernel sends the death signal once for each
    # thread that was the child's parent in turn, and `erni agent`'s SIGTERM handler, re-entered
    # by the second one, waited forever on a lock its first run held. A child that shrugs off
    # SIGTERM stands for any such handler: it must die all the same.
    proc = launcher("""
        import subprocess, sys, threading, time
        from erni.sim import netns

        for _ in range(8):
            threading.Thread(target=time.sleep, args=(600,), daemon=True).start()
        child = subprocess.Popen(
            [sys.executable, "-c", "import os, signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                                   "print('child', os.getpid(), flush=True); time.sleep(600)"],
            preexec_fn=netns.die_with_parent(), start_new_session=True)
        time.sleep(600)
    """)
    try:
        children.append(read_pid(proc, "child"))   # up, its SIGTERM handling in place
        proc.kill()
        proc.wait(10)
        wait_until(lambda: gone(children[0]), timeout=5, message="the child outlived its killed launcher")
    finally:
        proc.kill()
        proc.wait(10)


def test_a_child_whose_launcher_dies_before_it_arms_its_death_signal_does_not_start(children):
    # PR_SET_PDEATHSIG set after the parent died never fires (the new parent, init, does not die):
    # the child finds its parent changed and exits before exec instead of running for good.
    proc = launcher("""
        import os, subprocess, time
        from erni.sim import netns

        arm = netns.die_with_parent()

        def late():  # the launcher is killed between fork and the child's prctl
            os.write(1, f"child {os.getpid()}\\n".encode())
            time.sleep(1.5)
            arm()

        subprocess.Popen(["sleep", "600"], preexec_fn=late)
        time.sleep(600)
    """)
    try:
        children.append(read_pid(proc, "child"))
        proc.kill()
        proc.wait(10)
        wait_until(lambda: gone(children[0]), timeout=10, message="the child started after its launcher died")
    finally:
        proc.kill()
        proc.wait(10)


def test_a_child_of_a_living_launcher_runs():
    # the check must not stop what a live launcher starts (the pid it compares is the launcher's)
    done = subprocess.run(["true"], preexec_fn=netns.die_with_parent(), timeout=30)
    assert done.returncode == 0
    out = subprocess.run([sys.executable, "-c", "import os; print(os.getppid())"], capture_output=True, text=True,
                         preexec_fn=netns.die_with_parent(), timeout=30)
    assert out.returncode == 0 and int(out.stdout) == os.getpid()
