"""Text that is shown is text: names keep to their character set wherever they enter, and anything
printed for the operator (a command's line, a log line) holds no character that acts on a
terminal, and no second line."""

from __future__ import annotations

import ast
import json
import logging
import unicodedata
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from erni.blackboard import ConfigError, ErniError, NetInfo, Peer, Pose, Task
from erni.blackboard.config import parse_config
from erni.blackboard.schemas import PeerList, WatchEvent
from erni.blackboard.text import NAME_PATTERN, is_name, printable
from erni.logs import MaskingFormatter
from erni.transport import codec
from erni.transport.wire import EnvelopeHead

ROOT = Path(__file__).resolve().parents[2]
ACTING = ("Cc", "Cf", "Cs", "Zl", "Zp")

names = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,62}\Z")
not_names = (st.text(min_size=1, max_size=70).filter(lambda t: not is_name(t))
             | st.sampled_from(["", "robot 1", "robot1\n", "r\x1b[2J", "-robot", ".r", "_r", "r" * 64, "robot\u202e1",
                                "rôbot", "r/odom", "robot1\x00", "\n"]))

# every place an agent's or a robot's name enters as data, with the rest of a valid object
PLACES: list[tuple[str, Any]] = [
    ("Pose.robot", lambda n: Pose.model_validate({"robot": n})),
    ("Pose.robot from JSON", lambda n: Pose.model_validate_json(json.dumps({"robot": n}))),
    ("Peer.name", lambda n: Peer.model_validate({"name": n})),
    ("NetInfo.node", lambda n: NetInfo.model_validate({"node": n, "kind": "neighbor_list"})),
    ("Task.source", lambda n: Task.parse({"verb": "BotMotion", "preposition": "stop", "source": n or "?"})),
    ("Task.destination", lambda n: Task.parse({"verb": "BotMotion", "preposition": "stop", "destination": n})),
    ("PeerList.agent", lambda n: PeerList.model_validate({"agent": n, "peers": []})),
    ("WatchEvent.agent", lambda n: WatchEvent.model_validate({"agent": n, "op": "add", "type": "Pose", "data": {}})),
    ("EnvelopeHead.sender", lambda n: EnvelopeHead.model_validate({"sender": n})),
    ("EnvelopeHead.to", lambda n: EnvelopeHead.model_validate({"sender": "a", "to": n or "?"})),
    ("config agent.name", lambda n: parse_config(f"[agent]\nname = {json.dumps(n)}\n")),
    ("codec Pose", lambda n: codec.body_of("Pose", msgspec.Raw(json.dumps({"robot": n}).encode()))),
    ("codec head", lambda n: _codec_frame({"sender": n})),
    ("codec to", lambda n: _codec_frame({"sender": "a", "to": n or "?"})),
]


def _codec_frame(head: dict[str, str]) -> Any:
    """The receive path's codec on one envelope of a Pose under `head` (it returns None where it refuses)."""
    taken = codec.decode_data(json.dumps({**head, "id": "m", "kind": "status", "type": "Pose",
                                          "body": {"robot": "r1"}}).encode())
    if taken is None:
        raise ErniError("refused by the codec")
    return taken


def _refused(call: Any) -> bool:
    try:
        call()
    except (ValidationError, ErniError, ValueError, msgspec.ValidationError, msgspec.DecodeError):
        return True
    return False


@settings(max_examples=300, deadline=None)
@given(place=st.sampled_from(PLACES), name=not_names)
def test_a_name_outside_the_character_set_is_refused_wherever_it_enters(place, name):
    label, make = place
    assert _refused(lambda: make(name)), f"{label} took {name!r}"


@settings(max_examples=200, deadline=None)
@given(place=st.sampled_from(PLACES), name=names)
def test_every_name_of_the_character_set_is_taken_everywhere(place, name):
    label, make = place
    assert not _refused(lambda: make(name)), f"{label} refused {name!r}"


def test_the_refusal_names_the_character_set():
    with pytest.raises(ValidationError, match="expected a name of letters, digits, '_', '.', '-'"):
        Pose(robot="r\x1b[2J")
    with pytest.raises(ConfigError, match=r"agent.name: expected a name of .*got 'robot\\n'"):
        parse_config('[agent]\nname = "robot\\n"\n', "robot.toml")
    assert NAME_PATTERN == r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$"


@settings(max_examples=500, deadline=None)
@given(st.text())
def test_printable_text_holds_no_acting_character_and_no_second_line(text):
    shown = printable(text)
    assert not any(unicodedata.category(ch) in ACTING for ch in shown)
    assert "\n" not in shown and "\r" not in shown
    if all(unicodedata.category(ch) not in ACTING for ch in text):
        assert shown == text  # visible text is left as it is


def test_printable_escapes_as_python_does():
    assert printable("a\x1b[2J\x07b\nc\x7f\x9b\u202e\U000e0001") == "a\\x1b[2J\\x07b\\nc\\x7f\\x9b\\u202e\\U000e0001"
    assert printable("robot 1 — 90°") == "robot 1 — 90°"


def test_a_log_line_is_one_line_of_printable_text_and_a_traceback_keeps_its_lines():
    fmt = MaskingFormatter("%(levelname)s %(message)s")
    record = logging.LogRecord("erni.test", logging.WARNING, __file__, 1, "refused %s from %s", ("status", "r\x1b]0;x\x07\nFAKE"), None)
    assert fmt.format(record) == "WARNING refused status from r\\x1b]0;x\\x07\\nFAKE"
    try:
        raise ErniError("boom")
    except ErniError:
        import sys

        record = logging.LogRecord("erni.test", logging.ERROR, __file__, 1, "failed", (), sys.exc_info())
    assert fmt.format(record).count("\n") >= 2  # the traceback's own lines


def test_every_command_prints_through_say():
    """A command prints what is its own text with print() of literal text only; everything else,
    where a name or a message from a peer or a file may be, goes through `say` (escaped, one line)."""
    offenders = []
    for path in sorted((ROOT / "erni" / "commands").glob("*.py")) + [ROOT / "erni" / "cli.py"]:
        if path.name == "_text.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                if not all(isinstance(a, ast.Constant) for a in node.args):
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "write" \
                    and ast.unparse(node.func.value) in ("sys.stdout", "sys.stderr"):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} (sys.std*.write)")
    assert offenders == []
