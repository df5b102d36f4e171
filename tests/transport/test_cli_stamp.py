"""The time a command prints beside a peer's result: any stamp a peer may send is printed, as a number
where no clock shows it (found by the fuzzer of frames after authentication: `erni task --wait`
raised OverflowError on a result stamped 1e300)."""

from __future__ import annotations

import argparse
import re

from erni.blackboard import AllocationResult, Task, TaskState
from erni.commands._client import stamp
from erni.commands.task import _line


def test_a_stamp_no_clock_shows_is_printed_as_its_number():
    for t in (1e300, -1e300, 1e20, -1e20):
        assert stamp(t) == f"t={t:g}"
    assert re.fullmatch(r"\d\d:\d\d:\d\d\.\d{3}", stamp(1_700_000_000.25))


def test_task_wait_prints_a_result_stamped_out_of_range_as_one_line():
    task = Task(verb="BotMotion", preposition="stop", destination="robot1", source="cli")
    result = AllocationResult(state=TaskState.RUNNING, message="on my way", stamp=1e300)
    line = _line(argparse.Namespace(json=False, agent="robot1"), task, result)
    assert line.startswith("t=1e+300 robot1 ") and "running" in line and "\n" not in line
