"""The code blocks of README.md and of the site's pages (docs/**/*.md) run as written.

Each fenced block is taken by its language:

- `sh`: run with bash (`set -e`), from the repository for the docs of `REPO_CWD` (their paths are
  relative to it), from a scratch folder holding the doc's files for the others;
  background jobs it leaves are stopped after it;
- `python`: run with the interpreter, in the same folder;
- `toml`: parsed; a whole agent config (`[agent]`) is checked with `erni agent CONFIG --check`, a
  config fragment's `[[plugin]]` tables are validated against each plugin's settings model (a
  team key standing in for the identity the docs say to give it);
- `json`: parsed;
- no language: output or another program's file (babeld.conf), shown, not run.

A block preceded by `<!-- doc-test: file PATH -->` is a file of the example: written to PATH in
the scratch folder before the doc's blocks run, and checked like a block of its language only by
what runs it. A block preceded by `<!-- doc-test: skip: REASON -->` is not run: it needs root,
hardware, a network download, or runs until Ctrl-C; the reason names what tests it instead.
`EXTERNAL_SKIPS` holds the same for docs this test may not mark. The count of each kind is
pinned below, so a block added, dropped or newly skipped is a decision made here.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import pytest

from erni.blackboard.testing import wait_until
from erni.sim.team import port_free

ROOT = Path(__file__).resolve().parents[1]
DOCS = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md"))]
REPO_CWD = {"README.md", "docs/explanation/simulator.md", "docs/explanation/control-node.md",
            "docs/explanation/mission.md", "docs/tutorials/first-team.md",
            "docs/reference/agent-config.md"}  # their paths start at the repository
MARK = re.compile(r"^<!-- doc-test: (skip|file):? ?(.*?) -->$")
FENCE = re.compile(r"^```([\w-]*)\s*$")
# blocks of docs this test does not mark: (doc, the block's first line) -> why it is not run
EXTERNAL_SKIPS = {
    ("docs/explanation/mission.md", "erni agent examples/robot-mission.toml            # transport + motion + mobinet + mission"):
        "an agent that runs until Ctrl-C, tasked through a control node on 127.0.0.1:47100 "
        "(tests/mission/test_cli.py)",
}


@dataclass(frozen=True)
class Block:
    doc: str
    line: int  # of the opening fence, 1-based
    lang: str
    text: str
    mark: str = ""  # "", "skip" or "file"
    arg: str = ""  # the skip's reason or the file's path

    @property
    def id(self) -> str:
        return f"{self.doc}:{self.line}"


def blocks(doc: str) -> list[Block]:
    """Every fenced block of `doc`, with the marker on the line before its fence."""
    lines = (ROOT / doc).read_text(encoding="utf-8").splitlines()
    found: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        text = "\n".join(lines[i + 1:end]) + "\n"
        mark = MARK.match(lines[i - 1]) if i else None
        kind, arg = (mark.group(1), mark.group(2)) if mark else ("", "")
        external = EXTERNAL_SKIPS.get((doc, lines[i + 1] if i + 1 < end else ""))
        if external and not kind:
            kind, arg = "skip", external
        found.append(Block(doc, i + 1, m.group(1), text, kind, arg))
        i = end + 1
    return found


ALL = [b for doc in DOCS for b in blocks(doc)]
GUIDE = "docs/tutorials/first-plugin.md"
RUN = [b for b in ALL if not b.mark and b.lang in ("sh", "python", "toml", "json")]


def test_the_blocks_are_counted() -> None:
    """What runs, what is a file of an example, what is skipped (and why), what is only shown."""
    kinds = {"run": len(RUN), "file": sum(b.mark == "file" for b in ALL),
             "skip": sum(b.mark == "skip" for b in ALL),
             "shown": sum(not b.mark and b.lang not in ("sh", "python", "toml", "json") for b in ALL)}
    assert kinds == {"run": 17, "file": 4, "skip": 40, "shown": 9}, kinds
    for b in ALL:
        assert b.mark != "skip" or len(b.arg) > 20, f"{b.id}: a skip says why and what tests it instead"
        assert b.lang or b.mark != "file", f"{b.id}: a file of an example names its language"
    unknown = sorted({b.lang for b in ALL} - {"", "sh", "python", "toml", "json"})
    assert not unknown, f"blocks of a language this test does not know how to run: {unknown}"


@pytest.fixture(scope="module")
def workdirs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A scratch folder per doc holding the doc's files; the repository for docs whose paths start there."""
    dirs: dict[str, Path] = {}
    for doc in DOCS:
        if doc in REPO_CWD:
            dirs[doc] = ROOT
            continue
        folder = tmp_path_factory.mktemp(Path(doc).stem)
        for b in blocks(doc):
            if b.mark == "file":
                path = folder / b.arg
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(b.text, encoding="utf-8")
        dirs[doc] = folder
    return dirs


