"""The page under a thumb, in Chromium with touch events (CDP Input.dispatchTouchEvent): a finger's
wobble on a robot selects it and never teleports it; teleport takes a long press then a drag and
asks first unless the robot is known to be simulated; a pinch zooms about the fingers; every
button and field is at least 44x44 CSS px (WCAG 2.5.5) on a phone, a tablet and a laptop; on a
phone the robot list comes before the command panel. Screenshots go to artifacts/ui/."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import pytest

from erni.blackboard import AllocationResult, Task, TaskState
from erni.blackboard.testing import wait_until
from tests.ui.test_browser import (
    ARTIFACTS,
    CHROMIUM,
    browser,  # noqa: F401  (the fixture)
)
from tests.ui.test_server import control  # noqa: F401  (the fixture)

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt install chromium)")

ROBOTS = ("robot1", "robot2", "robot3", "robot4")
VIEWPORTS = [("phone", 390, 800), ("tablet", 768, 1024), ("laptop", 1400, 850)]
TARGET = 44  # CSS px, WCAG 2.5.5 (AAA) target size
HOLD = 0.7   # s, longer than the page's long press
READ = 400   # ms an operator takes to read a question or a menu before choosing (a quicker "yes" is ignored)

# Every WebSocket message the page sends, as sent (the page sends synchronously from its handlers).
RECORD = """window.sent = []; const send = WebSocket.prototype.send;
WebSocket.prototype.send = function (data) { if (typeof data === 'string') window.sent.push(JSON.parse(data));
  return send.call(this, data); };"""


class Touch:
    """Fingers on the page through the DevTools protocol, as a touch screen sends them."""

    def __init__(self, page: Any) -> None:
        self.page = page
        self.cdp = page.context.new_cdp_session(page)

    def _send(self, kind: str, points: list[tuple[float, float]]) -> None:
        self.cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": [
            {"x": x, "y": y, "id": i, "radiusX": 5, "radiusY": 5, "force": 1} for i, (x, y) in enumerate(points)]})

    def down(self, *points: tuple[float, float]) -> None:
        self._send("touchStart", list(points))

    def move(self, *points: tuple[float, float]) -> None:
        self._send("touchMove", list(points))

    def up(self) -> None:
        self._send("touchEnd", [])

    def drag(self, start: tuple[float, float], end: tuple[float, float], steps: int = 8, hold: float = 0.0) -> None:
        """One finger from `start` to `end`, after resting `hold` seconds on `start`."""
        self.down(start)
        if hold:
            self.page.wait_for_timeout(hold * 1000)
        for i in range(1, steps + 1):
            self.move((start[0] + (end[0] - start[0]) * i / steps, start[1] + (end[1] - start[1]) * i / steps))
            self.page.wait_for_timeout(16)
        self.up()

    def pinch(self, centre: tuple[float, float], d0: float, d1: float, steps: int = 8) -> None:
        """Two fingers on a horizontal line through `centre`, `d0` apart, spread (or closed) to `d1`."""
        cx, cy = centre

        def at(d: float) -> tuple[tuple[float, float], tuple[float, float]]:
            return (cx - d / 2, cy), (cx + d / 2, cy)

        self.down(*at(d0))
        for i in range(1, steps + 1):
            self.move(*at(d0 + (d1 - d0) * i / steps))
            self.page.wait_for_timeout(16)
        self.up()


# True when a tap on the middle of Stop reaches Stop, whatever is open.
STOP_ON_TOP = """() => { const s = document.getElementById('cmd-stop'), r = s.getBoundingClientRect();
  return document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2) === s; }"""


def open_page(browser: Any, url: str, width: int, height: int) -> Any:  # noqa: F811
    context = browser.new_context(viewport={"width": width, "height": height}, has_touch=True,
                                  is_mobile=width < 1000, device_scale_factor=1)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.add_init_script(RECORD)
    page.goto(url)
    page.wait_for_selector(f'g.robot[data-name="{ROBOTS[-1]}"]', timeout=20000)
    page.wait_for_timeout(300)  # fonts and the first fit
    page.errors = errors
    return page


def centre(page: Any, name: str) -> tuple[float, float]:
    """Page coordinates of a robot's centre as drawn."""
    b = page.locator(f'g.robot[data-name="{name}"] circle.body').bounding_box()
    return b["x"] + b["width"] / 2, b["y"] + b["height"] / 2


