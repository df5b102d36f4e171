"""The browser's microphone, end to end: Chromium captures a WAV file as its microphone, the page
streams it over the WebSocket, the control node's recogniser receives 16 kHz mono PCM, and
what it recognises is answered on the page. With VOSK_MODEL_PATH set, the real recogniser
hears espeak-ng saying "attention"."""

from __future__ import annotations

import contextlib
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import erni.plugins.ui.plugin as ui_plugin
from erni.blackboard import Agent, Pose
from erni.blackboard.testing import wait_until
from erni.plugins.ui import UIPlugin
from erni.plugins.ui.speech import RATE
from tests.ui.test_browser import ARGS, CHROMIUM
from tests.ui.test_speech import dominant_hz, write_wav

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"no Chromium at {CHROMIUM} (apt install chromium)")
ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts" / "ui"


class Recorder:
    """Stands in for vosk to capture what reaches the recogniser; 'hears' a text at each flush."""

    def __init__(self, text: str | None) -> None:
        self.text = text
        self.pcm = bytearray()
        self.chunks = 0
        self.threads: set[str] = set()
        self.lock = threading.Lock()

    def feed(self, pcm: bytes) -> str | None:
        with self.lock:
            self.pcm += pcm
            self.chunks += 1
            self.threads.add(threading.current_thread().name)
        return None

    def stream(self) -> Recorder:
        return self

    def flush(self) -> str | None:
        return self.text


def start_control(settings: dict[str, Any]) -> tuple[Agent, UIPlugin]:
    agent = Agent("control", workers=2)
    ui = agent.add_plugin(UIPlugin, settings={"listen": "127.0.0.1:0", "speak": False, "verb": "BotMotion",
                                              "rate_hz": 20, **settings}, name="ui")
    agent.start()
    with agent.transaction() as tx:
        tx.add(Pose(robot="robot1", x=0.0, y=0.0))
    return agent, ui  # type: ignore[return-value]


def streamed(ui: UIPlugin, monkeypatch: pytest.MonkeyPatch) -> Callable[[], float]:
    """Count the audio the page streams to the recogniser: return a function giving the seconds of it
    received so far (16 kHz, 16-bit mono)."""
    listener = ui.listener
    assert listener is not None, ui.speech_error
    got = [0]
    feed = listener.feed

    def counted(source: str, pcm: bytes) -> None:
        got[0] += len(pcm)
        feed(source, pcm)

    monkeypatch.setattr(listener, "feed", counted)
    return lambda: got[0] / (2 * RATE)


def heard_everything(ui: UIPlugin, timeout: float = 30.0) -> None:
    """Wait until the recogniser has heard all the audio the page streamed and the UI's answers are
    committed and shown. The page's microphone is off once its utterance was flushed (its stream is
    gone); a flush of a source of our own queued after that is taken off the queue only when the
    page's last utterance was heard (one thread hears them in turn); a marker handed to the UI then
    runs after the runs that answered it, and its picture holds the tasks they sent."""
    listener = ui.listener
    assert listener is not None
    wait_until(lambda: not ui.mic_clients and not listener.streams, timeout=timeout,
               message="the page's microphone was not turned off and flushed")
    listener.end_utterance("test")
    wait_until(listener.queue.empty, timeout=timeout, message="the recogniser did not hear what it was given")
    done = threading.Event()
    ui.later(lambda: ui.after_commit(done.set))
    assert done.wait(timeout), f"the UI did not run within {timeout} s"


def open_with_microphone(wav: Path, url: str, body: Any) -> Any:
    """Run `body(page)` in a Chromium whose microphone plays `wav`."""
    from playwright.sync_api import sync_playwright

    args = ARGS + ["--use-fake-ui-for-media-stream", "--use-fake-device-for-media-stream",
                   f"--use-file-for-fake-audio-capture={wav}", "--autoplay-policy=no-user-gesture-required"]
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=args)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 850})
            page.goto(url)
            page.wait_for_selector('g.robot[data-name="robot1"]')
            return body(page)
        finally:
            browser.close()


@pytest.fixture
def recorder(monkeypatch) -> Iterator[Recorder]:
    rec = Recorder("attention")
    monkeypatch.setattr(ui_plugin, "choose_recognizer", lambda kind, vosk_model, wake=None, front=None: lambda: rec)
    yield rec


