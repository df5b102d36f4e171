"""The real-mesh tier's tests: skipped with the reason where namespaces cannot be made; none may leave any."""

from __future__ import annotations

import functools

import pytest

from erni.sim import netns


@functools.cache
def unavailable() -> str | None:
    """Why this machine cannot run the tier (None: it can), asked once per session."""
    return netns.unavailable_reason()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    marked = [item for item in items if item.get_closest_marker("netns")]
    if marked and (reason := unavailable()):
        for item in marked:
            item.add_marker(pytest.mark.skip(reason=f"real-mesh tier unavailable: {reason}"))


def erni_namespaces() -> set[str]:
    """The namespaces of erni runs that exist now."""
    return {n for n in netns._namespaces() if netns.NAMESPACE.match(n)}


@pytest.fixture(autouse=True)
def nothing_left_behind(request: pytest.FixtureRequest):
    """Fail a real-mesh test that leaves a namespace of its own behind."""
    if request.node.get_closest_marker("netns") is None or unavailable():
        yield
        return
    before = erni_namespaces()
    yield
    left = erni_namespaces() - before
    assert not left, f"the test left namespaces behind: {sorted(left)}"
