"""The start-up heap of a long-running process, kept out of the cyclic garbage collector's way.

A started agent holds tens of thousands of objects it made at start (modules, classes, plugin
state, schemas) that live as long as the process. Python's collector scans all of them in each
full (generation 2) collection: 10-20 ms of CPU for a robot agent, far more in the simulator's
process, with the interpreter lock held the whole time. In a team on one machine every agent
starts at the same moment and so collects at about the same moment too, and the machine stalls
for every robot at once. `freeze()` moves what start-up left alive into the collector's
permanent generation (`gc.freeze`), so a full collection scans only what came after.

Frozen objects are still freed when their last reference goes; only a reference cycle among them
would outlive its use, so freeze what lives as long as the process, and `thaw()` before a
process tears down and builds again (a test run, a series of simulated teams).
"""

from __future__ import annotations

import gc


def freeze() -> int:
    """Collect what start-up left behind, then freeze every live object; return how many are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def thaw() -> None:
    """Give the frozen objects back to the collector (its oldest generation)."""
    gc.unfreeze()
