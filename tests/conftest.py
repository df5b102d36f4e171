"""Suite-wide guards: every test must join the threads it started."""

from __future__ import annotations

import threading
import time

import pytest
from hypothesis import HealthCheck, settings

# Shared 2-core machines are noisy: no per-example deadline, no "too slow" health check.
settings.register_profile("erni", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("erni")


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook, which reads the groups into the node ids
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under pytest-xdist (`-n 3 --dist loadgroup`): a file's tests run on one worker, so its module
    fixtures (a team, a browser) start once, and every real-mesh test on the same one, since
    network namespaces and nftables are the machine's, not the worker's."""
    for item in items:
        group = "netns" if item.get_closest_marker("netns") else item.nodeid.split("::")[0]
        item.add_marker(pytest.mark.xdist_group(group))


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
