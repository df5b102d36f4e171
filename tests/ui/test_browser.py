"""End to end in headless Chromium against a running team: a control agent (transport + UI) and
three robot agents driving simulated robots. The page must show the robots moving, task them
with the mouse and by typing, teleport by holding and dragging, and show lost robots and a lost
control node. Screenshots go to artifacts/ui/."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from playwright.sync_api import TimeoutError as PlaywrightTimeout

from erni.blackboard import Agent, Link, Neighbor, NetInfo, Pose, Task
from erni.blackboard.testing import wait_until
from erni.plugins.ui import UIPlugin
from tests.ui.team import Team, start_team, transport_settings

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]
ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts" / "ui"
NINE = "I don't know robot 9; I know robots 1, 2 and 3"

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt install chromium)")


@pytest.fixture(scope="module")
def team() -> Iterator[Team]:
    team = start_team(3)
    yield team
    team.stop()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser, team) -> Iterator[Any]:
    pg = browser.new_page(viewport={"width": 1400, "height": 850})
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.add_init_script("window.spoken = []; if (window.speechSynthesis) { const say = speechSynthesis.speak.bind("
                       "speechSynthesis); speechSynthesis.speak = (u) => { window.spoken.push(u.text); say(u); }; }")
    pg.goto(team.ui.url)
    pg.wait_for_selector('g.robot[data-name="robot3"]', timeout=30000)
    yield pg
    pg.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


def shot(pg: Any, name: str) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / f"{name}.png").write_bytes(pg.screenshot())  # written here: no executor thread in Playwright


def screen(pg: Any, x: float, y: float) -> tuple[float, float]:
    """Page coordinates of world point (x, y) on the map as the page draws it now."""
    return tuple(pg.evaluate("([x, y]) => { const r = document.getElementById('map').getBoundingClientRect();"
                             " const p = erni.toScreen(x, y); return [r.left + p[0], r.top + p[1]]; }", [x, y]))


def drawn(pg: Any, name: str) -> dict[str, Any]:
    """What the page draws for a robot: world position and state."""
    g = pg.locator(f'g.robot[data-name="{name}"]')
    return {"x": float(g.get_attribute("data-x")), "y": float(g.get_attribute("data-y")),
            "state": g.get_attribute("data-state")}


def own_pose(team: Team, name: str) -> Pose:
    pose = team.pose(name)
    assert pose is not None
    return pose


def settle(team: Team, name: str) -> None:
    wait_until(lambda: abs(own_pose(team, name).v) < 0.01 and abs(own_pose(team, name).w) < 0.02, timeout=20)


def say(pg: Any, text: str) -> str:
    pg.fill("#say-text", text)
    pg.press("#say-text", "Enter")
    pg.wait_for_function("t => document.querySelector('#last-reply .heard') && "
                         "document.querySelector('#last-reply .heard').textContent.includes(t)", arg=text)
    return pg.inner_text("#last-reply .said")


def test_page_shows_every_robot_and_follows_their_motion(team, page):
    for name in ("robot1", "robot2", "robot3"):
        p, d = own_pose(team, name), drawn(page, name)
        assert math.hypot(p.x - d["x"], p.y - d["y"]) < 0.05 and d["state"] == "ok"
    assert page.locator("#robot-table tbody tr").count() == 3
    assert page.inner_text("#conn-text") == "control node connected"
    x0 = drawn(page, "robot1")["x"]
    assert say(page, "robot 1 go forward 1 metre") == "Roger: robot 1, go forward 1 metre"
    page.wait_for_function("x0 => +document.querySelector('g.robot[data-name=robot1]').dataset.x > x0 + 0.3", arg=x0)
    page.wait_for_selector('#tasks .task[data-robot="robot1"][data-state="succeeded"]', timeout=20000)
    settle(team, "robot1")
    assert own_pose(team, "robot1").x == pytest.approx(x0 + 1.0, abs=0.08)
    page.wait_for_function("x => Math.abs(+document.querySelector('g.robot[data-name=robot1]').dataset.x - x) < 0.03",
                           arg=own_pose(team, "robot1").x)
    assert say(page, "robot 9 turn left") == NINE
    assert page.evaluate("window.spoken") == ["Roger: robot 1, go forward 1 metre", NINE]  # the browser says the replies
    page.uncheck("#speak-browser")
    say(page, "robot 8 turn left")
    assert page.evaluate("window.spoken") == ["Roger: robot 1, go forward 1 metre", NINE]
    shot(page, "01-team-moving")


def test_wheel_zooms_about_the_cursor_drag_pans_and_fit_shows_everyone(team, page):
    scale0 = page.evaluate("erni.ui.view.scale")
    anchor = screen(page, 0.5, 0.5)
    page.mouse.move(*anchor)
    page.mouse.wheel(0, -400)
    page.wait_for_function("s => erni.ui.view.scale > s * 1.1", arg=scale0)
    assert screen(page, 0.5, 0.5) == pytest.approx(anchor, abs=1.5)  # the point under the cursor stays put
    page.mouse.move(anchor[0] + 150, anchor[1] + 40)
    page.mouse.down()
    page.mouse.move(anchor[0] - 50, anchor[1] - 60, steps=5)
    page.mouse.up()
    assert screen(page, 0.5, 0.5) == pytest.approx((anchor[0] - 200, anchor[1] - 100), abs=1.5)
    page.click("#zoom-fit")
    inside = page.evaluate("""() => { const m = document.getElementById('map').getBoundingClientRect();
        return [...document.querySelectorAll('g.robot circle.body')].map(c => { const b = c.getBoundingClientRect();
          return b.left >= m.left && b.right <= m.right && b.top >= m.top && b.bottom <= m.bottom; }); }""")
    assert inside == [True, True, True]


def test_click_a_robot_then_the_map_sends_a_goto_it_executes(team, page):
    start = own_pose(team, "robot2")
    page.fill("#p-speed", "0.8")
    page.mouse.click(*screen(page, start.x, start.y))
    assert page.locator('#robot-table input[data-name="robot2"]').is_checked()
    assert "Go to" in page.inner_text("#hint")
    gx, gy = start.x + 1.2, start.y + 0.9  # away from the other robots
    page.mouse.click(*screen(page, gx, gy))
    page.wait_for_selector('#tasks .task[data-robot="robot2"]:is([data-state="running"], [data-state="succeeded"])',
                           timeout=20000)
    shot(page, "02-goto-running")
    task = wait_until(lambda: [t for t in team.robots[1].query(Task) if t.preposition == "goto"], timeout=20)[0]
    assert (task.params.x, task.params.y) == (pytest.approx(gx, abs=0.03), pytest.approx(gy, abs=0.03))
    page.wait_for_selector('#tasks .task[data-robot="robot2"][data-state="succeeded"]', timeout=30000)
    end = own_pose(team, "robot2")
    assert math.hypot(end.x - gx, end.y - gy) < 0.25


def hold_and_drag(pg: Any, start: tuple[float, float], end: tuple[float, float]) -> None:
    """Press on `start`, hold past the page's long press, drag to `end` and release."""
    pg.mouse.move(*start)
    pg.mouse.down()
    pg.wait_for_timeout(700)
    pg.mouse.move((start[0] + end[0]) / 2, (start[1] + end[1]) / 2, steps=4)
    pg.mouse.move(*end, steps=4)
    pg.mouse.up()


