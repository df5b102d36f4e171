"""A risky spoken command, or one the recogniser is unsure of, is read back and runs only on "yes";
any other unsure hearing is asked again;
every refused or unsure utterance gets one line, spoken (espeak-ng, written to a WAV) and
printed in the page's log, saying what was heard and what is expected. Typed commands run at
once. On a running team: the control node's UI plugin and simulated robots."""

from __future__ import annotations

import asyncio
import re
import shutil
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from erni.blackboard import Task
from erni.blackboard.testing import wait_until
from erni.plugins.ui.voice import Speaker
from tests.ui.team import Team, start_team
from tests.ui.test_operator_meaning import halted, tasks_on, typed
from tests.ui.test_server import of, talk

pytestmark = pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng is not installed")


@pytest.fixture(scope="module")
def team(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Team]:
    team = start_team(2)
    wav = tmp_path_factory.mktemp("voice") / "said.wav"
    team.ui.speaker = Speaker(extra_args=["-w", str(wav)]).start()  # the control node's voice, into a file
    yield team
    team.stop()


def heard(team: Team, text: str, *, unsure: bool = False) -> str:
    """Hand the UI an utterance as its recogniser does; return the line it answered, once it is printed."""
    since = time.time()
    team.ui._recognised("mic", text, unsure=unsure)
    prefix = f"voice: \u201c{text}\u201d \u2192 "
    line = wait_until(lambda: [ln["text"] for ln in team.ui.server.state()["log"]
                               if ln["t"] >= since and ln["text"].startswith(prefix)], timeout=10,
                      message=f"no answer to {text!r}")[0]
    return re.sub(r" \((robot\d+(, )?)+\)$", "", line[len(prefix):])  # the log names the robots too


def spoken(team: Team, say: str) -> None:
    assert team.ui.speaker is not None
    speaker = team.ui.speaker
    wait_until(lambda: say in speaker.spoken, timeout=20, message=f"{say!r} was not spoken")


def answered(team: Team) -> None:
    """Wait until the UI's run that answered the last utterance has committed: a marker handed to
    the plugin now runs in a later run (each run takes what was handed before it began), so any
    task that answer sent is on the control node's blackboard by then."""
    done = threading.Event()
    team.ui.later(lambda: team.ui.after_commit(done.set))
    assert done.wait(10), "the UI did not run again within 10 s"


def sent(team: Team, preposition: str) -> list[Task]:
    return [t for t in team.control.query(Task) if t.preposition == preposition]


def test_a_long_spoken_move_is_read_back_and_runs_only_on_yes(team):
    assert heard(team, "attention") == "Listening"
    say = heard(team, "robot one go forward fifty two metres")
    assert say == "Robot 1, go forward 52 metres \u2014 say yes to confirm"
    spoken(team, say)
    assert heard(team, "no") == "Not sent: robot 1, go forward 52 metres"
    answered(team)
    assert not sent(team, "forward")  # nothing went out
    assert heard(team, "robot one go forward fifty two metres").endswith("say yes to confirm")
    assert heard(team, "robot two where are you").startswith("Not sent: robot 1, go forward 52 metres. Robot 2 is at")
    assert heard(team, "yes") == ("I heard \u201cyes\u201d: Nothing to confirm; yes answers a read-back; say a command "
                                  "like robot 1 go forward 2 metres")
    assert not sent(team, "forward")
    assert heard(team, "robot one go forward fifty two metres").endswith("say yes to confirm")
    assert heard(team, "yes") == "Roger: robot 1, go forward 52 metres"
    forward = wait_until(lambda: tasks_on(team, "robot1", "forward"), timeout=10)[0]
    assert forward.params.distance == 52.0
    wait_until(lambda: (p := team.pose("robot1")) is not None and p.v > 0.1, timeout=10)
    assert heard(team, "robot one stop") == "Roger: robot 1, stop"
    halted(team, "robot1")


def test_a_command_to_several_robots_or_off_the_map_is_read_back_and_a_stop_never_waits(team):
    heard(team, "attention")
    assert heard(team, "everyone turn left ten degrees") == "Everyone, turn left 10 degrees \u2014 say yes to confirm"
    assert heard(team, "all stop") == "Roger: everyone, stop"  # at once, and the read-back is dropped
    assert heard(team, "yes").startswith("I heard \u201cyes\u201d: Nothing to confirm")
    assert not sent(team, "turn")
    # the arena's floor plan ends at x = 6
    assert heard(team, "robot two go to nine one").endswith("go to x 9, y 1 \u2014 say yes to confirm")
    assert heard(team, "cancel") == "Not sent: robot 2, go to x 9, y 1"
    # short and on the map: read back only for its numbers, as every spoken distance, angle or coordinate
    assert heard(team, "robot two go to one one") == "Did you say: robot 2, go to x 1, y 1? Say yes or no"
    assert heard(team, "yes") == "Roger: robot 2, go to x 1, y 1"
    wait_until(lambda: [t for t in tasks_on(team, "robot2", "goto") if t.done], timeout=20)


def test_a_spoken_number_is_read_back_and_a_command_without_one_runs_at_once(team):
    heard(team, "attention")
    assert heard(team, "robot two turn one hundred seventy degrees") == (
        "Did you say: robot 2, turn left 170 degrees? Say yes or no")
    assert heard(team, "no") == "Not sent: robot 2, turn left 170 degrees"
    assert not [t for t in sent(team, "turn") if t.destination == "robot2" and t.params.angle == 170]
    assert heard(team, "robot two turn left") == "Roger: robot 2, turn left 90 degrees"  # no number heard
    wait_until(lambda: [t for t in tasks_on(team, "robot2", "turn") if t.done], timeout=20)
    team.ui.spoken.read_back_numbers = False  # `read_back_numbers = false` in the UI's settings
    try:
        assert heard(team, "robot two turn right fifteen degrees") == "Roger: robot 2, turn right 15 degrees"
    finally:
        team.ui.spoken.read_back_numbers = True


