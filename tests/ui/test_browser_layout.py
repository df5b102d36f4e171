"""The page on a handheld, in Chromium: a phone (390x800) and a tablet (1024x700) layout checked by
assertions on what is drawn (the map visible and at least half a phone's screen, nothing
overlapping, nothing spilling sideways, Stop within reach), the idle page doing no work, and
pages of another origin refused by a real browser. Screenshots go to artifacts/ui/."""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from erni.blackboard import Pose
from erni.blackboard.testing import wait_until
from tests.ui.test_browser import ARGS, ARTIFACTS, CHROMIUM
from tests.ui.test_server import control  # noqa: F401  (the fixture)

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt install chromium)")

ROBOTS = ("robot1", "robot2", "robot3", "robot4")

# Boxes of the parts of the page, in page coordinates: [left, top, right, bottom], or null when not shown.
BOXES = """() => {
  const box = (el) => { if (!el) return null; const r = el.getBoundingClientRect();
    const shown = getComputedStyle(el).display !== 'none' && r.width > 0 && r.height > 0;
    return shown ? [r.left, r.top, r.right, r.bottom] : null; };
  const all = (sel) => [...document.querySelectorAll(sel)].map(box).filter(Boolean);
  return {
    view: [0, 0, innerWidth, innerHeight], scrollWidth: document.documentElement.scrollWidth,
    header: box(document.getElementById('top')), map: box(document.getElementById('map')),
    side: box(document.getElementById('side')),
    headerItems: all('#top > *'),
    overlays: ['.maptools', '#legend', '#scale', '#hint', '#cursor'].map((s) => box(document.querySelector(s))),
    panels: all('#side > .panel'), controls: all('#side button, #side input, #side table'),
    stop: box(document.getElementById('cmd-stop')), say: box(document.getElementById('say-text')),
    robots: all('g.robot circle.body'),
  };
}"""


def overlap(a: list[float], b: list[float]) -> bool:
    return a[0] < b[2] - 0.5 and b[0] < a[2] - 0.5 and a[1] < b[3] - 0.5 and b[1] < a[3] - 0.5


def inside(a: list[float], b: list[float]) -> bool:
    return a[0] >= b[0] - 0.5 and a[1] >= b[1] - 0.5 and a[2] <= b[2] + 0.5 and a[3] <= b[3] + 0.5


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        # a DNS rebinding: the attacker's domain resolves to this host
        b = p.chromium.launch(executable_path=CHROMIUM, args=[*ARGS, "--host-resolver-rules=MAP attacker.example 127.0.0.1"])
        yield b
        b.close()


def open_page(browser: Any, url: str, width: int, height: int, touch: bool) -> Any:
    context = browser.new_context(viewport={"width": width, "height": height}, has_touch=touch,
                                  is_mobile=touch, device_scale_factor=1)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_selector(f'g.robot[data-name="{ROBOTS[-1]}"]', timeout=20000)
    page.errors = errors
    return page


@pytest.mark.parametrize("name,width,height,touch", [("phone", 390, 800, True), ("tablet", 1024, 700, True),
                                                     ("laptop", 1400, 850, False)])
def test_layout_on_a_phone_a_tablet_and_a_laptop(control, browser, name, width, height, touch):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, width, height, touch)
    try:
        page.wait_for_timeout(300)  # fonts and the first fit
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / f"layout-{name}-{width}x{height}.png").write_bytes(page.screenshot())
        b = page.evaluate(BOXES)
        view = b["view"]
        assert b["scrollWidth"] <= width, "the page spills sideways"
        assert b["map"] is not None and inside(b["map"], view)
        map_w, map_h = b["map"][2] - b["map"][0], b["map"][3] - b["map"][1]
        if name == "phone":
            assert map_w >= 0.95 * width and map_h >= 0.5 * height, (map_w, map_h)  # at least half the screen
            stop = b["stop"]
            assert stop is not None and stop[3] <= height, "Stop is not on the first screen"
        else:
            assert map_w * map_h >= 0.4 * width * height, (map_w, map_h)
        for item in b["headerItems"]:  # nothing in the header spills out of it (over the map, the legend)
            assert inside(item, b["header"]), item
        assert b["header"][3] <= b["map"][1] + 0.5
        overlays = [o for o in b["overlays"] if o is not None]
        for i, o in enumerate(overlays):
            assert inside(o, b["map"]), o
            for other in overlays[i + 1:]:
                assert not overlap(o, other), (o, other)
        assert not overlap(b["map"], b["side"])
        for c in b["controls"]:  # toolbar and fields stay inside the side panel
            assert c[0] >= b["side"][0] - 0.5 and c[2] <= b["side"][2] + 0.5, c
        for i, p in enumerate(b["panels"]):
            for other in b["panels"][i + 1:]:
                assert not overlap(p, other)
        assert len(b["robots"]) == len(ROBOTS) and all(inside(r, b["map"]) for r in b["robots"])
        assert not page.errors
    finally:
        page.context.close()


