"""requirements.lock: what the suite runs with, in agreement with pyproject.toml's ranges.

pyproject.toml gives ranges (a library's users need them); the lock, made by `tools/lock.sh`
(uv's resolver, every platform, Python >= 3.11), pins one version of each package with its hashes.
The README's test command installs from it, so these tests are what keeps the two files one story.
"""

from __future__ import annotations

import importlib.metadata
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from packaging.markers import Marker, default_environment
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
LOCK = ROOT / "requirements.lock"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
LOCKED_EXTRAS = ("test",)  # what tools/lock.sh asks uv for, beside the runtime dependencies
REFRESH = "refresh it with tools/lock.sh and commit both files"

# Interpreters the lock is made for (requires-python >= 3.11), on Linux, where ERNI runs.
ENVIRONMENTS = [
    {"python_version": v, "python_full_version": f"{v}.0", "sys_platform": "linux", "platform_system": "Linux",
     "implementation_name": "cpython", "platform_python_implementation": "CPython", "os_name": "posix",
     "platform_machine": machine, "extra": ""}
    for v in ("3.11", "3.12", "3.13") for machine in ("x86_64", "aarch64")]


@dataclass
class Pin:
    name: str
    version: Version
    marker: Marker | None
    hashes: list[str] = field(default_factory=list)
    via: list[str] = field(default_factory=list)

    def applies(self, env: dict[str, str]) -> bool:
        return self.marker is None or self.marker.evaluate(env)


def read_lock(text: str) -> list[Pin]:
    """The pins of a uv / pip-compile requirements file: `name==version [; marker]`, hashes, `# via` lines."""
    pins: list[Pin] = []
    in_via = False
    for raw in text.splitlines():
        line = raw.strip()
        if not line or (line.startswith("#") and not pins):
            continue
        if m := re.match(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;\\]+)\s*(?:;\s*([^\\]+?))?\s*\\?$", raw):
            pins.append(Pin(canonicalize_name(m.group(1)), Version(m.group(2)),
                            Marker(m.group(3)) if m.group(3) else None))
            in_via = False
        elif line.startswith("--hash="):
            pins[-1].hashes.append(line.removeprefix("--hash=").rstrip(" \\"))
        elif line.startswith("# via"):
            rest = line.removeprefix("# via").strip()
            in_via = not rest
            if rest:
                pins[-1].via.append(rest)
        elif in_via and line.startswith("#"):
            pins[-1].via.append(line.lstrip("# ").strip())
        else:
            raise AssertionError(f"requirements.lock: unexpected line {raw!r}")
    return pins


@pytest.fixture(scope="module")
def pins() -> list[Pin]:
    assert LOCK.is_file(), f"requirements.lock is missing: {REFRESH}"
    return read_lock(LOCK.read_text())


def direct_requirements() -> list[Requirement]:
    project = PYPROJECT["project"]
    reqs = [Requirement(r) for r in project["dependencies"]]
    for extra in LOCKED_EXTRAS:
        reqs += [Requirement(r) for r in project["optional-dependencies"][extra]]
    return reqs


def test_every_line_of_the_lock_is_a_hashed_pin(pins: list[Pin]) -> None:
    assert len(pins) > 20, "requirements.lock holds almost nothing"
    unhashed = [p.name for p in pins if not p.hashes or not all(h.startswith("sha256:") for h in p.hashes)]
    assert not unhashed, f"pins without sha256 hashes: {unhashed} ({REFRESH})"
    assert "tools/lock.sh" in LOCK.read_text().split("\n", 3)[1], "the lock's header should name tools/lock.sh"


def test_every_requirement_of_pyproject_is_locked_within_its_range(pins: list[Pin]) -> None:
    """Each direct dependency (runtime and test), in every supported environment, has one pin inside its range."""
    problems = []
    for req in direct_requirements():
        for env in ENVIRONMENTS:
            if req.marker is not None and not req.marker.evaluate(env):
                continue
            found = [p for p in pins if p.name == canonicalize_name(req.name) and p.applies(env)]
            if len(found) != 1:
                problems.append(f"{req}: {len(found)} pins for Python {env['python_version']} "
                                f"on {env['platform_machine']}")
            elif not req.specifier.contains(found[0].version, prereleases=True):
                problems.append(f"{req}: locked {found[0].version}")
    assert not problems, f"requirements.lock disagrees with pyproject.toml ({REFRESH}): " + "; ".join(sorted(set(problems)))


