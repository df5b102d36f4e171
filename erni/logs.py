"""Logging set-up shared by the commands: one line per record, agent/plugin in the logger name."""

from __future__ import annotations

import logging
import re
import sys
from collections.abc import Callable

from erni.blackboard.clock import monotonic
from erni.blackboard.text import printable

FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"
SECRET = re.compile(r"(?i)(token=|bearer )[^\s&'\"]+")


def mask_secrets(text: str) -> str:
    """`text` with GUI tokens (`?token=...`, `Bearer ...`) shown as `***`: a log is no place for them."""
    return SECRET.sub(r"\1***", text)


class MaskingFormatter(logging.Formatter):
    """A formatter whose lines (exceptions included) never show a token, and whose message is one line
    of printable text: a name or a reason from a peer that holds a terminal escape or a newline is
    shown escaped (`printable`). A traceback keeps its lines."""

    def format(self, record: logging.LogRecord) -> str:
        message = record.getMessage()
        shown = printable(message)
        if shown is not message:
            record = logging.makeLogRecord({**record.__dict__, "msg": shown, "args": None})
        return mask_secrets(super().format(record))


def setup_logging(level: str = "INFO") -> None:
    """Send log records to stderr as `time LEVEL erni.<agent>.<plugin>: message`."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(MaskingFormatter(FORMAT, datefmt="%H:%M:%S"))
    root.addHandler(handler)
    root.setLevel(level)


class RateLimitedLog:
    """Log each reason at most once per `period` seconds, with the count held back since: a peer or
    a page that repeats a bad input cannot flood the log. Reasons are a few fixed words (never a
    peer's text), so their table stays small."""

    def __init__(self, log: logging.Logger, period: float = 5.0, clock: Callable[[], float] = monotonic):
        self.log, self.period = log, period
        self.clock = clock
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, reason: str, text: str) -> None:
        """Log `text` as a warning, unless `reason` was logged less than `period` s ago (then count it)."""
        self._emit(logging.WARNING, reason, text)

    def info(self, reason: str, text: str) -> None:
        """As `warning`, at level INFO."""
        self._emit(logging.INFO, reason, text)

    def _emit(self, level: int, reason: str, text: str) -> None:
        now = self.clock()
        if now - self._last.get(reason, -1e9) >= self.period:
            more = self._suppressed.pop(reason, 0)
            self._last[reason] = now
            self.log.log(level, "%s%s", text, f" (+{more} more since last report)" if more else "")
        else:
            self._suppressed[reason] = self._suppressed.get(reason, 0) + 1