def world(page: Any, x: float, y: float) -> tuple[float, float]:
    """World coordinates of page point (x, y) on the map as drawn now."""
    return tuple(page.evaluate("([x, y]) => { const r = document.getElementById('map').getBoundingClientRect();"
                               " return erni.toWorld(x - r.left, y - r.top); }", [x, y]))


def teleports(page: Any) -> list[dict[str, Any]]:
    return [m for m in page.evaluate("window.sent") if m.get("type") == "command" and m.get("action") == "teleport"]


def shot(page: Any, name: str) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / f"{name}.png").write_bytes(page.screenshot())


@pytest.mark.parametrize("name,width,height", VIEWPORTS)
def test_a_wobbling_finger_selects_a_robot_and_never_teleports_it(control, browser, name, width, height):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, width, height)
    try:
        touch = Touch(page)
        for wobble in (3, 7, 11):  # CSS px a resting finger drifts, in any direction
            x, y = centre(page, "robot2")
            touch.drag((x, y), (x + wobble * 0.6, y - wobble * 0.8), steps=4)
            page.wait_for_timeout(100)
            assert not teleports(page), f"a {wobble} px wobble teleported robot2"
        # the tap selected it (the list redraws on the page's next frame: a loaded machine delays it)
        page.locator('#robot-table input[data-name="robot2"]:checked').wait_for(timeout=15000)
        x, y = centre(page, "robot3")
        touch.drag((x, y), (x + 60, y + 40), steps=8)  # a quick swipe starting on a robot pans the map
        page.wait_for_timeout(200)
        assert not teleports(page)
        assert not [t for t in agent.query(Task) if t.preposition == "teleport"]
        assert not page.errors
    finally:
        page.context.close()


def test_a_long_press_then_drag_teleports_after_a_confirmation(control, browser):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, 390, 800)
    try:
        touch = Touch(page)
        start = centre(page, "robot2")
        end = (start[0] + 70, start[1] + 90)
        touch.drag(start, end, steps=10, hold=HOLD)
        dialog = page.locator("#confirm")
        dialog.wait_for(state="visible", timeout=5000)
        assert "robot2" in page.inner_text("#confirm-text") and "odometry" in page.inner_text("#confirm-text")
        assert not teleports(page), "teleported before the operator confirmed"
        assert page.evaluate(STOP_ON_TOP), "the question covers the Stop bar"
        shot(page, "touch-confirm-teleport-390x800")
        page.wait_for_timeout(READ)
        page.tap("#confirm-cancel")  # cancelled: nothing is sent
        assert not dialog.is_visible()
        page.wait_for_timeout(200)
        assert not teleports(page)

        start = centre(page, "robot2")
        touch.drag(start, end, steps=10, hold=HOLD)
        dialog.wait_for(state="visible", timeout=5000)
        page.tap("#confirm-ok")  # too quick: a press as the question opens does not answer it
        assert not teleports(page) and dialog.is_visible()
        page.wait_for_timeout(READ)
        page.tap("#confirm-ok")
        sent = teleports(page)
        assert len(sent) == 1 and sent[0]["robots"] == ["robot2"]
        wx, wy = world(page, *end)
        assert (sent[0]["params"]["x"], sent[0]["params"]["y"]) == (pytest.approx(wx, abs=0.02),
                                                                     pytest.approx(wy, abs=0.02))
        task = wait_until(lambda: [t for t in agent.query(Task) if t.preposition == "teleport"], timeout=5)[0]
        assert task.destination == "robot2"

        # the robot answers as a simulator does: the page then trusts a drag of it without asking
        with agent.transaction() as tx:
            tx.change(task.model_copy(update={"result": AllocationResult(
                state=TaskState.SUCCEEDED, progress=1.0, message="pose set", values={"moved": True})}))
        page.wait_for_selector(f'#tasks .task[data-key="{task.uid}"][data-state="succeeded"]', timeout=5000)
        start = centre(page, "robot2")
        touch.drag(start, (start[0] - 50, start[1] + 60), steps=10, hold=HOLD)
        page.wait_for_function("() => window.sent.filter(m => m.action === 'teleport').length === 2", timeout=5000)
        assert not dialog.is_visible()

        # a robot whose teleport only re-based its odometry is a real robot: the page says so and asks
        with agent.transaction() as tx:
            tx.change(task.model_copy(update={"result": AllocationResult(
                state=TaskState.SUCCEEDED, progress=1.0, message="odometry re-localised", values={"moved": False})}))
        page.wait_for_function("() => erni.ui.real.get('robot2') === true", timeout=5000)
        start = centre(page, "robot2")
        touch.drag(start, (start[0] + 40, start[1] - 70), steps=10, hold=HOLD)
        dialog.wait_for(state="visible", timeout=5000)
        assert "real robot" in page.inner_text("#confirm-text")
        page.keyboard.press("Escape")
        assert len(teleports(page)) == 2
        assert not page.errors
    finally:
        page.context.close()


