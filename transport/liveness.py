"""How long a peer may be silent before it is down, on a link that loses frames.

A quiet peer (one that sends us nothing else) tells it is alive by an in-session beacon every
interval, and `peer_timeout` spans a few of them (4 at the defaults). Over a lossy multi-hop path
a live peer loses that many in a row often: three hops at 30 % loss each deliver about a third of
the frames, and four beacons in a row are lost in about one window of five. So each beacon to a
peer carries its number (`Beacon.seq`, counted per receiver), the receiver counts how many of
them arrive (`BeaconCount`, recent beacons weighing most, less one standard error), and the
silence that marks that peer down is stretched until a live peer's chance of losing all the beacons in it is at most
`FALSE_DOWN` (`silence_stretch`), up to `MAX_STRETCH` times: on a link that loses nothing the
limit is `peer_timeout`, as before, and a dead peer on a very lossy one is down within ten.
"""

from __future__ import annotations

import math

FALSE_DOWN = 1e-3
"""The chance, at most, that a live peer loses every beacon of its silence limit."""

MAX_STRETCH = 10.0
"""The longest a silence limit grows, in multiples of the limit on a link that loses nothing."""

KEEP = 0.9
"""The weight the counts so far keep at each beacon that arrives (about the last 10 count). A
longer memory is steadier but slow when a link starts losing: simulated, a link that drops from
no loss to 70 % is taken for down 0.6 times on average in the next 100 beacons with 0.9, and 1.2
times with 0.98; on a steady link of 20-80 % delivery both are taken for down 1-2.5 times in
10 000 beacons."""

MIN_SENT = 3.0
"""Beacons a peer must have sent (by their numbers) before its count is used. A short count is
used with its wide standard error (`delivery()`), so a link that has lost some of only a few
beacons is already given a long limit."""

REORDERED = 8
"""A beacon this many numbers below the last counted is late (reordered); further below, the
peer counts again from the start (it restarted)."""


class BeaconCount:
    """How many of one peer's numbered beacons arrive: a ratio of the recent ones."""

    __slots__ = ("last", "got", "sent")

    def __init__(self) -> None:
        self.last = 0      # the newest number counted (0: none yet)
        self.got = 0.0     # beacons that arrived, each older one weighing KEEP times less
        self.sent = 0.0    # beacons the peer sent meanwhile, by their numbers, weighted alike

    def heard(self, seq: int) -> None:
        """Count the beacon numbered `seq` (a number below 1 is not counted)."""
        if seq < 1:
            return
        gap = seq - self.last
        if self.last and gap <= 0:
            if gap >= -REORDERED:
                return  # a duplicate, or one that came late: its number stays counted as lost (errs long)
            self.got = self.sent = 0.0  # the peer restarted and numbers from 1 again
        elif self.last:
            self.got = self.got * KEEP + 1.0
            self.sent = self.sent * KEEP + gap
        self.last = seq

    def share(self) -> float:
        """The share of the peer's recent beacons that arrived (1.0 until enough were sent)."""
        return self.got / self.sent if self.sent >= MIN_SENT else 1.0

    def delivery(self) -> float:
        """`share()` less one standard error of it: a limit stretched for it errs on the long side."""
        share = self.share()
        if share >= 1.0:
            return share
        return max(0.0, share - math.sqrt(share * (1.0 - share) / self.sent))


def silence_stretch(delivery: float, beacons: float) -> float:
    """How many times its lossless limit a peer may be silent when a share `delivery` of its
    beacons arrive and that limit spans `beacons` of them: at least 1, at most MAX_STRETCH."""
    if delivery >= 1.0:
        return 1.0
    if delivery <= 0.0:
        return MAX_STRETCH
    needed = math.log(FALSE_DOWN) / math.log1p(-delivery)  # beacons that all go lost with chance FALSE_DOWN
    return min(MAX_STRETCH, max(1.0, needed / beacons))
