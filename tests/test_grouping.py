"""The suite's worker grouping, checked with the pytest and pytest-xdist that are installed.

A small suite of three files runs in a child pytest with the project's own addopts: every file's
tests must land on one worker (and the run must use more than one). The same suite under plain
`--dist load`, which spreads files, must be failed by tests/grouping.py's check: that check is
what tells the real suite that its grouping was lost.
"""

from __future__ import annotations

import collections
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS_PER_FILE = 20

SMALL_CONFTEST = """
import os
import pytest

pytest_plugins = ["tests.grouping"]

@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):  # before any fixture: where each test was sent
    with open({out!r}, "a") as f:
        f.write(f"{{item.module.__name__}} {{os.environ.get('PYTEST_XDIST_WORKER', 'none')}}\\n")
"""


def project_addopts() -> list[str]:
    """pyproject.toml's addopts without the marker selection (the small suite has no marks)."""
    words = shlex.split(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["addopts"])
    out: list[str] = []
    skip = False
    for word in words:
        if skip:
            skip = False
        elif word == "-m":
            skip = True
        else:
            out.append(word)
    return out


def run_small_suite(tmp_path: Path, options: list[str]) -> tuple[subprocess.CompletedProcess[str], dict[str, set[str]]]:
    suite = tmp_path / "suite"
    suite.mkdir()
    out = tmp_path / "workers.txt"
    (suite / "conftest.py").write_text(SMALL_CONFTEST.format(out=str(out)))
    for name in ("test_alpha", "test_beta", "test_gamma"):
        (suite / f"{name}.py").write_text("".join(f"def test_{i}():\n    pass\n" for i in range(TESTS_PER_FILE)))
    done = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-o", "addopts=",
                           "--rootdir", str(suite), "-c", "/dev/null", *options, str(suite)],
                          cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
                          capture_output=True, text=True, timeout=300)
    workers: dict[str, set[str]] = collections.defaultdict(set)
    if out.exists():
        for line in out.read_text().splitlines():
            module, worker = line.split()
            workers[module].add(worker)
    return done, workers


def test_the_project_options_keep_each_file_on_one_worker(tmp_path: Path) -> None:
    options = project_addopts()
    assert "-n" in options, options
    done, workers = run_small_suite(tmp_path, options)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert set(workers) == {"test_alpha", "test_beta", "test_gamma"}, workers
    assert all(len(w) == 1 for w in workers.values()), f"a file's tests ran on several workers: {dict(workers)}"
    assert len(set().union(*workers.values())) > 1, f"the run used one worker only: {dict(workers)}"


def test_a_file_spread_over_workers_fails_the_run_with_the_reason(tmp_path: Path) -> None:
    done, workers = run_small_suite(tmp_path, ["-n", "2", "--dist", "load"])
    assert any(len(w) > 1 for w in workers.values()), f"`--dist load` kept every file together: {dict(workers)}"
    assert done.returncode != 0
    assert "the suite needs a file's tests on one worker" in done.stdout, done.stdout[-3000:]
