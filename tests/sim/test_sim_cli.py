"""`erni sim` as a user runs it: starts, reports the team up, and Ctrl-C leaves nothing behind."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def processes_mentioning(text: str) -> list[int]:
    """PIDs of processes whose command line contains `text` (this test's unique run directory)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in cmd and int(entry.name) != os.getpid():
            pids.append(int(entry.name))
    return pids


class SimProcess:
    """`erni sim` in its own session; always killed with everything it started, even on failure."""

    def __init__(self, run_dir: Path, *args: str, headless: bool = True) -> None:
        self.run_dir = run_dir
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "erni", "sim", *(["--headless"] if headless else []), "--run-dir", str(run_dir),
             *args],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.lines: list[str] = []
        self._heard = threading.Condition()  # notified on every line and at the end of the output
        self._ended = False
        self._reader = threading.Thread(target=self._read, name="sim-cli-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._heard:
                self.lines.append(line.rstrip("\n"))
                self._heard.notify_all()
        with self._heard:
            self._ended = True
            self._heard.notify_all()

    def wait_for(self, text: str, timeout: float) -> str:
        def found() -> str | None:
            return next((line for line in self.lines if text in line), None)

        with self._heard:
            self._heard.wait_for(lambda: found() is not None or self._ended, timeout)
            line = found()
        if line is not None:
            return line
        raise AssertionError(f"no line with {text!r} within {timeout} s; output:\n" + "\n".join(self.lines))

    def gui_url(self, timeout: float = 1.0) -> str:
        """The GUI's URL with its token. Its output is a pipe, not a terminal: the line shows the URL with
        `token=***` and names the config that holds the token (the ui plugin's `token`), read here."""
        import tomllib

        line = self.wait_for("  GUI ", timeout=timeout)
        masked = line.split("GUI", 1)[1].split()[0]
        assert masked.endswith("?token=***"), line
        config = self.run_dir / "agents" / "control.toml"
        assert str(config) in line, line
        ui = next(p for p in tomllib.loads(config.read_text())["plugin"] if p["class"] == "ui")
        return masked.replace("token=***", f"token={ui['settings']['token']}")

    def cleanup(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        for pid in processes_mentioning(str(self.run_dir)):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self._reader.join(10)


@pytest.fixture
def sim(tmp_path):
    started: list[SimProcess] = []

    def start(*args: str) -> SimProcess:
        p = SimProcess(tmp_path / "run", *args)
        started.append(p)
        return p

    yield start
    for p in started:
        p.cleanup()


def test_ctrl_c_stops_the_whole_team_and_frees_its_ports(sim, tmp_path):
    p = sim("--robots", "2", "--control-port", "0")
    p.wait_for("Ctrl-C stops the team", timeout=90)
    line = p.wait_for("erni peers --via", timeout=1)
    host, port = line.split("--via")[1].strip().split(":")
    agents = processes_mentioning(str(tmp_path / "run" / "agents"))
    assert len(agents) == 3  # two robots and the control node, each a real process
    p.proc.send_signal(signal.SIGINT)
    assert p.proc.wait(30) == 0
    p.wait_for("erni sim: stopped", timeout=5)
    assert processes_mentioning(str(tmp_path / "run")) == []
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, int(port)))  # the control node's port is free again


def test_duration_ends_the_run_with_exit_code_zero(sim):
    p = sim("--robots", "1", "--duration", "1", "--control-port", "0")
    assert p.proc.wait(90) == 0
    p.wait_for("duration reached", timeout=5)
    p.wait_for("team up in", timeout=1)


