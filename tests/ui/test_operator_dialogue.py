"""The dialogue's rules for what an operator means, without a team: going to a robot puts several
robots apart and short of it, a read-back expires, a new cruise speed stays within its bounds,
"cancel that" names what it cancels."""

from __future__ import annotations

import itertools
import math

import pytest

from erni.plugins.ui.dialogue import APART, SHORT, Dialogue, Naming, RobotView, quantities

TEAM = {f"robot{i}": RobotView(f"robot{i}", x=float(x), y=float(y), theta=0.0)
        for i, (x, y) in enumerate([(0, 0), (3, 0), (3, 0.2), (3, -0.2), (-2, 1)], start=1)}


def test_several_robots_going_to_one_stop_short_of_it_and_apart():
    d = Dialogue(Naming(), verb="BotMotion")
    reply = d.hear("everyone come to robot one", TEAM)
    assert reply.say == "Roger: robots 2, 3, 4 and 5, go to robot 1"
    goals = {t.destination: (t.params.x, t.params.y) for t in reply.tasks}
    assert sorted(goals) == ["robot2", "robot3", "robot4", "robot5"]
    for g in goals.values():
        assert math.hypot(*g) >= SHORT - 0.01  # short of robot 1, at the origin
    for a, b in itertools.combinations(goals.values(), 2):
        assert math.hypot(a[0] - b[0], a[1] - b[1]) >= APART - 0.01
    assert math.hypot(*goals["robot5"]) == pytest.approx(SHORT, abs=0.01)  # alone on its side: just short


@pytest.mark.parametrize("text,say", [
    ("robot 1 go to robot 9", "I don't know robot 9; I know robots 1, 2, 3, 4, 5 and 6"),
    ("robot 1 go to robot 1", "Robot 1 is already there; name another robot to go to it"),
    ("robot 1 go to robot 6", "I don't know where robot 6 is now; say go to and a point, like go to 3 4"),
])
def test_going_to_a_robot_that_cannot_be_found_is_refused(text, say):
    team = {**TEAM, "robot6": RobotView("robot6")}  # no pose yet
    reply = Dialogue(Naming(), verb="BotMotion").hear(text, team)
    assert (reply.say, reply.tasks, reply.accepted) == (say, [], False)


def test_a_read_back_expires():
    d = Dialogue(Naming(), verb="BotMotion", read_back=5.0, read_back_timeout=0.0)
    assert d.hear("robot 1 go forward 6 metres", TEAM).say == "Robot 1, go forward 6 metres \u2014 say yes to confirm"
    late = d.hear("yes", TEAM)
    assert (late.say, late.tasks) == ("Too late: robot 1, go forward 6 metres was not sent; say it again", [])
    assert d.hear("robot 1 go forward 5 metres", TEAM).say == "Roger: robot 1, go forward 5 metres"  # at the bound


def test_what_ends_tasks_is_not_read_back_even_for_several_robots():
    d = Dialogue(Naming(), verb="BotMotion", read_back=5.0)
    assert d.hear("everyone turn left", TEAM).say.endswith("say yes to confirm")
    for text in ("everyone cancel everything", "robots 1 and 2 clear", "everybody halt"):
        reply = d.hear(text, TEAM)
        assert "Roger: " in reply.say and len(reply.tasks) >= 2, reply.say


@pytest.mark.parametrize("text,says", [
    ("robot 2 turn 180 degrees", True), ("robot two turn one hundred eighty degrees", True),
    ("robot one go forward point five metres", True), ("robot 1 go to x 3 y 4", True),
    ("robot 1 patrol from 1 2 to 3 4", True), ("robots one two and three go forward 2 metres", True),
    ("robot 1 turn left", False), ("robots one two and three stop", False), ("robot 2 go to robot 1", False),
    ("robot 3 relay between robot 1 and control node", False), ("everybody spread out", False),
])
def test_a_quantity_is_a_number_that_names_no_robot(text, says):
    assert quantities(text) is says


