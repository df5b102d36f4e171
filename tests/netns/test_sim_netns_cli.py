"""`erni sim --netns` as a user runs it: tasking from another terminal, the GUI, Ctrl-C, a killed launcher, refusals."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import tomllib
import urllib.request
from pathlib import Path

import pytest

from erni.blackboard.testing import wait_until
from erni.cli import main
from erni.sim import netns


def launch(tmp_path: Path, *args: str) -> tuple[subprocess.Popen[str], list[str]]:
    """Start `erni sim` and read its output until the team is up; return the process and the lines."""
    proc = subprocess.Popen([sys.executable, "-m", "erni", "sim", "mesh-line", "--netns", "--run-dir",
                             str(tmp_path / "run"), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    assert proc.stdout is not None
    lines: list[str] = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip())
        if line.startswith("Ctrl-C stops the team"):
            return proc, lines
    proc.kill()
    raise AssertionError("erni sim --netns did not come up:\n" + "\n".join(lines))


def gui_url(text: str) -> str:
    """The GUI's URL with its token: into a pipe `erni sim` masks it (`token=***`) and names the control
    node's config, whose ui plugin holds it."""
    line = re.search(r"GUI\s+(http://\S+)[^\n]*", text)
    assert line and line.group(1).endswith("?token=***"), text
    config = Path(re.search(r"token in (\S+control\.toml)", line.group(0)).group(1))
    ui = next(p for p in tomllib.loads(config.read_text())["plugin"] if p["class"] == "ui")
    return line.group(1).replace("token=***", f"token={ui['settings']['token']}")


def tag_of(lines: list[str]) -> str:
    m = next(m for line in lines if (m := re.search(r"namespace erni-([0-9a-f]{4})\)", line)))
    return m.group(1)


def namespaces(tag: str) -> list[str]:
    return [n for n in netns._namespaces() if n.startswith(f"erni-{tag}")]


@pytest.mark.netns
@pytest.mark.slow
def test_a_user_tasks_the_far_robot_from_another_terminal_opens_the_gui_and_ctrl_c_removes_everything(tmp_path):
    proc, lines = launch(tmp_path, "--robots", "3")
    tag = tag_of(lines)
    try:
        text = "\n".join(lines)
        via = re.search(r"erni task --via (\S+)", text).group(1)
        url = gui_url(text)
        pids = [int(p) for p in re.findall(r"pid (\d+)", text)]
        assert url.startswith("http://127.0.0.1:")  # where the loopback tier has it: forwarded into the namespace
        with urllib.request.urlopen(url, timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        env = {**os.environ, "ERNI_IDENTITY": re.search(r"export ERNI_IDENTITY=(\S+)", text).group(1)}
        done = subprocess.run([sys.executable, "-m", "erni", "task", "--via", via, "robot3", "BotMotion", "turn",
                               "angle=30", "--wait"], capture_output=True, text=True, env=env, timeout=60)
        assert done.returncode == 0, done.stdout + done.stderr
        assert "succeeded" in done.stdout.lower()
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert namespaces(tag) == [] and not (netns.STATE_DIR / f"{tag}.json").exists()
    assert not [line for line in netns._ip("-o", "link", "show").splitlines() if f"erni{tag}m" in line]
    for pid in pids:  # every agent and daemon is gone
        assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text().lower()


@pytest.mark.netns
@pytest.mark.slow
def test_a_killed_launcher_leaves_nothing_running_and_netns_clean_removes_its_namespaces(tmp_path):
    proc, lines = launch(tmp_path, "--robots", "2", "--headless")
    tag = tag_of(lines)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)
    left = namespaces(tag)
    assert len(left) == 4  # the segment, two robots, the control node
    # agents and babeld die with the launcher: nothing keeps running in the orphaned namespaces
    wait_until(lambda: all(not netns._ip("netns", "pids", n, check=False).split() for n in left), timeout=15)
    done = subprocess.run([sys.executable, "-m", "erni", "sim", "--netns-clean"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0 and tag in done.stdout, done.stdout + done.stderr
    assert namespaces(tag) == [] and not (netns.STATE_DIR / f"{tag}.json").exists()


def test_without_root_it_refuses_and_says_how_to_run_without(monkeypatch, capsys):
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert main(["sim", "--netns", "--headless"]) == 2
    err = capsys.readouterr().err
    assert "need root" in err and "without --netns" in err and "\n" not in err.strip()


def test_without_babeld_it_names_the_package_to_install(monkeypatch, capsys):
    import shutil

    real = shutil.which
    monkeypatch.setattr(os, "geteuid", lambda: 0)
    monkeypatch.setattr(shutil, "which", lambda tool: None if tool == "babeld" else real(tool) or f"/usr/sbin/{tool}")
    assert main(["sim", "--netns"]) == 2
    err = capsys.readouterr().err
    assert "babeld not found" in err and "apt-get install babeld" in err and "without --netns" in err


def test_babel_without_netns_is_refused(capsys):
    assert main(["sim", "--mobinet", "babel", "--headless"]) == 2
    assert "add --netns" in capsys.readouterr().err
