"""No silent loss: a full disk makes an agent refuse work instead of losing it, and say so;
finished tasks leave both ends after the retention; nothing waits forever on a dead peer."""

from __future__ import annotations

import errno
import sqlite3
import subprocess
from pathlib import Path

import pytest

from erni.blackboard import Agent, Peer, Pose, Task, TaskState
from erni.blackboard.testing import wait_until
from erni.transport.plugin import TransportPlugin
from erni.transport.tasking import Received
from tests.transport.helpers import HeldClock, auth_settings, free_port, make_agent


@pytest.fixture
def small_disk(tmp_path):
    """A real 4 MiB file system (tmpfs) that the test can fill up."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mount)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip()}): the full-disk test needs root")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(path: Path) -> Path:
    """Write a file until the disk is full."""
    filler = path / "filler"
    with filler.open("wb", buffering=0) as f:  # unbuffered: nothing left to fail when it is closed
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError as err:
            assert err.errno == errno.ENOSPC
    return filler


def journal_rows(path: Path) -> dict[str, str]:
    db = sqlite3.connect(path)
    try:
        return dict(db.execute("SELECT uid, type FROM objects").fetchall())
    finally:
        db.close()


def robot_with_journal(name: str, port: int, journal: Path, delay: float = 0.05, **settings) -> Agent:
    agent = Agent(name, workers=2, journal=journal)
    agent.add_plugin("transport", settings={**auth_settings(name), "discovery_port": port,
                                            "beacon_period": 0.1, "peer_timeout": 0.6, **settings},
                     name="transport")
    agent.add_plugin("echo", settings={"verbs": ["BotMotion"], "delay": delay}, name="motion")
    return agent.start()


def send(control: Agent, dest: str, distance: float) -> Task:
    task = Task(verb="BotMotion", preposition="forward", params={"distance": distance}, source="control",
                destination=dest)
    with control.transaction() as tx:
        tx.add(task)
    return task


def final(agent: Agent, task: Task, timeout: float = 5.0) -> Task:
    return wait_until(lambda: (t := agent.blackboard.get(task.uid)) is not None and t.done and t, timeout=timeout)


@pytest.mark.parametrize("talking", [False, True], ids=["quiet", "sharing its Pose"])
def test_a_full_disk_makes_the_agent_refuse_tasks_and_say_so_then_recover(small_disk, talking):
    """The control node learns that robot1 refuses tasks from robot1's beacons, also while robot1
    shares its Pose with it (a peer that gets statuses gets no beacons, unless what they say changed)."""
    import threading

    port = free_port()
    journal = small_disk / "robot1.sqlite"
    control = make_agent("control", port, echo=False, role="control")
    robot = robot_with_journal("robot1", port, journal)
    stop = threading.Event()

    def walk() -> None:
        pose = Pose(robot="robot1")
        with robot.transaction() as tx:
            tx.add(pose)
        while not stop.wait(0.01):
            pose = pose.evolve(x=pose.x + 0.01)
            with robot.transaction() as tx:
                tx.change(pose)

    walker = threading.Thread(target=walk, daemon=True)
    if talking:
        walker.start()
    try:
        wait_until(lambda: (p := control.blackboard.get("peer:robot1")) is not None and p.up)
        before = send(control, "robot1", 1.0)
        assert final(control, before).state is TaskState.SUCCEEDED
        filler = fill(small_disk)
        peer = wait_until(lambda: (p := control.blackboard.get("peer:robot1")).degraded and p, timeout=5)
        assert "disk full" in peer.degraded and peer.up
        refused = [send(control, "robot1", 2.0 + i) for i in range(5)]
        for task in refused:
            result = final(control, task).result
            assert result.state is TaskState.FAILED and result.message.startswith("refused by robot1: disk full")
        assert not any(robot.blackboard.contains(t.uid) for t in refused), "nothing acknowledged, nothing kept"
        filler.unlink()  # the operator makes room
        wait_until(lambda: not control.blackboard.get("peer:robot1").degraded, timeout=5)
        after = send(control, "robot1", 9.0)
        assert final(control, after).state is TaskState.SUCCEEDED
        assert robot.journal.flush()
        rows = journal_rows(journal)
        assert before.uid in rows and after.uid in rows and not any(t.uid in rows for t in refused)
        if talking:
            assert control.blackboard.get("pose:robot1").x >= 0.03  # it was talking all along
    finally:
        stop.set()
        if talking:
            walker.join(2)
        control.stop()
        robot.stop()


def test_a_write_that_fails_is_kept_in_memory_retried_and_never_silent(small_disk, caplog):
    """The disk fills between the check and the write: the rows wait in memory, one line says so."""
    journal = small_disk / "r1.sqlite"
    agent = Agent("r1", journal=journal)
    agent.start()
    try:
        filler = fill(small_disk)
        big = [Task(verb="BotMotion", preposition="say", source="me",
                    params={"tones": [[10, 60]] * 20}).with_result(TaskState.RUNNING, message="x" * 20_000)
               for _ in range(50)]
        with agent.transaction() as tx:
            for task in big:
                tx.add(task)
        assert not agent.journal.flush(), "flush says the rows are not on disk"
        assert "journal write failed" in agent.degraded
        assert caplog.text.count("journal write failed") == 1, "one line when it starts failing"
        filler.unlink()
        wait_until(lambda: not agent.journal.failed, timeout=5)  # retried every second
        assert "journal writes again" in caplog.text
        assert len(journal_rows(journal)) == len(big)
    finally:
        agent.stop()


def test_finished_tasks_leave_both_ends_after_the_retention(tmp_path):
    port = free_port()
    control = Agent("control", workers=2, journal=tmp_path / "control.sqlite", retention=0.5)
    control.add_plugin("transport", settings={**auth_settings("control"), "discovery_port": port,
                                              "beacon_period": 0.1, "peer_timeout": 0.6}, name="transport")
    control.start()
    robot = Agent("robot1", workers=2, journal=tmp_path / "robot1.sqlite", retention=0.5)
    robot.add_plugin("transport", settings={**auth_settings("robot1"), "discovery_port": port,
                                            "beacon_period": 0.1, "peer_timeout": 0.6}, name="transport")
    robot.add_plugin("echo", settings={"verbs": ["BotMotion"], "delay": 0.0}, name="motion")
    robot.start()
    try:
        wait_until(lambda: (p := control.blackboard.get("peer:robot1")) is not None and p.up)
        tasks = [send(control, "robot1", 1.0 + i) for i in range(200)]
        wait_until(lambda: all((t := control.blackboard.get(x.uid)) is None or t.done for x in tasks), timeout=20)
        # a removed task's receipt goes in the transport's next window, after the task itself
        wait_until(lambda: not any(a.query(Task) or a.query(Received) for a in (control, robot)), timeout=10)
        assert control.journal.flush() and robot.journal.flush()
        for agent, name in ((control, "control"), (robot, "robot1")):
            rows = journal_rows(tmp_path / f"{name}.sqlite")
            assert rows == {}, f"{name} journal keeps {len(rows)} finished rows"
            bridge = agent.plugin("transport")
            for memory in ("tasks_out", "tasks_in"):  # one record per task sent or received
                assert not getattr(bridge, memory), f"{name} remembers {memory}"
        assert control.retention.removed == 200  # the robot's copies went by its retention or the requester's cancel
    finally:
        control.stop()
        robot.stop()


def test_a_task_on_a_peer_that_died_fails_with_link_lost_within_its_deadline():
    """Timed on the control node's clock, held once the robot's last frame is heard: the task
    fails after its 1 s link deadline, counted from that frame, and at the first look after it."""
    port = free_port()
    clock = HeldClock()
    control = make_agent("control", port, echo=False, role="control", link_deadline=1.0, clock=clock)
    robot = make_agent("robot1", port, echo=False)
    try:
        wait_until(lambda: (p := control.blackboard.get("peer:robot1")) is not None and p.up)
        task = send(control, "robot1", 1.0)
        wait_until(lambda: robot.blackboard.contains(task.uid))
        bridge = control.plugin("transport")
        looks, runs = [0], [0]
        check, execute = bridge._check_links, bridge.execute

        def counted_check() -> None:
            looks[0] += 1
            check()

        def counted_execute() -> None:
            execute()
            runs[0] += 1  # over: what the run changed is committed

        bridge._check_links, bridge.execute = counted_check, counted_execute
        held = clock.hold()
        wait_until(lambda: bridge.peers["robot1"].heard_at == held, timeout=30)
        robot.stop()  # it dies for good

        def looked_after(seconds: float) -> None:
            """Move the control node's clock on by more than a beacon period (0.1 s: a run falls
            due) and wait for a look at the silence in a run that is over."""
            n, r = looks[0], runs[0]
            clock.advance(seconds)
            wait_until(lambda: looks[0] > n and runs[0] > r, timeout=30)

        looked_after(0.9)  # 0.9 s since the last frame: within the deadline
        assert not control.blackboard.get(task.uid).done
        looked_after(0.2)  # 1.1 s: past it
        result = control.blackboard.get(task.uid).result
        assert result.state is TaskState.FAILED, result
        assert result.message == "link lost: robot1 not heard for 1 s (link_deadline 1 s)"
    finally:
        control.stop()
        robot.stop()


def test_a_peer_back_within_the_deadline_goes_on_and_one_back_late_is_told_to_stop(tmp_path, monkeypatch):
    port = free_port()
    control = make_agent("control", port, echo=False, role="control", link_deadline=2.5)
    robot = robot_with_journal("robot1", port, tmp_path / "robot1.sqlite", delay=60.0)
    listen = "{}:{}".format(*robot.plugin("transport").address)
    bridge = control.plugin("transport")
    assert isinstance(bridge, TransportPlugin)
    looks: list[float] = []  # when the control node looked at its links, in runs that have committed
    check = bridge._check_links

    def looked() -> None:
        at = bridge.clock()
        check()
        bridge.after_commit(lambda: looks.append(at))

    def robot1_up() -> bool:
        peer = control.blackboard.get("peer:robot1")
        return isinstance(peer, Peer) and peer.up

    monkeypatch.setattr(bridge, "_check_links", looked)
    try:
        wait_until(robot1_up)
        task = send(control, "robot1", 1.0)
        wait_until(lambda: robot.blackboard.contains(task.uid))
        robot.stop()
        wait_until(lambda: not robot1_up(), timeout=5)  # seen gone
        left = bridge.peers["robot1"].heard_at  # its last frame before it went
        robot = robot_with_journal("robot1", port, tmp_path / "robot1.sqlite", delay=60.0, listen=listen)
        wait_until(robot1_up, timeout=5)  # back in time: the task goes on
        # and goes on past the deadline counted from when it left: the deadline runs from the last frame
        wait_until(lambda: looks and looks[-1] > left + 2.5 + 0.1, timeout=10)
        assert not control.blackboard.get(task.uid).done, "a peer back within the deadline keeps its task"
        robot.stop()
        assert final(control, task, timeout=6).result.message.startswith("link lost")  # away too long
        robot = robot_with_journal("robot1", port, tmp_path / "robot1.sqlite", delay=60.0, listen=listen)
        assert robot.blackboard.contains(task.uid), "it comes back with the task (from its journal)"
        wait_until(lambda: not robot.blackboard.contains(task.uid), timeout=5)  # and is told to drop it
    finally:
        control.stop()
        robot.stop()
