"""GUI benchmark: blackboard change -> page update, and page command -> task on the blackboard.

A control agent with the UI plugin serves its page on loopback; an aiohttp WebSocket client
plays the page. Measured, p50/p99 over --samples:

- pose -> page: a Pose changed on the blackboard until the state message carrying it arrives
  (the UI publishes at `rate_hz`, so half a period is expected on average),
- say -> task: a typed utterance sent until its task is on the blackboard (grammar, dialogue,
  later() hand-off, transaction),
- the floor, in the same run: a WebSocket echo round trip to a bare aiohttp server,
- say -> reply: a typed utterance sent until its spoken reply arrives on the page, with
  `--load N` processes spinning on the CPU meanwhile and 20 robots moving (a Pose change
  every 10 ms), as on a loaded control node,
- grammar: utterances parsed per second.

    python bench/bench_ui.py [--samples 100] [--rates 10,50] [--load 4]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import aiohttp  # noqa: E402
from aiohttp import web  # noqa: E402

from erni.blackboard import Agent, Pose, Task  # noqa: E402
from erni.plugins.ui import UIPlugin, parse  # noqa: E402


def pct(values: list[float], q: float) -> float:
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))]


async def echo_floor(samples: int) -> list[float]:
    async def ws(request: web.Request) -> web.WebSocketResponse:
        sock = web.WebSocketResponse()
        await sock.prepare(request)
        async for msg in sock:
            await sock.send_str(msg.data)
        return sock

    app = web.Application()
    app.router.add_get("/ws", ws)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
    out = []
    async with aiohttp.ClientSession() as s, s.ws_connect(f"ws://127.0.0.1:{port}/ws") as sock:
        for i in range(samples):
            t0 = time.perf_counter()
            await sock.send_str(json.dumps({"i": i}))
            await sock.receive()
            out.append(time.perf_counter() - t0)
    await runner.cleanup()
    return out


async def ui_paths(agent: Agent, ui: UIPlugin, samples: int, rate: float) -> tuple[list[float], list[float]]:
    pose_lat, say_lat = [], []
    async with aiohttp.ClientSession() as s, s.ws_connect(ui.url.replace("http://", "ws://").replace("/?", "/ws?")) \
            as sock:
        for i in range(samples):
            x = 1000.0 + i
            t0 = time.perf_counter()
            await asyncio.to_thread(_change_pose, agent, x)
            while True:
                msg = json.loads((await sock.receive()).data)
                if msg["type"] == "state" and any(r["pose"] and r["pose"]["x"] == x for r in msg["robots"]):
                    pose_lat.append(time.perf_counter() - t0)
                    break
            await asyncio.sleep(random.uniform(0, 1.0 / rate))  # a random phase of the publishing period
        for i in range(samples):
            before = len(agent.query(Task))
            t0 = time.perf_counter()
            await sock.send_str(json.dumps({"type": "say", "text": f"robot 1 go to {i} 1", "selection": []}))
            while len(agent.query(Task)) == before and time.perf_counter() - t0 < 5:
                await asyncio.sleep(0.0002)
            say_lat.append(time.perf_counter() - t0)
    return pose_lat, say_lat


async def say_reply(ui: UIPlugin, samples: int) -> list[float]:
    """Typed utterance -> its reply on the page, while the page also receives the moving team's state."""
    out = []
    async with aiohttp.ClientSession() as s, s.ws_connect(ui.url.replace("http://", "ws://").replace("/?", "/ws?")) \
            as sock:
        for i in range(samples):
            t0 = time.perf_counter()
            await sock.send_str(json.dumps({"type": "say", "text": f"robot 1 go to {i} 1", "selection": []}))
            while True:
                msg = json.loads((await sock.receive()).data)
                if msg["type"] == "reply":
                    out.append(time.perf_counter() - t0)
                    break
            await asyncio.sleep(random.uniform(0.0, 0.1))
    return out


def _spin(stop: Any) -> None:
    while not stop.is_set():
        pass


def _move(agent: Agent, stop: Any) -> None:
    k = 0
    while not stop.is_set():
        k += 1
        with agent.transaction() as tx:
            tx.change(Pose(robot=f"robot{k % 20 + 1}", x=k * 0.001))
        time.sleep(0.01)


