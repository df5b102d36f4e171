"""`erni tasks`: print the task language (verbs, prepositions, parameters)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from erni.blackboard.tasks import PREPOSITIONS, VERBS, language_table
from erni.commands._text import say_lines


def register(sub: Any) -> None:
    """Add the `tasks` sub-command."""
    p = sub.add_parser("tasks", help="print the task language",
                       description="Print every verb and preposition with its parameters.")
    p.add_argument("--json", action="store_true", help="JSON schema of each preposition's parameters")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print the language table (Markdown) or its JSON schemas."""
    if args.json:
        out = {verb: {"scope": v.scope, "handled_by": v.handled_by, "doc": v.doc,
                      "prepositions": {name: {"doc": p.doc, "params": p.params.model_json_schema()}
                                       for (vb, name), p in PREPOSITIONS.items() if vb == verb}}
               for verb, v in VERBS.items()}
        say_lines(json.dumps(out, indent=2))
    else:
        say_lines(language_table())
    return 0
