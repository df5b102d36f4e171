"""The UI plugin's web server over real HTTP and WebSocket: page, state, token, page messages
turned into tasks, hostile messages answered without dropping the connection."""

from __future__ import annotations

import asyncio
import json
import socket
from collections.abc import Iterator
from typing import Any

import aiohttp
import pytest

from erni.blackboard import Agent, Pose, Task
from erni.blackboard.testing import wait_until
from erni.plugins.ui import UIPlugin
from erni.plugins.ui.plugin import is_loopback


@pytest.fixture
def control(monkeypatch) -> Iterator[Any]:
    """Factory of started control agents with the UI plugin (no transport: tasks stay local)."""
    monkeypatch.delenv("VOSK_MODEL_PATH", raising=False)
    agents: list[Agent] = []

    def start(robots: tuple[str, ...] = ("robot1", "robot2"), **settings: Any) -> tuple[Agent, UIPlugin]:
        agent = Agent("control", workers=2)
        ui = agent.add_plugin(UIPlugin, settings={"listen": "127.0.0.1:0", "speak": False, "verb": "BotMotion",
                                                  "rate_hz": 20, "recogniser": "vosk", **settings}, name="ui")
        agents.append(agent)
        agent.start()
        with agent.transaction() as tx:
            for i, name in enumerate(robots):
                tx.add(Pose(robot=name, x=float(i), y=1.0, battery=12.5))
        return agent, ui  # type: ignore[return-value]

    yield start
    for a in agents:
        a.stop()


def base(ui: UIPlugin) -> str:
    return f"http://127.0.0.1:{ui.server.port}"


def token(ui: UIPlugin) -> str:
    return ui.server.token


def tok(ui: UIPlugin, path: str) -> str:
    """The URL of `path` with the page's token."""
    return f"{base(ui)}{path}{'&' if '?' in path else '?'}token={token(ui)}"


async def fetch(url: str, headers: dict[str, str] | None = None) -> tuple[int, str]:
    async with aiohttp.ClientSession() as s, s.get(url, headers=headers or {}) as r:
        return r.status, await r.text()


def get(url: str, headers: dict[str, str] | None = None) -> tuple[int, str]:
    return asyncio.run(fetch(url, headers))


async def talk(url: str, sends: list[Any], until: Any, timeout: float = 5.0,
               headers: dict[str, str] | None = None) -> list[dict[str, Any]]:
    """Open the WebSocket, send each message (text or bytes), collect messages until `until(msgs)`."""
    got: list[dict[str, Any]] = []
    async with aiohttp.ClientSession() as s, s.ws_connect(url, headers=headers or {}) as ws:
        for m in sends:
            await (ws.send_bytes(m) if isinstance(m, bytes) else ws.send_str(m if isinstance(m, str) else json.dumps(m)))
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        while not until(got):
            left = end - loop.time()
            if left <= 0:
                raise AssertionError(f"no expected message within {timeout} s; got {[m['type'] for m in got]}")
            msg = await ws.receive(timeout=left)
            if msg.type != aiohttp.WSMsgType.TEXT:
                raise AssertionError(f"WebSocket closed: {msg.type}")
            got.append(json.loads(msg.data))
    return got


def ws_run(ui: UIPlugin, sends: list[Any], until: Any, query: str | None = None,
           headers: dict[str, str] | None = None) -> list[dict[str, Any]]:
    query = f"?token={token(ui)}" if query is None else query
    return asyncio.run(talk(f"ws://127.0.0.1:{ui.server.port}/ws{query}", sends, until, headers=headers))


def of(msgs: list[dict[str, Any]], kind: str) -> list[dict[str, Any]]:
    return [m for m in msgs if m["type"] == kind]


