"""ERNI's command grammar as a JSGF grammar, for a recogniser that decodes only what the parser accepts.

`jsgf()` writes the grammar from the tables the parser reads (numbers, units, subjects, the spoken
forms of each action, questions, control phrases, fillers, strategies), so a phrase added to those
tables is heard as well as typed, and a recogniser restricted to it hears "robots one two and three
stop" rather than any string of the vocabulary. `Rules` reads such a grammar back: `accepts()` says
whether a sentence is in it and `sample()` draws sentences from it (the tests check that every
sentence of the spoken grammar is understood by the parser).
"""

from __future__ import annotations

import random
import re
from collections.abc import Iterable

from erni.blackboard.errors import ErniError
from erni.plugins.ui import grammar as g


class GrammarError(ErniError, ValueError):
    """A JSGF text `Rules` cannot read; the message says where."""


HEADER = "#JSGF V1.0;\ngrammar erni;\n"


def _alts(words: Iterable[str]) -> str:
    return " | ".join(sorted(words))


def _spoken(word: str) -> bool:
    """Written forms (m, cm, ft, deg) and hesitations absent from dictionaries stay out of speech."""
    return word in set(g.vocabulary()) and bool(re.fullmatch(r"[a-z]+", word))


def _phrases(phrases: Iterable[str]) -> str:
    return " | ".join(f"({p})" if " " in p else p for p in dict.fromkeys(phrases))


def jsgf(robots: int = 20, wake: Iterable[str] | None = None) -> str:
    """Return the JSGF grammar of the commands as spoken (public rule <utterance>).

    Numbers in every spoken form the parser takes ("two point five", "minus three", "one hundred
    and twenty", "half a", "one and a half"), robot numbers up to `robots`, any number of robots in
    a list ("robots one two and three": "and" before the last), every word for everyone
    ("everybody", "team", "all robots"), the wake words (`wake`, default `grammar.ATTENTION`), and
    a filler ("please", "uh", "hey") before the command, after its subject, and "please"/"thank
    you" at its end. Every optional word is a chance for noise to be heard as a word, so typed
    variants are left to the parser: written forms (digits, "m/s"), "robot 1 and 2", "turn left by
    90", the rarer fillers. Everything this grammar produces, the parser understands.
    """
    wake = tuple(wake) if wake is not None else g.ATTENTION
    units = sorted(u for u in g.UNITS if _spoken(u) and ("metre" not in u))  # one spelling per sound
    digits = [w for w, v in g.ONES.items() if v > 0]
    robot_numbers = [w for w, v in {**g.ONES, **g.TEENS, **g.TENS}.items() if 0 < v <= robots]
    questions = [p for phrases in g.QUESTIONS.values() for p in phrases]
    actions = [form for forms in g.SPOKEN_ACTIONS.values() for form in forms]
    actions += [f"({s})" for s in g._plain_strategies()]
    fillers = sorted(w for w in g.FILLER if w in ("please", "hey", "uh", "um", "okay"))  # the common ones:
    # each optional word is a chance for noise to be heard as a word
    rules = {
        "digit": _alts(digits),
        "any_digit": _alts(w for w in g.ONES),
        "teen": _alts(g.TEENS),
        "tens": _alts(g.TENS),
        "small": "<digit> | <teen> | <tens> [<digit>]",
        "hundreds": "(<digit> | a) hundred [[and] <small>]",
        "fraction": "point <any_digit> [<any_digit>]",
        "number": f"[{_alts(g.NEGATIVE)}] ((<small> | zero | oh) [<fraction>] [and a half] | <hundreds> [<fraction>] | "
                  "half [a | an] | (a | an) half)",
        "unit": _alts(units),
        "distance": "<number> [<unit>]",
        "n": _alts(robot_numbers),
        "everyone": _phrases([*sorted(g.EVERYONE - {"all"}), "all [robots]", *g.EVERYONE_PHRASES]),
        "robots": "robot <n> | robots <n> <n>* and <n>",  # "and" before the last: "one eight" never slips in
        "subject": "<everyone> | <robots>",
        "point": "[x] <distance> [and | comma] [y] <distance> | [the] origin",
        "action": " | ".join(f"({a})" for a in actions),
        "question": _phrases(questions),
        "asked": f"<robots> | ({_alts(g.EVERYONE)}) [robots]",
        "ask": "(where | how) (is | are) <asked> | what (is | are) <asked> doing",
        "count": _phrases(g.COUNT_QUESTIONS),
        "control": _phrases([*wake, *g.SLEEP, *g.CONFIRM, *g.DENY]),
        "filler": _alts(fillers),
        "polite": _phrases(["please", "thank you", "thanks"]),
    }
    lines = [HEADER]
    lines += [f"<{name}> = {body};" for name, body in rules.items()]
    lines.append("public <utterance> = [<filler>] (<control> | <count> | <ask> | <subject> | "
                 "[<subject> [<filler>]] (<action> | <question>)) [<polite>];")
    return "\n".join(lines) + "\n"