def test_a_long_press_without_a_drag_opens_the_robot_menu(control, browser):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, 390, 800)
    try:
        touch = Touch(page)
        x, y = centre(page, "robot3")
        touch.drag((x, y), (x + 6, y + 5), steps=3, hold=HOLD)  # held, and wobbling: the menu, no teleport
        menu = page.locator("#menu")
        menu.wait_for(state="visible", timeout=5000)
        assert menu.locator(".title").inner_text() == "robot3"
        assert not teleports(page)
        box, view = menu.bounding_box(), page.viewport_size
        assert box["y"] >= 0 and box["y"] + box["height"] <= view["height"] + 0.5  # the whole menu on screen
        assert box["x"] >= 0 and box["x"] + box["width"] <= view["width"] + 0.5
        assert box["y"] + box["height"] <= page.locator("#cmd-stop").bounding_box()["y"], "the menu runs under Stop"
        assert page.evaluate(STOP_ON_TOP), "the menu covers the Stop bar"
        shot(page, "touch-menu-390x800")
        page.wait_for_timeout(READ)
        page.tap('#menu button[data-act="teleport"]')  # the menu's Teleport to…, then a tap on the map
        mx, my = centre(page, "robot1")
        page.tap("#map", position={"x": 30, "y": my - page.locator("#map").bounding_box()["y"] + 120})
        page.locator("#confirm").wait_for(state="visible", timeout=5000)
        assert not teleports(page)
        page.wait_for_timeout(READ)
        page.tap("#confirm-ok")
        assert [m["robots"] for m in teleports(page)] == [["robot3"]]
        assert not page.errors
    finally:
        page.context.close()


@pytest.mark.parametrize("name,width,height", VIEWPORTS)
def test_a_pinch_zooms_about_the_fingers(control, browser, name, width, height):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, width, height)
    try:
        touch = Touch(page)
        m = page.locator("#map").bounding_box()
        mid = (m["x"] + m["width"] * 0.45, m["y"] + m["height"] * 0.55)
        scale0 = page.evaluate("erni.ui.view.scale")
        anchor = world(page, *mid)
        touch.pinch(mid, 80, 200)  # spread 2.5 times
        scale1 = page.evaluate("erni.ui.view.scale")
        assert scale1 == pytest.approx(scale0 * 2.5, rel=0.05), "a pinch did not zoom"
        assert world(page, *mid) == pytest.approx(anchor, abs=3 / scale1)  # the point between the fingers stays
        touch.pinch(mid, 200, 100)  # closed to half
        assert page.evaluate("erni.ui.view.scale") == pytest.approx(scale1 / 2, rel=0.05)
        assert not teleports(page) and not page.errors
    finally:
        page.context.close()


