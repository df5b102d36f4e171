"""Damage on an ARCOS link, counted per kind and logged so an operator sees it, never a flood.

The reader skips what does not frame (garbage bytes, bad checksums, impossible lengths) and the
decoder refuses what frames but does not parse (a truncated SIP, a sonar count of 255); each is
a count here. The first damage of a kind is logged at once; after that one line per kind at most
every `period` seconds, with how many came since the line before and in all.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from types import MappingProxyType

from erni.blackboard.clock import monotonic

KINDS = {
    "garbage_bytes": "bytes of garbage skipped",
    "bad_checksum": "packets with a bad checksum",
    "bad_length": "packets with an impossible length",
    "truncated_sip": "truncated SIPs",
    "bad_sonar_count": "SIPs with a sonar count they do not carry",
    "bad_packet": "other packets that do not parse",
}
"""Kind -> what its count counts (the log's words)."""


class LineDamage:
    """Counters of damage per kind; `note` counts and logs rate-limited, `flush` logs what waits."""

    def __init__(self, label: str, log: logging.Logger, *, period: float = 10.0,
                 clock: Callable[[], float] = monotonic) -> None:
        self.label, self.log, self.period, self.clock = label, log, period, clock
        self.totals: Mapping[str, int] = MappingProxyType({})  # replaced on change: readers take it as it is
        self._unlogged: dict[str, int] = {}
        self._detail: dict[str, str] = {}
        self._logged_at: dict[str, float] = {}

    def note(self, kind: str, count: int = 1, detail: str = "") -> None:
        """Count `count` damage of `kind` (one of KINDS); log it now if its kind has not been logged lately."""
        if count <= 0:
            return
        self.totals = MappingProxyType({**self.totals, kind: self.totals.get(kind, 0) + count})
        self._unlogged[kind] = self._unlogged.get(kind, 0) + count
        if detail:
            self._detail[kind] = detail
        self.flush(kind)

    def flush(self, only: str | None = None) -> None:
        """Log the counts of every kind (or `only`) whose period has passed since its last line."""
        if not self._unlogged:
            return
        now = self.clock()
        for kind in [only] if only is not None else list(self._unlogged):
            last = self._logged_at.get(kind)
            if kind not in self._unlogged or (last is not None and now - last < self.period):
                continue
            count = self._unlogged.pop(kind)
            self._logged_at[kind] = now
            since = "" if last is None else f" in the last {now - last:.0f} s, {self.totals.get(kind, 0)} in all"
            detail = self._detail.pop(kind, "")
            self.log.warning("%s: damaged data from the robot: %s: %d%s%s", self.label, KINDS.get(kind, kind),
                             count, since, f"; last: {detail}" if detail else "")

    def summary(self) -> str:
        """One line of the counts so far, '' without damage: `truncated_sip=3 garbage_bytes=40`."""
        return " ".join(f"{k}={v}" for k, v in sorted(self.totals.items()))
