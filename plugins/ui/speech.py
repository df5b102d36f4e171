"""Speech input: audio sources delivering 16 kHz mono 16-bit PCM, and a recogniser thread.

Audio reaches the recogniser as 16 kHz mono little-endian int16 frames, whatever its source:
a WAV file (any PCM rate and channel count, resampled here), a local microphone (`arecord`,
optional), or the browser's microphone streamed over the GUI's WebSocket. `Listener` owns
the recogniser on a thread of its own and hands each recognised utterance to a callback.

Two recognisers, both restricted to the command grammar: vosk (`Recognizer`) when a vosk model
is given, and CMU PocketSphinx (`SphinxRecognizer`) with the US English acoustic model and
pronouncing dictionary shipped in its PyPI package, decoding ERNI's grammar as JSGF
(`erni.plugins.ui.jsgf`). A model whose vocabulary lacks words of the grammar is refused with
one line naming them: it would otherwise "work" and never hear those words.
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


def missing_words(words: list[str], known: Callable[[str], bool]) -> list[str]:
    """The words of the grammar a model's vocabulary lacks."""
    return [w for w in sorted(set(words)) if not known(w)]


def lacking(model: str | Path, missing: list[str], total: int) -> SpeechError:
    """The one-line refusal of a model that lacks words of the grammar."""
    shown = ", ".join(missing[:12]) + (f" and {len(missing) - 12} more" if len(missing) > 12 else "")
    return SpeechError(f"the speech model at {model} lacks {len(missing)} of the grammar's {total} words "
                       f"({shown}): it could never hear them; give an English model that has them")


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
        missing = missing_words(words, lambda w: self.model.vosk_model_find_word(w) >= 0)
        if missing:
            raise lacking(model_dir, missing, len(set(words)))
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


def sphinx_model() -> tuple[Path, Path]:
    """The US English acoustic model and pronouncing dictionary of the pocketsphinx package."""
    try:
        import pocketsphinx
    except ImportError:
        raise SpeechError("pocketsphinx is not installed: pip install 'erni[speech]'") from None
    root = Path(pocketsphinx.get_model_path())
    return root / "en-us" / "en-us", root / "en-us" / "cmudict-en-us.dict"


class SphinxRecognizer:
    """CMU PocketSphinx decoding ERNI's grammar (JSGF); `stream()` gives one decoder per audio source."""

    def __init__(self, grammar: str, *, model: Path | None = None, dictionary: Path | None = None) -> None:
        from erni.plugins.ui.jsgf import words

        default_model, default_dict = sphinx_model()
        self.model, self.dictionary = model or default_model, dictionary or default_dict
        if not (self.model / "mdef").is_file():
            raise SpeechError(f"no PocketSphinx acoustic model at {self.model} (expected a directory with mdef)")
        try:
            known = {line.split(maxsplit=1)[0].split("(")[0] for line in
                     self.dictionary.read_text(encoding="utf-8", errors="replace").splitlines() if line.strip()}
        except OSError as err:
            raise SpeechError(f"cannot read the pronouncing dictionary {self.dictionary}: {err.strerror}") from None
        needed = words(grammar)
        missing = missing_words(needed, known.__contains__)
        if missing:
            raise lacking(self.dictionary, missing, len(needed))
        self.grammar = grammar

    def stream(self) -> SphinxStream:
        """Return a fresh decoder for one source (a page, the local microphone, a file)."""
        from pocketsphinx import Decoder, Endpointer

        try:
            decoder = Decoder(hmm=str(self.model), dict=str(self.dictionary), lm=None, samprate=RATE,
                              loglevel="FATAL")
            decoder.add_jsgf_string("erni", self.grammar)
            decoder.activate_search("erni")
        except (RuntimeError, ValueError) as err:
            raise SpeechError(f"cannot start PocketSphinx with {self.model}: {err}") from None
        return SphinxStream(decoder, Endpointer(sample_rate=RATE))


class SphinxStream:
    """One source's utterances through PocketSphinx: a voice activity detector cuts the audio into
    utterances, each decoded against the grammar when it ends (or at `flush()`)."""

    def __init__(self, decoder: Any, endpointer: Any) -> None:
        self.decoder, self.ep = decoder, endpointer
        self.buffer = bytearray()
        self.in_utterance = False

    def feed(self, pcm: bytes) -> str | None:
        """Accept audio; return the text of an utterance that just ended, if any."""
        self.buffer += pcm
        size = self.ep.frame_bytes
        text = None
        while len(self.buffer) >= size:
            frame = bytes(self.buffer[:size])
            del self.buffer[:size]
            speech = self.ep.process(frame)
            if speech is None:
                continue
            if not self.in_utterance:
                self.decoder.start_utt()
                self.in_utterance = True
            self.decoder.process_raw(speech, False, False)
            if not self.ep.in_speech:
                text = self._end() or text
        return text

    def flush(self) -> str | None:
        """End the current utterance (the source stopped); return its text, if any."""
        if self.buffer and self.in_utterance:
            self.decoder.process_raw(bytes(self.buffer), False, False)
        self.buffer.clear()
        return self._end() if self.in_utterance else None

    def _end(self) -> str | None:
        self.decoder.end_utt()
        self.in_utterance = False
        hyp = self.decoder.hyp()
        text = hyp.hypstr.strip() if hyp is not None else ""
        return text or None


def choose_recognizer(kind: str, vosk_model: str | None) -> Callable[[], Any]:
    """Return a loader of the recogniser to use (run on the speech thread), or raise SpeechError saying why none.

    `auto`: vosk when a vosk model is given (setting or VOSK_MODEL_PATH), else PocketSphinx.
    """
    from erni.plugins.ui.grammar import vocabulary
    from erni.plugins.ui.jsgf import jsgf

    given = vosk_model or os.environ.get("VOSK_MODEL_PATH", "").strip()
    if kind == "vosk" or (kind == "auto" and given):
        path = model_path(vosk_model)
        return _Loader("vosk", lambda: Recognizer(path, vocabulary()))
    sphinx_model()  # installed?
    grammar = jsgf()
    return _Loader("pocketsphinx", lambda: SphinxRecognizer(grammar))


class _Loader:
    """A recogniser loader that says which recogniser it loads."""

    def __init__(self, backend: str, load: Callable[[], Any]) -> None:
        self.backend, self.load = backend, load

    def __call__(self) -> Any:
        return self.load()


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
