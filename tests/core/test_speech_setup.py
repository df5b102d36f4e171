"""The README's first command gives the control node a speech front end, and `erni sim` says what it lacks."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from erni.commands import sim

ROOT = Path(__file__).resolve().parents[2]


def test_pocketsphinx_is_a_main_dependency() -> None:
    """`pip install .` brings the recogniser and its English model: the page is never left at 'no recogniser'."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert any(dep.split(">")[0].split("=")[0].strip() == "pocketsphinx" for dep in project["dependencies"])


def test_the_speech_front_end_has_a_recogniser_without_any_download(monkeypatch: pytest.MonkeyPatch) -> None:
    from erni.plugins.ui.speech import choose_recognizer

    monkeypatch.delenv("VOSK_MODEL_PATH", raising=False)
    loader = choose_recognizer("auto", None)
    assert loader.backend == "pocketsphinx"  # type: ignore[attr-defined]


def test_erni_sim_names_the_command_that_adds_spoken_feedback(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sim.shutil, "which", lambda exe: None)
    assert sim.speech_notes(headless=False) == [
        "spoken feedback off: espeak-ng is not installed (sudo apt install espeak-ng)"]
    assert sim.speech_notes(headless=True) == []
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert "`spoken feedback off: espeak-ng is not installed (sudo apt install espeak-ng)`" in readme


def test_erni_sim_names_the_command_that_adds_a_recogniser(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util

    monkeypatch.setattr(sim.shutil, "which", lambda exe: "/usr/bin/espeak-ng")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pocketsphinx" else real(name, *a))
    assert sim.speech_notes(headless=False) == ["voice commands off: no speech recogniser (pip install pocketsphinx)"]
