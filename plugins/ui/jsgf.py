"""ERNI's command grammar as a JSGF grammar, for a recogniser that decodes only what the parser accepts.

`jsgf()` writes the grammar from the same tables the parser reads (numbers, units, subjects,
questions, control phrases, fillers, strategies), so a recogniser restricted to it hears
"robots five and six turn right ninety degrees" rather than any string of the vocabulary.
The recogniser's grammar is the spoken core (see `jsgf()`); the parser accepts more.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

from erni.plugins.ui import grammar as g

HEADER = "#JSGF V1.0;\ngrammar erni;\n"


def _alts(words: Iterable[str]) -> str:
    return " | ".join(sorted(words))


def _spoken(word: str) -> bool:
    """Written forms (m, cm, ft, deg) and hesitations absent from dictionaries stay out of speech."""
    return word in set(g.vocabulary()) and bool(re.fullmatch(r"[a-z]+", word))


def _phrases(phrases: tuple[str, ...] | list[str]) -> str:
    return " | ".join(f"({p})" if " " in p else p for p in phrases)


def jsgf(robots: int = 20) -> str:
    """Return the JSGF grammar of the commands as spoken (public rule <utterance>).

    It is the spoken core of the parser's grammar: each command in its plain spoken forms, numbers
    in words, robot numbers up to `robots`, "please" at the end. Every optional word a recogniser
    may insert is a chance to mishear, so the typed variants (digits, "m/s", fillers anywhere,
    "could you") are left to the parser; everything this grammar produces, the parser understands.
    """
    units = sorted(u for u in g.UNITS if _spoken(u) and ("metre" not in u))  # one spelling per sound
    digits = [w for w, v in g.ONES.items() if v > 0]
    robot_numbers = [w for w, v in {**g.ONES, **g.TEENS, **g.TENS}.items() if 0 < v <= robots]
    questions = [p for phrases in g.QUESTIONS.values() for p in phrases]
    strategies = list(g._plain_strategies())
    rules = {
        "digit": _alts(digits),
        "teen": _alts(g.TEENS),
        "tens": _alts(g.TENS),
        "small": "<digit> | <teen> | <tens> [<digit>]",
        "int": "<small> | zero | <digit> hundred [<small>]",
        "number": "[minus] <int> [point <digit>]",
        "unit": _alts(units),
        "distance": "<number> [<unit>]",
        "n": _alts(robot_numbers),
        "subject": "robot <n> | robots <n> and <n> | everyone | all robots",
        "point": "<number> <number> | x <number> y <number>",
        "action": " | ".join([
            "stop", "halt", "freeze", "cancel", "clear", "random walk", "turn around",
            "turn (left | right) [<number> degrees]",
            "go to <point>", "go forward <distance>", "go back <distance>", "teleport to <point>",
            "set velocity to <number> [meters per second]", "avoid obstacles", "stop avoiding obstacles",
            "spread out [<distance>]", "cover <point>", "relay between robot <n> and (robot <n> | control)",
            "patrol from <point> to <point>", *(f"({s})" for s in strategies)]),
        "question": _phrases(questions),
        "ask": "where is <subject> | what is <subject> doing",
        "count": _phrases(g.COUNT_QUESTIONS),
        "control": _phrases(g.ATTENTION + g.SLEEP),
    }
    lines = [HEADER]
    lines += [f"<{name}> = {body};" for name, body in rules.items()]
    lines.append("public <utterance> = (<control> | <count> | <ask> | <subject> | [<subject>] (<action> | <question>))"
                 ";")
    return "\n".join(lines) + "\n"


def words(grammar: str) -> list[str]:
    """Every word a JSGF grammar can produce (its terminals)."""
    body = "\n".join(line.split("=", 1)[1] for line in grammar.splitlines() if "=" in line)
    return sorted(set(re.findall(r"(?<![<\w])[a-z]+(?![\w>])", body)))