def test_the_page_streams_its_microphone_as_16k_mono_pcm(tmp_path, recorder):
    rate = 48000
    t = np.arange(rate * 3) / rate
    wav = write_wav(tmp_path / "tone.wav", 9000 * np.sin(2 * np.pi * 440.0 * t), rate)
    agent, ui = start_control({})
    try:
        def body(page: Any) -> str:
            page.wait_for_selector("#mic:not([disabled])")
            page.click("#mic")
            page.wait_for_selector("#mic.on")
            wait_until(lambda: len(recorder.pcm) >= 2 * RATE * 2, timeout=15, message="no microphone audio arrived")
            page.click("#mic")  # off: the utterance ends, the recogniser is flushed
            page.wait_for_function("document.querySelector('#last-reply .said') && "
                                   "document.querySelector('#last-reply .said').textContent === 'Listening'")
            (ARTIFACTS / "10-microphone.png").parent.mkdir(parents=True, exist_ok=True)
            (ARTIFACTS / "10-microphone.png").write_bytes(page.screenshot())
            return page.inner_text("#listening")

        listening = open_with_microphone(wav, ui.url, body)
    finally:
        agent.stop()
    with recorder.lock:
        pcm = bytes(recorder.pcm)
    assert len(pcm) % 2 == 0 and recorder.threads == {"ui-speech"}
    second = pcm[RATE * 2: 2 * RATE * 2]  # the second second: past the start-up (slower on a loaded machine)
    assert dominant_hz(second) == pytest.approx(440.0, abs=5)  # 16 kHz: a 440 Hz tone stays at 440 Hz
    level = np.abs(np.frombuffer(second, dtype="<i2")).max()
    assert 3000 < level < 20000  # a mono signal at the file's level, not silence or clipping
    assert listening == "voice: listening"


@pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng is not installed")
def test_pocketsphinx_hears_listen_through_the_browser_microphone(tmp_path, monkeypatch):
    pytest.importorskip("pocketsphinx")
    from tests.ui.test_recognition import as_heard, speak

    monkeypatch.delenv("VOSK_MODEL_PATH", raising=False)
    pcm = as_heard(speak(tmp_path, "listen"), np.random.default_rng(3))
    wav = write_wav(tmp_path / "listen.wav", np.frombuffer(pcm, dtype="<i2"), RATE)
    agent, ui = start_control({})
    try:
        def body(page: Any) -> None:
            page.wait_for_selector("#mic:not([disabled])", timeout=20000)
            page.click("#mic")
            page.wait_for_function("document.querySelector('#last-reply .said') && "
                                   "document.querySelector('#last-reply .said').textContent === 'Listening'",
                                   timeout=30000)

        open_with_microphone(wav, ui.url, body)
    finally:
        agent.stop()


# A representative part of the speech test set, said with pauses between, in a quiet room (white
# noise runs the whole session, and steady noise keeps the voice activity detector from ending an
# utterance: the noise conditions are measured clip by clip, tests/ui/test_speech_set.py): the wake
# word, a stop to everybody, a turn, a line outside the grammar (nothing may move), a list of three robots.
SESSION = ["listen", "everybody stop", "robot two turn left", "robot three go home", "robots one two and three stop"]


@pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng is not installed")
def test_spoken_commands_streamed_in_real_time_through_the_page_do_only_what_was_said(tmp_path, monkeypatch):
    """Chromium plays the session as its microphone, in real time; the page streams it to the control
    node, PocketSphinx hears it. Every task sent is one the operator said, and the stops reach every robot."""
    pytest.importorskip("pocketsphinx")
    from erni.blackboard import Task
    from tests.ui import speech_set as S

    monkeypatch.delenv("VOSK_MODEL_PATH", raising=False)
    rng = np.random.default_rng(15)
    parts = [np.zeros(RATE)]
    for text in SESSION:
        parts += [S.synthesise(text, "en-us", 160), np.zeros(int(1.5 * RATE))]
    pcm = np.frombuffer(S.as_heard(np.concatenate(parts), None, rng), dtype="<i2")
    wav = write_wav(tmp_path / "session.wav", pcm, RATE)
    seconds = len(pcm) / RATE
    agent, ui = start_control({})
    received = streamed(ui, monkeypatch)
    with agent.transaction() as tx:
        for name in ("robot2", "robot3"):
            tx.add(Pose(robot=name, x=1.0, y=1.0))
    try:
        def body(page: Any) -> None:
            page.wait_for_selector("#mic:not([disabled])", timeout=20000)
            page.click("#mic")
            page.wait_for_selector("#mic.on")
            # one pass of the file, as the control node receives it (Chromium loops it)
            wait_until(lambda: received() >= seconds - 0.5, timeout=seconds + 60,
                       message=f"the {seconds:.1f} s session did not reach the recogniser in one pass")
            # on a loaded machine the stream runs behind the file: the mic stays on until the session's
            # last command, its second stop, has been heard (a loop's replay says nothing new)
            with contextlib.suppress(AssertionError):
                wait_until(lambda: sum("stop" in line["text"] for line in ui.server.state()["log"]
                                       if line["text"].startswith("voice:")) >= 2, timeout=30)
            page.click("#mic")

        open_with_microphone(wav, ui.url, body)
        heard_everything(ui)
        tasks = [(t.preposition, t.destination, t.params.model_dump().get("angle")) for t in agent.query(Task)]
        log = [line["text"] for line in ui.server.state()["log"] if line["text"].startswith("voice:")]
    finally:
        agent.stop()
    print(tasks, log)
    allowed = {("stop", f"robot{n}", None) for n in (1, 2, 3)} | {("turn", "robot2", 90.0)}
    assert set(tasks) <= allowed, (tasks, log)  # nothing carried out that was not said
    assert {t for t in tasks if t[0] == "stop"} == {("stop", f"robot{n}", None) for n in (1, 2, 3)}, (tasks, log)


