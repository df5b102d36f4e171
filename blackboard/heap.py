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

`cap_arenas()` keeps the threads of an agent on one malloc arena. glibc gives each thread that
allocates while another holds the arena's lock an arena of its own, and an agent's twenty threads
then keep pages in several: 0.6-1.5 MB of a robot agent's RSS (BENCHMARKS, "Memory above the import
floor"). Its threads take turns on the interpreter lock anyway, so they rarely wait on malloc's.

`trim()` gives back to the system the pages that start-up allocated and freed again (schemas
built while models were defined, parsed configs): malloc keeps them in its heap otherwise, and
a started robot agent holds 0.7-0.9 MB more for it.
"""

from __future__ import annotations

import ctypes
import gc
import os

M_ARENA_MAX = -8  # glibc's mallopt() parameter: the most arenas all threads share


def freeze() -> int:
    """Collect what start-up left behind, then freeze every live object; return how many are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def thaw() -> None:
    """Give the frozen objects back to the collector (its oldest generation)."""
    gc.unfreeze()


def cap_arenas(count: int = 1) -> bool:
    """Let this process's threads share at most `count` malloc arenas (glibc); True when set.

    Call it before threads start. An explicit `MALLOC_ARENA_MAX` in the environment wins, and a C
    library without `mallopt` (not glibc) is left as it is.
    """
    if "MALLOC_ARENA_MAX" in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_ARENA_MAX, count))


def trim() -> bool:
    """Return the free pages of malloc's heaps to the system (glibc's `malloc_trim`); True when some went.

    A C library without `malloc_trim` (not glibc) is left as it is.
    """
    try:
        malloc_trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return False
    return bool(malloc_trim(0))


def thread_arenas(pid: int | str = "self") -> int:
    """How many malloc arenas threads of a process made besides the main one.

    glibc reserves each one's heap as 64 MB on a 64 MB boundary: the part in use readable and
    writable, the rest inaccessible until it grows. Other anonymous mappings can start on such a
    boundary too (the kernel aligns large ones for huge pages), so the whole reservation is matched.
    """
    size = 64 << 20
    spans: list[tuple[int, int, str, bool]] = []  # start, end, permissions, anonymous
    with open(f"/proc/{pid}/maps") as f:
        for line in f:
            parts = line.split()
            lo, hi = (int(x, 16) for x in parts[0].split("-"))
            spans.append((lo, hi, parts[1], len(parts) == 5))
    count = 0
    for k, (lo, hi, perms, anonymous) in enumerate(spans):
        if not anonymous or lo % size or not perms.startswith("rw"):
            continue
        if hi - lo == size:  # grown to the whole reservation
            count += 1
        elif k + 1 < len(spans):
            nlo, nhi, nperms, nanonymous = spans[k + 1]
            if nanonymous and nlo == hi and nperms.startswith("---") and nhi == lo + size:
                count += 1
    return count
