"""Suite-wide guards: every test must join the threads it started."""

from __future__ import annotations

import fcntl
import functools
import threading
import time
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, settings

# Shared 2-core machines are noisy: no per-example deadline, no "too slow" health check.
settings.register_profile("erni", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("erni")

pytest_plugins = ["tests.grouping"]  # fails a file whose tests reach a second xdist worker


def _extra_threads(before: set[threading.Thread]) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t not in before and t.is_alive()]


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """Fail a test that leaves a thread running (after a 2 s grace for joins in progress)."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    leaked = _extra_threads(before)
    while leaked and time.monotonic() < deadline:
        time.sleep(0.01)
        leaked = _extra_threads(before)
    if leaked:
        names = ", ".join(sorted(t.name for t in leaked))
        pytest.fail(f"test leaked {len(leaked)} thread(s): {names}", pytrace=False)


# -- the real-mesh tier: network namespaces, babeld and nftables are the machine's, not a worker's ----

REAL_MESH_LOCK_WAIT = 1800.0  # s: a progress timeout, far beyond the longest real-mesh file
REAL_MESH_FILES = pytest.StashKey[set[str]]()


@functools.cache
def real_mesh_unavailable() -> str | None:
    """Why this machine cannot run the real-mesh tier (None: it can), asked once per process."""
    from erni.sim import netns

    return netns.unavailable_reason()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    marked = [item for item in items if item.get_closest_marker("netns")]
    # a file that reads the machine's routing table holds the real-mesh lock too: a real-mesh team adds
    # and removes routes in the root namespace (its management links) while it runs
    routes = [item for item in items if item.get_closest_marker("host_routes")]
    config.stash[REAL_MESH_FILES] = {item.nodeid.split("::")[0] for item in marked + routes}
    if marked and (reason := real_mesh_unavailable()):
        for item in marked:
            item.add_marker(pytest.mark.skip(reason=f"real-mesh tier unavailable: {reason}"))


def _erni_namespaces() -> set[str]:
    from erni.sim import netns

    return {n for n in netns._namespaces() if netns.NAMESPACE.match(n)}


@pytest.fixture(scope="module", autouse=True)
def one_real_mesh_at_a_time(request: pytest.FixtureRequest) -> Iterator[None]:
    """A file with real-mesh tests holds a machine-wide lock while it runs (its module fixtures, a team
    in namespaces, included), whichever worker or pytest process runs it: no other test sees its
    namespaces appear, and no other run's clean-up of dead runs can take one of its own."""
    if request.node.nodeid not in request.config.stash.get(REAL_MESH_FILES, set()) or real_mesh_unavailable():
        yield
        return
    from erni.sim import netns

    netns.STATE_DIR.mkdir(mode=0o755, parents=True, exist_ok=True)
    with open(netns.STATE_DIR / "tests.lock", "w") as lock:
        deadline = time.monotonic() + REAL_MESH_LOCK_WAIT
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    pytest.fail(f"another real-mesh test held {lock.name} for {REAL_MESH_LOCK_WAIT:.0f} s",
                                pytrace=False)
                time.sleep(0.2)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(autouse=True)
def nothing_left_behind(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail a real-mesh test that leaves a namespace of its own behind (its file holds the lock, so
    every namespace that appeared during the test is the test's)."""
    if request.node.get_closest_marker("netns") is None or real_mesh_unavailable():
        yield
        return
    before = _erni_namespaces()
    yield
    left = _erni_namespaces() - before
    assert not left, f"the test left namespaces behind: {sorted(left)}"