def test_every_optional_extra_is_served_by_the_lock(pins: list[Pin]) -> None:
    """`erni[speech]`, `[zenoh]`, `[ros2]`, `[bench]`: each of their ranges holds the version the tests used."""
    problems = []
    for extra, reqs in PYPROJECT["project"]["optional-dependencies"].items():
        for req in map(Requirement, reqs):
            found = [p for p in pins if p.name == canonicalize_name(req.name)]
            if not found or not any(req.specifier.contains(p.version, prereleases=True) for p in found):
                problems.append(f"[{extra}] {req}: locked {[str(p.version) for p in found] or 'nothing'}")
    assert not problems, "; ".join(problems)


def test_the_lock_holds_nothing_that_pyproject_no_longer_asks_for(pins: list[Pin]) -> None:
    """A pin that names pyproject.toml as its reason is one of its requirements now; every pin has a reason."""
    direct = {canonicalize_name(r.name) for r in direct_requirements()}
    stale = [p.name for p in pins if "erni (pyproject.toml)" in p.via and p.name not in direct]
    assert not stale, f"locked for pyproject.toml but no longer asked for there: {stale} ({REFRESH})"
    locked = {p.name for p in pins}
    orphans = [p.name for p in pins if not any(v == "erni (pyproject.toml)" or canonicalize_name(v) in locked
                                               for v in p.via)]
    assert not orphans, f"pins that nothing needs: {orphans} ({REFRESH})"


def test_the_installed_versions_are_the_locked_ones(pins: list[Pin]) -> None:
    """The suite runs with what the lock says: installed from it as the README does, nothing newer, nothing older."""
    env = {**default_environment(), "extra": ""}
    differ = []
    for pin in (p for p in pins if p.applies(env)):
        try:
            have = Version(importlib.metadata.version(pin.name))
        except importlib.metadata.PackageNotFoundError:
            differ.append(f"{pin.name} not installed (locked {pin.version})")
            continue
        if have != pin.version:
            differ.append(f"{pin.name} {have} (locked {pin.version})")
    assert not differ, ("installed versions differ from requirements.lock: " + ", ".join(differ) +
                        "; install as the README says (pip install -r requirements.lock) or, after changing "
                        "pyproject.toml, " + REFRESH)


def test_read_lock_reads_markers_hashes_and_reasons() -> None:
    text = ("# header\n#    tools/lock.sh\n"
            "numpy==2.4.6 ; python_full_version < '3.12' \\\n    --hash=sha256:aa \\\n    --hash=sha256:bb\n"
            "    # via\n    #   erni (pyproject.toml)\n    #   scipy\n"
            "scipy==1.17.1 \\\n    --hash=sha256:cc\n    # via erni (pyproject.toml)\n")
    numpy, scipy = read_lock(text)
    assert (numpy.name, str(numpy.version), numpy.hashes, numpy.via) == (
        "numpy", "2.4.6", ["sha256:aa", "sha256:bb"], ["erni (pyproject.toml)", "scipy"])
    assert numpy.applies(ENVIRONMENTS[0]) and not numpy.applies(ENVIRONMENTS[2])
    assert scipy.marker is None and scipy.via == ["erni (pyproject.toml)"]
    with pytest.raises(AssertionError, match="unexpected line"):
        read_lock("numpy>=2 \\\n    --hash=sha256:aa\n")


def test_ci_runs_the_readme_test_command_in_a_new_environment() -> None:
    """.ci/run runs the README's test command as written (each line, stopping CI when it fails)."""
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```sh\n(.*?)```", readme, re.S)
    (command,) = [b for b in blocks if "pytest -q" in b and "requirements.lock" in b]
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    lines = [line.strip() for line in command.strip().splitlines()]
    assert lines[0].startswith("python3 -m venv "), f"the README's test command should start in a new venv: {lines}"
    at = [ci.index(f"{line} || exit 1") if f"{line} || exit 1" in ci else -1 for line in lines]
    assert -1 not in at, f".ci/run does not run the README's test command {lines} (each line followed by `|| exit 1`)"
    assert at == sorted(at) and at[-1] - at[0] == len(lines) - 1, f".ci/run runs the README's lines apart: {at}"
