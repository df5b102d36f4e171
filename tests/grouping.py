"""A pytest plugin: fail a file whose tests reach a second pytest-xdist worker.

The suite keeps a file on one worker (`--dist loadfile` in pyproject.toml's addopts), so that its
module fixtures (a team of agents, a browser) start once. Nothing else would notice if a pytest or
pytest-xdist release stopped honouring that, as one did with `--dist loadgroup`: two teams would start
at once and fail on time. tests/conftest.py loads this plugin; tests/test_grouping.py runs it on a
small suite with and without the grouping.
"""

from __future__ import annotations

import os

import pytest


@pytest.fixture(scope="module", autouse=True)
def one_worker_per_file(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> None:
    """Under pytest-xdist, fail a file whose tests reach a second worker: its module fixtures (a team,
    a browser) would start twice at once. `--dist loadfile` (pyproject.toml) keeps a file on one worker
    with every pytest-xdist; this is the check that it still does (tests/test_grouping.py checks the
    scheduling itself)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker is None:  # one process (-n 0): nothing to share
        return
    claims = tmp_path_factory.getbasetemp().parent / "file-owners"  # one folder per run, shared by its workers
    claims.mkdir(exist_ok=True)
    claim = claims / request.node.nodeid.replace("/", "_").replace(":", "_")
    mine = claims / f"{claim.name}.{worker}"
    mine.write_text(worker)
    try:
        os.link(mine, claim)  # atomic and exclusive: the first worker of the file owns it
    except FileExistsError:
        owner = claim.read_text().strip()
        if owner != worker:
            pytest.fail(f"{request.node.nodeid}: its tests run on {owner} and {worker} - the suite needs a file's "
                        f"tests on one worker (`--dist loadfile` in pyproject.toml's addopts)", pytrace=False)