def test_page_assets_and_state_are_served(control):
    agent, ui = control()
    assert ui.url == f"http://127.0.0.1:{ui.server.port}/?token={token(ui)}" and len(token(ui)) >= 16
    status, html = get(ui.url)
    assert status == 200 and '<svg id="map"' in html and "static/app.js" in html
    for asset, marker in [("app.js", "new WebSocket"), ("style.css", ".robot.lost"), ("icon.svg", "<svg")]:
        status, text = get(f"{base(ui)}/static/{asset}")
        assert status == 200 and marker in text
    assert get(base(ui) + "/static/missing.js")[0] == 404
    state = wait_until(lambda: (s := json.loads(get(tok(ui, "/api/state"))[1])).get("robots") and s, timeout=5)
    assert [(r["name"], r["number"], r["state"], r["pose"]["x"]) for r in state["robots"]] == [
        ("robot1", 1, "ok", 0.0), ("robot2", 2, "ok", 1.0)]
    assert state["verb"] == "BotMotion" and state["speech"]["available"] is False
    assert "alphacephei.com/vosk/models" in state["speech"]["error"]


def test_low_battery_and_stall_show_as_abnormal(control):
    agent, ui = control(low_battery=11.0)
    with agent.transaction() as tx:
        tx.change(Pose(robot="robot1", battery=10.4))
        tx.change(Pose(robot="robot2", battery=12.0, stall_left=True))
    state = wait_until(lambda: (s := ui.server.state())["robots"][1:] and s["robots"][1]["reasons"] and s,
                       timeout=5)
    assert [(r["state"], r["reasons"]) for r in state["robots"]] == [
        ("warn", ["battery 10.4 V"]), ("warn", ["stalled"])]


def test_a_token_is_required_on_localhost_too(control):
    agent, ui = control()
    for path in ("/", "/api/state"):
        status, text = get(base(ui) + path)
        assert status == 403 and text.startswith("missing or wrong token: open the URL the control node printed")
        assert get(base(ui) + path + "?token=wrong")[0] == 403
        assert get(tok(ui, path))[0] == 200
    assert get(base(ui) + "/api/state", {"Authorization": f"Bearer {token(ui)}"})[0] == 200
    assert get(base(ui) + "/static/app.js")[0] == 200  # the page's assets are not secret
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        ws_run(ui, [], lambda m: False, query="")
    assert refused.value.status == 403
    assert of(ws_run(ui, [], lambda m: of(m, "state")), "hello")
    agent2, set_ui = control(token="s3cret-enough")
    assert set_ui.url.endswith("/?token=s3cret-enough") and get(set_ui.url)[0] == 200
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("10.0.0.5")
    from erni import ConfigError

    with pytest.raises(ConfigError, match="token: expected at least 8 characters"):
        Agent("x").add_plugin(UIPlugin, settings={"token": "short"})


def test_a_page_of_another_origin_can_neither_open_the_websocket_nor_read_the_state(control):
    agent, ui = control()
    for origin in ("http://evil.example", f"http://evil.example:{ui.server.port}", "null",
                   f"http://127.0.0.1:{ui.server.port + 1}", f"https://localhost:{ui.server.port}"):
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:  # the token leaked: still refused
            ws_run(ui, [{"type": "command", "robots": ["robot1"], "action": "forward", "params": {"distance": 1}}],
                   lambda m: False, headers={"Origin": origin})
        assert refused.value.status == 403, origin
        status, text = get(tok(ui, "/api/state"), {"Origin": origin})
        assert status == 403 and "may not use this control node" in text, origin
    assert not agent.query(Task)
    same = {"Origin": f"http://127.0.0.1:{ui.server.port}"}  # the page itself
    assert of(ws_run(ui, [], lambda m: of(m, "state"), headers=same), "hello")
    assert ui.server.refused == 10


def test_dns_rebinding_is_refused_by_the_host_header(control):
    agent, ui = control()
    port = ui.server.port
    for host in (f"evil.example:{port}", "evil.example", f"rebind.127.0.0.1.nip.io:{port}", f"0.0.0.0:{port}"):
        for path in ("/", "/api/state", "/static/app.js"):
            status, text = get(tok(ui, path), {"Host": host})
            assert status == 403 and text.startswith(f"Host {host!r} is not this control node"), (host, path)
        with pytest.raises(aiohttp.WSServerHandshakeError):
            ws_run(ui, [], lambda m: False, headers={"Host": host, "Origin": f"http://{host}"})
    for host in (f"localhost:{port}", f"127.0.0.1:{port}", f"[::1]:{port}", "127.0.0.1"):
        assert get(tok(ui, "/"), {"Host": host})[0] == 200, host
    agent2, named = control(allowed_hosts=["gui.lab.example"])
    assert get(f"{base(named)}/?token={token(named)}", {"Host": "gui.lab.example"})[0] == 200


