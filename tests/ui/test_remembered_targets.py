"""A typed command that names no robot goes to the robots last named only when they were named, or answered
about, in the exchange just before, and the answer names them; older than that the dialogue asks and sends
nothing until "yes". A stop never asks. Through the real `Dialogue`, as the console makes it."""

from __future__ import annotations

import pytest

from erni.plugins.ui.dialogue import Dialogue, Naming, RobotView

TEAM = {f"robot{i}": RobotView(f"robot{i}", x=float(i), y=0.0, theta=0.0) for i in (1, 2, 3)}


def typed(**kw: object) -> Dialogue:
    """The console's dialogue."""
    return Dialogue(Naming(), verb="RemoteBotMotion", confirm_remembered=True, confirm_beyond=10.0,
                    **kw)  # type: ignore[arg-type]


def test_a_command_right_after_the_robot_was_named_acts_and_names_it():
    d = typed()
    assert d.hear("robot 3 go forward 1 metre", TEAM).tasks
    reply = d.hear("clear", TEAM)
    assert reply.say == "Roger: robot 3, clear your behaviours"
    assert [(t.destination, t.preposition) for t in reply.tasks] == [("robot3", "clear")]


def test_clear_long_after_the_robot_was_named_is_asked_and_sends_nothing_until_yes():
    d = typed()
    d.hear("robot 3 go forward 1 metre", TEAM)
    d.hear("how many robots", TEAM)  # an exchange that mentions no robot
    asked = d.hear("clear", TEAM)
    assert asked.tasks == [] and asked.asked
    assert asked.say == ("Robot 3: clear your behaviours? No robot named; robot 3 was named 2 commands ago "
                         "\u2014 type yes to confirm, or name the robots")
    done = d.hear("yes", TEAM)
    assert done.say == "Roger: robot 3, clear your behaviours"
    assert [(t.destination, t.preposition) for t in done.tasks] == [("robot3", "clear")]
    # the "yes" named robot 3 again: the next command acts on it at once
    assert d.hear("turn left", TEAM).say == "Roger: robot 3, turn left 90 degrees"


def test_a_no_sends_nothing_and_the_question_does_not_make_the_robot_fresh():
    d = typed()
    d.hear("robot 3 go forward 1 metre", TEAM)
    d.hear("robot 9 turn left", TEAM)  # refused: an exchange about another robot
    assert d.hear("clear", TEAM).asked
    no = d.hear("no", TEAM)
    assert (no.say, no.tasks) == ("Not sent: robot 3, clear your behaviours", [])
    again = d.hear("clear", TEAM)
    assert again.asked and again.tasks == [] and "robot 3 was named 4 commands ago" in (again.say or "")


def test_naming_the_robot_acts_at_once_however_long_ago():
    d = typed()
    d.hear("robot 3 go forward 1 metre", TEAM)
    for _ in range(3):
        d.hear("how many robots", TEAM)
    assert d.hear("robot 3 clear", TEAM).say == "Roger: robot 3, clear your behaviours"
    assert d.hear("everyone turn left", TEAM).say == "Roger: everyone, turn left 90 degrees"


def test_a_status_answer_about_the_remembered_robot_counts_as_naming_it():
    d = typed()
    d.hear("robot 2 go forward 1 metre", TEAM)
    d.hear("how many robots", TEAM)
    assert d.hear("where are you", TEAM).say == "Robot 2 is at x 2.0, y 0.0, heading 0 degrees"
    assert d.hear("random walk", TEAM).say == "Roger: robot 2, random walk"


def test_a_cruise_speed_for_robots_named_long_ago_is_asked_too():
    d = typed()
    d.hear("robots 1 and 2 go forward 1 metre", TEAM)
    d.hear("how many robots", TEAM)
    asked = d.hear("set speed 0.2", TEAM)
    assert asked.asked and asked.tasks == [] and asked.say.startswith(
        "Robots 1 and 2: cruise speed 0.2 metres per second? No robot named; robots 1 and 2 were named")
    assert d.memory.speeds == {}
    assert d.hear("yes", TEAM).say.startswith("Roger: robots 1 and 2, cruise speed 0.2")
    assert d.memory.speeds == {"robot1": 0.2, "robot2": 0.2}


@pytest.mark.parametrize("stop,to", [("stop", ["robot3"]), ("everyone stop", ["robot1", "robot2", "robot3"])])
def test_a_stop_is_never_asked_and_drops_a_waiting_question(stop, to):
    d = typed()
    d.hear("robot 3 go forward 1 metre", TEAM)
    d.hear("how many robots", TEAM)
    d.hear("how many robots", TEAM)
    assert d.hear("clear", TEAM).asked
    reply = d.hear(stop, TEAM)
    assert reply.stop and sorted(t.destination for t in reply.tasks) == to
    assert d.hear("yes", TEAM).tasks == []  # the question went with the stop


def test_a_stop_with_no_robot_ever_named_goes_to_everyone_at_once():
    reply = typed().hear("stop", TEAM)
    assert reply.say == "Roger: everyone, stop" and len(reply.tasks) == 3


def test_without_confirm_remembered_the_last_targets_are_used_as_before():
    d = Dialogue(Naming())
    d.hear("robot 3 go forward 1 metre", TEAM)
    d.hear("how many robots", TEAM)
    assert d.hear("clear", TEAM).say == "Roger: robot 3, clear your behaviours"


def test_a_typed_move_far_beyond_a_sensible_length_is_asked():
    d = typed()
    asked = d.hear("robot 1 go forward 100 meters", TEAM)
    assert asked.tasks == [] and asked.say == ("Robot 1, go forward 100 metres \u2014 more than 10 metres; "
                                               "type yes to confirm")
    assert d.hear("robot 1 stop", TEAM).tasks  # a stop acts at once and drops the question
    assert d.hear("yes", TEAM).tasks == []
