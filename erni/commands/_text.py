"""What the commands print: one line per event, its control characters escaped.

Every line a command prints goes through `say`, which escapes what would act on a terminal
instead of showing (`erni.blackboard.text.printable`): a result message, a name, a reason from a
peer, a file or a bag can neither retitle the window, clear the screen, move the cursor nor forge
a line of its own. A command's own text of several lines (a help, a table) goes through
`say_lines`, one line at a time.
"""

from __future__ import annotations

import sys
from typing import IO


def say(text: object = "", *, file: IO[str] | None = None, end: str = "\n", flush: bool = False) -> None:
    """Print `text` as one line with its control characters escaped (stdout unless `file`)."""
    from erni.blackboard.text import printable  # imported at the first line said: a parser is built without it
    print(printable(str(text)), file=file or sys.stdout, end=end, flush=flush)


def say_lines(text: str, *, file: IO[str] | None = None, flush: bool = False) -> None:
    """Print a command's own text of several lines: each line as `say` prints it."""
    for line in text.split("\n"):
        say(line, file=file, flush=flush)