def test_holding_then_dragging_a_robot_teleports_it(team, page):
    p = own_pose(team, "robot3")
    page.mouse.move(*screen(page, p.x, p.y))  # a quick drag pans the map: the robot stays
    page.mouse.down()
    page.mouse.move(*screen(page, p.x + 1.0, p.y - 1.0), steps=6)
    page.mouse.up()
    page.wait_for_timeout(300)
    assert page.locator("#confirm").is_hidden()
    assert not [t for t in team.robots[2].query(Task) if t.preposition == "teleport"]
    assert math.hypot(own_pose(team, "robot3").x - p.x, own_pose(team, "robot3").y - p.y) < 0.05
    tx, ty = p.x + 1.5, p.y - 1.0
    hold_and_drag(page, screen(page, p.x, p.y), screen(page, tx, ty))
    page.wait_for_selector("#confirm", state="visible", timeout=5000)  # not yet known to be a simulator: asked
    assert "robot3" in page.inner_text("#confirm-text")
    shot(page, "03a-teleport-asked")
    page.wait_for_timeout(400)
    page.click("#confirm-ok")
    wait_until(lambda: math.hypot(own_pose(team, "robot3").x - tx, own_pose(team, "robot3").y - ty) < 0.1,
               timeout=20, message="robot3 was not teleported where it was dropped")
    page.wait_for_function("([x, y]) => { const g = document.querySelector('g.robot[data-name=robot3]');"
                           " return Math.hypot(+g.dataset.x - x, +g.dataset.y - y) < 0.1; }", arg=[tx, ty])
    turned = math.remainder(own_pose(team, "robot3").theta - p.theta, 2 * math.pi)  # +pi and -pi are one heading
    assert turned == pytest.approx(0, abs=0.05)  # heading kept
    # the simulator moved it (moved=True in the result): the page now teleports it without asking
    page.wait_for_function("() => erni.ui.real.get('robot3') === false", timeout=20000)
    ux, uy = tx - 0.5, ty + 0.5
    hold_and_drag(page, screen(page, tx, ty), screen(page, ux, uy))
    wait_until(lambda: math.hypot(own_pose(team, "robot3").x - ux, own_pose(team, "robot3").y - uy) < 0.1,
               timeout=20, message="robot3 was not teleported the second time")
    assert page.locator("#confirm").is_hidden()
    shot(page, "03-teleported")