def test_bound_to_any_address_the_printed_url_names_this_host(control):
    from erni.plugins.ui.server import is_local_address, public_address

    agent, ui = control(listen="0.0.0.0:0")
    host = ui.url.split("//")[1].split(":")[0]
    assert host == public_address() and is_local_address(host)
    if not is_loopback(public_address()):  # a machine with a network: never the useless 127.0.0.1
        assert host != "127.0.0.1"
    assert get(ui.url)[0] == 200 and get(ui.url.split("?")[0])[0] == 403


def test_typed_utterance_becomes_tasks_and_a_spoken_reply(control):
    agent, ui = control()
    msgs = ws_run(ui, [{"type": "say", "text": "robots 1 and 2 go forward 2 feet", "selection": []}],
                  lambda m: of(m, "reply"))
    reply = of(msgs, "reply")[0]
    assert (reply["text"], reply["accepted"], reply["channel"]) == ("Roger: robots 1 and 2, go forward 0.61 metres",
                                                                    True, "typed")
    assert reply["client"] == of(msgs, "hello")[0]["client"]
    tasks = wait_until(lambda: len(t := agent.query(Task)) == 2 and t, timeout=5)
    assert sorted((t.verb, t.preposition, t.destination, t.params.distance, t.source) for t in tasks) == [
        ("BotMotion", "forward", "robot1", 0.6096, "control"), ("BotMotion", "forward", "robot2", 0.6096, "control")]
    msgs = ws_run(ui, [{"type": "say", "text": "robot 9 stop", "selection": []}], lambda m: of(m, "reply"))
    assert of(msgs, "reply")[0]["text"] == "I don't know robot 9"
    # the page's selection is the default target of an utterance without a subject
    ws_run(ui, [{"type": "say", "text": "turn left", "selection": ["robot2"]}], lambda m: of(m, "reply"))
    turn = wait_until(lambda: [t for t in agent.query(Task) if t.preposition == "turn"], timeout=5)
    assert [(t.destination, t.params.angle) for t in turn] == [("robot2", 90.0)]
    wait_until(lambda: any("robot 9 stop" in line["text"] and "I don't know robot 9" in line["text"]
                           for line in ui.server.state()["log"]), timeout=5)


def test_commands_supersede_the_robots_previous_task_and_cancel_removes_one(control):
    agent, ui = control()
    goto = {"type": "command", "robots": ["robot1"], "action": "goto", "params": {"x": 3, "y": 4}}
    ws_run(ui, [goto], lambda m: of(m, "state"))
    first = wait_until(lambda: agent.query(Task), timeout=5)[0]
    assert (first.preposition, first.params.x, first.params.y, first.destination) == ("goto", 3.0, 4.0, "robot1")
    ws_run(ui, [{**goto, "action": "randomwalk", "params": {"speed": 0.5}}], lambda m: of(m, "state"))
    walk = wait_until(lambda: [t for t in agent.query(Task) if t.preposition == "randomwalk"], timeout=5)[0]
    assert [t.uid for t in agent.query(Task)] == [walk.uid]  # the goto was cancelled
    ws_run(ui, [{**goto, "action": "teleport", "params": {"x": 1, "y": 1, "heading": 30}}], lambda m: of(m, "state"))
    wait_until(lambda: len(agent.query(Task)) == 2, timeout=5)  # teleport does not cancel the walk
    ws_run(ui, [{"type": "cancel_task", "uid": walk.uid}], lambda m: of(m, "state"))
    wait_until(lambda: walk.uid not in {t.uid for t in agent.query(Task)}, timeout=5)
    msgs = ws_run(ui, [{"type": "cancel_task", "uid": walk.uid}], lambda m: of(m, "error"))
    assert of(msgs, "error")[0]["message"] == f"no running task {walk.uid}"


