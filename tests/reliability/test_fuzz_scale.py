"""Every surface of the at-scale fuzzer (`python -m tests.reliability.fuzz_run`), with a small budget.

CI gives each surface `ERNI_FUZZ_SCALE_EXAMPLES` inputs (default 200) through the same generators
and checks as the 100,000-input run; none may crash, hang or make the product log a traceback.
"""

from __future__ import annotations

import logging
import os

import pytest

from tests.reliability import fuzz_run

EXAMPLES = int(os.environ.get("ERNI_FUZZ_SCALE_EXAMPLES", "200"))


@pytest.fixture(scope="module", autouse=True)
def tracebacks():
    root = logging.getLogger()
    root.addHandler(fuzz_run.TRACEBACKS)
    fuzz_run.team()   # the endpoints of the transport surfaces, started before any test's thread check
    yield
    root.removeHandler(fuzz_run.TRACEBACKS)
    fuzz_run.close_all()


@pytest.mark.parametrize("name", list(fuzz_run.SURFACES))
def test_surface(name):
    lines: list[str] = []
    result = fuzz_run.run_surface(name, EXAMPLES, seed=0, hang=10.0, report=lines.append)
    assert result.inputs == EXAMPLES
    assert result.crashes == 0, "\n".join(result.examples)
