"""Damaged data from an ARCOS robot (garbage, a truncated SIP, a sonar count of 255) is logged per
kind at most once per 10 s with counts, and shown in the robot's state and its tasks' results."""

from __future__ import annotations

import logging
from collections import deque
from typing import Any

from erni.blackboard import Agent, Pose, Task
from erni.blackboard.testing import wait_until
from erni.plugins.motion import arcos
from erni.plugins.motion.damage import LineDamage
from erni.plugins.motion.plugin import RobotMotionControl
from tests.motion.conftest import sim_only_because

SONAR_255 = arcos.frame(bytes([arcos.SIP_STOPPED]) + bytes(arcos._SIP_HEAD.size) + bytes([255]))
TRUNCATED = arcos.frame(bytes([arcos.SIP_MOVING, 1, 2, 3]))
GARBAGE = b"\x00\x13\x37 line noise \x99"


def test_the_first_damage_of_a_kind_is_logged_at_once_then_once_per_period_with_counts(caplog):
    now = [100.0]
    damage = LineDamage("robot1 (socket://x)", logging.getLogger("test.damage"), clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="test.damage"):
        damage.note("truncated_sip", detail="SIP of 4 bytes truncated")
        for _ in range(36):
            now[0] += 0.1
            damage.note("truncated_sip", detail="SIP of 5 bytes truncated")
        damage.note("garbage_bytes", 12)
        damage.flush()
        assert len(caplog.records) == 2  # one line per kind so far, however many came
        now[0] = 110.0
        damage.flush()
        now[0] = 115.0
        damage.flush()  # nothing new since the last line
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "robot1 (socket://x): damaged data from the robot: truncated SIPs: 1; last: SIP of 4 bytes truncated",
        "robot1 (socket://x): damaged data from the robot: bytes of garbage skipped: 12",
        "robot1 (socket://x): damaged data from the robot: truncated SIPs: 36 in the last 10 s, 37 in all; "
        "last: SIP of 5 bytes truncated",
    ]
    assert dict(damage.totals) == {"truncated_sip": 37, "garbage_bytes": 12}
    assert all(r.levelno == logging.WARNING for r in caplog.records)


@sim_only_because("injects damaged packets into the simulated robot's SIP stream")
def test_a_robot_sending_damaged_sips_is_logged_and_shown_in_its_state_and_results(make_host, caplog):
    host = make_host()
    agent = Agent("robot1", workers=2)
    plugin = agent.add_plugin(RobotMotionControl, settings={"url": host.url(), "model": "pioneer3",
                                                            "sync_timeout": 0.3}, name="motion")
    agent.start()
    try:
        wait_until(lambda: agent.query(Pose), timeout=5, message="no Pose published")
        firmware = host.firmware(0)
        bad = deque([GARBAGE, TRUNCATED, SONAR_255] * 3)
        send = firmware._send

        def damaged(body: bytes) -> None:  # on the simulator's thread: before a SIP, one damaged packet
            if bad and arcos.is_sip(body):
                firmware._out += bad.popleft()
            send(body)

        with caplog.at_level(logging.WARNING, logger="erni.motion.driver"):
            firmware._send = damaged  # type: ignore[method-assign]
            task = Task(verb="BotMotion", preposition="velocity", params={"v": 0.1}, source="test")
            with agent.transaction() as tx:
                tx.add(task)
            driver = plugin.resource.driver
            state: Any = wait_until(lambda: not bad and (s := driver.state) is not None
                                    and len(s.damage) == 3 and s.damage["bad_sonar_count"] == 3 and s,
                                    timeout=5, message="the damage was not counted")
            assert driver.connected
            with agent.transaction() as tx:
                tx.remove(task.uid)
                tx.add(Task(verb="BotMotion", preposition="stop", source="test"))
            stop = wait_until(lambda: next((t for t in agent.query(Task) if t.preposition == "stop"
                                            and t.done), None), timeout=5)
    finally:
        agent.stop()
    assert state.damage["truncated_sip"] == 3 and state.damage["garbage_bytes"] == 3 * len(GARBAGE)
    assert stop.result.values["line_damage"] == dict(state.damage)
    lines = [r.getMessage() for r in caplog.records if "damaged data" in r.getMessage()]
    assert len(lines) == 3, lines  # one per kind within 10 s, not one per packet
    prefix = f"robot1 ({host.url()}): damaged data from the robot: "
    assert any(ln.startswith(f"{prefix}bytes of garbage skipped: ") for ln in lines)  # as many as one read held
    assert f"{prefix}truncated SIPs: 1; last: packet 0x33: SIP of 4 bytes truncated; expected at least 20" in lines
    assert (f"{prefix}SIPs with a sonar count they do not carry: 1; "
            "last: packet 0x32: SIP announces 255 sonar readings but only 0 fit") in lines
