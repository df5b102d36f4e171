"""The GUI's outbound state as types (`protocol.Picture` and the events): the same JSON the page read
when it was a hand-built dict, field names the page's JavaScript reads, and numbers that are finite
whatever a Pose holds."""

from __future__ import annotations

import json
import math
import re
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from erni.blackboard import AllocationResult, NetInfo, Pose, TaskState
from erni.blackboard.agent import Agent
from erni.blackboard.schemas import Peer
from erni.blackboard.testing import wait_until
from erni.blackboard.world import Link, Neighbor
from erni.plugins.ui import UIPlugin
from erni.plugins.ui.dialogue import tasks_for
from erni.plugins.ui.grammar import STANDARD_ACTIONS, strategies
from erni.plugins.ui.protocol import (
    CancelTaskMsg,
    ErrorMsg,
    HelloMsg,
    LinkRow,
    LogLine,
    Metrics,
    Picture,
    PongMsg,
    PoseRow,
    ReplyMsg,
    RobotRow,
    SelectOut,
    SpeechState,
    TaskRow,
)
from erni.plugins.ui.server import page_json
from erni.testing import ManualClock, agent_with

APP_JS = (Path(__file__).parents[2] / "plugins" / "ui" / "static" / "app.js").read_text()
WALL = 1_700_000_000.0


@pytest.fixture
def scene(monkeypatch) -> Iterator[tuple[Agent, UIPlugin, dict[str, Any]]]:
    """A control node's UI with three robots (one warning, one with a Pose no validator checked holding
    NaN and infinity, one known only as a lost peer), two links (one stale), a running task, a task
    cancelled from the page and the log they left; and the picture of it as the page got it before the
    picture was typed (the JSON of the hand-built dict, written out here)."""
    monkeypatch.delenv("VOSK_MODEL_PATH", raising=False)
    clock = ManualClock(wall_start=WALL)  # never advanced: every stamp the picture shows is WALL
    agent = agent_with(UIPlugin, settings={"listen": "127.0.0.1:0", "speak": False, "verb": "BotMotion",
                                           "recogniser": "vosk", "rate_hz": 50},
                       name="control", plugin_name="ui", clock=clock)
    ui: UIPlugin = agent.plugins[0]  # type: ignore[assignment]
    goto = tasks_for("goto", {"x": 1.0, "y": 2.0}, ["robot1"], verb="BotMotion", source="control")[0]
    goto = goto.evolve(created=WALL - 2)
    fwd = tasks_for("forward", {"distance": 1.5}, ["robot2"], verb="BotMotion", source="control")[0]
    fwd = fwd.evolve(created=WALL - 1, result=AllocationResult(
        state=TaskState.RUNNING, progress=0.5, message="half way", stamp=WALL,
        values={"moved": True, "d": 0.25, "path": [1, 2], "name": "x"}))
    with agent:
        with agent.transaction() as tx:
            tx.add(Pose(robot="robot1", x=1.23456, y=-2.0, theta=0.5, v=0.123, w=0.0, battery=11.04,
                        stall_left=True, stamp=WALL))
            tx.add(Pose.model_construct(uid="pose:robot2", robot="robot2", x=math.nan, y=math.inf, theta=0.25,
                                        v=-math.inf, w=0.0, battery=math.nan, sonar=[], stamp=WALL,
                                        stall_left=False, stall_right=False, bumpers=0, motors_enabled=True))
            tx.add(Peer(uid="peer:robot3", name="robot3", role="robot", up=False, address="127.0.0.1:9"))
            tx.add(NetInfo(node="robot1", kind="neighbors", stamp=WALL,
                           neighbors=[Neighbor(name="robot2", quality=0.8)],
                           links=[Link(a="robot1", b="robot3", quality=0.5)]))
            tx.add(goto)
            tx.add(fwd)
        wait_until(lambda: len(ui.server.state().get("tasks", [])) == 2, timeout=10)  # type: ignore[arg-type]
        ui._from_page("page1", CancelTaskMsg(type="cancel_task", uid=fwd.uid))  # as the server hands it over
        wait_until(lambda: any(t["state"] == "cancelled" for t in ui.server.state()["tasks"]),  # type: ignore[index,union-attr]
                   timeout=10)
        error = ui.speech_error
        assert error  # vosk with no model: the page says why the microphone is off
        before = {
            "agent": "control", "verb": "BotMotion", "actions": list(STANDARD_ACTIONS), "strategies": strategies(),
            "speech": {"available": False, "error": error, "recogniser": ""},
            "listening": False,
            "robots": [
                {"name": "robot1", "number": 1, "up": True, "state": "warn", "reasons": ["battery 11.0 V", "stalled"],
                 "pose": {"x": 1.235, "y": -2.0, "theta": 0.5, "v": 0.12, "w": 0.0, "battery": 11.0},
                 "address": "", "task": "goto x=1.0 y=2.0"},
                {"name": "robot2", "number": 2, "up": True, "state": "ok", "reasons": [],
                 "pose": {"x": None, "y": None, "theta": 0.25, "v": None, "w": 0.0, "battery": None},
                 "address": "", "task": ""},
                {"name": "robot3", "number": 3, "up": False, "state": "lost", "reasons": [], "pose": None,
                 "address": "127.0.0.1:9", "task": ""},
            ],
            "links": [{"a": "robot1", "b": "robot2", "quality": 0.8, "stale": False},
                      {"a": "robot1", "b": "robot3", "quality": 0.5, "stale": True}],
            "floorplan": None,
            "metrics": {"robots": 3, "up": 2, "links": 1, "mean_quality": 0.8, "components": 2,
                        "articulation_points": [], "degree": 0.67, "network_known": True},
            "tasks": [
                {"uid": fwd.uid, "robot": "robot2", "verb": "BotMotion", "preposition": "forward",
                 "text": "forward distance=1.5", "params": {"distance": 1.5, "speed": 0.3}, "source": "control",
                 "created": WALL - 1, "state": "cancelled", "progress": 0.5, "message": "cancelled from the GUI",
                 "values": {"moved": True, "d": 0.25, "name": "x"}},
                {"uid": goto.uid, "robot": "robot1", "verb": "BotMotion", "preposition": "goto",
                 "text": "goto x=1.0 y=2.0", "params": {"x": 1.0, "y": 2.0, "speed": 0.3, "tolerance": 0.1}, "source": "control",
                 "created": WALL - 2, "state": "pending", "progress": 0.0, "message": "", "values": {}},
            ],
            "log": [
                {"t": WALL, "level": "info", "text": "control node control serving the GUI; tasks go as BotMotion"},
                {"t": WALL, "level": "warn", "text": error},
                {"t": WALL, "level": "warn", "text": "robot3 is not heard"},
                {"t": WALL, "level": "dim", "text": "robot2: forward cancelled \u2014 cancelled from the GUI"},
            ],
        }
        # the cancel's log line may come a run after the cancelled row: let the page's state settle on it
        # (should it never, the test's comparisons say how it differs)
        try:
            wait_until(lambda: ui.server.state() == before, timeout=10)
        except AssertionError:
            pass
        yield agent, ui, before


