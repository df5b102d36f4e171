"""Text that is shown is text: the character set of names, and the printable form of any text.

A **name** (of an agent, a robot, a peer, the sender and receiver of a frame) is 1 to 63 characters:
ASCII letters, digits, `_`, `.` and `-`, the first a letter or a digit (`robot2`, `control`,
`sim-1.lab`). It is checked where a name enters: a config, an identity, a frame, a log or a bag
(a topic `/r\\x1b[2J/odom` names no robot), so it may be shown, put in a file name, a Zenoh key
or a ROS 2 topic as it is.

Any other text a peer or a file supplies (a result's message, a reason, a role) may hold any
character; `printable` escapes those that act on a terminal instead of showing (control and format
characters, line and paragraph separators) before it is printed, so it stays on its one line.
"""

from __future__ import annotations

import re
import unicodedata
from typing import Annotated, Any

from pydantic import AfterValidator

from erni.blackboard.errors import UsageError, shown

NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$"
"""The names of agents and robots (anchored at both ends; `$` as the Rust regex of pydantic's `pattern`
reads it: the end of the text). Python's `re` matches `$` before a final newline: use `is_name`."""
NAME_CHARS = "letters, digits, '_', '.', '-' (at most 63, the first a letter or a digit)"
"""The character set of a name, as an error message says it."""
NAME = re.compile(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,62}\Z")
"""`NAME_PATTERN` for Python's `re` (`NAME.match(text)`: the whole text, a final newline too)."""


_SEEN: dict[str, bool] = {}  # the answers for the few names a team has: every frame and Pose names one


def is_name(text: Any) -> bool:
    """Whether `text` is a name: a str of the name character set, whole."""
    if not isinstance(text, str):
        return False
    known = _SEEN.get(text)
    if known is None:
        known = NAME.match(text) is not None
        if len(_SEEN) < 4096 and len(text) <= 64:  # bounded: hostile strings cannot grow it
            _SEEN[text] = known
    return known


def check_name(text: str) -> str:
    """Return `text` if it is a name; raise UsageError naming the character set otherwise."""
    if not is_name(text):
        raise UsageError(f"expected a name of {NAME_CHARS}, got {shown(text)}")
    return text


def check_name_or_empty(text: str) -> str:
    """A name, or '' (a field not known yet)."""
    return text if text == "" else check_name(text)


Name = Annotated[str, AfterValidator(check_name)]
"""A str field that holds a name."""

NameOrEmpty = Annotated[str, AfterValidator(check_name_or_empty)]
"""A name, or '' where the field says it may be unknown."""

_HIDDEN = frozenset({"Cc", "Cf", "Cs", "Zl", "Zp"})  # control, format, surrogates, line and paragraph separators
_SHORT = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def _escaped(ch: str) -> str:
    if ch in _SHORT:
        return _SHORT[ch]
    code = ord(ch)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}" if code < 0x10000 else f"\\U{code:08x}"


def printable(text: str) -> str:
    """`text` with every character that is not shown but acts (ESC, BEL, a newline, a carriage return,
    DEL, the C1 controls, bidirectional overrides, zero-width and other format characters, line and
    paragraph separators) written as its Python escape (`\\x1b`, `\\n`, `\\u202e`): what a terminal
    prints is then exactly one line of visible characters, whatever a peer or a file put in it."""
    if text.isprintable():  # the common case: nothing to escape (spaces other than ' ' fall through)
        return text
    return "".join(_escaped(ch) if unicodedata.category(ch) in _HIDDEN else ch for ch in text)
