"""The layout without symbolic links: a checkout where `erni/blackboard` is a text file naming
`../blackboard` (a zip, Windows, `git -c core.symlinks=false clone`) imports, finds its examples and
builds the same wheel; an editable install in strict mode type-checks a plugin author's module."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ("erni", "blackboard", "transport", "plugins", "sim", "examples")
LINKS = ("blackboard", "transport", "plugins", "sim", "examples")


def _without_links(dest: Path) -> Path:
    """Copy the package's source as git writes it with symlinks off: each link a file of its target."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in SOURCE:
        shutil.copytree(ROOT / name, dest / name, symlinks=True, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dest / name)
    for name in LINKS:
        link = dest / "erni" / name
        assert link.is_symlink(), f"erni/{name} is expected to be a link in the repository"
        target = os.readlink(link)
        link.unlink()
        link.write_text(target)
    return dest


@pytest.fixture(scope="module")
def linkless(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _without_links(tmp_path_factory.mktemp("linkless"))


def _run(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=cwd, env={**os.environ, **env}, capture_output=True, text=True, timeout=300)


def test_a_checkout_without_links_imports_every_part_and_finds_its_examples(linkless: Path, tmp_path: Path) -> None:
    assert (linkless / "erni" / "blackboard").read_text() == "../blackboard"
    code = ("import erni, erni.blackboard.agent, erni.transport.endpoint, erni.plugins.motion, erni.sim.scenario as s; "
            "print(erni.plugins.motion.__file__); print(s.find_scenario('poi'))")
    out = _run([sys.executable, "-c", code], tmp_path, PYTHONPATH=str(linkless))
    assert out.returncode == 0, out.stderr
    motion, poi = out.stdout.split()
    assert Path(motion) == linkless / "plugins" / "motion" / "__init__.py"
    assert Path(poi) == linkless / "examples" / "scenario-poi.toml"


def test_an_incomplete_checkout_fails_with_one_line_naming_what_is_missing(linkless: Path, tmp_path: Path) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(linkless / "erni", broken / "erni")
    out = _run([sys.executable, "-c", "import erni"], tmp_path, PYTHONPATH=str(broken))
    assert out.returncode != 0
    assert out.stderr.strip().splitlines()[-1].startswith("ImportError: erni: ")
    assert "blackboard/ package" in out.stderr


def _wheel_names(source: Path, out: Path) -> list[str]:
    done = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out),
                 str(source)], source)
    assert done.returncode == 0, done.stderr
    (wheel,) = out.glob("erni-*.whl")
    with zipfile.ZipFile(wheel) as z:
        return sorted(n for n in z.namelist() if ".dist-info/" not in n)


@pytest.mark.slow
def test_the_wheel_from_a_checkout_without_links_is_the_wheel_from_the_repository(linkless: Path,
                                                                                  tmp_path: Path) -> None:
    with_links = _wheel_names(_without_links_copy_kept(tmp_path / "linked"), tmp_path / "a")
    without = _wheel_names(linkless, tmp_path / "b")
    assert "erni/blackboard/agent.py" in without and "erni/examples/scenario-poi.toml" in without
    assert without == with_links


def _without_links_copy_kept(dest: Path) -> Path:
    """A copy of the package's source with its links kept (pip would build in place otherwise)."""
    for name in SOURCE:
        shutil.copytree(ROOT / name, dest / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dest / name)
    return dest


PLUGIN = '''
from erni import Plugin, Task


class Greeter(Plugin):
    def greeting(self, task: Task) -> str:
        return f"hello from {self.name}: {task.verb}"
'''


@pytest.mark.slow
def test_a_plugin_author_type_checks_against_a_strict_editable_install(linkless: Path, tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    # the venv sees the packages of the environment running the suite (pydantic, mypy, setuptools, as
    # installed from the lock), not the machine's own Python's, and installs ERNI itself
    inner = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                           capture_output=True, text=True, check=True).stdout.strip()
    outer = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (Path(inner) / "outer-environment.pth").write_text("".join(f"{path}\n" for path in sorted(outer)))
    done = _run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps",
                 "--no-build-isolation", "-e", str(linkless), "--config-settings", "editable_mode=strict"], tmp_path)
    assert done.returncode == 0, done.stderr
    author = tmp_path / "author"
    author.mkdir()
    (author / "greeter.py").write_text(PLUGIN)
    checked = _run([str(python), "-m", "mypy", "--strict", "--no-incremental", "greeter.py"], author)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    bad = author / "bad.py"
    bad.write_text(PLUGIN + "\n\nx: int = Greeter.greeting\n")
    refused = _run([str(python), "-m", "mypy", "--strict", "--no-incremental", "bad.py"], author)
    assert refused.returncode == 1 and "Incompatible types" in refused.stdout, refused.stdout


def test_the_mapped_packages_are_every_package_of_the_tree() -> None:
    from setuptools import find_packages

    listed = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    found = find_packages(str(ROOT), include=["erni", "erni.*"])  # through the links
    assert sorted(listed) == sorted([*found, "erni.examples"]), "pyproject.toml's [tool.setuptools] packages"
