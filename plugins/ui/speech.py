"""Speech input: audio sources delivering 16 kHz mono 16-bit PCM, and a vosk recogniser thread.

Audio reaches the recogniser as 16 kHz mono little-endian int16 frames, whatever its source:
a WAV file (any PCM rate and channel count, resampled here), a local microphone (`arecord`,
optional), or the browser's microphone streamed over the GUI's WebSocket. `Listener` owns
the recogniser on a thread of its own and hands each recognised utterance to a callback.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import shutil
import subprocess
import threading
import wave
from collections.abc import Callable, Iterator
from math import gcd
from pathlib import Path
from typing import Any

import numpy as np

from erni.blackboard.errors import ErniError

RATE = 16000
FRAME_SAMPLES = 1600  # 100 ms
MODELS_URL = "https://alphacephei.com/vosk/models"

log = logging.getLogger("erni.ui.speech")


class SpeechError(ErniError):
    """Speech input cannot work: no model, unreadable audio, no device; the message says which."""


def model_path(configured: str | None = None) -> Path:
    """Return the vosk model directory from the setting or VOSK_MODEL_PATH, or raise SpeechError."""
    raw = configured or os.environ.get("VOSK_MODEL_PATH", "").strip()
    if not raw:
        raise SpeechError(f"no vosk model: set vosk_model or VOSK_MODEL_PATH to a model directory "
                          f"(get one from {MODELS_URL}); typed commands still work")
    path = Path(raw).expanduser()
    if not (path / "am").is_dir() and not (path / "conf").is_dir():
        raise SpeechError(f"no vosk model at {path} (expected a model directory with am/ and conf/; "
                          f"get one from {MODELS_URL}); typed commands still work")
    return path


def to_pcm16(samples: np.ndarray, rate: int) -> bytes:
    """Return float or int samples (frames x channels, or 1-D) as 16 kHz mono int16 bytes."""
    data = np.asarray(samples, dtype=np.float64)
    if data.ndim == 2:
        data = data.mean(axis=1)
    if rate != RATE:
        from scipy.signal import resample_poly

        g = gcd(RATE, rate)
        data = resample_poly(data, RATE // g, rate // g)
    return np.clip(np.round(data), -32768, 32767).astype("<i2").tobytes()


def frames(pcm: bytes, samples: int = FRAME_SAMPLES) -> Iterator[bytes]:
    """Split 16-bit PCM into frames of `samples` samples (the last may be shorter)."""
    step = samples * 2
    for i in range(0, len(pcm), step):
        yield pcm[i:i + step]


def read_wav(path: str | Path) -> bytes:
    """Return a PCM WAV file's audio as 16 kHz mono int16 bytes, or raise SpeechError."""
    try:
        with wave.open(str(path), "rb") as w:
            width, channels, rate = w.getsampwidth(), w.getnchannels(), w.getframerate()
            raw = w.readframes(w.getnframes())
    except FileNotFoundError:
        raise SpeechError(f"{path}: no such WAV file") from None
    except (wave.Error, EOFError) as err:
        raise SpeechError(f"{path}: not a PCM WAV file ({err})") from None
    if width == 1:
        data = (np.frombuffer(raw, dtype=np.uint8).astype(np.float64) - 128.0) * 256.0
    elif width == 2:
        data = np.frombuffer(raw, dtype="<i2").astype(np.float64)
    elif width == 4:
        data = np.frombuffer(raw, dtype="<i4").astype(np.float64) / 65536.0
    else:
        raise SpeechError(f"{path}: {8 * width}-bit samples; expected 8, 16 or 32-bit PCM")
    if channels > 1:
        data = data[: len(data) // channels * channels].reshape(-1, channels)
    return to_pcm16(data, rate)


def wav_frames(path: str | Path) -> Iterator[bytes]:
    """Yield a WAV file's audio as 100 ms frames of 16 kHz mono int16."""
    yield from frames(read_wav(path))


def put_dropping_oldest(q: queue.Queue[Any], item: Any) -> int:
    """Put `item` without blocking, dropping the oldest entries until it fits; return how many."""
    dropped = 0
    while True:
        try:
            q.put_nowait(item)
            return dropped
        except queue.Full:
            try:
                q.get_nowait()
                dropped += 1
            except queue.Empty:
                pass


def grammar_phrases(words: list[str]) -> str:
    """Return the JSON phrase list a vosk recogniser is restricted to (the words plus [unk])."""
    return json.dumps(sorted(set(words)) + ["[unk]"])


class Recognizer:
    """A vosk model with the command grammar; `stream()` gives one recogniser per audio source."""

    def __init__(self, model_dir: Path, words: list[str]) -> None:
        try:
            import vosk
        except ImportError:
            raise SpeechError("vosk is not installed: pip install 'erni[speech]'") from None
        vosk.SetLogLevel(-1)
        try:
            self.model = vosk.Model(str(model_dir))
        except Exception as err:  # vosk raises a bare Exception for unreadable models
            raise SpeechError(f"cannot load the vosk model at {model_dir}: {err}") from None
        self.grammar = grammar_phrases(words)
        self._vosk = vosk

    def stream(self) -> Stream:
        """Return a fresh recogniser for one source (a page, the local microphone, a file)."""
        return Stream(self._vosk.KaldiRecognizer(self.model, RATE, self.grammar))


class Stream:
    """One source's utterances: feed 16 kHz mono int16, get texts when utterances end."""

    def __init__(self, rec: Any) -> None:
        self.rec = rec

    def feed(self, pcm: bytes) -> str | None:
        """Accept audio; return the text of an utterance that just ended, if any."""
        if self.rec.AcceptWaveform(pcm):
            return self._text(self.rec.Result())
        return None

    def flush(self) -> str | None:
        """End the current utterance; return its text, if any."""
        return self._text(self.rec.FinalResult())

    @staticmethod
    def _text(result: str) -> str | None:
        text = json.loads(result).get("text", "").strip()
        return text if text and text != "[unk]" else None


class Listener:
    """Runs a recogniser on thread `ui-speech`: `feed()` audio from any thread, texts go to `on_text`.

    Each source (a page, the local microphone, a file) has a stream of its own, so two
    microphones never mix into one utterance.

    Given a loader instead of a recogniser, the thread loads it first (a vosk model takes
    seconds to load: never on the blackboard's threads); a SpeechError goes to `on_error`.
    """

    FLUSH = b""

    def __init__(self, recognizer: Any, on_text: Callable[[str, str], None], *, max_queue: int = 200,
                 on_error: Callable[[str], None] | None = None) -> None:
        self.recognizer = recognizer  # has stream(); or a callable that loads one on the thread
        self.on_text = on_text
        self.on_error = on_error
        self.error = ""
        self.queue: queue.Queue[tuple[str, bytes] | None] = queue.Queue(max_queue)
        self.dropped = 0
        self.streams: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._run, name="ui-speech", daemon=True)

    def start(self) -> Listener:
        self._thread.start()
        return self

    def feed(self, source: str, pcm: bytes) -> None:
        """Queue audio from `source` (never blocks: the oldest audio is dropped when full)."""
        self.dropped += put_dropping_oldest(self.queue, (source, pcm))

    def end_utterance(self, source: str) -> None:
        """Finish what `source` was saying (the microphone was turned off, the file ended)."""
        self.feed(source, self.FLUSH)

    def stop(self) -> None:
        """Stop the thread (joined)."""
        if not self._thread.is_alive():
            return
        put_dropping_oldest(self.queue, None)
        self._thread.join(timeout=5)

    def _run(self) -> None:
        if not hasattr(self.recognizer, "stream"):
            try:
                self.recognizer = self.recognizer()
            except SpeechError as err:
                self.error = str(err)
                if self.on_error is not None:
                    self.on_error(self.error)
                while self.queue.get() is not None:  # audio goes nowhere until stop()
                    pass
                return
        while (item := self.queue.get()) is not None:
            source, pcm = item
            try:
                if pcm == self.FLUSH:
                    stream = self.streams.pop(source, None)
                    text = stream.flush() if stream is not None else None
                else:
                    stream = self.streams.get(source) or self.streams.setdefault(source, self.recognizer.stream())
                    text = stream.feed(pcm)
            except Exception:  # a recogniser failure must not end speech input
                log.exception("speech recogniser failed")
                continue
            if text:
                self.on_text(source, text)


class Microphone:
    """The control node's own microphone through `arecord`, on thread `ui-mic`; optional."""

    def __init__(self, sink: Callable[[bytes], None], device: str | None = None) -> None:
        exe = shutil.which("arecord")
        if exe is None:
            raise SpeechError("no local microphone: arecord (alsa-utils) is not installed")
        args = [exe, "-q", "-t", "raw", "-f", "S16_LE", "-r", str(RATE), "-c", "1"]
        if device:
            args += ["-D", device]
        self.args = args
        self.sink = sink
        self.proc: subprocess.Popen[bytes] | None = None
        self._thread = threading.Thread(target=self._run, name="ui-mic", daemon=True)

    def start(self) -> Microphone:
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=2)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def _run(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        while chunk := self.proc.stdout.read(FRAME_SAMPLES * 2):
            self.sink(chunk)
        err = self.proc.stderr.read().decode(errors="replace").strip() if self.proc.stderr else ""
        if self.proc.wait() not in (0, -15) and err:
            log.warning("local microphone stopped: %s", err.splitlines()[-1])