def test_a_spoken_number_is_read_back_and_a_typed_one_runs_at_once():
    spoken = Dialogue(Naming(), verb="BotMotion", read_back=5.0, read_back_numbers=True)
    typed = Dialogue(Naming(), verb="BotMotion")
    team = ["robot1", "robot2"]
    asked = spoken.hear("robot 2 turn 190 degrees", team)
    assert (asked.say, asked.tasks) == ("Did you say: robot 2, turn left 190 degrees? Say yes or no", [])
    assert [t.params.angle for t in spoken.hear("yes", team).tasks] == [190.0]
    assert spoken.hear("robot 2 turn right", team).tasks  # nothing to mishear: at once
    assert spoken.hear("robot 2 stop", team).tasks  # a stop never waits
    assert [t.params.angle for t in typed.hear("robot 2 turn 190 degrees", team).tasks] == [190.0]


def test_faster_and_slower_stay_within_the_cruise_speeds():
    d = Dialogue(Naming(), verb="BotMotion")
    assert d.hear("robot 1 set speed 2", TEAM).say == "Roger: robot 1, cruise speed 2 metres per second"
    assert d.hear("faster", TEAM).say == ("Already at the fastest cruise speed, 2 metres per second; say set speed "
                                          "to a number between 0.05 and 2")
    assert d.hear("robot 1 set speed 0.05", TEAM).accepted
    assert d.hear("slow down", TEAM).say.startswith("Already at the slowest cruise speed")
    assert d.hear("robot 1 set speed to 0", TEAM).say == ("A speed of 0 is not a cruise speed; say set speed to 0.3, "
                                                          "or stop")
    d.hear("robots 1 and 2 set speed 0.2", TEAM)
    assert d.hear("robot 2 faster", TEAM).say == "Roger: robot 2, faster, cruise speed 0.3 metres per second"
    reply = d.hear("robots 1 and 2 go forward 1", TEAM)
    assert reply.say == "Roger: robots 1 and 2, go forward 1 metre at their cruise speeds"
    assert [(t.destination, t.params.speed) for t in reply.tasks] == [("robot1", 0.2), ("robot2", 0.3)]


def test_cancel_that_names_what_it_cancels_and_then_there_is_nothing_left():
    d = Dialogue(Naming(), verb="BotMotion")
    walk = d.hear("robots 1 and 2 random walk", TEAM)
    assert d.hear("robot 3 status", TEAM).accepted
    cancel = d.hear("cancel that", TEAM)
    assert (cancel.say, cancel.tasks, cancel.withdraw) == ("Roger: cancelled robots 1 and 2, random walk", [],
                                                          [t.uid for t in walk.tasks])
    assert d.hear("undo", TEAM).say == "Nothing to cancel: no command carried out yet; to halt a robot say robot 1 stop"
    turn = d.hear("robot 1 turn left", TEAM)
    ended = d.hear("cancel that", TEAM, running=[])  # the front end has seen the turn end
    assert (ended.say, ended.withdraw) == ("Nothing to cancel: robot 1, turn left 90 degrees has ended", [])
    assert turn.tasks and d.hear("robot 2 cancel everything", TEAM).tasks[0].preposition == "clear"


def test_the_wake_words_are_configurable_and_reach_the_recogniser_s_grammar():
    from pydantic import ValidationError

    from erni.plugins.ui.jsgf import jsgf
    from erni.plugins.ui.plugin import UISettings

    d = Dialogue(Naming(), verb="BotMotion", listening=False, wake=("hello team",))
    assert not d.hear("attention", TEAM).say and not d.listening  # not a wake word here: ignored
    assert d.hear("hello team", TEAM).say == "Listening" and d.listening
    assert d.hear("robot 1 stop", TEAM).tasks  # and it is heard from then on
    settings = UISettings(wake=["hello team", "listen"])
    assert "hello team" in jsgf(wake=tuple(settings.wake))
    with pytest.raises(ValidationError, match="wake"):
        UISettings(wake=["Hey!"])
    assert UISettings().wake == ["attention", "wake up", "listen", "listen up"]
