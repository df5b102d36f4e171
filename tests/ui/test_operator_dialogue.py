"""The dialogue's rules for what an operator means, without a team: going to a robot puts several
robots apart and short of it, a read-back expires, what is read back when spoken (several robots, a
clear, a teleport, a deployment; never a stop) and confirmed when typed (a move off the map or beyond
`confirm_beyond`), a new cruise speed stays within its bounds, "cancel that" names what it cancels."""

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


def spoken(verb: str = "BotMotion") -> Dialogue:
    """The spoken dialogue with the UI's defaults, but no read-back of numbers: what is read back here is
    read back for its kind, not for a number in it."""
    return Dialogue(Naming(), verb=verb, read_back=5.0, read_back_numbers=False)


@pytest.mark.parametrize("text,asked", [
    # the real-time check's confident mishearing of "robots 1 and 2 turn right 90 degrees"
    ("robots one and two clear please", "Robots 1 and 2, clear your behaviours"),
    ("robots 1 and 2 turn right 90 degrees", "Robots 1 and 2, turn right 90 degrees"),
    ("everyone cancel everything", "Everyone, cancel your tasks"),
    ("robots 1 and 2 random walk", "Robots 1 and 2, random walk"),
    ("robots 1 and 2 avoid obstacles off", "Robots 1 and 2, stop avoiding obstacles"),
    ("robots 2 and 3 faster", "Robots 2 and 3, faster"),
])
def test_a_spoken_command_to_several_robots_is_read_back_however_sure_the_hearing(text, asked):
    d = spoken()
    reply = d.hear(text, TEAM)
    assert (reply.say, reply.tasks, reply.asked) == (f"{asked} \u2014 say yes to confirm", [], True)
    assert d.memory.speeds == {}  # a cruise speed too waits for the yes
    done = d.hear("yes", TEAM)
    assert done.say is not None and done.say.startswith(f"Roger: {asked[0].lower()}{asked[1:]}"), done.say
    assert len({t.destination for t in done.tasks}) >= 2 or set(d.memory.speeds) == {"robot2", "robot3"}
    d.hear(text, TEAM)
    assert d.hear("no", TEAM).say == f"Not sent: {asked[0].lower()}{asked[1:]}"


def test_a_spoken_stop_is_never_read_back_and_drops_a_read_back_waiting():
    d = spoken()
    assert d.hear("robots one and two clear please", TEAM).asked
    stop = d.hear("robots one and two stop", TEAM)
    assert (stop.say, stop.asked, {t.destination for t in stop.tasks}) == (
        "Roger: robots 1 and 2, stop", False, {"robot1", "robot2"})
    assert d.hear("yes", TEAM).say == "Nothing to confirm; yes answers a read-back"
    assert not d.hear("everybody stop", TEAM).asked


def test_several_robots_by_their_sticky_targets_are_read_back_too():
    d = spoken()
    d.select(["robot1", "robot2"])  # picked on the page
    assert d.hear("turn left", TEAM).say == "Robots 1 and 2, turn left 90 degrees \u2014 say yes to confirm"


@pytest.mark.parametrize("text,asked", [
    ("robot 1 clear", "Robot 1, clear your behaviours"),
    ("robot 1 cancel everything", "Robot 1, cancel your tasks"),  # BotMotion: a clear
    ("robot 1 teleport to 1 1", "Robot 1, teleport to x 1, y 1"),
    ("robot 1 spread out", "Robot 1, spread out"),
    ("robot 1 cover 1 1", "Robot 1, cover x 1, y 1"),
    ("robot 4 relay between robot 1 and robot 3", "Robot 4, relay between robot 1 and robot 3"),
    ("robot 1 patrol from 0 0 to 2 2", "Robot 1, patrol from 0, 0 to 2, 2"),
])
def test_a_spoken_clear_teleport_or_deployment_is_read_back_for_one_robot_too(text, asked):
    d = spoken()
    reply = d.hear(text, TEAM)
    assert (reply.say, reply.tasks) == (f"{asked} \u2014 say yes to confirm", [])
    done = d.hear("yes", TEAM)
    assert [t.destination for t in done.tasks] == [f"robot{text.split()[1]}"]


def test_a_spoken_command_to_one_robot_that_ends_its_tasks_or_moves_it_a_little_runs_at_once():
    d = spoken("RemoteBotMotion")
    for text in ("robot 1 cancel", "robot 1 turn left", "robot 1 go forward 2 metres", "robot 1 set speed 0.2",
                 "robot 1 go to robot 2"):
        reply = d.hear(text, TEAM)
        assert reply.say is not None and reply.say.startswith("Roger: robot 1"), (text, reply.say)
    assert d.hear("cancel that", TEAM).say.startswith("Roger: cancelled")  # withdraws: never waits


