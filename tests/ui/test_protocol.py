"""Page messages: every valid message parses to its type, anything else is refused in one line."""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

import aiohttp
import pytest
from hypothesis import given
from hypothesis import strategies as st

from erni.plugins.ui.protocol import BadMessage, CommandMsg, HostileMessage, MicMsg, SayMsg, parse_message
from erni.plugins.ui.server import WebServer


def test_valid_messages_parse_to_their_types():
    cmd = parse_message('{"type":"command","robots":["robot1"],"action":"goto","params":{"x":1,"y":-2.5}}')
    assert isinstance(cmd, CommandMsg) and cmd.params == {"x": 1, "y": -2.5}
    say = parse_message(json.dumps({"type": "say", "text": "robot 1 stop", "selection": ["robot2"]}))
    assert isinstance(say, SayMsg) and say.selection == ["robot2"]
    assert parse_message('{"type":"mic","on":true}') == MicMsg(type="mic", on=True)


@pytest.mark.parametrize("text,message", [
    ("{nope", "message is not JSON"),
    ("[1,2]", "unknown message type 'list'; expected one of command, say, select, cancel_task, mic, ping"),
    ('{"type":"launch"}', "unknown message type 'launch'; expected one of command, say, select, cancel_task, mic, ping"),
    ('{"type":"command","robots":["robot1"],"action":"stop","params":{"x":[1]}}', "command: params.x"),
    ('{"type":"command","robots":["robot 1"],"action":"stop"}', "command: robots[0]: expected a name of letters, digits"),
    ('{"type":"command","robots":["r1"],"action":"goto","params":{"x":NaN,"y":0}}', "command: params.x"),
    ('{"type":"command","robots":["r1"],"action":"stop","extra":1}', "command: unknown key 'extra'"),
    ('{"type":"say","text":""}', "say: text: String should have at least 1 character"),
    ('{"type":"mic","on":true,"rate":44100}', "mic: rate: Input should be 16000"),
    ('{"type":"cancel_task"}', "cancel_task: missing 'uid'"),
])
def test_bad_messages_are_refused_naming_the_field(text, message):
    with pytest.raises(BadMessage) as err:
        parse_message(text)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


json_values = st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=20),
                           lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
                           max_leaves=12)


@given(st.dictionaries(st.sampled_from(["type", "robots", "action", "params", "text", "selection", "uid", "on", "rate"]),
                       json_values, max_size=6) | json_values)
def test_any_json_is_a_message_or_a_one_line_refusal(data):
    try:
        text = json.dumps(data)
    except ValueError:
        return
    try:
        msg = parse_message(text)
    except BadMessage as err:
        assert "\n" not in str(err)
    else:
        assert msg.type in ("command", "say", "select", "cancel_task", "mic", "ping")


@pytest.mark.parametrize("text,message", [
    ("[" * 100_000 + "]" * 100_000, "message of 200000 characters; expected at most 32768"),
    ('{"type":"ping","x":' + "[" * 1000 + "]" * 1000 + "}", "message nested 1001 levels deep; expected at most 8"),
    ('{"type":"say","text":"' + "[" * 1000 + '"}', "say: text: String should have at most 300 characters"),
], ids=["long", "deep", "brackets-in-a-string"])
def test_deep_or_long_text_is_refused_before_it_is_parsed(text, message):
    with pytest.raises(BadMessage) as err:
        parse_message(text)
    assert str(err.value).startswith(message)
    assert isinstance(err.value, HostileMessage) == ("expected at most 8" in message or "32768" in message)


def test_a_deeply_nested_message_gets_one_line_and_the_connection_closed(caplog):
    """Nesting that would make json.loads raise RecursionError: one answer, a close, no traceback."""
    got: list[Any] = []
    server = WebServer("127.0.0.1", 0, token="t0k", on_message=lambda c, m: got.append(m),
                       on_audio=lambda c, b: None, on_close=lambda c: None).start()

    async def talk() -> tuple[list[Any], Any]:
        answers: list[Any] = []
        url = f"http://127.0.0.1:{server.port}/ws?token=t0k"
        async with aiohttp.ClientSession() as s, s.ws_connect(url) as ws:
            await ws.send_str('{"type":"select","robots":' + "[" * 10_000 + "]" * 10_000 + "}")
            while (msg := await ws.receive(timeout=5)).type == aiohttp.WSMsgType.TEXT:
                answers.append(json.loads(msg.data))
            return answers, ws.close_code

    try:
        with caplog.at_level(logging.DEBUG):
            answers, code = asyncio.run(talk())
    finally:
        server.stop()
    errors = [a["message"] for a in answers if a["type"] == "error"]
    assert errors == ["message nested 10001 levels deep; expected at most 8; closing the connection"]
    assert code == 1009 and not got and server.bad_messages == 1
    assert not any(r.exc_info for r in caplog.records), [r.getMessage() for r in caplog.records]


@pytest.mark.parametrize("key", ["\n", "a\rb", "\x00", "\u2028"])
def test_a_refusal_naming_an_unprintable_key_is_one_line(key):
    import json

    text = json.dumps({"type": "command", "robots": ["robot1"], "action": "goto", "params": {key: 1}})
    with pytest.raises(BadMessage) as err:
        parse_message(text)
    assert len(str(err.value).splitlines()) == 1 and str(err.value).startswith("command: params."), str(err.value)