@pytest.mark.parametrize("message,error", [
    ("not json", "message is not JSON"),
    ('{"type":"fly"}', "unknown message type 'fly'"),
    ('{"type":"command","robots":["robot1"],"action":"dance"}', "unknown action 'dance'; expected one of"),
    ('{"type":"command","robots":["robot1"],"action":"goto","params":{"x":1}}', "I can't do that: goto: missing 'y'"),
    ('{"type":"command","robots":["robot1"],"action":"forward","params":{"distance":-1}}',
     "I can't do that: forward: distance: Input should be greater than 0 (got -1"),
    ('{"type":"mic","on":true}', "speech recognition off: no vosk model"),
    (b"\x01\x02\x03", "audio frame of odd length: expected 16-bit samples"),
])
def test_hostile_messages_get_one_line_errors_and_the_connection_stays(control, message, error):
    agent, ui = control()
    msgs = ws_run(ui, [message, {"type": "ping"}], lambda m: of(m, "error") and of(m, "pong"))
    assert of(msgs, "error")[0]["message"].startswith(error)
    assert not agent.query(Task)


def test_a_busy_port_disables_only_the_ui_and_names_the_address(control, caplog):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        agent, ui = control(listen=f"127.0.0.1:{port}")
        assert ui._disabled
    assert f"cannot serve the GUI on 127.0.0.1:{port}" in caplog.text
    assert agent.query(Pose)  # the agent goes on


def test_a_broken_vosk_model_leaves_typed_commands_working(control, tmp_path):
    (tmp_path / "am").mkdir()
    (tmp_path / "conf").mkdir()
    agent, ui = control(vosk_model=str(tmp_path))
    state = wait_until(lambda: (s := ui.server.state())["speech"]["error"] and s, timeout=20)
    assert state["speech"]["available"] is False
    assert state["speech"]["error"].startswith(f"cannot load the vosk model at {tmp_path}")
    msgs = ws_run(ui, [{"type": "mic", "on": True}, {"type": "say", "text": "robot 1 stop", "selection": []}],
                  lambda m: of(m, "error") and of(m, "reply"))
    assert of(msgs, "error")[0]["message"].startswith("speech recognition off: cannot load the vosk model")
    assert of(msgs, "reply")[0]["text"] == "Roger: robot 1, stop"


