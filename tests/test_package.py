"""The distribution: one import name, its example data found after an install, strict types, lint."""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUNTIME = ("blackboard", "transport", "plugins")  # what runs on a robot: never the simulator


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(out), str(ROOT)], check=True, capture_output=True, timeout=300)
    (found,) = out.glob("erni-*.whl")
    return found


def test_the_wheel_installs_one_import_name(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        top_level = z.read(next(n for n in names if n.endswith(".dist-info/top_level.txt"))).decode().split()
        entry_points = z.read(next(n for n in names if n.endswith(".dist-info/entry_points.txt"))).decode()
    assert top_level == ["erni"]
    assert {n.split("/")[0] for n in names} == {"erni", wheel.name.split("-")[0] + "-" + wheel.name.split("-")[1]
                                                + ".dist-info"}
    for part in ("blackboard/agent.py", "transport/endpoint.py", "plugins/motion/arcos.py", "sim/team.py",
                 "netgraph/graph.py", "strategies/widep.py", "examples/scenario-poi.toml", "py.typed",
                 "plugins/ui/static/index.html"):
        assert f"erni/{part}" in names, part
    for line in entry_points.splitlines():  # every plugin entry point names a module inside erni
        if "=" in line and ":" in line:
            assert line.split("=", 1)[1].strip().startswith("erni."), line


def test_the_wheel_brings_the_speech_recogniser(wheel: Path) -> None:
    """`pip install .` installs PocketSphinx (and its English model) with ERNI, not only with an extra."""
    with zipfile.ZipFile(wheel) as z:
        meta = z.read(next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))).decode()
    requires = [line.split(":", 1)[1].strip() for line in meta.splitlines() if line.startswith("Requires-Dist:")]
    assert any(r.startswith("pocketsphinx") and "extra ==" not in r for r in requires), requires


def test_an_installed_copy_finds_its_example_scenarios_from_anywhere(wheel: Path, tmp_path: Path) -> None:
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target),
                    str(wheel)], check=True, capture_output=True, timeout=300)
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    code = ("import json, erni, erni.sim.scenario as s; "
            "print(json.dumps([erni.__file__, str(s.find_scenario('relay1')), s.load_scenario(s.find_scenario('poi')).count]))")
    env = {**os.environ, "PYTHONPATH": str(target)}
    out = subprocess.run([sys.executable, "-c", code], cwd=elsewhere, env=env, capture_output=True, text=True,
                         timeout=60, check=True).stdout
    package, relay1, robots = json.loads(out)
    assert Path(package).is_relative_to(target)
    assert Path(relay1) == target / "erni" / "examples" / "scenario-relay1.toml"
    assert robots == 3


def _imports(path: Path) -> list[str]:
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names += [node.module] + [f"{node.module}.{a.name}" for a in node.names]
    return names


def test_no_runtime_module_imports_the_simulator() -> None:
    offenders = []
    for folder in RUNTIME:
        for path in sorted((ROOT / folder).rglob("*.py")):
            offenders += [f"{path.relative_to(ROOT)}: {name}" for name in _imports(path)
                          if name == "erni.sim" or name.startswith("erni.sim.")]
    assert offenders == []


def test_loading_every_runtime_module_loads_nothing_of_the_simulator() -> None:
    modules = [".".join(("erni",) + p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
               for folder in RUNTIME for p in sorted((ROOT / folder).rglob("*.py"))]
    code = ("import importlib, json, sys\n"
            f"for m in {modules!r}: importlib.import_module(m)\n"
            "print(json.dumps(sorted(n for n in sys.modules if n == 'erni.sim' or n.startswith('erni.sim.'))))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         check=True).stdout
    assert len(modules) > 30
    assert json.loads(out) == []


def test_lint_refuses_bare_imports_of_the_source_folders(tmp_path: Path) -> None:
    clean = subprocess.run([sys.executable, "-m", "ruff", "check", "--quiet", str(ROOT)], cwd=ROOT,
                           capture_output=True, text=True, timeout=120)
    assert clean.returncode == 0, clean.stdout + clean.stderr
    bad = ROOT / "tests" / "_bare_import_probe.py"
    bad.write_text("import blackboard\nfrom plugins.motion import arcos\nfrom sim.team import Team\n")
    try:
        probe = subprocess.run([sys.executable, "-m", "ruff", "check", "--output-format", "concise",
                                "--no-cache", str(bad)], cwd=ROOT, capture_output=True, text=True, timeout=60)
    finally:
        bad.unlink()
    assert probe.returncode == 1
    assert probe.stdout.count("TID251") == 3, probe.stdout


def test_the_package_passes_mypy_strict() -> None:
    result = subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary"], cwd=ROOT, capture_output=True,
                            text=True, timeout=900)
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]