def _env(cwd: Path) -> dict[str, str]:
    """The environment of a user who installed ERNI: `erni` and `python` as on the PATH, no identity."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("ERNI_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTHONPATH", None)
    return env


def _run_sh(block: Block, cwd: Path, timeout: float = 90.0) -> subprocess.CompletedProcess[str]:
    for port in sorted({int(p) for p in re.findall(r"127\.0\.0\.1:(\d{4,5})", block.text)}):
        # a port of the kernel's ephemeral range (47100 is) may be held a moment by any socket bound to 0
        if "&" in block.text:
            with contextlib.suppress(AssertionError):  # still held: skipped below
                wait_until(partial(port_free, "127.0.0.1", port), timeout=20, interval=0.2)
        if not port_free("127.0.0.1", port) and "&" in block.text:
            pytest.skip(f"{block.id}: 127.0.0.1:{port} is in use on this machine; the block starts an agent there")
    # background jobs the block leaves (the agents of a two-terminal example) stop with it
    script = "set -e\ntrap 'kill $(jobs -p) 2>/dev/null || true; wait' EXIT\n" + block.text
    proc = subprocess.Popen(["bash", "-c", script], cwd=cwd, env=_env(cwd), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"{block.id}: still running after {timeout:g} s\n{out}\n{err}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _check_toml(block: Block, cwd: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = tomllib.loads(block.text)
    if "agent" in data:
        config = tmp_path / "config.toml"
        config.write_text(block.text, encoding="utf-8")
        out = subprocess.run([sys.executable, "-m", "erni", "agent", str(config), "--check"], cwd=cwd,
                             env=_env(cwd), capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, f"{block.id}: erni agent --check: {out.stderr}"
        return
    from erni.blackboard.agent import resolve_plugin, validate_settings

    # a fragment's transport gets its identity as the doc's text says (`erni keys issue`): a team key stands in
    monkeypatch.setenv("ERNI_TEAM_KEY", "a team key standing in for the identity")
    for plugin in data.get("plugin", []):
        cls = resolve_plugin(plugin["class"])
        validate_settings(cls, plugin.get("settings", {}))


@pytest.mark.parametrize("block", RUN, ids=[b.id for b in RUN])
def test_the_block_runs_as_written(block: Block, workdirs: dict[str, Path], tmp_path: Path,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    cwd = workdirs[block.doc]
    if block.lang == "json":
        json.loads(block.text)
    elif block.lang == "toml":
        _check_toml(block, cwd, tmp_path, monkeypatch)
    elif block.lang == "python":
        out = subprocess.run([sys.executable, "-c", block.text], cwd=cwd, env={**_env(cwd), "PYTHONPATH": "."},
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, f"{block.id}:\n{out.stderr}"
    else:
        out = _run_sh(block, cwd)
        assert out.returncode == 0, f"{block.id} exited {out.returncode}:\n{out.stdout}\n{out.stderr}"
        assert "Traceback" not in out.stderr, f"{block.id}:\n{out.stderr}"


def test_the_plugin_guide_tasks_its_plugin_and_its_test_passes(workdirs: dict[str, Path]) -> None:
    """The plugin tutorial: the agent of the guide's config is tasked by the guide's command, and the
    guide's test of the plugin passes (what the blocks above run, with their output read)."""
    (start, test) = [b for b in RUN if b.doc == GUIDE and b.lang == "sh"]
    out = _run_sh(start, workdirs[GUIDE])
    assert out.returncode == 0, out.stderr
    assert "greeter.toml: ok (agent robot1, 2 plugin(s): transport, greeter)" in out.stdout
    assert re.search(r"robot1 \w+ succeeded .* hi: going to \(1\.0, 2\.0\)", out.stdout), out.stdout
    out = _run_sh(test, workdirs[GUIDE])
    assert out.returncode == 0 and "2 passed" in out.stdout, out.stdout + out.stderr


def test_the_plugin_guide_pyproject_makes_an_installable_plugin(workdirs: dict[str, Path], tmp_path: Path) -> None:
    """The plugin tutorial's pyproject.toml is whole: a wheel built from the guide's folder holds the
    plugin's module and names it as an entry point of the group the agent reads."""
    import zipfile

    from erni.blackboard.agent import ENTRY_POINT_GROUP

    folder = workdirs[GUIDE]
    (folder / "mypackage" / "__init__.py").touch()
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                          "--wheel-dir", str(tmp_path), str(folder)], capture_output=True, text=True, timeout=300,
                         env=_env(folder))
    assert out.returncode == 0, out.stdout + out.stderr
    (wheel,) = tmp_path.glob("mypackage-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        entry_points = next(zf.read(n).decode() for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "mypackage/greeter.py" in names, names
    assert f"[{ENTRY_POINT_GROUP}]\ngreeter = mypackage.greeter:Greeter" in entry_points, entry_points


def test_the_readme_names_the_commands_erni_sim_prints() -> None:
    """The set-up paragraph quotes what `erni sim` prints for tasking the team from another terminal."""
    from types import SimpleNamespace

    from erni.commands.sim import _print_team

    class Robot:
        x = y = 0.0

    team = SimpleNamespace(control_address=("127.0.1.250", 47100), names=["robot1"], robots=[Robot()],
                           run_dir=Path("RUN"), mesh=None, url=None, cli_identity="RUN/keys/cli.pem",
                           agents={"robot1": SimpleNamespace(address=("127.0.1.1", 47100), pid=1),
                                   "control": SimpleNamespace(address=("127.0.1.250", 47100), pid=2)},
                           host=SimpleNamespace(url=lambda i: "socket://127.0.0.1:1"))
    import contextlib
    import io

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        _print_team(team, 1.0)
    commands = [line.strip() for line in printed.getvalue().splitlines()
                if line.strip().startswith(("export ", "erni "))]
    assert len(commands) == 5, printed.getvalue()
    setup = (ROOT / "README.md").read_text(encoding="utf-8").split("## Set up", 1)[1].split("Run the tests", 1)[0]
    setup = " ".join(setup.split())
    for command in commands:
        assert f"`{command}`" in setup, f"README's set-up paragraph does not quote `{command}`"
