"""A stop over a flapping link: the control node's stop reaches robots whose link comes and goes,
and they halt and stay halted with every motion task cancelled.

The team's transports are real (UDP/TCP on loopback, sessions, acknowledgements and retries); the
flapping link is the transport's inbound filter dropping every frame between the control node and
the flapping robots for 0.5 s out of every second, on both sides, as a radio at the edge of its
range does.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from erni.blackboard import Task
from erni.blackboard.testing import wait_until
from erni.transport.plugin import TransportPlugin
from tests.ui.team import Team, start_team
from tests.ui.test_two_tier import say

MISSION = {"network_aware": False, "audio": False}


@pytest.fixture
def team() -> Iterator[Team]:
    team = start_team(3, mission=MISSION)
    yield team
    team.stop()


class Flapper:
    """Cuts the link between the control node and `robots` for `down` s out of every `period` s."""

    def __init__(self, team: Team, robots: set[str], down: float = 0.5, period: float = 1.0) -> None:
        self.robots, self.down, self.period = robots, down, period
        self.cut = False
        self.cuts = 0
        self._stop = threading.Event()
        for agent in [team.control, *team.robots]:
            for plugin in agent.plugins:
                if isinstance(plugin, TransportPlugin):
                    me = agent.name
                    plugin.endpoint.inbound_filter = lambda sender, role, me=me: self.allows(me, sender)
        self._thread = threading.Thread(target=self._run, name="flapper", daemon=True)

    def allows(self, me: str, sender: str) -> bool:
        if not self.cut:
            return True
        return not ((me == "control" and sender in self.robots) or (me in self.robots and sender == "control"))

    def _run(self) -> None:
        while not self._stop.is_set():
            self.cut = True
            self.cuts += 1
            self._stop.wait(self.down)
            self.cut = False
            self._stop.wait(self.period - self.down)
        self.cut = False

    def __enter__(self) -> Flapper:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)


def moving(team: Team, robot: str) -> bool:
    p = team.pose(robot)
    return p is not None and (abs(p.v) > 0.05 or abs(p.w) > 0.1)


def halted(team: Team, robot: str) -> bool:
    p = team.pose(robot)
    return p is not None and abs(p.v) < 0.01 and abs(p.w) < 0.02


def test_everybody_stop_over_a_flapping_link_halts_every_robot_and_cancels_every_motion(team):
    since = time.time()
    assert say(team, "robot 1 turn left 360 degrees")["text"].startswith("Roger")  # BotMotion straight to the robot
    assert say(team, "robot 2 go back 2 meters")["text"].startswith("Roger")      # BotMotion
    # RemoteBotMotion, MissionControl's job; from robot 3's start (x -1.5, heading west) it would end off the
    # arena's floor plan (x -4.5): confirmed once
    assert say(team, "robot 3 go forward 3 meters")["text"].endswith("type yes to confirm")
    assert say(team, "yes")["text"] == "Roger: robot 3, go forward 3 metres"
    robots = ["robot1", "robot2", "robot3"]
    wait_until(lambda: all(moving(team, r) for r in robots), timeout=10, message="the robots did not all start")
    with Flapper(team, set(robots)) as flapper:
        wait_until(lambda: flapper.cut, timeout=30)
        sent = time.monotonic()  # the stop is said while the link is down
        assert say(team, "everybody stop")["text"] == "Roger: everyone, stop"
        # each robot halts while the link still flaps: the stop's frames are retried until acknowledged.
        # That the stop halted them, before any motion ended on its own (the turn takes 8 s), is told
        # by every motion task ending cancelled (below), not by a time: this wait is for progress
        wait_until(lambda: all(halted(team, r) for r in robots), timeout=30,
                   message="not every robot halted under the flapping link")
        took = time.monotonic() - sent
        flaps = flapper.cuts
        # the link keeps flapping, two cuts and two returns more; nothing resumes
        wait_until(lambda: flapper.cuts >= flaps + 3, timeout=30, message="the link stopped flapping")
        assert all(halted(team, r) for r in robots), [team.pose(r) for r in robots]
        assert flapper.cuts >= 3
    for robot in robots:
        tasks = wait_until(lambda r=robot: (ts := [t for t in team.control.query(Task) if t.destination == r
                                                     and t.created >= since and t.preposition not in
                                                     ("cancel", "stop", "avoid_obstacles")])
                           and all(t.done for t in ts) and ts, timeout=15,
                           message=f"the motion tasks of {robot} were not reported ended")
        for t in tasks:
            assert t.state.value == "cancelled", (robot, t.preposition, t.result)
    print(f"\nstop over a flapping link (0.5 s down in every second): every robot standing {took:.2f} s after it "
          f"was said")