def test_a_spoken_cruise_speed_for_several_robots_re_sends_what_runs_when_yes_is_said():
    d = spoken()
    walk = d.hear("robot 2 random walk", TEAM).tasks
    assert d.hear("robots 2 and 3 slower", TEAM).asked
    done = d.hear("yes", TEAM, running=[])  # the walk has ended meanwhile: it is not started again
    assert (done.tasks, done.withdraw, d.memory.speeds) == ([], [], {"robot2": 0.2, "robot3": 0.2})
    assert d.hear("robots 2 and 3 faster", TEAM).asked
    again = d.hear("yes", TEAM, running=walk)  # still running: re-sent at the new speed
    assert [(t.preposition, t.destination, t.params.speed) for t in again.tasks] == [("randomwalk", "robot2", 0.3)]
    d.memory.speeds.update({"robot2": 2.0, "robot3": 2.0})
    assert d.hear("robots 2 and 3 faster", TEAM).say.startswith("Already at the fastest")  # refused, not asked


BOUNDS = (-4.0, -4.0, 6.0, 4.5)  # tests/ui/arena.toml


def typed(**kw: object) -> Dialogue:
    """The typed dialogue as the UI makes it: the floor plan's bounds and `confirm_beyond`'s default."""
    return Dialogue(Naming(), verb="BotMotion", **{"area": BOUNDS, "confirm_beyond": 10.0, **kw})  # type: ignore[arg-type]


def test_a_typed_move_that_would_leave_the_map_is_confirmed_once():
    d = typed()
    asked = d.hear("robot 1 go forward 100 meters", TEAM)  # robot 1 at the origin, heading east
    assert (asked.say, asked.tasks, asked.asked) == (
        "Robot 1, go forward 100 metres \u2014 it ends off the map (x -4 to 6, y -4 to 4.5); type yes to confirm",
        [], True)
    done = d.hear("yes", TEAM)
    assert (done.say, [t.params.distance for t in done.tasks]) == ("Roger: robot 1, go forward 100 metres", [100.0])
    assert d.hear("yes", TEAM).say == "Nothing to confirm; yes answers a read-back"  # once
    for text, why in [("robot 1 go back 5 metres", "it ends off the map"), ("robot 1 go to 9 0", "it ends off the map"),
                      ("robot 5 teleport to -5 0", "it ends off the map"),
                      ("robot 1 patrol from 0 0 to 7 2", "it ends off the map"),
                      ("robot 1 drive at 0.2", "it drives until stopped")]:
        reply = d.hear(text, TEAM)
        assert reply.asked and not reply.tasks and why in (reply.say or ""), (text, reply.say)
        assert d.hear("no", TEAM).say.startswith("Not sent: ")


def test_a_typed_move_on_the_map_runs_at_once():
    team = {"robot1": RobotView("robot1", x=-4.0, y=3.0, theta=0.0), "robot2": RobotView("robot2", x=-1.5, y=3.0,
                                                                                          theta=0.0)}
    d = Dialogue(Naming(), verb="RemoteBotMotion", area=(-8.0, -4.0, 8.0, 10.0), confirm_beyond=10.0)  # erni sim's world
    # tests/sim/test_stop_matrix.py's typed motions, from its robots' start
    for text in ("robot 1 turn left 360 degrees", "robot 2 go back 2 meters", "robot 1 go forward 3 meters",
                 "robot 1 go forward 11 meters", "robots 1 and 2 go to 7 9", "everyone random walk"):
        reply = d.hear(text, team)
        assert reply.say is not None and reply.say.startswith("Roger: ") and reply.tasks, (text, reply.say)
    assert d.hear("everybody stop", team).say == "Roger: everyone, stop"


def test_where_the_map_cannot_tell_a_typed_move_longer_than_the_bound_is_confirmed():
    d = typed(area=None)
    assert d.hear("robot 1 go forward 10 meters", TEAM).say == "Roger: robot 1, go forward 10 metres"
    assert d.hear("robot 1 go forward 10.5 meters", TEAM).say == (
        "Robot 1, go forward 10.5 metres \u2014 more than 10 metres; type yes to confirm")
    assert d.hear("robot 1 go to 12 0", TEAM).asked
    assert d.hear("no", TEAM).say == "Not sent: robot 1, go to x 12, y 0"
    assert d.hear("robot 1 go to 3 4", TEAM).say == "Roger: robot 1, go to x 3, y 4"
    lost = {"robot1": RobotView("robot1")}  # no pose yet: the floor plan cannot place a forward's end
    assert typed().hear("robot 1 go forward 20 meters", lost).asked
    assert typed().hear("robot 1 go forward 9 meters", lost).tasks
    unbounded = typed(area=None, confirm_beyond=math.inf)  # `confirm_beyond = 0`: no bound on distance
    assert unbounded.hear("robot 1 go forward 100 meters", TEAM).tasks
    assert unbounded.hear("robot 1 drive at 0.2", TEAM).asked  # a held velocity still leaves any map
    assert Dialogue(Naming()).hear("robot 1 go forward 100 meters", TEAM).tasks  # no confirm_beyond: at once


def test_the_typed_bound_is_a_setting_with_a_default():
    from erni.plugins.ui.plugin import UISettings

    assert UISettings().confirm_beyond == 10.0
    assert UISettings(confirm_beyond=0).confirm_beyond == 0
    with pytest.raises(ValueError, match="confirm_beyond"):
        UISettings(confirm_beyond=-1)


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