def test_the_typed_picture_is_the_json_the_page_got_before(scene):
    _, ui, before = scene
    picture = ui.snapshot()
    assert isinstance(picture, Picture)
    assert json.loads(json.dumps(ui.picture(), allow_nan=False)) == before  # strict JSON: no NaN to turn into null
    assert ui.picture() == before == ui.server.state()
    assert Picture.model_validate_json(picture.model_dump_json()) == picture
    with urllib.request.urlopen(ui.url.replace("/?", "/api/state?"), timeout=10) as r:
        assert json.loads(r.read()) == before  # what /api/state serves
    assert picture.robots[1].pose == PoseRow(x=None, y=None, theta=0.25, v=None, w=0.0, battery=None)


def test_a_pose_that_is_not_finite_goes_as_null_and_the_server_needs_no_null_walk(scene):
    """The page read NaN (sent as null by the server's JSON writer) as "position unreadable": the typed
    row holds None, so the state is JSON without the server's slow walk, and the page shows the same."""
    _, ui, _ = scene
    nulled: list[bool] = []
    text = page_json({"type": "state", **ui.picture()}, lambda: nulled.append(True))
    assert not nulled and json.loads(text)["robots"][1]["pose"]["x"] is None
    assert ui.server.non_finite == 0


# -- the names the page reads ---------------------------------------------------------------------


def _function(name: str) -> str:
    """The body of a top-level `function name(...)` of app.js (up to the next line starting a statement)."""
    found = re.search(rf"^function {name}\(.*?(?=^\S)", APP_JS, re.S | re.M)
    assert found, f"app.js has no function {name}"
    return found.group(0)


def _reads(body: str, var: str) -> set[str]:
    """The properties read right off `var` (`r.pose.x` reads `pose` off r; `pose.x` is read off r.pose)."""
    return set(re.findall(rf"(?<![\w.]){re.escape(var)}\.([A-Za-z_]\w*)", body))


