"""Map labels in Chromium: robot names, their state lines and link qualities never cover each other
or a robot, at the default zoom (the page's first fit) on a laptop and on a phone, for a crowded
team whose every neighbour pair is linked. Screenshots go to artifacts/ui/."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import pytest

from erni.blackboard import Link, NetInfo, Pose
from tests.ui.test_browser import ARGS, ARTIFACTS, CHROMIUM
from tests.ui.test_server import control  # noqa: F401  (the fixture)

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt install chromium)")

# a team standing close: two rows 0.8 m apart, robots 0.9 m apart in a row, one far off (a long fit)
TEAM = {f"robot{i + 1}": (0.9 * (i % 5), 0.8 * (i // 5)) for i in range(10)} | {"robot11": (9.0, 5.0)}
LINKS = [(a, b) for a in TEAM for b in TEAM if a < b
         and ((TEAM[a][0] - TEAM[b][0]) ** 2 + (TEAM[a][1] - TEAM[b][1]) ** 2) ** 0.5 < 1.3] + [("robot5", "robot11")]

LABELS = """() => {
  const box = (el) => { const r = el.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; };
  return {
    names: [...document.querySelectorAll('#robots g.robot text.tag')].map((t) => [t.textContent, box(t)]),
    states: [...document.querySelectorAll('#robots g.robot text.lost-tag')].map(box),
    links: [...document.querySelectorAll('#links text.link-label')].map(box),
    robots: [...document.querySelectorAll('#robots g.robot circle.body')].map(box),
    map: box(document.getElementById('map')),
  };
}"""


def overlap(a: list[float], b: list[float]) -> bool:
    return a[0] < b[2] - 0.5 and b[0] < a[2] - 0.5 and a[1] < b[3] - 0.5 and b[1] < a[3] - 0.5


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.mark.parametrize("name,width,height,touch", [("laptop", 1400, 850, False), ("phone", 390, 800, True)])
def test_labels_do_not_overlap_at_the_default_zoom(control, browser, name, width, height, touch):  # noqa: F811
    agent, ui = control(robots=())
    with agent.transaction() as tx:
        for robot, (x, y) in TEAM.items():
            tx.add(Pose(robot=robot, x=x, y=y, battery=10.0 if robot == "robot3" else 12.5))  # robot3: low battery
        tx.add(NetInfo(uid="netinfo:test", node="robot1", kind="network_topology",
                       links=[Link(a=a, b=b, quality=round(0.3 + 0.6 * i / len(LINKS), 2)) for i, (a, b) in enumerate(LINKS)]))
    context = browser.new_context(viewport={"width": width, "height": height}, has_touch=touch, is_mobile=touch,
                                  device_scale_factor=1)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(ui.url)
        page.wait_for_selector('g.robot[data-name="robot11"]', timeout=20000)
        page.wait_for_selector("#links line.link-line >> nth=1", state="attached", timeout=20000)
        page.wait_for_timeout(300)  # fonts and the first fit
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / f"labels-{name}-{width}x{height}.png").write_bytes(page.screenshot())
        got = page.evaluate(LABELS)
        assert sorted(n for n, _ in got["names"]) == sorted(TEAM), "every robot is named"
        assert got["states"], "robot3's low battery is written beside it"
        assert got["links"], "link qualities are shown where there is room"
        labels = [b for _, b in got["names"]] + got["states"] + got["links"]
        for i, a in enumerate(labels):
            for b in labels[i + 1:]:
                assert not overlap(a, b), f"labels overlap: {a} {b}"
            for robot in got["robots"]:
                assert not overlap(a, robot), f"a label covers a robot: {a} {robot}"
            assert got["map"][0] <= a[0] and a[2] <= got["map"][2], f"a label leaves the map: {a}"
        assert not errors
    finally:
        context.close()