def test_the_floorplan_is_served_and_bad_files_are_refused_by_name(control, tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('bounds = [0, 0, 4, 3]\n[[wall]]\na = [1, 0]\nb = [1, 2]\n[[circle]]\ncenter = [3, 1]\nradius = 0.2\n'
                    '[[robot]]\nx = 0.5\n')
    agent, ui = control(floorplan=str(plan))
    fp = json.loads(get(tok(ui, "/api/state"))[1])["floorplan"]
    assert fp == {"bounds": [0.0, 0.0, 4.0, 3.0], "wall": [{"a": [1.0, 0.0], "b": [1.0, 2.0]}],
                  "circle": [{"center": [3.0, 1.0], "radius": 0.2}], "polygon": []}
    from erni import ConfigError

    bad = tmp_path / "bad.toml"
    bad.write_text("[[circle]]\ncenter = [1, 1]\nradius = -1\n")
    for path, why in [(tmp_path / "none.toml", "none.toml: no such floor plan file"),
                      (bad, r"bad.toml: circle\[0\].radius: Input should be greater than 0")]:
        with pytest.raises(ConfigError, match=why):
            Agent("x").add_plugin(UIPlugin, settings={"floorplan": str(path)})


def test_a_wav_file_setting_is_recognised_and_answered(control, tmp_path, monkeypatch):
    import numpy as np

    import erni.plugins.ui.plugin as ui_plugin
    from erni.plugins.ui.speech import RATE, read_wav
    from tests.ui.test_browser_mic import Recorder
    from tests.ui.test_speech import write_wav

    wav = write_wav(tmp_path / "cmd.wav", 5000 * np.sin(np.arange(RATE * 2) / 3.0), 22050)
    rec = Recorder("attention")
    monkeypatch.setattr(ui_plugin, "choose_recognizer", lambda kind, vosk_model, wake=None, front=None: lambda: rec)
    agent, ui = control(wav=str(wav))
    wait_until(lambda: any("voice: \u201cattention\u201d \u2192 Listening" in line["text"]
                           for line in ui.server.state()["log"]), timeout=20)
    with rec.lock:
        assert bytes(rec.pcm) == read_wav(wav)  # every frame of the file, in order, at 16 kHz
    assert ui.server.state()["listening"] is True


def test_robots_outside_the_naming_pattern_are_shown_by_name_and_the_token_is_not_logged(control, caplog):
    import logging

    caplog.set_level(logging.INFO, logger="erni")
    agent, ui = control(robots=("robot2", "scout"), token="hush-hush-hush")
    state = wait_until(lambda: len((s := ui.server.state())["robots"]) == 2 and s, timeout=5)
    assert [(r["name"], r["number"]) for r in state["robots"]] == [("robot2", 2), ("scout", "sc")]
    assert "hush-hush-hush" not in caplog.text and "(token required)" in caplog.text


def test_stop_acts_in_every_state_by_voice_typing_and_the_button(control):
    agent, ui = control(robots=("robot1", "robot2", "robot3"))
    assert ui.spoken.listening is False  # voice starts standing by
    ui._recognised("wav", "everyone stop")  # heard while standing by: still acts, and is answered
    stops = wait_until(lambda: len(t := [t for t in agent.query(Task) if t.preposition == "stop"]) == 3 and t,
                       timeout=5)
    assert sorted(t.destination for t in stops) == ["robot1", "robot2", "robot3"]
    wait_until(lambda: any("voice: \u201ceveryone stop\u201d \u2192 Roger: everyone, stop" in line["text"]
                           for line in ui.server.state()["log"]), timeout=5)
    assert ui.spoken.listening is False
    msgs = ws_run(ui, [{"type": "say", "text": "go to sleep", "selection": []},
                       {"type": "say", "text": "freeze", "selection": []}],
                  lambda m: len(of(m, "reply")) == 2)
    assert [r["text"] for r in of(msgs, "reply")] == ["Standing by", "Roger: everyone, stop"]
    before = len(agent.query(Task))
    msgs = ws_run(ui, [{"type": "command", "robots": [], "action": "stop", "params": {}}], lambda m: of(m, "reply"))
    assert of(msgs, "reply")[0]["text"] == "Roger: robots 1, 2 and 3, stop"  # nothing selected: everyone
    wait_until(lambda: len(agent.query(Task)) >= before, timeout=5)
    msgs = ws_run(ui, [{"type": "command", "robots": [], "action": "forward", "params": {"distance": 1}}],
                  lambda m: of(m, "error"))
    assert of(msgs, "error")[0]["message"].startswith("Select robots first")


def test_a_task_withdrawn_by_its_client_keeps_a_row_and_a_line(control):
    agent, ui = control()
    walk = Task(verb="BotMotion", preposition="randomwalk", source="cli-1234", destination="robot1")
    with agent.transaction() as tx:
        tx.add(walk)
    wait_until(lambda: any(r["uid"] == walk.uid for r in ui.server.state()["tasks"]), timeout=5)
    with agent.transaction() as tx:  # as the transport does when the client cancels a task relayed here
        tx.remove(walk)
    row = wait_until(lambda: [r for r in ui.server.state()["tasks"] if r["uid"] == walk.uid
                              and r["state"] == "cancelled"], timeout=5)[0]
    assert row["message"] == "withdrawn by cli-1234"
    assert any(line["text"] == "robot1: randomwalk cancelled \u2014 withdrawn by cli-1234"
               for line in ui.server.state()["log"])


def test_a_flood_of_bad_page_messages_is_answered_each_but_logged_a_few_times(control, caplog):
    """One token holder sends 10,000 bad messages: each gets its error answer, the log gets one line
    and the count held back (`LOG_PERIOD`), not 10,000 lines."""
    import logging

    caplog.set_level(logging.INFO, logger="erni.ui.http")
    agent, ui = control()
    n = 10_000
    url = f"ws://127.0.0.1:{ui.server.port}/ws?token={token(ui)}"
    msgs = asyncio.run(talk(url, ['{"type":"fly"}'] * n + [{"type": "ping"}],
                            lambda m: len(of(m, "error")) == n and of(m, "pong"), timeout=120))
    assert len(of(msgs, "error")) == n and ui.server.bad_messages == n
    lines = [r for r in caplog.records if r.name == "erni.ui.http" and "bad message" in r.getMessage()]
    assert 1 <= len(lines) <= 3, f"{len(lines)} log lines for {n} bad messages"
