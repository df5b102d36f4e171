"""ERNI's command grammar as a JSGF grammar, for a recogniser that decodes only what the parser accepts.

`jsgf()` writes the grammar from the same tables the parser reads (numbers, units, subjects,
questions, control phrases, fillers, strategies), so a recogniser restricted to it hears
"robots five and six turn right ninety degrees" rather than any string of the vocabulary.
Fillers are allowed before and after a command (the parser drops them anywhere).
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


def jsgf() -> str:
    """Return the JSGF grammar of every utterance the command grammar understands (public rule <utterance>)."""
    units = [u for u in g.UNITS if _spoken(u)]
    degrees = [d for d in g.DEGREES if _spoken(d)]
    fillers = [f for f in g.FILLER if _spoken(f)] + list(g.FILLER_PHRASES)
    digits = [w for w, v in g.ONES.items() if v > 0]
    questions = [p for phrases in g.QUESTIONS.values() for p in phrases]
    strategies = [words for words in g._plain_strategies()]
    rules = {
        "digit": _alts(digits),
        "zero": "zero | oh",
        "teen": _alts(g.TEENS),
        "tens": _alts(g.TENS),
        "small": "<digit> | <teen> | <tens> [<digit>]",
        "int": "<small> | zero | [a | <digit>] hundred [and] [<small>]",
        "number": "[minus | negative] (<int> [point (<digit> | <zero>)+] [and a half] | half [a | an] | a half)",
        "unit": _alts(units),
        "distance": "<number> [<unit>]",
        "subject": "robot [number] <small> | robots <small> ([and] [robot] <small>)* | everyone | everybody "
                   "| all [robots] | team | every robot | all of you | you all",
        "point": "[x] <distance> [and | comma] [y] <distance> | origin",
        "stop": "(stop | halt | freeze)+ [everything | moving | all]",
        "cancel": "(cancel | abort) [that | it | everything] [all tasks | tasks | task]",
        "clear": "clear [all | everything] [tasks | behaviours | behaviors | stack]",
        "walk": "[do a | start a | start | do] (random walk | wander | explore) [around]",
        "turn": f"(turn | rotate) (around | [to] (left | right) [[by] <number> [{_alts(degrees)}]] "
                f"| [by] <number> [{_alts(degrees)}] [to] (left | right))",
        "goto": "(go | move | drive | head) to <point>",
        "forward": "[go | move | drive | head] (forward | forwards | ahead | straight) [ahead] <distance>",
        "backward": "[go | move | drive | head] (back | backward | backwards | reverse) [up] <distance>",
        "teleport": f"(teleport | jump) [to] <point> [(facing | heading) <number> [{_alts(degrees)}]]",
        "velocity": "(set velocity | set speed | velocity | speed | drive at | move at | go at) [to | of] <distance> "
                    "[per second]",
        "avoid": "avoid obstacles [on | off | (at | within | by) <distance>] | stop avoiding obstacles "
                 "| do not avoid obstacles",
        "spread": "spread [out] [<distance>]",
        "cover": "(cover | deploy to) <point>",
        "end": "[robot] <small> | control [node] | base [station]",
        "relay": "relay [between | for] <end> [and] <end>",
        "patrol": "patrol [from] <point> to <point>",
        "action": "<stop> | <cancel> | <clear> | <walk> | <turn> | <goto> | <forward> | <backward> | <teleport> "
                  "| <velocity> | <avoid> | <spread> | <cover> | <relay> | <patrol>"
                  + "".join(f" | ({s})" for s in strategies),
        "question": _phrases(questions),
        "ask": "(where is | where are | how is | how are) <subject> [doing] | (what is | what are) <subject> doing",
        "count": _phrases(g.COUNT_QUESTIONS),
        "control": _phrases(g.ATTENTION + g.SLEEP),
        "filler": _phrases(fillers),
    }
    lines = [HEADER]
    lines += [f"<{name}> = {body};" for name, body in rules.items()]
    lines.append("public <utterance> = (<control> | <count> | <ask> | <subject> "
                 "| [<subject>] (<action> | <question>) | <action> <subject>) [please];")
    return "\n".join(lines) + "\n"


def words(grammar: str) -> list[str]:
    """Every word a JSGF grammar can produce (its terminals)."""
    body = "\n".join(line.split("=", 1)[1] for line in grammar.splitlines() if "=" in line)
    return sorted(set(re.findall(r"(?<![<\w])[a-z]+(?![\w>])", body)))
