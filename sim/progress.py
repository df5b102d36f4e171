"""Progress display for long simulator work: a redrawn bar on a terminal, milestone lines elsewhere."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """Shows `label done/total` as a bar on a terminal, or as a few plain lines when piped."""

    def __init__(self, stream: TextIO | None = None, width: int = 30, every: float = 2.0) -> None:
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.width = width
        self.every = every
        self._last_label = ""
        self._last_print = 0.0
        self._open = False
        self._t0 = time.monotonic()

    def __call__(self, label: str, done: float, total: float) -> None:
        """Report that `done` of `total` units of `label` are finished."""
        frac = 0.0 if total <= 0 else max(0.0, min(1.0, done / total))
        elapsed = time.monotonic() - self._t0
        if self.tty:
            filled = int(round(frac * self.width))
            bar = "#" * filled + "-" * (self.width - filled)
            amount = f"{done:g}/{total:g}" if total else ""
            self.stream.write(f"\r[{bar}] {amount:>9} {label:<28} {elapsed:5.1f} s\x1b[K")
            self.stream.flush()
            self._open = True
            return
        now = time.monotonic()
        if label != self._last_label or frac >= 1.0 or now - self._last_print >= self.every:
            if label != self._last_label or now - self._last_print >= self.every or (frac >= 1.0 and total):
                self.stream.write(f"  {label}: {done:g}/{total:g} ({elapsed:.1f} s)\n")
                self.stream.flush()
                self._last_print = now
            self._last_label = label

    def done(self, message: str = "") -> None:
        """End the bar (newline) and print `message` if any."""
        if self._open:
            self.stream.write("\n")
            self._open = False
        if message:
            self.stream.write(message + "\n")
        self.stream.flush()