def test_the_stop_button_with_nothing_selected_stops_everyone_on_a_phone(control, browser):  # noqa: F811
    from erni.blackboard import Task

    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, 390, 800, True)
    try:
        page.tap("#cmd-stop")
        page.wait_for_selector("#last-reply.ok .said", timeout=10000)
        assert page.inner_text("#last-reply .said") == "Roger: robots 1, 2, 3 and 4, stop"
        stops = wait_until(lambda: [t for t in agent.query(Task) if t.preposition == "stop"], timeout=5)
        assert sorted(t.destination for t in stops) == list(ROBOTS)
    finally:
        page.context.close()


def test_the_idle_page_does_no_work(control, browser):  # noqa: F811
    agent, ui = control(robots=ROBOTS)
    page = open_page(browser, ui.url, 1024, 700, False)
    try:
        page.wait_for_timeout(500)
        before = page.evaluate("erni.ui.renders")
        page.wait_for_timeout(3000)  # a window to count renders in, not a timing assertion
        assert page.evaluate("erni.ui.renders") == before, "the page re-rendered while nothing changed"
        with agent.transaction() as tx:  # a change is drawn: the counter counts
            tx.change(Pose(robot="robot2", x=3.0, y=1.0, battery=12.5))
        page.wait_for_function("() => +document.querySelector('g.robot[data-name=robot2]').dataset.x === 3")
        assert page.evaluate("erni.ui.renders") > before
    finally:
        page.context.close()


def test_a_page_of_another_origin_cannot_reach_the_gui_in_a_real_browser(control, browser):  # noqa: F811
    """A foreign page that even knows the token, and a rebound domain, are both refused by the node."""
    from aiohttp import web

    from erni.blackboard import Task
    from tests.ui.team import free_port

    agent, ui = control(robots=ROBOTS)
    port, token = ui.server.port, ui.server.token
    evil_port = free_port()
    attack = f"""<script>
      document.title = "pending";
      const ws = new WebSocket("ws://127.0.0.1:{port}/ws?token={token}");
      ws.onopen = () => {{ ws.send(JSON.stringify({{type: "command", robots: ["robot1"], action: "forward",
                                                     params: {{distance: 1}}}})); document.title = "opened"; }};
      ws.onerror = () => {{ document.title = "refused"; }};
    </script>"""
    ready = threading.Event()
    stop = threading.Event()

    def serve() -> None:
        async def main() -> None:
            async def page(_: web.Request) -> web.Response:
                return web.Response(text=attack, content_type="text/html")

            app = web.Application()
            app.router.add_get("/", page)
            runner = web.AppRunner(app)
            await runner.setup()
            await web.TCPSite(runner, "127.0.0.1", evil_port).start()
            ready.set()
            while not stop.is_set():
                await asyncio.sleep(0.05)
            await runner.cleanup()

        asyncio.run(main())

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    ready.wait(10)
    context = browser.new_context()
    try:
        page = context.new_page()
        page.goto(f"http://127.0.0.1:{evil_port}/")  # another origin: another port of the same host
        page.wait_for_function("document.title !== 'pending'", timeout=10000)
        assert page.title() == "refused"
        assert not agent.query(Task)
    finally:
        context.close()
    rebound = browser.new_context()  # DNS rebinding: a domain of the attacker now resolving to this host
    try:
        page = rebound.new_page()
        response = page.goto(f"http://attacker.example:{port}/?token={token}")
        assert response is not None and response.status == 403
        assert "is not this control node" in page.inner_text("body")
    finally:
        rebound.close()
        stop.set()
        thread.join(5)