def _change_pose(agent: Agent, x: float) -> None:
    with agent.transaction() as tx:
        tx.change(Pose(robot="robot1", x=x))


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=100)
    ap.add_argument("--rates", default="10,50", help="UI publishing rates (Hz) to measure")
    ap.add_argument("--load", type=int, default=4, help="CPU-spinning processes during the say -> reply run")
    results.add_argument(ap)
    args = ap.parse_args()
    targets = []
    floor = asyncio.run(echo_floor(args.samples))
    f50, f99 = pct(floor, 0.5) * 1e3, pct(floor, 0.99) * 1e3
    print(f"floor: WebSocket echo round trip p50 {f50:.3f} ms, p99 {f99:.3f} ms")
    print("| path | rate_hz | p50 (ms) | p99 (ms) | p50 / floor p50 |")
    print("|---|---|---|---|---|")
    print(f"| WebSocket echo round trip (floor) | – | {f50:.2f} | {f99:.2f} | 1.0 |")
    for rate in [float(r) for r in args.rates.split(",")]:
        agent = Agent("control", workers=2)
        ui = agent.add_plugin(UIPlugin, settings={"listen": "127.0.0.1:0", "speak": False, "verb": "BotMotion",
                                                  "rate_hz": rate, "supersede": False, "history": 10000},
                              name="ui")
        agent.start()
        try:
            _add(agent)
            pose_lat, say_lat = asyncio.run(ui_paths(agent, ui, args.samples, rate))  # type: ignore[arg-type]
        finally:
            agent.stop()
        for name, lat in (("Pose change -> page state", pose_lat), ("typed say -> task on the blackboard", say_lat)):
            p50, p99 = pct(lat, 0.5) * 1e3, pct(lat, 0.99) * 1e3
            print(f"| {name} | {rate:g} | {p50:.2f} | {p99:.2f} | {p50 / f50:.1f} |")
            targets.append(results.target(
                f"{name.replace('->', '→')}, rate_hz {rate:g}",
                "about half the page's period" if name.startswith("Pose") else "reported",
                f"WebSocket echo, {f50:.2f} ms", f"{p50:.2f} ms (p99 {p99:.2f})", None))
    import multiprocessing
    import threading

    agent = Agent("control", workers=2)
    ui = agent.add_plugin(UIPlugin, settings={"listen": "127.0.0.1:0", "speak": False, "verb": "BotMotion",
                                              "history": 60}, name="ui")
    agent.start()
    stop_spin, stop_move = multiprocessing.Event(), threading.Event()
    spinners = [multiprocessing.Process(target=_spin, args=(stop_spin,), daemon=True) for _ in range(args.load)]
    try:
        with agent.transaction() as tx:
            for k in range(1, 21):
                tx.add(Pose(robot=f"robot{k}", x=0.0))
        mover = threading.Thread(target=_move, args=(agent, stop_move), daemon=True)
        mover.start()
        for p in spinners:
            p.start()
        idle = asyncio.run(say_reply(ui, 5))  # warm-up
        lat = asyncio.run(say_reply(ui, args.samples))  # type: ignore[arg-type]
    finally:
        stop_spin.set()
        stop_move.set()
        for p in spinners:
            p.join(5)
        agent.stop()
    del idle
    p50, p99, worst = pct(lat, 0.5) * 1e3, pct(lat, 0.99) * 1e3, max(lat) * 1e3
    print(f"| typed say -> reply on the page, {args.load} CPU spinners on {multiprocessing.cpu_count()} cores, "
          f"20 robots moving | 10 | {p50:.2f} | {p99:.2f} (max {worst:.0f}) | {p50 / f50:.1f} |")
    texts = ["robots 5 and 6 turn right 90 degrees", "robot three go to minus two point five and one",
             "everyone stop", "go forward 2 feet", "robot 1 patrol from 0 0 to 5 5"]
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < 1.0:
        parse(texts[n % len(texts)])
        n += 1
    print(f"grammar: {n / (time.perf_counter() - t0):.0f} utterances/s parsed")
    targets.append(results.target(f"typed say → reply on the page, {args.load} CPU spinners", "reported",
                                  f"WebSocket echo, {f50:.2f} ms", f"{p50:.2f} ms (p99 {p99:.2f})", None))
    results.write("bench_ui", targets, path=args.results,
                  about="a WebSocket client plays the page of a control agent with the UI plugin, beside a "
                  "WebSocket echo")
    return 0


def _add(agent: Agent) -> None:
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot1", x=0.0))


if __name__ == "__main__":
    raise SystemExit(main())