def test_rectangle_selection_and_command_buttons(team, page):
    for name in ("robot1", "robot2", "robot3"):
        settle(team, name)
    a, b = own_pose(team, "robot1"), own_pose(team, "robot2")
    c = own_pose(team, "robot3")
    for name, p in (("robot1", a), ("robot2", b), ("robot3", c)):  # the page draws them there (it may lag under load)
        page.wait_for_function("([n, x, y]) => { const g = document.querySelector(`g.robot[data-name=${n}]`);"
                               " return g && Math.hypot(+g.dataset.x - x, +g.dataset.y - y) < 0.1; }",
                               arg=[name, p.x, p.y], timeout=20000)
    x0, x1 = min(a.x, b.x) - 0.4, max(a.x, b.x) + 0.4
    y0, y1 = min(a.y, b.y) - 0.4, max(a.y, b.y) + 0.4
    assert not (x0 < c.x < x1 and y0 < c.y < y1), "robot3 must lie outside the rectangle"
    page.keyboard.down("Shift")
    page.mouse.move(*screen(page, x0, y1))
    page.mouse.down()
    page.mouse.move(*screen(page, x1, y0), steps=5)
    page.mouse.up()
    page.keyboard.up("Shift")
    try:  # the table follows the selection on the page's next update
        page.wait_for_function("() => ['robot1', 'robot2'].every(n => "
                               "document.querySelector(`#robot-table input[data-name=\"${n}\"]`).checked)", timeout=10000)
    except PlaywrightTimeout:
        pass  # the assertion below shows what was selected
    checked = [page.locator(f'#robot-table input[data-name="{n}"]').is_checked() for n in ("robot1", "robot2", "robot3")]
    assert checked == [True, True, False]
    page.fill("#p-angle", "45")
    page.click("#cmd-turn-left")
    for robot in team.robots[:2]:
        turn = wait_until(lambda robot=robot: [t for t in robot.query(Task) if t.preposition == "turn"], timeout=20)[0]
        assert turn.params.angle == 45.0
    assert not [t for t in team.robots[2].query(Task) if t.preposition == "turn"]
    page.click("#cmd-randomwalk")
    wait_until(lambda: own_pose(team, "robot1").v > 0.1 and own_pose(team, "robot2").v > 0.1, timeout=20)
    shot(page, "04-random-walk")
    page.click("#cmd-stop")
    settle(team, "robot1")
    settle(team, "robot2")
    page.wait_for_selector('#tasks .task[data-robot="robot1"][data-state="cancelled"]', timeout=20000)


def test_right_click_menu_tasks_one_robot(team, page):
    p = own_pose(team, "robot1")
    page.mouse.click(*screen(page, p.x, p.y), button="right")
    menu = page.locator("#menu")
    assert menu.is_visible() and menu.locator(".title").inner_text() == "robot1"
    shot(page, "05-context-menu")
    page.fill("#p-distance", "0.5")  # the menu uses the command panel's parameters
    menu.locator('button[data-act="backward"]').click()
    assert not menu.is_visible()
    page.wait_for_selector('#tasks .task[data-robot="robot1"][data-state="succeeded"] >> text=backward', timeout=20000)
    settle(team, "robot1")
    q = own_pose(team, "robot1")
    assert math.hypot(q.x - p.x, q.y - p.y) == pytest.approx(0.5, abs=0.08)


def test_network_links_are_drawn_coloured_by_quality(team, page):
    with team.robots[0].transaction() as tx:  # as MobiNet publishes it; the transport shares it with control
        tx.add(NetInfo(uid="netinfo:test", node="robot1", kind="network_topology",
                       neighbors=[Neighbor(name="robot2", quality=0.9)],
                       links=[Link(a="robot1", b="robot2", quality=0.9), Link(a="robot2", b="robot3", quality=0.2)]))
    page.wait_for_selector("#links line.link-line >> nth=1", state="attached", timeout=20000)
    lines = page.eval_on_selector_all("#links line.link-line", "ls => ls.map(l => [l.dataset.a, l.dataset.b, "
                                      "+l.dataset.quality, l.getAttribute('stroke')])")
    assert sorted((a, b, q) for a, b, q, _ in lines) == [("robot1", "robot2", 0.9), ("robot2", "robot3", 0.2)]
    colours = {q: c for _, _, q, c in lines}
    assert colours[0.9] != colours[0.2]
    assert "cut nodes" in page.inner_text("#metrics") and "robot2" in page.inner_text("#metrics")
    shot(page, "06-links")
    with team.robots[0].transaction() as tx:  # old news: shown stale, left out of the metrics
        tx.change(NetInfo(uid="netinfo:test", node="robot1", kind="network_topology", stamp=time.time() - 60,
                          links=[Link(a="robot1", b="robot2", quality=0.9)]))
    page.wait_for_selector('#links line.link-line.stale[data-a="robot1"]', state="attached", timeout=20000)
    assert "links0" in page.inner_text("#metrics").replace("\n", "").replace(" ", "")


