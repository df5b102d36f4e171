"""An acknowledgement means durable: a task an agent acknowledged survives a kill -9 of that agent.

The control node runs as a real agent process with a SQLite journal; command-line clients' real
endpoints (role cli, identities of the test team) keep 100 tasks in flight to it; the moment a
client hears an acknowledgement the test kills the agent with SIGKILL, starts it again from its
config and journal, and the clients' retries carry on. Six rounds; then every task whose
acknowledgement a client heard must be in the journal.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from erni.blackboard import Task
from erni.blackboard.testing import wait_until
from erni.transport.endpoint import CLIENT_ROLE, Endpoint
from erni.transport.identity import load_identity
from tests.transport.helpers import free_port, identity

ROOT = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.fault, pytest.mark.slow]


def _config(tmp_path: Path, port: int) -> Path:
    config = tmp_path / "control.toml"
    config.write_text(f"""
[agent]
name = "control"
workers = 2
journal = "{tmp_path / 'control.sqlite'}"

[[plugin]]
class = "transport"
[plugin.settings]
listen = "127.0.0.1:{port}"
identity = "{identity('control')}"
discovery_port = 0
""")
    return config


class Control:
    """The control node's process, started again from the same config and journal after each kill."""

    def __init__(self, config: Path, log: Path):
        self.config, self.log = config, log
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, port: int) -> None:
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "erni", "agent", str(self.config)], cwd=ROOT,
                                         stdout=out, stderr=subprocess.STDOUT)
        proc = self.proc

        def up() -> bool:
            """Its TCP port takes connections: the transport is up."""
            assert proc.poll() is None, f"the control node exited:\n{self.log.read_text()[-2000:]}"
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            except OSError:
                return False
            return True

        wait_until(up, timeout=30, interval=0.05, message="the control node did not start within 30 s")

    def kill9(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)

    def wait(self) -> None:
        if self.proc is not None:
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def test_no_acknowledged_task_is_lost_across_six_kill_9s_with_100_in_flight(tmp_path):
    port = free_port()
    control = Control(_config(tmp_path, port), tmp_path / "control.log")
    control.start(port)
    # four clients on one host: after a restart each needs a hint that its session is gone, and the
    # agent sends a host two a second
    clients = [Endpoint(f"cli{i}", identity=load_identity(identity(f"cli{i}", CLIENT_ROLE)), senders=1,
                        role=CLIENT_ROLE, ttl=120.0, ack_timeout=0.5, connect_timeout=0.2) for i in range(4)]
    lock = threading.Lock()
    uid_of: dict[str, str] = {}  # message id -> task uid
    acked: set[str] = set()  # task uids whose acknowledgement a client heard
    kill_at: list[int] = []  # kill the control node when this many of the round's tasks are acknowledged
    round_acked = [0]

    def on_delivered(addr, mid) -> None:
        with lock:
            uid = uid_of.get(mid)
            if uid is None or uid in acked:
                return
            acked.add(uid)
            round_acked[0] += 1
            if kill_at and round_acked[0] == kill_at[0]:
                kill_at.clear()
                control.kill9()  # at once: the task just acknowledged must already be durable

    try:
        for c in clients:
            c.on_delivered = on_delivered
            c.start()
        target = ("127.0.0.1", port)
        for rnd in range(6):
            with lock:
                round_acked[0] = 0
                kill_at[:] = [10 + 13 * rnd]  # a different point of the round each time
            for i in range(100):  # 25 per client: each client's queue keeps its tasks in flight
                client = clients[i % len(clients)]
                task = Task(uid=f"r{rnd}-t{i:03d}", verb="BotMotion", preposition="stop", source=client.name,
                            destination="control")
                with lock:
                    uid_of[client.send(target, "task.add", task, reliable=True)] = task.uid
            with contextlib.suppress(AssertionError):  # said below
                wait_until(lambda: not kill_at, timeout=60)
            assert not kill_at, f"round {rnd}: only {round_acked[0]} tasks acknowledged in 60 s"
            control.wait()
            control.start(port)
            with contextlib.suppress(AssertionError):
                wait_until(lambda: round_acked[0] >= 100, timeout=60, interval=0.05)
            assert round_acked[0] == 100, f"round {rnd}: {round_acked[0]} of 100 tasks acknowledged after the restart"
    finally:
        for c in clients:
            c.stop()
        control.stop()
    db = sqlite3.connect(tmp_path / "control.sqlite")
    try:
        kept = {row[0] for row in db.execute("SELECT uid FROM objects WHERE type = 'Task'")}
    finally:
        db.close()
    lost = sorted(acked - kept)
    assert len(acked) == 600
    assert not lost, f"{len(lost)} of 600 acknowledged tasks lost across 6 kill -9s: {lost[:10]}"
