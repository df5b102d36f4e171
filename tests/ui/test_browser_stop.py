"""Nothing of the page stands between the operator and Stop, in Chromium at a desk (1400x850), on a
tablet (768x1024) and on a phone (390x800): with each question and menu the page can open — the
teleport question, its "Re-base odometry?" form for a real robot, a robot's menu opened on the map
and from the robot list, the map armed by Go to… or by the menu's Teleport to…, a robot held for a
teleport — a real mouse click or tap at Stop's place on the screen sends the stop to the control
node (the tasks it publishes for the robots) and closes what was open; nothing else is sent, and
nothing that was open acts afterwards. Screenshots go to artifacts/ui/."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import pytest

from erni.blackboard import AllocationResult, Task, TaskState
from erni.blackboard.testing import wait_until
from tests.ui.test_browser import (
    ARTIFACTS,
    CHROMIUM,
    browser,  # noqa: F401  (the fixture)
)
from tests.ui.test_browser_touch import HOLD, RECORD, Touch, centre
from tests.ui.test_server import control  # noqa: F401  (the fixture)

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt install chromium)")

ROBOTS = ("robot1", "robot2", "robot3", "robot4")

# What is open on the page now: the question (its title), the menu (its robot), the armed action.
OPEN = """() => ({ question: document.getElementById('confirm').classList.contains('hidden') ? null
    : document.getElementById('confirm-title').textContent,
  menu: document.getElementById('menu').classList.contains('hidden') ? null
    : document.querySelector('#menu .title').textContent,
  armed: erni.ui.armed ? erni.ui.armed.action : null, lifted: !!(erni.ui.drag && erni.ui.drag.lifted) })"""


def open_page(browser: Any, url: str, width: int, height: int, touch: bool) -> Any:  # noqa: F811
    context = browser.new_context(viewport={"width": width, "height": height}, has_touch=touch,
                                  is_mobile=touch and width < 1000, device_scale_factor=1)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.add_init_script(RECORD)
    page.goto(url)
    page.wait_for_selector(f'g.robot[data-name="{ROBOTS[-1]}"]', timeout=20000)
    page.wait_for_timeout(300)  # fonts and the first fit
    page.errors = errors
    return page


def empty_spot(page: Any) -> tuple[float, float]:
    """A point of the map with no robot on it (below the row the robots stand in)."""
    m = page.locator("#map").bounding_box()
    x, y = centre(page, "robot1")
    return x, min(y + 90, m["y"] + m["height"] - 30)


Opener = Callable[[Any, Touch | None, str], None]


def robot_menu_on_the_map(page: Any, touch: Touch | None, robot: str) -> None:
    if touch is None:
        page.mouse.click(*centre(page, robot), button="right")
    else:
        x, y = centre(page, robot)
        touch.drag((x, y), (x + 2, y + 2), steps=2, hold=HOLD)  # held in place: its menu
    page.locator("#menu").wait_for(state="visible", timeout=5000)


def robot_menu_from_the_list(page: Any, touch: Touch | None, robot: str) -> None:
    page.locator(f'#robot-table tr[data-name="{robot}"] td.name').click(button="right")
    page.locator("#menu").wait_for(state="visible", timeout=5000)


def armed_by_the_menu(page: Any, touch: Touch | None, robot: str) -> None:
    robot_menu_on_the_map(page, touch, robot)
    page.wait_for_timeout(400)  # read before choosing
    page.locator('#menu button[data-act="teleport"]').click()


def teleport_question(page: Any, touch: Touch | None, robot: str) -> None:
    armed_by_the_menu(page, touch, robot)
    page.mouse.click(*empty_spot(page))
    page.locator("#confirm").wait_for(state="visible", timeout=5000)


def armed_go_to(page: Any, touch: Touch | None, robot: str) -> None:
    page.locator(f'#robot-table input[data-name="{robot}"]').check()
    page.locator("#cmd-goto").click()


def held_for_a_teleport(page: Any, touch: Touch | None, robot: str) -> None:
    assert touch is not None
    x, y = centre(page, robot)
    touch.down((x, y))  # the finger stays on the robot, lifted and dragged; a second finger presses Stop
    page.wait_for_timeout(HOLD * 1000)
    touch.move((x + 40, y + 40))


# Each state with something open between the operator and the robots: its name, what opens it, on
# which robot (robot3 is known to be real: its teleport asks "Re-base odometry?"), what is open
# then, and whom the stop goes to (everyone when nothing is selected).
STATES: list[tuple[str, Opener, str, dict[str, Any], tuple[str, ...]]] = [
    ("the teleport question", teleport_question, "robot2", {"question": "Teleport?"}, ROBOTS),
    ("the re-base question", teleport_question, "robot3", {"question": "Re-base odometry?"}, ROBOTS),
    ("the robot menu on the map", robot_menu_on_the_map, "robot2", {"menu": "robot2"}, ROBOTS),
    ("the robot menu from the list", robot_menu_from_the_list, "robot2", {"menu": "robot2"}, ROBOTS),
    ("the map armed by Teleport to…", armed_by_the_menu, "robot2", {"armed": "teleport"}, ROBOTS),
    ("the map armed by Go to…", armed_go_to, "robot2", {"armed": "goto"}, ("robot2",)),
]
HELD = ("a robot held for a teleport", held_for_a_teleport, "robot2", {"lifted": True}, ROBOTS)


def stops(agent: Any) -> list[Task]:
    return [t for t in agent.query(Task) if t.preposition == "stop"]


def sent(page: Any) -> list[dict[str, Any]]:
    return [m for m in page.evaluate("window.sent") if m.get("type") in ("command", "say")]


def press_stop(page: Any, how: str) -> None:
    """A real press at the middle of Stop as drawn: whatever lies there on the screen gets it."""
    b = page.locator("#cmd-stop").bounding_box()
    x, y = b["x"] + b["width"] / 2, b["y"] + b["height"] / 2
    if how == "mouse":
        page.mouse.click(x, y)
    elif how == "tap":
        page.touchscreen.tap(x, y)
    else:  # a second finger, while the first one stays on the map
        touch = Touch(page)
        held = page.evaluate("(() => { const d = erni.ui.drag; if (!d) return null;"
                             " const r = document.getElementById('map').getBoundingClientRect();"
                             " return [r.left + d.at[0], r.top + d.at[1]]; })()")
        assert held is not None, "no finger on the map"
        touch.down(tuple(held), (x, y))
        page.wait_for_timeout(60)
        touch.move(tuple(held))  # the second finger lifts; the first stays
        page.wait_for_timeout(60)


@pytest.mark.parametrize("name,width,height,how", [
    ("laptop", 1400, 850, "mouse"), ("tablet", 768, 1024, "tap"), ("tablet", 768, 1024, "mouse"),
    ("phone", 390, 800, "tap")])
def test_stop_acts_through_every_question_and_menu_of_the_page(control, browser, name, width, height, how):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, width, height, touch=how != "mouse")
    touch = Touch(page) if how != "mouse" else None
    failures: list[str] = []
    try:
        with agent.transaction() as tx:  # robot3's last teleport only re-based its odometry: it is a real robot
            tx.add(Task(verb="BotMotion", preposition="teleport", params={"x": 2.0, "y": 1.0}, destination="robot3",
                        source="control", result=AllocationResult(state=TaskState.SUCCEEDED, progress=1.0,
                                                                 values={"moved": False})))
        page.wait_for_function("() => erni.ui.real.get('robot3') === true", timeout=5000)
        for state, opens, robot, shown, robots in [*STATES, *([HELD] if how == "tap" else [])]:
            page.locator("#sel-none").click()
            page.evaluate("window.scrollTo(0, 0)")  # the map in view again on a phone
            before, quiet = {t.uid for t in stops(agent)}, len(sent(page))  # a stop supersedes the last one
            opens(page, touch, robot)
            now = page.evaluate(OPEN)
            assert all(now[k] == v for k, v in shown.items()), f"{state}: not open as expected: {now}"
            assert len(sent(page)) == quiet, f"{state}: opening it sent {sent(page)[quiet:]}"
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            (ARTIFACTS / f"stop-{state.replace(' ', '-').replace('…', '')}-{width}x{height}-{how}.png"
             ).write_bytes(page.screenshot())
            on_top = landed(page)
            press_stop(page, "second finger" if state == HELD[0] else how)
            try:
                wait_until(lambda b=before: [t for t in stops(agent) if t.uid not in b], timeout=3)
                page.wait_for_timeout(100)
                sent_to = sorted(t.destination or "" for t in stops(agent) if t.uid not in before)
                if sent_to != sorted(robots):
                    failures.append(f"{state}: the stop went to {sent_to}, not {sorted(robots)}")
            except AssertionError:
                failures.append(f"{state}: no stop was sent (on top at Stop's middle: {on_top})")
            if state == HELD[0] and touch is not None:
                touch.up()  # the first finger leaves the map
            page.wait_for_timeout(150)
            now = page.evaluate(OPEN)
            if now["question"] or now["menu"] or now["armed"] or now["lifted"]:
                failures.append(f"{state}: still open after Stop: {now}")
            page.keyboard.press("Escape")
            page.mouse.click(*empty_spot(page))  # a click on the map after Stop: nothing that was open acts
            page.wait_for_timeout(150)
            others = [m for m in sent(page)[quiet:] if m.get("action") != "stop"]
            if others:
                failures.append(f"{state}: besides the stop, the page sent {others}")
        assert not failures, f"at {width}x{height} by {how}:\n" + "\n".join(failures)
        if how == "mouse":  # from the keyboard too: Enter on the focused Stop, once
            page.locator("#sel-none").click()
            before = {t.uid for t in stops(agent)}
            page.focus("#cmd-stop")
            page.keyboard.press("Enter")
            wait_until(lambda: [t for t in stops(agent) if t.uid not in before], timeout=3)
            page.wait_for_timeout(200)
            assert sorted(t.destination or "" for t in stops(agent) if t.uid not in before) == list(ROBOTS)
        assert not [t for t in agent.query(Task) if t.preposition in ("teleport", "goto") and not t.result], \
            "a question or menu acted"
        assert not page.errors
    finally:
        page.context.close()


def landed(page: Any) -> str:
    """What is on top at Stop's middle: the element a press there reaches."""
    return page.evaluate("""() => { const s = document.getElementById('cmd-stop'), r = s.getBoundingClientRect();
      const e = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
      return e ? (e.id ? '#' + e.id : e.tagName.toLowerCase() + (e.className ? '.' + e.className : '')
        + (e.dataset && e.dataset.act ? `[${e.dataset.act}]` : '')) : 'nothing'; }""")