def test_a_confident_clear_to_two_robots_is_read_back_and_runs_only_on_yes(team):
    """The real-time check heard "robots 1 and 2 turn right 90 degrees" as this, sure of it, and sent it."""
    heard(team, "attention")
    say = heard(team, "robots one and two clear please")
    assert say == "Robots 1 and 2, clear your behaviours \u2014 say yes to confirm"
    spoken(team, say)
    answered(team)
    assert not sent(team, "clear")
    assert heard(team, "yes") == "Roger: robots 1 and 2, clear your behaviours"
    for name in ("robot1", "robot2"):
        wait_until(lambda name=name: tasks_on(team, name, "clear"), timeout=10, message=f"{name} got no clear")
    assert heard(team, "robot two teleport to one one") == "Robot 2, teleport to x 1, y 1 \u2014 say yes to confirm"
    assert heard(team, "everybody stop") == "Roger: everyone, stop"  # at once; the teleport is not sent
    assert heard(team, "yes").startswith("I heard \u201cyes\u201d: Nothing to confirm")
    assert not sent(team, "teleport")


def test_a_typed_move_off_the_map_is_confirmed_once(team):
    """Typed on the page, a move that would end off the arena's floor plan waits for one "yes"."""
    assert typed(team, "robot 1 go forward 100 meters") == [
        "Robot 1, go forward 100 metres \u2014 it ends off the map (x -4 to 6, y -4 to 4.5); type yes to confirm"]
    answered(team)
    assert not [t for t in sent(team, "forward") if t.params.distance == 100]
    assert typed(team, "yes", "yes") == ["Roger: robot 1, go forward 100 metres",
                                         "Nothing to confirm; yes answers a read-back"]
    wait_until(lambda: [t for t in tasks_on(team, "robot1", "forward") if t.params.distance == 100], timeout=10)
    assert typed(team, "robot 1 stop") == ["Roger: robot 1, stop"]
    halted(team, "robot1")


def test_typed_commands_run_at_once(team):
    assert typed(team, "everyone turn left 10 degrees") == ["Roger: everyone, turn left 10 degrees"]
    turns = wait_until(lambda: len(t := [t for t in sent(team, "turn") if t.done and t.params.angle == 10]) == 2 and t,
                       timeout=15)
    assert {t.destination for t in turns} == {"robot1", "robot2"}


def test_an_unsure_hearing_is_read_back_or_asked_again_and_nothing_moves(team):
    heard(team, "attention")
    before = len(team.control.query(Task))
    say = heard(team, "robot one go forward two metres", unsure=True)
    assert say == "Did you say: robot 1, go forward 2 metres? Say yes or no"
    spoken(team, say)
    assert heard(team, "no") == "Not sent: robot 1, go forward 2 metres"
    say = heard(team, "robot one go to the kitchen", unsure=True)
    assert say == "Say again? I heard \u201crobot one go to the kitchen\u201d, but I am not sure"
    spoken(team, say)
    say = heard(team, "robot one go forward fifty two metres")
    assert heard(team, "yes", unsure=True) == (
        "Say again? I heard \u201cyes\u201d, but I am not sure; robot 1, go forward 52 metres not sent")
    assert heard(team, "yes").startswith("I heard \u201cyes\u201d: Nothing to confirm")
    answered(team)
    assert len(team.control.query(Task)) == before
    assert heard(team, "halt", unsure=True).startswith("Roger: ")  # a stop acts however it was heard


@pytest.mark.parametrize("text,say", [
    ("robot one go forward", "I heard \u201crobot one go forward\u201d: How far? Say a distance, like forward 2 metres"),
    ("robot nine turn left", "I heard \u201crobot nine turn left\u201d: I don't know robot 9; I know robots 1 and 2"),
    ("robot one fly", "I heard \u201crobot one fly\u201d: I didn't understand fly; say a command like robot 1 go "
                      "forward 2 metres"),
    ("please", "I heard \u201cplease\u201d: I didn't hear a command; say a command like robot 1 go forward 2 metres"),
    ("robot one set speed to five", "I heard \u201crobot one set speed to five\u201d: 5 metres per second is too fast; "
                                    "at most 2"),
    ("no", "I heard \u201cno\u201d: Nothing to say no to; say a command like robot 1 go forward 2 metres"),
])
def test_every_refused_utterance_gets_one_spoken_and_printed_line_saying_what_was_heard_and_expected(team, text, say):
    heard(team, "attention")
    before = len(team.control.query(Task))
    assert heard(team, text) == say
    spoken(team, say)
    answered(team)
    assert len(team.control.query(Task)) == before


def test_the_voice_wrote_what_it_said(team):
    assert team.ui.speaker is not None and team.ui.speaker.failures == 0
    assert Path(team.ui.speaker.args[-1]).stat().st_size > 1000


def test_the_page_is_told_a_read_back_awaits_an_answer(team):
    heard(team, "attention")
    url = f"ws://127.0.0.1:{team.ui.server.port}/ws?token={team.ui.server.token}"
    speak = threading.Timer(0.5, lambda: team.ui._recognised("mic", "robot two go forward six metres"))
    speak.start()
    msgs = asyncio.run(talk(url, [{"type": "ping"}], lambda m: of(m, "reply")))
    speak.join()
    reply = of(msgs, "reply")[0]
    assert (reply["text"], reply["channel"], reply["asked"]) == (
        "Robot 2, go forward 6 metres \u2014 say yes to confirm", "voice", True)
    assert heard(team, "no") == "Not sent: robot 2, go forward 6 metres"