# (function of app.js, the variable in it, the type that variable holds)
READS: list[tuple[str, str, type[BaseModel]]] = [
    ("checkedRobot", "r", RobotRow), ("checkedRobot", "p", PoseRow), ("checked", "s", Picture),
    ("checked", "l", LinkRow), ("checked", "t", TaskRow), ("render", "s", Picture), ("render", "r", RobotRow),
    ("render", "r.pose", PoseRow), ("render", "s.speech", SpeechState), ("learnRobotKinds", "s", Picture),
    ("learnRobotKinds", "r", RobotRow), ("learnRobotKinds", "t", TaskRow), ("renderMetrics", "m", Metrics),
    ("renderMetrics", "s", Picture), ("renderMap", "s", Picture), ("renderMap", "l", LinkRow),
    ("renderMap", "r.pose", PoseRow), ("renderMap", "a.pose", PoseRow), ("renderMap", "b.pose", PoseRow),
    ("renderRobotTable", "s", Picture), ("renderRobotTable", "r", RobotRow), ("renderRobotTable", "r.pose", PoseRow),
    ("renderStrategies", "s", Picture), ("renderTasks", "s", Picture), ("renderTasks", "t", TaskRow),
    ("renderLog", "s", Picture), ("renderLog", "l", LogLine), ("fit", "s", Picture), ("onReply", "m", ReplyMsg),
]
EVENTS: list[type[BaseModel]] = [HelloMsg, ReplyMsg, SelectOut, ErrorMsg, PongMsg]
# fields the page does not read, and why they are sent all the same
UNREAD = {
    (Picture, "actions"): "the grammar's actions: the page's buttons are its own, /api/state tells a script",
    (TaskRow, "created"): "the server sorts the task list by it, newest first",
    (ReplyMsg, "asked"): "a read-back awaits an answer: for a script on the WebSocket",
    (SpeechState, "recogniser"): "which recogniser runs (vosk, pocketsphinx): for /api/state readers",
}


@pytest.mark.parametrize(("function", "var", "kind"), READS, ids=[f"{f}:{v}" for f, v, _ in READS])
def test_what_the_page_reads_off_a_value_is_a_field_of_its_type(function, var, kind):
    reads = _reads(_function(function), var)
    assert reads, f"{function} reads nothing off {var}: the table of this test is out of date"
    assert reads <= set(kind.model_fields), (f"app.js {function} reads {sorted(reads - set(kind.model_fields))} "
                                              f"off {var}, which {kind.__name__} has not")


def test_what_the_page_reads_off_a_message_is_a_field_of_some_message():
    reads = _reads(_function("onMessage"), "m")
    fields = set().union(*(set(k.model_fields) for k in EVENTS), {"type"})
    assert reads and reads <= fields, sorted(reads - fields)
    assert set(re.findall(r'm\.type === "(\w+)"', _function("onMessage"))) == \
        {k.model_fields["type"].default for k in EVENTS} - {"pong"} | {"state"}


def test_every_field_sent_is_read_by_the_page_or_said_why_not():
    read_anywhere = set(re.findall(r"\.([A-Za-z_]\w*)", APP_JS)) | set(re.findall(r'"(\w+)"', APP_JS))
    for kind in {k for _, _, k in READS} | set(EVENTS):
        for name in kind.model_fields:
            if (kind, name) in UNREAD:
                assert not re.search(rf"\.{name}\b", APP_JS), f"app.js reads {kind.__name__}.{name} now: drop it from UNREAD"
                continue
            assert name in read_anywhere, f"{kind.__name__}.{name} is sent but app.js never reads it"


# -- numbers whatever a Pose holds ----------------------------------------------------------------

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=200, deadline=None)
@given(x=ANY_FLOAT, y=ANY_FLOAT, theta=ANY_FLOAT, v=ANY_FLOAT, w=ANY_FLOAT, battery=st.none() | ANY_FLOAT)
def test_any_pose_gives_a_picture_that_is_strict_json(x, y, theta, v, w, battery):
    row = PoseRow.of(x, y, theta, v, w, battery)
    for got, given_ in zip((row.x, row.y, row.theta, row.v, row.w, row.battery), (x, y, theta, v, w, battery)):
        assert (got is None) == (given_ is None or not math.isfinite(given_))  # a number, or no number: null
        assert got is None or math.isfinite(got)
    picture = Picture(
        agent="control", verb="BotMotion", actions=[], strategies=[], listening=True,
        speech=SpeechState(available=False, error="", recogniser=""),
        robots=[RobotRow(name="robot1", number=1, up=True, state="ok", reasons=[], pose=row, address="", task="")],
        links=[], floorplan=None, tasks=[], log=[],
        metrics=Metrics(robots=1, up=1, links=0, mean_quality=None, components=1, articulation_points=[],
                        degree=0, network_known=False))
    text = json.dumps(picture.model_dump(mode="json"), allow_nan=False)
    assert Picture.model_validate_json(text) == picture