def words(grammar: str) -> list[str]:
    """Every word a JSGF grammar can produce (its terminals)."""
    body = "\n".join(line.split("=", 1)[1] for line in grammar.splitlines() if "=" in line)
    return sorted(set(re.findall(r"(?<![<\w])[a-z]+(?![\w>])", body)))


# -- reading a grammar back ----------------------------------------------------------------

_LEX = re.compile(r"\s*(<[\w.]+>|[()\[\]|*+]|[^\s()\[\]|*+<>;]+)")

Node = tuple[str, object]  # ("word", str) | ("ref", str) | ("seq", [Node]) | ("alt", [Node]) | ("opt"|"star"|"plus", Node)


class Rules:
    """A JSGF grammar (the subset `jsgf()` writes: words, <rules>, ( ), [ ], |, * and +) read back."""

    def __init__(self, grammar: str) -> None:
        self.rules: dict[str, Node] = {}
        self.public = ""
        for line in grammar.splitlines():
            m = re.match(r"\s*(public\s+)?<([\w.]+)>\s*=\s*(.*);\s*$", line)
            if m:
                self.rules[m.group(2)] = self._parse(m.group(3))
                if m.group(1):
                    self.public = m.group(2)
        if not self.public:
            raise GrammarError("the grammar has no public rule")
        self._regex = re.compile(self._pattern(("ref", self.public)) + r"\Z")

    def _parse(self, body: str) -> Node:
        tokens = [t for t in _LEX.findall(body) if t]
        node, end = self._alt(tokens, 0)
        if end != len(tokens):
            raise GrammarError(f"unexpected {tokens[end]!r} in {body!r}")
        return node

    def _alt(self, t: list[str], i: int) -> tuple[Node, int]:
        options = []
        node, i = self._seq(t, i)
        options.append(node)
        while i < len(t) and t[i] == "|":
            node, i = self._seq(t, i + 1)
            options.append(node)
        return (options[0] if len(options) == 1 else ("alt", options)), i

    def _seq(self, t: list[str], i: int) -> tuple[Node, int]:
        items: list[Node] = []
        while i < len(t) and t[i] not in ("|", ")", "]"):
            if t[i] in ("(", "["):
                close = ")" if t[i] == "(" else "]"
                inner, i = self._alt(t, i + 1)
                if i >= len(t) or t[i] != close:
                    raise GrammarError(f"expected {close!r}")
                node: Node = inner if close == ")" else ("opt", inner)
            elif t[i].startswith("<"):
                node = ("ref", t[i][1:-1])
            else:
                node = ("word", t[i])
            i += 1
            while i < len(t) and t[i] in ("*", "+"):
                node = ("star" if t[i] == "*" else "plus", node)
                i += 1
            items.append(node)
        return ("seq", items), i

    def _pattern(self, node: Node) -> str:
        kind, value = node
        if kind == "word":
            return re.escape(str(value)) + " "
        if kind == "ref":
            if value not in self.rules:
                raise GrammarError(f"undefined rule <{value}>")
            return self._pattern(self.rules[str(value)])
        if kind == "seq":
            return "".join(self._pattern(n) for n in value)  # type: ignore[attr-defined]
        if kind == "alt":
            return "(?:" + "|".join(self._pattern(n) for n in value) + ")"  # type: ignore[attr-defined]
        suffix = {"opt": "?", "star": "*", "plus": "+"}[kind]
        return "(?:" + self._pattern(value) + ")" + suffix  # type: ignore[arg-type]

    def accepts(self, sentence: str) -> bool:
        """True when the grammar produces this sentence (words separated by spaces)."""
        return self._regex.match(" ".join(sentence.split()) + " ") is not None

    def sample(self, rng: random.Random, rule: str | None = None) -> str:
        """A random sentence of the grammar (of `rule`, by default the public one)."""
        out: list[str] = []
        self._draw(("ref", rule or self.public), rng, out)
        return " ".join(out)

    def _draw(self, node: Node, rng: random.Random, out: list[str]) -> None:
        kind, value = node
        if kind == "word":
            out.append(str(value))
        elif kind == "ref":
            self._draw(self.rules[str(value)], rng, out)
        elif kind == "seq":
            for n in value:  # type: ignore[attr-defined]
                self._draw(n, rng, out)
        elif kind == "alt":
            self._draw(rng.choice(value), rng, out)  # type: ignore[arg-type]
        elif kind == "opt":
            if rng.random() < 0.5:
                self._draw(value, rng, out)  # type: ignore[arg-type]
        else:
            for _ in range((kind == "plus") + rng.choice((0, 0, 1, 2))):
                self._draw(value, rng, out)  # type: ignore[arg-type]