# The real-time check's finding, through the page: a command to two robots heard confidently
# ("robots 1 and 2 turn right 90 degrees" was heard as "robots one and two clear please" and sent to
# both at once). The voice is listening (the operator said "attention" before); a question first (it
# sends nothing, and the recogniser's front end settles on the voice), then a clear to two robots that
# PocketSphinx hears right and sure, the operator's "confirm", and a stop (which never waits).
READ_BACK_SESSION = ["how many robots", "robots two and three clear", "confirm", "everybody stop"]


@pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng is not installed")
def test_a_confident_command_to_two_robots_streamed_through_the_page_waits_for_the_operator_s_yes(tmp_path,
                                                                                                  monkeypatch):
    """Chromium plays the session as its microphone, in real time; PocketSphinx hears it on the control
    node. The clear to robots 2 and 3 is read back and sent only after the operator's "confirm"; the
    stop that follows acts at once, to every robot."""
    pytest.importorskip("pocketsphinx")
    from tests.ui import speech_set as S

    monkeypatch.delenv("VOSK_MODEL_PATH", raising=False)
    rng = np.random.default_rng(52)
    parts = [np.zeros(RATE)]
    for text in READ_BACK_SESSION:
        parts += [S.synthesise(text, "en-us", 130), np.zeros(int(1.5 * RATE))]
    pcm = np.frombuffer(S.as_heard(np.concatenate(parts), None, rng), dtype="<i2")
    wav = write_wav(tmp_path / "read-back.wav", pcm, RATE)
    seconds = len(pcm) / RATE
    agent, ui = start_control({})
    received = streamed(ui, monkeypatch)
    ui.spoken.listening = True
    with agent.transaction() as tx:
        for name in ("robot2", "robot3"):
            tx.add(Pose(robot=name, x=1.0, y=1.0))
    # uid of each clear -> when the UI put it on the control node's blackboard (its run commits it next);
    # a clear that got there any other way has no time here and fails the check below
    published: dict[str, float] = {}
    send = ui._send

    def sending(action: str, tasks: list[Any]) -> None:
        for t in tasks:
            if t.preposition == "clear":
                published.setdefault(t.uid, time.time())
        send(action, tasks)

    monkeypatch.setattr(ui, "_send", sending)
    try:
        def body(page: Any) -> None:
            page.wait_for_selector("#mic:not([disabled])", timeout=20000)
            page.click("#mic")
            page.wait_for_selector("#mic.on")
            # one pass of the file, as the control node receives it (Chromium loops it)
            wait_until(lambda: received() >= seconds - 0.5, timeout=seconds + 60,
                       message=f"the {seconds:.1f} s session did not reach the recogniser in one pass")
            page.click("#mic")

        open_with_microphone(wav, ui.url, body)
        try:  # the recogniser may lag behind real time on a busy machine
            wait_until(lambda: any("everybody stop" in line["text"] for line in ui.server.state()["log"]), timeout=20)
        except AssertionError:
            pass  # the assertions below say what was heard
        heard_everything(ui)
        state = ui.server.state()
        tasks = state["tasks"]  # sent, running or not (a stop supersedes the clear: its row stays)
        everything = [line["text"] for line in state["log"]]
        log = [(line["t"], line["text"]) for line in state["log"] if line["text"].startswith("voice:")]
    finally:
        agent.stop()
    said = [text for _, text in log]
    print(everything)
    # read back: as a command to several robots ("Robots 2 and 3, clear your behaviours — say yes to confirm"), or,
    # when the hearing is doubted, as "Did you say: robots 2 and 3, clear your behaviours? ..."
    asked = [t for t, text in log if text.startswith("voice: \u201crobots two and three clear\u201d \u2192 ")
             and ("Robots 2 and 3, clear your behaviours \u2014 say yes to confirm" in text
                  or text.split(" \u2192 ", 1)[1].startswith("Did you say: robots 2 and 3, clear your behaviours?"))]
    done = [t for t, text in log if "\u2192 Roger: robots 2 and 3, clear your behaviours" in text]
    assert asked, said  # read back, however sure the hearing
    clears = [t for t in tasks if t["preposition"] == "clear"]
    if done:  # the operator's "confirm" heard as said: carried out then, not before
        assert sorted(t["robot"] for t in clears) == ["robot2", "robot3"], said
        assert asked[0] < done[0] and all(asked[0] < published.get(t["uid"], 0.0) for t in clears), "sent before the answer"
    else:  # misheard, it is asked again and nothing is sent
        assert not clears, said
    stops = {t["robot"] for t in tasks if t["preposition"] == "stop"}
    assert stops == {"robot1", "robot2", "robot3"}, said
    assert {t["preposition"] for t in tasks} <= {"clear", "stop"}, said  # nothing else carried out
