"""Every surface of the at-scale fuzzer (`python -m tests.reliability.fuzz_run`), with a small budget.

CI gives each surface `ERNI_FUZZ_SCALE_EXAMPLES` inputs (default 200) through the same generators
and checks as the 100,000-input run, the deeper harnesses (`fuzz_deep.py`: onto the blackboard and
into the page state) included; none may crash, hang, make the product log a traceback or break an
invariant.
"""

from __future__ import annotations

import logging
import os

import pytest

from tests.reliability import fuzz_deep, fuzz_run

EXAMPLES = int(os.environ.get("ERNI_FUZZ_SCALE_EXAMPLES", "200"))


@pytest.fixture(scope="module", autouse=True)
def tracebacks():
    root = logging.getLogger()
    root.addHandler(fuzz_run.TRACEBACKS)
    fuzz_run.team()   # the endpoints of the transport surfaces, started before any test's thread check
    for start in (fuzz_deep.control, fuzz_deep.robot, fuzz_deep.page, fuzz_deep.replayer):
        start()   # ... and the agents, endpoints and web servers of the deeper harnesses
    yield
    root.removeHandler(fuzz_run.TRACEBACKS)
    fuzz_run.close_all()


@pytest.mark.parametrize("name", list(fuzz_run.SURFACES))
def test_surface(name):
    lines: list[str] = []
    result = fuzz_run.run_surface(name, EXAMPLES, seed=0, hang=10.0, report=lines.append)
    assert result.inputs == EXAMPLES
    assert result.crashes == 0 and result.violations == 0, "\n".join(result.examples)
