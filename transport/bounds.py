"""Bounds on what the transport plugin holds for each sender: nothing one peer sends grows without limit.

An authenticated peer is not an authorized one, and an authorized one may still be hostile or
broken: a robot's key that sends 20,000 `NetInfo` objects under fresh uids, a client that gives
10,000 tasks, a Zenoh router without access control that lets anyone declare liveliness tokens in
fresh names. `SenderBounds` counts, for the transport plugin (`plugin.py`):

- status objects held per sender and type, in number and in bytes (their JSON), for the types
  whose uid the policy leaves free (a `Pose`, a `Peer`, a `Territory` has one uid per sender:
  one object each, at most a frame);
- tasks held per requester (the peer they came from), finished ones included until retention
  takes them;
- peers known only from hints (broadcast beacons, Zenoh liveliness tokens) and addresses learned
  from routing tables (MobiNet's `NetInfo`), in total and per source.

What is over a bound is refused and counted (the endpoint's counters: `refused.status_bound`,
`refused.task_bound`, `dropped.hint_bound`), never silently kept, and a warning says so at most
once per sender and bound every `WARN_EVERY` seconds, with the count since.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

WARN_EVERY = 10.0
"""Seconds between two warnings of one sender over one bound (the ones between are counted)."""


class SenderBounds:
    """What the transport holds for each sender, against the limits of its settings."""

    def __init__(self, settings: Any, count: Callable[[str], None], log: logging.Logger,
                 clock: Callable[[], float]):
        self.settings, self._count, self.log, self._clock = settings, count, log, clock
        self._status: dict[tuple[str, str], dict[str, int]] = {}  # (sender, type) -> uid -> bytes
        self._status_bytes: dict[tuple[str, str], int] = {}  # (sender, type) -> bytes held
        self._status_key: dict[str, tuple[str, str]] = {}  # uid -> (sender, type)
        self._tasks: dict[str, dict[str, None]] = {}  # requester -> uids of its tasks held, oldest first
        self._requester: dict[str, str] = {}  # task uid -> requester
        self._hinted: dict[str, str] = {}  # peer known only from a hint -> its source
        self._learned: dict[str, str] = {}  # address learned from a routing table -> its source
        self._by_source: dict[tuple[str, str], int] = {}  # ("peer" | "address", source) -> how many
        self._warned: dict[tuple[str, str], tuple[float, int]] = {}  # (who, bound) -> (last warned, since)

    # -- status objects -------------------------------------------------------------------

    def status(self, sender: str, type_name: str, uid: str, size: int) -> str:
        """Hold status `uid` of `sender` (`size` bytes of JSON; a change replaces the old size): ''
        when it fits, else why not (the caller refuses it)."""
        key = (sender, type_name)
        held = self._status.get(key)
        old = held.get(uid) if held is not None else None
        s = self.settings
        count = len(held) if held is not None else 0
        if old is None and count >= s.status_objects:
            return (f"{sender} holds {count} {type_name} objects here (status_objects = {s.status_objects}): "
                    f"{type_name} {uid[:64]} refused")
        total = self._status_bytes.get(key, 0) - (old or 0) + size
        if total > s.status_bytes:
            return (f"{sender}'s {type_name} objects would hold {total} bytes here (status_bytes = "
                    f"{s.status_bytes}): {type_name} {uid[:64]} of {size} bytes refused")
        if held is None:
            held = self._status[key] = {}
        held[uid] = size
        self._status_bytes[key] = total
        self._status_key[uid] = key
        return ""

    def status_gone(self, uid: str) -> None:
        """Status `uid` is no longer held (removed by its sender)."""
        key = self._status_key.pop(uid, None)
        if key is None:
            return
        held = self._status.get(key, {})
        size = held.pop(uid, 0)
        left = self._status_bytes.get(key, 0) - size
        if held:
            self._status_bytes[key] = left
        else:
            self._status.pop(key, None)
            self._status_bytes.pop(key, None)

    # -- tasks ----------------------------------------------------------------------------

    def tasks_of(self, requester: str) -> list[str]:
        """The uids of the tasks held for `requester`, oldest first."""
        return list(self._tasks.get(requester, ()))

    def task_full(self, requester: str) -> bool:
        """Whether `requester` holds `tasks_per_requester` tasks here already."""
        return len(self._tasks.get(requester, ())) >= int(self.settings.tasks_per_requester)

    def task(self, requester: str, uid: str) -> None:
        """Task `uid` of `requester` is held here (given now, or rehydrated)."""
        if self._requester.get(uid) == requester:
            return
        self.task_gone(uid)
        self._tasks.setdefault(requester, {})[uid] = None
        self._requester[uid] = requester

    def task_gone(self, uid: str) -> None:
        """Task `uid` left the board."""
        requester = self._requester.pop(uid, None)
        if requester is None:
            return
        held = self._tasks.get(requester)
        if held is not None:
            held.pop(uid, None)
            if not held:
                del self._tasks[requester]

    # -- hints ----------------------------------------------------------------------------

    def hint(self, name: str, source: str) -> str:
        """Hold peer `name`, known from a hint of `source`: '' when it fits, else why not."""
        if name in self._hinted:
            return ""
        return self._admit("peer", self._hinted, name, source)

    def learned(self, address: str, source: str) -> str:
        """Hold `address`, learned from the routing table of `source`: '' when it fits, else why not."""
        if address in self._learned:
            return ""
        return self._admit("address", self._learned, address, source)

    def _admit(self, what: str, held: dict[str, str], key: str, source: str) -> str:
        s = self.settings
        kind = "peers known only from hints" if what == "peer" else "addresses learned from routing tables"
        if len(held) >= s.hinted_peers:
            return f"{len(held)} {kind} (hinted_peers = {s.hinted_peers}): {what} {key[:64]} refused"
        mine = self._by_source.get((what, source), 0)
        if mine >= s.hinted_per_source:
            return (f"{mine} {kind} from {source[:64] or '(no source)'} (hinted_per_source = "
                    f"{s.hinted_per_source}): {what} {key[:64]} refused")
        held[key] = source
        self._by_source[(what, source)] = mine + 1
        return ""

    def is_hinted(self, name: str) -> bool:
        """Whether peer `name` is known only from hints (never heard in a session)."""
        return name in self._hinted

    def hint_gone(self, name: str) -> None:
        """Peer `name` is no longer a hint only: heard in a session, or forgotten."""
        source = self._hinted.pop(name, None)
        if source is not None:
            left = self._by_source.get(("peer", source), 1) - 1
            if left > 0:
                self._by_source[("peer", source)] = left
            else:
                self._by_source.pop(("peer", source), None)

    def hinted(self) -> int:
        """How many peers are known only from hints."""
        return len(self._hinted)

    # -- refusals -------------------------------------------------------------------------

    def refuse(self, counter: str, who: str, bound: str, why: str) -> None:
        """Count a refusal (`counter`) and warn of it, at most once per `who` and `bound` in
        `WARN_EVERY` seconds, with the number refused since the last warning."""
        self._count(counter)
        key = (who[:64], bound)
        now = self._clock()
        last, since = self._warned.get(key, (-math.inf, 0))
        if now - last < WARN_EVERY:
            self._warned[key] = (last, since + 1)
            return
        if len(self._warned) >= 4096 and key not in self._warned:  # bounded: forget the oldest
            del self._warned[next(iter(self._warned))]
        self._warned[key] = (now, 0)
        self.log.warning("over a bound: %s%s", why, f" (+{since} more refused since)" if since else "")