def _package_files() -> list[Path]:
    """Every source file of the package once (the linked folders through their own names)."""
    files = [p for folder in (*RUNTIME, "sim") for p in (ROOT / folder).rglob("*.py")]
    return sorted(files + [p for p in (ROOT / "erni").rglob("*.py") if not any(
        (ROOT / "erni" / link) in p.parents for link in ("blackboard", "transport", "plugins", "sim"))])


def test_every_error_class_of_the_package_derives_from_erni_error() -> None:
    import importlib
    import inspect

    from erni import ErniError

    errors = {}
    for path in _package_files():
        rel = path.relative_to(ROOT).with_suffix("")
        parts = rel.parts if rel.parts[0] == "erni" else ("erni", *rel.parts)
        name = ".".join(parts).removesuffix(".__init__")
        if name.endswith("__main__"):
            continue
        module = importlib.import_module(name)
        for cls_name, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, BaseException) and cls.__module__ == name:
                errors[f"{name}.{cls_name}"] = cls
    assert len(errors) >= 15, sorted(errors)
    assert sorted(n for n, cls in errors.items() if not issubclass(cls, ErniError)) == []


def test_no_builtin_exception_is_raised_outside_pydantic_validators() -> None:
    import builtins

    builtin = {n for n in dir(builtins) if isinstance(getattr(builtins, n), type)
               and issubclass(getattr(builtins, n), BaseException)}
    # ImportError: erni/__init__.py's own, when a checkout lacks the folders it is made of (it cannot
    # raise ERNI's errors: they live in those folders)
    allowed = {"NotImplementedError", "SystemExit", "KeyboardInterrupt", "AssertionError", "ImportError"}
    offenders = []
    for path in _package_files():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        in_validator = {id(node) for fn in ast.walk(tree) if isinstance(fn, ast.FunctionDef)
                        and any("validator" in ast.unparse(d) for d in fn.decorator_list) for node in ast.walk(fn)}
        # a module's __getattr__ (PEP 562: a package's names imported when first used, made by erni/_lazy.py) says a name it
        # lacks with AttributeError, which hasattr and getattr with a default rely on
        in_getattr = {id(node) for fn in ast.walk(tree) if isinstance(fn, ast.FunctionDef) and fn.name == "__getattr__"
                      for node in ast.walk(fn)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Raise) and node.exc is not None and id(node) not in in_validator:
                exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
                if isinstance(exc, ast.Name) and exc.id == "AttributeError" and id(node) in in_getattr:
                    continue
                if isinstance(exc, ast.Name) and exc.id in builtin - allowed:
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}: raise {exc.id}")
    assert offenders == []


def _smallest_plugin() -> str:
    text = (ROOT / "docs" / "tutorials" / "first-plugin.md").read_text(encoding="utf-8")
    section = text.split("## The smallest plugin", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def test_the_documented_smallest_plugin_is_strictly_typed(tmp_path: Path) -> None:
    example = tmp_path / "greeter.py"
    example.write_text(_smallest_plugin() + "\nreveal_type(Greeter().settings.greeting)\n", encoding="utf-8")
    result = subprocess.run([sys.executable, "-m", "mypy", "--strict", "--no-incremental", "--follow-imports=silent",
                             "--config-file", str(ROOT / "pyproject.toml"), str(example)],
                            cwd=ROOT, capture_output=True, text=True, timeout=600,
                            env={**os.environ, "MYPYPATH": str(ROOT)})
    assert re.search(r'Revealed type is "(builtins\.)?str"', result.stdout), result.stdout
    assert "error:" not in result.stdout, result.stdout


def test_the_documented_smallest_plugin_runs() -> None:
    from erni import TaskState
    from erni.testing import agent_with, run_task

    namespace: dict[str, object] = {}
    exec(compile(_smallest_plugin(), "docs/tutorials/first-plugin.md", "exec"), namespace)
    with agent_with(namespace["Greeter"], settings={"greeting": "hi"}, workers=1) as agent:  # type: ignore[arg-type]
        done = run_task(agent, "BotMotion", "goto", x=1, y=2)
    assert done.state is TaskState.SUCCEEDED and done.result is not None
    assert done.result.message == "hi: going to (1.0, 2.0)"