def test_deployment_strategy_buttons_send_deploy_tasks(team, page):
    def deploy(prep: str) -> Task:
        return wait_until(lambda: [t for t in team.robots[0].query(Task) if (t.verb, t.preposition) == ("Deploy", prep)],
                          timeout=20, message=f"no Deploy {prep} reached robot1")[0]

    names = page.eval_on_selector_all("#strategies button", "bs => bs.map(b => b.dataset.act)")
    assert {"widep", "spread", "relay", "patrol"} <= set(names)
    page.check('#robot-table input[data-name="robot1"]')
    page.click('#strategies button[data-act="widep"]')
    assert "point of interest" in page.inner_text("#hint")
    page.mouse.click(*screen(page, 4.0, -1.0))
    widep = deploy("widep")
    assert (widep.params.x, widep.params.y) == (pytest.approx(4.0, abs=0.03), pytest.approx(-1.0, abs=0.03))
    page.click('#strategies button[data-act="patrol"]')
    page.mouse.move(*screen(page, -1.0, -1.0))
    page.mouse.down()
    page.mouse.move(*screen(page, 2.0, -3.0), steps=5)
    page.mouse.up()
    patrol = deploy("patrol").params
    assert [patrol.xmin, patrol.ymin, patrol.xmax, patrol.ymax] == pytest.approx([-1.0, -3.0, 2.0, -1.0], abs=0.03)
    page.click('#strategies button[data-act="relay"]')
    for name in ("robot2", "robot3"):
        p = own_pose(team, name)
        page.mouse.click(*screen(page, p.x, p.y))
    relay = deploy("relay").params
    assert (relay.source, relay.destination) == ("robot2", "robot3")
    shot(page, "06b-strategies")


def test_a_killed_robot_is_shown_as_lost(team, page):
    if page.evaluate("erni.ui.real.get('robot3')") is not False:  # run alone: one teleport, so the page learns
        p = own_pose(team, "robot3")
        hold_and_drag(page, screen(page, p.x, p.y), screen(page, p.x, p.y + 0.8))
        page.wait_for_selector("#confirm", state="visible", timeout=5000)
        page.wait_for_timeout(400)
        page.click("#confirm-ok")
    page.wait_for_function("() => erni.ui.real.get('robot3') === false", timeout=20000)  # known to be simulated
    team.kill("robot3")
    page.wait_for_selector('g.robot[data-name="robot3"][data-state="lost"]', timeout=20000)
    assert page.evaluate("erni.ui.real.has('robot3')") is False  # what comes back may be a real robot: ask again
    assert "link lost" in page.inner_text('#robot-table tr[data-name="robot3"]')
    assert drawn(page, "robot1")["state"] == "ok"
    assert "robots up2/3" in page.inner_text("#metrics").replace("\n", "").replace(" ", "").replace("robotsup", "robots up")
    page.wait_for_selector("#log >> text=robot3: link lost", timeout=20000)
    shot(page, "07-robot-lost")


def test_losing_the_control_node_is_shown_and_the_page_reconnects(team, page):
    port = team.ui.server.port
    team.control.stop()
    page.wait_for_selector("#conn.lost", timeout=20000)
    assert page.is_visible("#banner")
    shot(page, "08-control-lost")
    control = Agent("control", workers=2)
    discovery = team.transport.settings.discovery_port
    control.add_plugin("transport", settings=transport_settings(discovery, "control"), name="transport")
    ui = control.add_plugin(UIPlugin, settings={"listen": f"127.0.0.1:{port}", "verb": "BotMotion", "speak": False,
                                                "token": team.ui.server.token}, name="ui")  # the URL stays valid
    team.control = control.start()
    team.ui = ui  # type: ignore[assignment]
    try:
        page.wait_for_selector("#conn.ok", timeout=20000)
        assert not page.is_visible("#banner")
        page.wait_for_selector('g.robot[data-name="robot1"][data-state="ok"]', timeout=20000)
        shot(page, "09-reconnected")
    finally:
        control.stop()  # this test started it: it ends here (the team's stop() is then a no-op)