# Every control an operator touches, with its box; a checkbox counts with the label that wraps it.
TARGETS = """() => [...document.querySelectorAll('button, input, select')].map((e) => {
  const t = e.type === 'checkbox' && e.closest('label') ? e.closest('label') : e;
  const r = t.getBoundingClientRect(), s = getComputedStyle(t);
  if (s.display === 'none' || s.visibility === 'hidden' || r.width === 0 || r.height === 0) return null;
  return { what: e.id || e.dataset.act || e.className || e.textContent.trim() || e.type, w: r.width, h: r.height };
}).filter(Boolean)"""


@pytest.mark.parametrize("name,width,height", VIEWPORTS)
def test_every_button_is_at_least_44_css_px_square(control, browser, name, width, height):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    with agent.transaction() as tx:  # a task row, with its cancel button
        tx.add(Task(verb="BotMotion", preposition="forward", params={"distance": 1.0}, destination="robot1",
                    source="control"))
    page = open_page(browser, ui.url, width, height)
    try:
        page.wait_for_selector("#tasks .task .x")
        shot(page, f"touch-{name}-{width}x{height}")
        small = [t for t in page.evaluate(TARGETS) if t["w"] < TARGET - 0.5 or t["h"] < TARGET - 0.5]
        assert not small, f"targets under {TARGET}x{TARGET} px at {width}x{height}: {small}"
        sizes = {t["what"]: (round(t["w"]), round(t["h"])) for t in page.evaluate(TARGETS)}
        print(f"{name} {width}x{height}: stop {sizes['cmd-stop']}, zoom-in {sizes['zoom-in']}, "
              f"min {min(w for w, _ in sizes.values())}x{min(h for _, h in sizes.values())}")
        page.mouse.click(*centre(page, "robot2"), button="right")  # the robot's menu
        page.locator("#menu").wait_for(state="visible")
        small = [t for t in page.evaluate(TARGETS) if t["w"] < TARGET - 0.5 or t["h"] < TARGET - 0.5]
        assert not small, f"menu targets under {TARGET}x{TARGET} px at {width}x{height}: {small}"
        assert not page.errors
    finally:
        page.context.close()


def test_on_a_phone_the_robot_list_comes_before_the_command_panel_and_stop_stays_in_reach(control, browser):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, 390, 800)
    try:
        box = page.evaluate("""() => { const top = (s) => document.querySelector(s).getBoundingClientRect().top;
          return { robots: top('#robot-table'), command: top('#cmd-goto'), rows: [...document.querySelectorAll(
            '#robot-table tbody tr')].map((r) => r.getBoundingClientRect().bottom) }; }""")
        assert box["robots"] < box["command"], "the robot list is below the command panel"
        assert box["rows"] and max(box["rows"]) <= 800, "the robot list is not on the first screen"
        page.evaluate("window.scrollTo(0, document.body.scrollHeight)")
        page.wait_for_timeout(200)
        stop = page.locator("#cmd-stop").bounding_box()
        assert stop["y"] >= 0 and stop["y"] + stop["height"] <= 800, "Stop scrolled out of reach"
        shot(page, "touch-phone-scrolled-390x800")
        assert not page.errors
    finally:
        page.context.close()


def test_a_drop_off_the_floor_plan_is_refused_with_one_line(control, browser):  # noqa: F811
    agent, ui = control(robots=ROBOTS, floorplan=str(Path(__file__).with_name("arena.toml")))
    page = open_page(browser, ui.url, 1400, 850)
    try:
        touch = Touch(page)
        bounds = page.evaluate("erni.ui.state.floorplan.bounds")
        m = page.locator("#map").bounding_box()
        outside = page.evaluate("([x, y]) => erni.toScreen(x, y)", [bounds[2] + 1.0, (bounds[1] + bounds[3]) / 2])
        start = centre(page, "robot2")
        end = (m["x"] + min(outside[0], m["width"] - 5), m["y"] + outside[1])
        assert world(page, *end)[0] > bounds[2]
        touch.drag(start, end, steps=10, hold=HOLD)
        page.wait_for_selector("#log .logline.error >> text=outside the floor plan", timeout=5000)
        line = page.inner_text("#log .logline.error")
        assert "\n" not in line.strip() and "robot2" in line
        assert not page.locator("#confirm").is_visible() and not teleports(page)
        assert math.isfinite(bounds[0])
    finally:
        page.context.close()
