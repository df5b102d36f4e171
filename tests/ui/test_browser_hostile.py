"""Hostile values inside trusted traffic, as the operator's page meets them, in headless Chromium.

- robot2's own key sends its Pose with x NaN and y Infinity inside its authenticated session (a
  sealed data frame on the real UDP socket): the control node refuses it, `/api/state` stays JSON,
  and the page shows every robot.
- A state that holds one robot the page cannot draw (a number the server could not send, a pose
  beyond any map, an object missing its fields): the server never emits a non-JSON value, and the
  page shows that robot as faulty and draws the rest.
"""

from __future__ import annotations

import json
import math
import os
import urllib.request
from collections.abc import Iterator
from typing import Any

import pytest

from erni.blackboard import Pose
from erni.blackboard.testing import wait_until
from erni.plugins.ui.server import WebServer
from erni.transport.wire import head_bytes, item_bytes, join_envelope
from tests.ui.team import Team, start_team

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt install chromium)")


@pytest.fixture(scope="module")
def team() -> Iterator[Team]:
    team = start_team(2)
    yield team
    team.stop()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


def strict_json(text: str) -> Any:
    """JSON as a browser's JSON.parse reads it: NaN and Infinity are no JSON."""
    def refuse(token: str) -> Any:
        raise ValueError(f"{token} is not JSON")
    return json.loads(text, parse_constant=refuse)


def api_state(url: str) -> Any:
    with urllib.request.urlopen(url.replace("/?token=", "/api/state?token="), timeout=10) as answer:
        return strict_json(answer.read().decode())


def open_page(browser: Any, url: str) -> tuple[Any, list[str]]:
    page = browser.new_page(viewport={"width": 1400, "height": 850})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    return page, errors


def send_hostile_pose(team: Team, seq: int) -> None:
    """robot2's transport, with its own session to the control node, seals a status no ERNI sender
    writes: its Pose with x NaN and y Infinity (a newer seq than any it sent)."""
    robot2 = next(a for a in team.robots if a.name == "robot2")
    endpoint = robot2.plugin("transport").endpoint  # type: ignore[attr-defined]
    control = team.transport.address
    session = endpoint.session_with(control)
    assert session is not None, "robot2 has no session with the control node"
    body = (b'{"uid":"pose:robot2","robot":"robot2","x":NaN,"y":Infinity,"theta":0.0,"v":0.0,"w":0.0,'
            b'"battery":12.0,"stall_left":false,"stall_right":false,"bumpers":0,"motors_enabled":true,'
            b'"sonar":[],"stamp":' + str(9e9).encode() + b"}")
    payload = join_envelope(head_bytes("robot2", "robot", session.peer, endpoint.inst, endpoint.address),
                            item_bytes(seq, f"hostile{seq}", "status", "Pose", body))
    endpoint.send_udp(session.seal(payload, 65536), control)


def test_a_robot_keys_pose_of_nan_and_infinity_is_refused_and_the_page_shows_every_robot(team, browser):
    dropped = team.transport.endpoint.counters.get("dropped.parse", 0)
    for seq in (10**9, 10**9 + 1, 10**9 + 2):
        send_hostile_pose(team, seq)
    wait_until(lambda: team.transport.endpoint.counters.get("dropped.parse", 0) >= dropped + 3, timeout=10,
               message=f"the control node did not refuse robot2's hostile Pose: {team.transport.endpoint.counters}")
    poses = {p.robot: p for p in team.control.query(Pose)}
    assert all(math.isfinite(v) for p in poses.values() for v in (p.x, p.y, p.theta)), poses
    state = api_state(team.ui.url)  # strict JSON: a NaN would raise
    assert {r["name"] for r in state["robots"]} == {"robot1", "robot2"}
    page, errors = open_page(browser, team.ui.url)
    try:
        page.wait_for_selector('g.robot[data-name="robot1"]', timeout=20000)
        page.wait_for_selector('g.robot[data-name="robot2"]', timeout=20000)
        assert page.is_hidden("#no-robots")
        assert page.locator("#robot-table tbody tr").count() == 2
    finally:
        page.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


def _robot(name: str, number: int, pose: Any, **extra: Any) -> dict[str, Any]:
    return {"name": name, "number": number, "up": True, "state": "ok", "reasons": [], "pose": pose,
            "address": "127.0.0.1:1", "task": "", **extra}


def _pose(x: float, y: float, theta: float = 0.0) -> dict[str, Any]:
    return {"x": x, "y": y, "theta": theta, "v": 0.0, "w": 0.0, "battery": 12.0}


def test_a_robot_the_page_cannot_draw_is_shown_faulty_and_the_rest_stays(team, browser):
    """Published straight to a web server (a real one, on its own port) beside a real picture of the
    team: the first robot is good, each of the others carries what no validated Pose holds."""
    picture = team.ui.picture()
    picture["robots"] = [
        _robot("robot1", 1, _pose(1.0, 2.0)),
        _robot("robot2", 2, _pose(math.nan, math.inf)),  # Python floats json.dumps would write as NaN
        _robot("robot3", 3, _pose(1e308, -1e308)),  # finite, but no screen holds it
        {"name": "robot4", "pose": "somewhere"},  # missing its fields, a pose that is no object
        _robot("robot5", 5, {"x": "1", "y": None}),
    ]
    server = WebServer("127.0.0.1", 0, token="hostile-test-token", on_message=lambda c, m: None,
                       on_audio=lambda c, b: None, on_close=lambda c: None).start()
    try:
        server.publish(picture)
        state = api_state(server.url)  # strict JSON: the server never sends NaN or Infinity
        assert state["robots"][1]["pose"]["x"] is None and state["robots"][1]["pose"]["y"] is None
        page, errors = open_page(browser, server.url)
        try:
            page.wait_for_selector('g.robot[data-name="robot1"]', timeout=20000)
            page.wait_for_selector('#robot-table tbody tr[data-name="robot5"]', timeout=20000)
            assert page.is_hidden("#no-robots")
            rows = page.locator("#robot-table tbody tr")
            assert rows.count() == 5
            states = {rows.nth(i).get_attribute("data-name"): rows.nth(i).get_attribute("data-state")
                      for i in range(5)}
            assert states == {"robot1": "ok", "robot2": "fault", "robot3": "fault", "robot4": "fault",
                              "robot5": "fault"}
            assert page.locator("g.robot").count() == 1  # only what can be drawn is drawn
            title = page.get_attribute('#robot-table tbody tr[data-name="robot2"] .name', "title") or ""
            assert "position unreadable" in title
        finally:
            page.close()
        assert not errors, f"JavaScript errors on the page: {errors}"
    finally:
        server.stop()
