"""Logging set-up shared by the commands: one line per record, agent/plugin in the logger name."""

from __future__ import annotations

import logging
import re
import sys

FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"
SECRET = re.compile(r"(?i)(token=|bearer )[^\s&'\"]+")


def mask_secrets(text: str) -> str:
    """`text` with GUI tokens (`?token=...`, `Bearer ...`) shown as `***`: a log is no place for them."""
    return SECRET.sub(r"\1***", text)


class MaskingFormatter(logging.Formatter):
    """A formatter whose lines (exceptions included) never show a token."""

    def format(self, record: logging.LogRecord) -> str:
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