def test_bad_scenario_is_one_clear_line_and_exit_2(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[radio]\ncomm_range = -3\n[robots]\ncount = 2\n')
    out = subprocess.run([sys.executable, "-m", "erni", "sim", str(bad), "--headless"], cwd=ROOT,
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 2
    assert out.stderr.strip() == (f"erni sim: {bad}: radio.comm_range: Input should be greater than 0 "
                                  "(got -3)")
    out = subprocess.run([sys.executable, "-m", "erni", "sim", "no-such-scenario", "--headless"], cwd=ROOT,
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 2 and "no such scenario" in out.stderr and "Traceback" not in out.stderr


def test_scenario_tasks_and_failures_happen_on_time(sim, tmp_path):
    scenario = tmp_path / "s.toml"
    scenario.write_text(
        'name = "timed"\nduration = 5.0\n[robots]\ncount = 2\n'
        '[[task]]\nat = 0.0\nto = "robot1"\nverb = "BotMotion"\npreposition = "forward"\n'
        'params = { distance = 0.5, speed = 0.5 }\n'
        '[[failure]]\nat = 1.0\nrobot = "robot2"\n')
    p = sim(str(scenario), "--control-port", "0")
    assert p.proc.wait(90) == 0
    sent = p.wait_for("robot1: BotMotion forward", timeout=1)
    done = p.wait_for("robot1: succeeded", timeout=1)
    failed = p.wait_for("robot2 fails (agent killed)", timeout=1)
    assert float(sent.split("t=")[1].split()[0]) < 1.0
    assert float(failed.split("t=")[1].split()[0]) >= 1.0
    assert float(done.split("t=")[1].split()[0]) < 4.5
    assert processes_mentioning(str(tmp_path / "run")) == []


def test_the_status_line_says_when_the_simulated_robots_skip_sips():
    from erni.commands.sim import sips_note

    assert sips_note(0, 0) == ""
    assert sips_note(1000, 0) == "; SIPs on time 100.0%"
    assert sips_note(995, 5) == "; SIPs on time 99.5%"  # within 1 %: no alarm
    busy = sips_note(900, 100)
    assert busy.startswith("; SIPs on time 90.0% (100 of 1000 skipped: this machine is too busy")


def test_the_commands_find_a_running_sim_team_without_via_until_it_stops(sim, tmp_path, monkeypatch):
    runtime = tmp_path / "runtime"
    runtime.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))  # this test's runtime directory, for the sim and the commands
    for var in ("ERNI_IDENTITY", "ERNI_TEAM_KEY"):
        monkeypatch.delenv(var, raising=False)

    def erni(*args: str, typed: str = "", **env: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "erni", *args], env={**os.environ, **env}, cwd=ROOT,
                              input=typed, capture_output=True, text=True, timeout=60)

    p = sim("--robots", "1", "--control-port", "0")
    p.wait_for("Ctrl-C stops the team", timeout=90)
    named = p.wait_for("find this team without --via", timeout=1)
    files = list((runtime / "erni").glob("sim-*.json"))
    assert len(files) == 1 and str(files[0]) in named, named
    assert files[0].stat().st_mode & 0o777 == 0o600
    via = p.wait_for("erni peers --via", timeout=1).split("--via")[1].strip()
    peers = erni("peers", "--json")  # no --via, no identity: the sim's team, with the run's identity
    assert peers.returncode == 0, peers.stderr
    assert "robot1" in peers.stdout and "neither ERNI_IDENTITY" not in peers.stderr
    task = erni("task", "robot1", "BotMotion", "forward", "distance=0.1", "--wait")
    assert task.returncode == 0 and "succeeded" in task.stdout, task.stdout + task.stderr
    typed = erni("console", typed="robot 1 turn left 10 degrees\n")
    assert typed.returncode == 0 and "robot1: turn succeeded" in typed.stdout, typed.stdout + typed.stderr
    # credentials of another team: that team is looked for by its beacons, not this one
    other = erni("peers", ERNI_TEAM_KEY="another-team-key")
    assert other.returncode == 1 and "no beacon" in other.stderr
    p.proc.send_signal(signal.SIGINT)
    assert p.proc.wait(30) == 0
    assert not files[0].exists()  # gone with the team
    gone = erni("peers")
    assert gone.returncode == 1 and "no beacon" in gone.stderr and via not in gone.stdout
