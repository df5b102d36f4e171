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

A recogniser restricted to a grammar always answers with a sentence of it, so each hearing carries
the recogniser's own doubt (`Heard.unsure`): PocketSphinx decodes every utterance twice once it
has ended (whole, then in a live stream's pieces with its front end settled on the utterance) and a
hearing is unsure when the search ended inside a sentence of the grammar, when the two decodes mean
different things, or when a word of it matches the audio poorly (its acoustic score per frame,
against the best-scoring sounds of each frame, is below `SphinxStream.MIN_WORD_SCORE`). A lone wake
word, which the big grammar fits poorly, is spotted by a keyphrase search of its own; vosk's hearing is
unsure when it has an out-of-grammar word ([unk]) or a word of low confidence. PocketSphinx's
utterances are cut by `NoiseFloorEndpointer`, which ends them in steady noise too and measures
their SNR: a command that would move robots, heard less than `SphinxStream.MIN_SNR` dB above the
background, is unsure. Lone stop phrases are spotted by a keyphrase search before the grammar is
decoded. An unsure hearing is never carried out as heard: the spoken dialogue reads a command
back ("Did you say ...? Say yes or no") and asks anything else again ("Say again?").
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import shutil
import subprocess
import tempfile
import threading
import wave
from collections.abc import Callable, Iterable, Iterator
from math import gcd
from pathlib import Path
from typing import Any

import numpy as np

from erni.blackboard.errors import ErniError

RATE = 16000
LOUD_ROOM = -40.0  # dBFS: the room's own level above which the front end's `auto` hears through RNNoise (quiet: -56)
FRAME_SAMPLES = 1600  # 100 ms
MODELS_URL = "https://alphacephei.com/vosk/models"

log = logging.getLogger("erni.ui.speech")


class SpeechError(ErniError):
    """Speech input cannot work: no model, unreadable audio, no device; the message says which."""


class Heard(str):
    """A recognised utterance: its text, and whether the recogniser doubts it.

    `unsure` is True when the recogniser's own evidence says the text may not be what was said;
    `why` names that evidence ("the two decodes differ: ...", "'five' matches the audio poorly").
    A `Heard` is a `str` (its text), so a callback written for texts still works.
    """

    unsure: bool
    why: str

    def __new__(cls, text: str, unsure: bool = False, why: str = "") -> Heard:
        heard = super().__new__(cls, text)
        heard.unsure, heard.why = unsure, why
        return heard

    @property
    def text(self) -> str:
        return str(self)

    def __repr__(self) -> str:
        return f"Heard({str(self)!r}, unsure={self.unsure}{f', why={self.why!r}' if self.why else ''})"


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
    """Return the JSON phrase list a vosk recogniser is restricted to (the words or phrases, plus [unk]).

    Written as UTF-8 text: vosk reads the words as they stand and does not undo JSON escapes, so an
    escaped non-ASCII word ("\\ub85c\\ubd07") would be missing from any model.
    """
    return json.dumps(sorted(set(words)) + ["[unk]"], ensure_ascii=False)


class Recognizer:
    """A vosk model with the command grammar; `stream()` gives one recogniser per audio source.

    The grammar is `words` (any sequence of them), or whole `phrases` when given.
    """

    def __init__(self, model_dir: Path, words: list[str], *, phrases: list[str] | None = None) -> None:
        try:
            import vosk
        except ImportError:
            raise SpeechError("vosk is not installed: pip install 'erni[speech]'") from None
        vosk.SetLogLevel(-1)
        try:
            self.model = vosk.Model(str(model_dir))
        except Exception as err:  # vosk raises a bare Exception for unreadable models
            raise SpeechError(f"cannot load the vosk model at {model_dir}: {err}") from None
        if phrases is not None:
            words = [w for phrase in phrases for w in phrase.split()]
        missing = missing_words(words, lambda w: self.model.vosk_model_find_word(w) >= 0)
        if missing:
            raise lacking(model_dir, missing, len(set(words)))
        self.grammar = grammar_phrases(phrases if phrases is not None else words)
        self._vosk = vosk

    def stream(self) -> Stream:
        """Return a fresh recogniser for one source (a page, the local microphone, a file)."""
        rec = self._vosk.KaldiRecognizer(self.model, RATE, self.grammar)
        rec.SetWords(True)  # each word's confidence: the evidence of an unsure hearing
        return Stream(rec)


class Stream:
    """One source's utterances: feed 16 kHz mono int16, get hearings when utterances end.

    A hearing with an out-of-grammar stretch ([unk]) or a word whose confidence (its posterior in
    vosk's lattice) is below `MIN_CONFIDENCE` is unsure.
    """

    MIN_CONFIDENCE = 0.9

    def __init__(self, rec: Any) -> None:
        self.rec = rec

    def feed(self, pcm: bytes) -> Heard | None:
        """Accept audio; return the hearing of an utterance that just ended, if any."""
        if self.rec.AcceptWaveform(pcm):
            return self._heard(self.rec.Result())
        return None

    def flush(self) -> Heard | None:
        """End the current utterance; return its hearing, if any."""
        return self._heard(self.rec.FinalResult())

    @classmethod
    def _heard(cls, result: str) -> Heard | None:
        found = json.loads(result)
        said = found.get("text", "").split()
        if not said:
            return None
        known = [w for w in said if w != "[unk]"]
        if len(known) < len(said):
            return Heard(" ".join(known), True, "part of it is outside the grammar")
        doubtful = [f"{w['word']!r} ({w['conf']:.2f})" for w in found.get("result", [])
                    if w.get("conf", 1.0) < cls.MIN_CONFIDENCE]
        if doubtful:
            return Heard(" ".join(said), True, f"low confidence in {', '.join(doubtful)}")
        return Heard(" ".join(said))


class NoiseFloorEndpointer:
    """Cuts a stream of 16 kHz int16 audio into utterances against the background's own level.

    The background (noise floor) is tracked in 30 ms frames: it follows a quieter frame at once and
    rises slowly (`RISE` dB a second) outside speech. An utterance starts when `ONSET` frames in a
    row are `START_DB` above the floor (with `PREROLL` seconds before them) and ends after `HANGOVER`
    seconds with no frame `SPEECH_DB` above it, or after `LONGEST` seconds. Steady sound that never
    falls back (noise that came on or grew) is no speech: after `STEADY` seconds within `STEADY_DB`
    the floor moves up to it, and the utterance ends there (or is dropped, `cancelled`, when nothing
    in it stood above the new floor). So an utterance ends in steady noise as in a quiet room.

    `process(frame)` takes `frame_bytes` of audio and returns the audio to add to the utterance
    (the pre-roll with its first frame), or None outside one; `in_speech` turns False on the frame
    that ends it. `snr` is the last utterance's speech against the floor (dB), `span` its first and
    last speech frame (seconds into its audio).
    """

    FRAME = 0.03  # seconds
    START_DB, SPEECH_DB = 3.0, 2.0  # above the floor: an utterance starts; a frame is speech
    ONSET, PREROLL, HANGOVER, LONGEST = 3, 0.3, 0.4, 8.0  # frames; seconds
    RISE = 1.0  # dB a second: how fast the floor follows louder background outside speech
    STEADY, STEADY_DB = 1.0, 3.0  # seconds within this range of levels: background, not speech
    QUIETEST = 30.0  # dB (rms 32, about -60 dBFS): the floor never goes below (digital silence)

    def __init__(self, sample_rate: int = RATE) -> None:
        self.samples = int(round(self.FRAME * sample_rate))
        self.frame_bytes = 2 * self.samples
        self.floor: float | None = None
        self.in_speech = False
        self.cancelled = False  # the utterance that just ended was steady background: drop its audio
        self.snr = 0.0
        self.span = (0.0, 0.0)
        self._before: list[tuple[bytes, float, float]] = []  # pre-roll frames, their levels, and as they came in
        self._levels: list[float] = []  # the current utterance's frame levels
        self._raw: list[float] = []  # and their levels as the audio came in (before a suppressor), for the SNR
        self.raw_floor: float | None = None
        self._onset = 0

    @staticmethod
    def level(frame: bytes) -> float:
        """A frame's power in dB (int16 units, 0 dB = rms 1)."""
        x = np.frombuffer(frame, dtype="<i2").astype(np.float64)
        return 10.0 * math.log10(float(np.mean(x * x)) + 1.0) if x.size else 0.0

    def _follow(self, floor: float | None, db: float) -> float:
        """The floor after a frame outside speech: a quieter frame at once, a louder one slowly."""
        floor = max(self.QUIETEST, db if floor is None else floor)
        return max(self.QUIETEST, db if db < floor else min(db, floor + self.RISE * self.FRAME))

    def process(self, frame: bytes, raw: bytes | None = None) -> bytes | None:
        """`raw`: the same frame as it came in, when `frame` was cleaned (the SNR is measured on it)."""
        db = self.level(frame)
        rdb = db if raw is None else self.level(raw)
        floor = max(self.QUIETEST, db if self.floor is None else self.floor)
        self.cancelled = False
        if not self.in_speech:
            self._before = [*self._before, (frame, db, rdb)][-(int(self.PREROLL / self.FRAME) + self.ONSET):]
            if db > floor + self.START_DB:
                self._onset += 1
                if self._onset >= self.ONSET:
                    self.in_speech, self._onset = True, 0
                    self._levels = [lv for _, lv, _ in self._before]
                    self._raw = [r for _, _, r in self._before]
                    audio = b"".join(f for f, _, _ in self._before)
                    self._before = []
                    self.floor = floor
                    return audio
            else:
                self._onset = 0
                if raw is not None:
                    self.raw_floor = self._follow(self.raw_floor, rdb)
            self.floor = self._follow(floor, db)
            return None
        self._levels.append(db)
        self._raw.append(rdb)
        if db < floor:
            self.floor = floor = max(self.QUIETEST, db)
        levels = self._levels
        steady = int(self.STEADY / self.FRAME)
        if len(levels) >= steady and max(levels[-steady:]) - min(levels[-steady:]) < self.STEADY_DB:
            new = sum(levels[-steady:]) / steady
            spoke = any(lv > new + self.START_DB for lv in levels[:-steady])
            self.floor = new
            if self.raw_floor is not None and self._raw:
                self.raw_floor = sum(self._raw[-steady:]) / len(self._raw[-steady:])
            self._finish(levels[:-steady], floor)
            self.cancelled = not spoke
            return frame
        speech = [i for i, lv in enumerate(levels) if lv > floor + self.SPEECH_DB]
        last = speech[-1] if speech else 0
        if (len(levels) - 1 - last) * self.FRAME >= self.HANGOVER or len(levels) * self.FRAME >= self.LONGEST:
            self._finish(levels, floor)
        return frame

    def end(self) -> None:
        """End the current utterance now (the source stopped)."""
        if self.in_speech:
            self._finish(self._levels, self.floor or self.QUIETEST)
        self._onset = 0
        self._before = []

    def _finish(self, levels: list[float], floor: float) -> None:
        """The utterance ends: its SNR and speech span."""
        self.in_speech = False
        speech = [(i, lv) for i, lv in enumerate(levels) if lv > floor + self.SPEECH_DB]
        if not speech:
            self.snr, self.span = 0.0, (0.0, 0.0)
            return
        if self.raw_floor is not None and len(self._raw) >= len(levels):  # cleaned audio: the SNR as it came in
            floor = self.raw_floor
            speech = [(i, self._raw[i]) for i, _ in speech]
        noise = 10 ** (floor / 10)
        power = [10 ** (lv / 10) - noise for _, lv in speech]
        loud = [p for p in power if p > 0.1 * max(power)]  # within 10 dB of the loudest, as SNRs are quoted
        self.snr = 10 * math.log10(max(sum(loud) / max(len(loud), 1), 1e-9) / noise)
        self.span = (speech[0][0] * self.FRAME, (speech[-1][0] + 1) * self.FRAME)


def sphinx_model() -> tuple[Path, Path]:
    """The US English acoustic model and pronouncing dictionary of the pocketsphinx package."""
    try:
        import pocketsphinx
    except ImportError:
        raise SpeechError("pocketsphinx is not installed: pip install 'erni[speech]'") from None
    root = Path(pocketsphinx.get_model_path())
    return root / "en-us" / "en-us", root / "en-us" / "cmudict-en-us.dict"


class SphinxRecognizer:
    """CMU PocketSphinx decoding ERNI's grammar (JSGF); `stream()` gives one decoder per audio source.

    `wake`: the wake phrases (default `grammar.ATTENTION`), also spotted on their own by a keyphrase
    search, so a lone wake word is heard even where the command grammar fits it poorly.
    """

    # the keyphrase search's threshold: a lone wake word of the speech test set's voices is spotted,
    # and no spotted phrase covers a command (they fall inside longer utterances, or on a stop)
    WAKE_THRESHOLD = 1e-30
    STOP_THRESHOLD = 1e-20  # the keyphrase threshold of a one-word stop phrase ("halt")
    STOPS_THRESHOLD = 1e-30  # of a longer one ("everybody stop"), less easily taken for something else
    # the search's beams, narrower than PocketSphinx's (1e-48, 7e-29): in noise a decode takes half the
    # time (a grammar decode of 3 s in white noise at 5 dB took 7-20 s with the default beams)
    BEAM, WBEAM = 1e-35, 1e-25

    def __init__(self, grammar: str, *, wake: Iterable[str] | None = None, model: Path | None = None,
                 dictionary: Path | None = None, front: Any = None) -> None:
        from erni.plugins.ui.grammar import ATTENTION
        from erni.plugins.ui.jsgf import Rules, words

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
        self.front = front if front is not None and front.active else None  # frontend.FrontEnd: cleans and cuts the audio
        self.rules = Rules(grammar)
        self.wake = tuple(p for p in (ATTENTION if wake is None else wake) if set(p.split()) <= known)
        self.others = tuple(p for p in (*NOT_STOPS, *self.wake) if set(p.split()) <= known)
        self.short = short_grammar(self.others)

    def stream(self) -> SphinxStream:
        """Return a fresh decoder for one source (a page, the local microphone, a file)."""
        from pocketsphinx import Decoder

        try:
            decoder = Decoder(hmm=str(self.model), dict=str(self.dictionary), lm=None, samprate=RATE,
                              loglevel="FATAL", beam=self.BEAM, wbeam=self.WBEAM)
            lists = {SphinxStream.STOPS: [(p, self.STOP_THRESHOLD if " " not in p else self.STOPS_THRESHOLD)
                                          for p in STOP_PHRASES]}
            if self.wake:
                lists[SphinxStream.WAKE] = [(p, self.WAKE_THRESHOLD) for p in self.wake]
            with tempfile.TemporaryDirectory() as tmp:  # a keyphrase list is read from a file
                for name, phrases in lists.items():
                    listed = Path(tmp) / f"{name}.kws"
                    listed.write_text("".join(f"{p} /{threshold:g}/\n" for p, threshold in phrases))
                    decoder.add_kws(name, str(listed))
            decoder.add_jsgf_string(SphinxStream.SHORT, self.short)  # the stop phrases, the answers, short commands
            decoder.add_jsgf_string(SphinxStream.COMMANDS, self.grammar)
            decoder.activate_search(SphinxStream.COMMANDS)
            live = Decoder(hmm=str(self.model), dict=str(self.dictionary), lm=None, samprate=RATE,
                           loglevel="FATAL", beam=self.BEAM, wbeam=self.WBEAM)
            live.add_jsgf_string(SphinxStream.COMMANDS, self.grammar)
            live.activate_search(SphinxStream.COMMANDS)
        except (RuntimeError, ValueError) as err:
            raise SpeechError(f"cannot start PocketSphinx with {self.model}: {err}") from None
        suppressor = self.front.suppressor() if self.front is not None else None
        endpointer = self.front.endpointer(suppressor) if self.front is not None else NoiseFloorEndpointer(RATE)
        return SphinxStream(decoder, endpointer, complete=self.rules.accepts, wake=bool(self.wake),
                            others=self.others, suppressor=suppressor, live=live)


# The stop phrasings a keyphrase search listens for in every short utterance, whatever the grammar
# made of it: a stop the grammar mishears ("halt" as "forward half") is still a stop.
STOP_PHRASES = ("stop", "halt", "freeze", "all stop", "everybody stop", "everyone stop")


# Short things said that a stop phrase could be taken for: a stop spotted by the keyphrase search
# stands unless a decode against the stop phrases and these together hears one of these.
NOT_STOPS = ("yes", "no", "confirm", "negative", "affirmative", "faster", "slower", "cancel", "cancel that", "undo",
             "clear", "status", "report", "random walk", "spread out", "go to sleep", "go home", "where are you",
             "how many robots", "everybody", "all robots", "robot one", "robot two", "robot three", "turn left",
             "turn right", "turn around", "go forward", "go back")


def short_grammar(others: Iterable[str]) -> str:
    """The JSGF of the stop phrases and the short lines they could be taken for (`NOT_STOPS`, the wake phrases)."""
    phrases = dict.fromkeys([*STOP_PHRASES, *others])
    return "#JSGF V1.0;\ngrammar short;\npublic <short> = " + " | ".join(phrases) + " ;\n"


class SphinxStream:
    """One source's utterances through PocketSphinx: an endpointer that tracks the background's
    level (`NoiseFloorEndpointer`) cuts the audio into utterances, in steady noise as in a quiet room,
    and when one ends (or at `flush()`) its audio is decoded against the grammar twice: whole, then
    in the 30 ms pieces a live stream comes in, the front end now settled on this utterance's voice
    and room. The hearing is unsure when the search ended inside a sentence (PocketSphinx then gives
    its best partial path), when the two decodes mean different things, when one of its words
    scores below `MIN_WORD_SCORE`, or, for a command that moves robots or picks them, when it has a
    hesitation ("uh": audio that fit no command word) or the speech stood less than `MIN_SNR` dB above
    the background (the operator is then asked "Did you say ...?" before anything moves).

    A short utterance is first searched for the stop phrasings (a keyphrase search): a stop phrase
    spotted covering all but `LONE_STOP` seconds of its speech, unless a decode against the stop
    phrases and the short lines they could be taken for (`NOT_STOPS`, the wake phrases) hears one of
    those lines instead, is the hearing at once: the phrase itself when that decode heard it too,
    else "everybody stop" (which stop was said is unsure, so it goes to everyone: a false stop is
    safe, a missed one is not). A stop heard by the grammar's first decode is answered at once too:
    it acts however sure it is, and so does a stop phrase spotted anywhere in a short utterance the
    grammar hears only in part, poorly or not at all. A wake phrase said on its own is spotted by a
    keyphrase search over the same audio: spotted with at most `LONE_WAKE` seconds of the utterance's
    speech outside it, it is the hearing (a wake phrase moves nothing).

    A second decoder (`live`) decodes the utterance against the grammar as it is spoken, so that a stop
    said inside a longer line ("hey robot one stop", "everyone freeze"), which no keyphrase search takes
    for a lone stop, is heard when the voice ends, not after the decodes that follow it: a stop it hears
    acts at once, as one the grammar's first decode hears does (after a spotted lone stop and an answer
    to a read-back, which it does not overrule). The live decoder then decodes that audio whole at the
    next audio handed over, and a stop it hears to other robots ("robot one" where the live decode
    heard "robot twenty") is heard too (the main decoder is left as it was). The live decoder starts
    each utterance from the cepstral mean the main decoder settled on; before the main decoder has
    heard an utterance there is no such mean, and the live decode is not listened to.
    """

    COMMANDS, WAKE, STOPS, SHORT = "erni", "wake", "stops", "short"
    LONGEST_ANSWER = 1.5  # seconds of speech: a longer utterance is no answer to a read-back
    # a word's acoustic score per 10 ms frame (natural log, against the best-scoring sound of each
    # frame): nearly every word of the right hearings of the speech test set scores above it
    MIN_WORD_SCORE = -7.0
    MIN_SNR = 20.0  # dB: speech less far above the background is doubted (a command is read back)
    LONE_WAKE = 0.35  # seconds of an utterance's speech outside a spotted wake phrase, at most, for it to stand alone
    LONGEST_WAKE = 6.0  # seconds: a longer utterance is no lone wake phrase and is not searched for one
    LONE_STOP = 0.35  # seconds of an utterance's speech outside a spotted stop phrase, at most
    LONGEST_STOP = 2.5  # seconds of speech: a longer utterance is not searched for a lone stop phrase

    def __init__(self, decoder: Any, endpointer: Any, complete: Callable[[str], bool] | None = None,
                 wake: bool = False, others: Iterable[str] = (), suppressor: Any = None, live: Any = None) -> None:
        self.decoder, self.ep = decoder, endpointer
        self.live = live  # a second decoder of the grammar, fed the utterance as it is spoken (a stop waits for no decode)
        self._live_on = False  # the live decoder is inside an utterance
        self._live_left = False  # ... of an utterance already heard (its end waits for the next one)
        # the live decode as the second hearing, instead of a decode in pieces after the first: off, as the
        # 5 dB test of the front end hears fewer lines with it (the main decoder's cepstral mean then moves
        # differently), though the whole speech set heard more in noise (bench_speech --live-again)
        self.live_again = False
        self._stopped: tuple[bytes, str] | None = None  # a stop the live decode heard, and its audio, to decode again
        self._heard_one = False  # the main decoder has decoded an utterance (its cepstral mean is this room's)
        self.suppressor = suppressor  # the front end's noise suppressor: what is heard is its cleaned audio
        self.answering = False  # a read-back awaits "yes" or "no": a short utterance is decoded against the answers
        self.others = frozenset(others)  # the short lines of the SHORT search that overrule a spotted stop
        self.complete = complete  # is a text a whole sentence of the grammar?
        self.wake = wake  # the decoder has the keyphrase search of the wake phrases
        self.evidence: dict[str, Any] = {}  # of the last hearing: decodes, word scores, SNR, phrases spotted
        self.buffer = bytearray()
        self.audio = bytearray()  # the current utterance's speech
        self.in_utterance = False
        self.settled = False  # the front end has heard an utterance (its cepstral mean is this voice's)
        self.near = ""  # of the last keyphrase search: the best phrase spotted, alone in the utterance or not

    def feed(self, pcm: bytes) -> Heard | None:
        """Accept audio; return the hearing of an utterance that just ended, if any."""
        self.buffer += pcm
        size = self.ep.frame_bytes
        heard = self._recheck()
        while len(self.buffer) >= size:
            frame = bytes(self.buffer[:size])
            del self.buffer[:size]
            if self.suppressor is not None:
                speech = self.ep.process(self.suppressor.process(frame), raw=frame)
            else:
                speech = self.ep.process(frame)
            if speech is None:
                continue
            self.in_utterance = True
            self.audio += speech
            self._hear_live(speech)
            if not self.ep.in_speech:
                if getattr(self.ep, "cancelled", False):  # steady background, no speech: nothing to decode
                    self.in_utterance, self.audio = False, bytearray()
                    self._live_end()
                    continue
                heard = self._end() or heard
        return heard

    def flush(self) -> Heard | None:
        """End the current utterance (the source stopped); return its hearing, if any."""
        if self.buffer and self.in_utterance:
            self.audio += self.buffer
        self.buffer.clear()
        if hasattr(self.ep, "end"):
            self.ep.end()
        again = self._recheck()
        return (self._end() if self.in_utterance else None) or again

    def _recheck(self) -> Heard | None:
        """After a stop the live decode heard, the whole grammar's decode of the same audio: a stop it hears to
        other robots is heard too (a stop to one robot too many is safe, one to the wrong robot is not)."""
        if self._stopped is None or self._live_on:
            return None
        audio, live = self._stopped
        self._stopped = None
        # on the live decoder, idle between utterances: a decode on the main one would move its cepstral mean,
        # and with it how the next utterances are heard
        self._start_live()
        self.live.process_raw(audio, False, True)
        self.live.end_utt()
        text, _ = self._decoded(self.live)
        self.evidence.update(recheck=text)
        if is_stop(text) and not same_meaning(text, live):
            return Heard(text, False, f"a stop, heard by the whole grammar after the live decode's {live!r}")
        return None

    def _hear_live(self, speech: bytes) -> None:
        """Decode the utterance's audio as it comes, on the live decoder."""
        if self.live is None:
            return
        if self._live_left:  # the last utterance's, left open by a stop heard before it was needed
            self._live_end()
        if not self._live_on:
            self._start_live()
            self._live_on = True
        self.live.process_raw(speech, False, False)

    def _start_live(self) -> None:
        """Start an utterance on the live decoder, from the cepstral mean the main decoder settled on (from its
        own it heard "everybody stop" as "move reverse ...")."""
        self.live.set_cmn(self.decoder.get_cmn())
        self.live.start_utt()

    def _live_end(self) -> tuple[str, list[tuple[str, float]]] | None:
        """End the live decoder's utterance: its hearing and word scores (None without one)."""
        if not self._live_on:
            return None
        self._live_on = self._live_left = False
        self.live.end_utt()
        # before the main decoder has heard an utterance there was no mean to start from: not a hearing to go by
        # (an end left for the next utterance comes when this is already true, and is not used)
        return self._decoded(self.live) if self._heard_one else None

    def _decode(self, audio: bytes, whole: bool) -> None:
        self.decoder.start_utt()
        if whole:
            self.decoder.process_raw(audio, False, True)
        else:
            step = self.ep.frame_bytes
            for i in range(0, len(audio), step):
                self.decoder.process_raw(audio[i:i + step], False, False)
        self.decoder.end_utt()

    def _decoded(self, decoder: Any = None) -> tuple[str, list[tuple[str, float]]]:
        """The hypothesis of the utterance just decoded (by `decoder`, default the main one), and each word's
        acoustic score per frame."""
        decoder = self.decoder if decoder is None else decoder
        hyp = decoder.hyp()
        text = hyp.hypstr.strip() if hyp is not None else ""
        scores = []
        for seg in decoder.seg() or []:
            if seg.word.startswith(("<", "[")) or seg.word == "<sil>":
                continue
            frames = max(1, seg.end_frame - seg.start_frame + 1)
            scores.append((seg.word.split("(")[0], (math.log(seg.ascore) if seg.ascore > 0 else -1e4) / frames))
        return text, scores

    def _span(self, audio: bytes) -> tuple[float, float]:
        """Where the speech of the utterance is (seconds into its audio), as the endpointer found it."""
        span = getattr(self.ep, "span", None)
        if isinstance(span, tuple) and span[1] > span[0]:
            return span
        return 0.0, len(audio) / 2 / RATE

    def _spotted(self, audio: bytes, search: str, lone: float, longest: float) -> str:
        """The phrase of keyphrase search `search` said on its own in this audio, or ""."""
        first, last = self._span(audio)
        self.near = ""
        if last - first > longest:
            return ""
        self.decoder.activate_search(search)
        try:
            self._decode(audio, whole=True)
            hits = []
            for seg in self.decoder.seg() or []:
                start, end = seg.start_frame / 100, (seg.end_frame + 1) / 100
                covered = max(0.0, min(end, last) - max(start, first))
                hits.append((covered - (end - start - covered), covered, seg.word.strip()))  # less beyond the speech
        finally:
            self.decoder.activate_search(self.COMMANDS)
        self.near = max(hits)[2] if hits else ""  # the best phrase spotted, alone or not
        alone = [phrase for _, covered, phrase in sorted(hits, reverse=True) if last - first - covered <= lone]
        if len(set(alone)) > 1:  # two phrases fit ("listen", "listen up"): the one a decode against them all hears
            short = self._short(audio)
            alone = [p for p in alone if p == short] or alone
        return alone[0] if alone else ""

    def _short(self, audio: bytes) -> str:
        """The utterance decoded against the stop phrases and the short lines they could be taken for."""
        self.decoder.activate_search(self.SHORT)
        try:
            self._decode(audio, whole=True)
            return self._decoded()[0]
        finally:
            self.decoder.activate_search(self.COMMANDS)

    def _end(self) -> Heard | None:
        self.in_utterance = False
        audio, self.audio = bytes(self.audio), bytearray()
        self._live_left = self._live_on  # the live decode is ended when it is needed, or at the next utterance
        if not audio:
            return None
        try:
            return self._hearing(audio)
        finally:
            self._heard_one = True

    def _hearing(self, audio: bytes) -> Heard | None:
        snr = getattr(self.ep, "snr", None)
        if not self.settled and self.suppressor is None:  # a fresh front end: let it settle on this voice and room
            self._decode(audio, whole=False)  # (on cleaned audio this first decode in pieces unsettles it instead: the
        self.settled = True  # first command after it was heard as nothing, and heard at once without it)
        stop = self._spotted(audio, self.STOPS, self.LONE_STOP, self.LONGEST_STOP)
        near = self.near
        self.evidence = {"stop": stop, "near": near, "snr": snr}
        if stop and (lone := self._lone_stop(audio, stop)) is not None:
            return lone
        decoded = None  # the whole grammar's decode, when the answers' check made it already
        if self.answering:
            answer, decoded = self._answer(audio)
            if answer is not None:
                return answer
        live = self._live_end()
        if live is not None:
            self.evidence.update(live=live[0])
            if is_stop(live[0]) and (heard := self._live_stop(audio, live)) is not None:
                return heard
        if decoded is None:
            self._decode(audio, whole=True)
            decoded = self._decoded()
        text, scores = decoded
        self.evidence.update(text=text, scores=scores)
        partial, poor = self._doubts(text, scores)
        if is_stop(text):  # a stop acts however sure it is: its hearing waits for no second decode
            if not self._doubtful(text, audio):  # (unless garbled or a short line of its own)
                return self._judged(text, partial, poor, text, None)
            return self._unconfirmed(text, audio, live[0] if live is not None else None)
        if near and (partial or poor or not text) and self._short(audio) not in self.others:
            # a stop phrase spotted in a short utterance the grammar heard only doubtfully: a stop to everyone
            return Heard("everybody stop", False, f"a stop phrase spotted ({near!r}) where the grammar doubts {text!r}")
        return self._second(audio, text, partial, poor, live, snr)

    def _live_stop(self, audio: bytes, live: tuple[str, list[tuple[str, float]]]) -> Heard | None:
        """The live decode heard a stop as it was said: it acts at once, however sure, and the whole grammar's
        decode may add to it (`_recheck`); unless it is doubtful (garbled, or a short line of its own), when it
        acts only if the whole grammar hears a stop too (None: go on to that decode)."""
        if self._doubtful(live[0], audio):
            self.evidence.update(doubted=live[0])
            return None
        self._stopped = (audio, live[0])
        return self._judged(live[0], *self._doubts(*live), live[0], None)

    def _second(self, audio: bytes, text: str, partial: bool, poor: list[str],
                live: tuple[str, list[tuple[str, float]]] | None, snr: float | None) -> Heard | None:
        """A hearing that is no stop, judged with its second decode (the front end settled on this utterance, or
        the live decode's with `live_again`); a lone wake phrase spotted is the hearing instead."""
        if self.live_again and live is not None:  # the second hearing: the live decode's, in the pieces it came in
            again = live[0]
        else:  # the second decode: the front end settled on this utterance
            self._decode(audio, whole=False)
            again, _ = self._decoded()
        wake = self._spotted(audio, self.WAKE, self.LONE_WAKE, self.LONGEST_WAKE) if self.wake else ""
        self.evidence.update(again=again, wake=wake)
        if wake:
            return Heard(wake) if wake == text else Heard(wake, False, f"a lone wake phrase (the grammar: {text!r})")
        return self._judged(text, partial, poor, again, snr)

    def _lone_stop(self, audio: bytes, stop: str) -> Heard | None:
        """A lone stop phrase the keyphrase search spotted is the hearing if a decode against it and what it could
        be taken for agrees (None when that decode hears one of those lines instead)."""
        short = self._short(audio)
        self.evidence.update(short=short)
        if short == stop:  # both heard the same stop phrase: it is the hearing, at once
            return Heard(stop, False, f"a stop phrase spotted ({stop!r})")
        if short not in self.others:  # a stop, but which is unsure: a stop to everyone, at once
            return Heard("everybody stop", False, f"a stop phrase spotted ({stop!r}, then {short!r})")
        return None

    def _doubtful(self, stop: str, audio: bytes) -> bool:
        """Whether a stop a grammar decode heard needs the decode in pieces to hear a stop too before it acts:
        the hearing has a hesitation (the grammar fit garbled audio with numbers, an "uh" and a stop word:
        "robots two thirteen one uh freeze"), or the utterance is short and the short lines' decode hears it as
        a line a stop could be taken for that is no part of the stop ("cancel that" heard as "please all stop",
        where the keyphrase search may spot "all stop" too; "robot two" of "robot two stop" is part of it)."""
        if has_hesitation(stop):
            return True
        first, last = self._span(audio)
        if last - first > self.LONGEST_STOP:
            return False
        if "short" not in self.evidence:  # (the lone-stop check may have decoded it already)
            self.evidence.update(short=self._short(audio))
        short = self.evidence["short"]  # a line that is part of the stop ("robot two" of "robot two stop") is no doubt
        return short in self.others and not set(short.split()) <= set(stop.split())

    def _unconfirmed(self, stop: str, audio: bytes, live: str | None = None) -> Heard | None:
        """A doubtful stop the whole grammar heard: it acts if the decode in pieces (the doubt rule's second
        decode, the front end settled on this utterance) hears a stop too, and, for a hearing with a hesitation,
        the live decode (when it heard the utterance) did too and the keyphrase search spots a stop phrase
        somewhere in the utterance (an independent search: garbled audio that all the grammar's decodes fit to
        "... uh freeze" mostly holds none). Else the utterance is heard as the decode in pieces heard it,
        without its stop words, and doubted: a command is read back or asked again, so nothing moves, and an
        operator who meant a stop says it again or presses Stop."""
        from erni.plugins.ui.grammar import STOP_WORDS

        garbled = has_hesitation(stop)
        if garbled and not self.near:  # the stop phrases searched for in all of it, however long
            self._spotted(audio, self.STOPS, self.LONE_STOP, math.inf)
        self._decode(audio, whole=False)
        again, _ = self._decoded()
        self.evidence.update(again=again, doubted=stop, near=self.near)
        if is_stop(again) and (not garbled or (self.near and (live is None or is_stop(live)))):
            return Heard(stop, False, f"a stop, heard again as {again!r}")
        rest = " ".join(w for w in again.split() if w not in STOP_WORDS)
        return Heard(rest, True, f"a stop heard doubtfully ({stop!r}), then {again!r}") if rest else None

    def _answer(self, audio: bytes) -> tuple[Heard | None, tuple[str, list[tuple[str, float]]] | None]:
        """A short utterance heard as an answer to a read-back: decoded against the short lines (`NOT_STOPS`: the
        answers, the stop phrases and the short commands they could be taken for, so that a short command has a
        sentence of its own to go to), twice, both hearing the same answer with every word fitting the audio, and
        the whole grammar not surely hearing a command that is no answer. Else None: the utterance then goes to
        the whole grammar (the operator may have said a command instead), with that grammar's decode when it was
        made here."""
        from erni.plugins.ui.grammar import CONFIRM, DENY

        first, last = self._span(audio)
        if last - first > self.LONGEST_ANSWER:
            return None, None
        self.decoder.activate_search(self.SHORT)
        try:
            self._decode(audio, whole=True)
            text, scores = self._decoded()
            self._decode(audio, whole=False)
            again, _ = self._decoded()
        finally:
            self.decoder.activate_search(self.COMMANDS)
        self.evidence.update(answer=text, answer_again=again, answer_scores=scores)
        if (text not in CONFIRM + DENY or text != again
                or any(score < self.MIN_WORD_SCORE for _, score in scores)):
            return None, None
        self._decode(audio, whole=True)
        decoded = command, command_scores = self._decoded()
        self.evidence.update(answer_command=command)
        if (command and command != text and (self.complete is None or self.complete(command))
                and all(score >= self.MIN_WORD_SCORE for _, score in command_scores)):
            return None, decoded  # the whole grammar is sure of a command that is no answer
        return Heard(text, False, "heard as an answer to a read-back"), decoded

    def _doubts(self, text: str, scores: list[tuple[str, float]]) -> tuple[bool, list[str]]:
        """Whether the search ended inside a sentence, and the words that fit the audio poorly."""
        partial = self.complete is not None and bool(text) and not self.complete(text)
        return partial, [f"{w!r} ({score:.1f})" for w, score in scores if score < self.MIN_WORD_SCORE]

    @classmethod
    def _judged(cls, text: str, partial: bool, poor: list[str], again: str, snr: float | None) -> Heard | None:
        if not text:
            return None
        if partial:  # the search ended inside a sentence
            return Heard(text, True, "only part of a command was heard")
        if not same_meaning(text, again):
            return Heard(text, True, f"the two decodes differ: {text!r} and {again!r}")
        if poor:
            return Heard(text, True, f"{', '.join(poor)} matches the audio poorly")
        hesitant = [w for w in text.split() if w in HESITATIONS]
        if hesitant and moves(text):  # the grammar took part of the audio for a hesitation
            return Heard(text, True, f"{hesitant[0]!r} was heard: part of it fit no command word")
        if snr is not None and snr < cls.MIN_SNR and moves(text):
            return Heard(text, True, f"the speech is only {snr:.0f} dB above the background")
        return Heard(text)


# Hesitations the grammar lets stand anywhere: the recogniser fits them to audio that fits no word of a
# command, so a command heard with one is doubted.
HESITATIONS = frozenset({"uh", "um", "umm", "uhm", "er", "erm", "ah"})


def has_hesitation(text: str) -> bool:
    """Whether a hearing has a hesitation in it (audio the grammar fit to no command word)."""
    return any(w in HESITATIONS for w in text.split())


def moves(text: str) -> bool:
    """True when a hearing would send tasks or pick robots (not a stop, a question, a yes or no, a wake word)."""
    from erni.plugins.ui.grammar import Refusal, parse

    try:
        cmd = parse(text)
    except Refusal:
        return False
    return cmd.kind == "select" or (cmd.kind == "action" and not cmd.is_stop)


def is_stop(text: str) -> bool:
    """True when a hearing asks for a stop (the dialogue carries it out however sure it is)."""
    from erni.plugins.ui.grammar import Refusal, parse

    try:
        return bool(text) and parse(text).is_stop
    except Refusal:
        return False


def same_meaning(a: str, b: str) -> bool:
    """True when two hearings ask for the same thing (or, refused, are the same words)."""
    from erni.plugins.ui.grammar import Refusal, parse

    if a.split() == b.split():
        return True
    try:
        return parse(a) == parse(b)
    except Refusal:
        return False


def choose_recognizer(kind: str, vosk_model: str | None, wake: tuple[str, ...] | None = None,
                      front: Any = None) -> Callable[[], Any]:
    """Return a loader of the recogniser to use (run on the speech thread), or raise SpeechError saying why none.

    `auto`: vosk when a vosk model is given (setting or VOSK_MODEL_PATH), else PocketSphinx.
    `wake`: the wake phrases to hear (default `grammar.ATTENTION`). `front`: the `frontend.FrontEnd` the
    audio goes through before PocketSphinx (vosk hears the audio as it came).
    """
    from erni.plugins.ui.grammar import vocabulary
    from erni.plugins.ui.jsgf import jsgf

    given = vosk_model or os.environ.get("VOSK_MODEL_PATH", "").strip()
    if kind == "vosk" or (kind == "auto" and given):
        path = model_path(vosk_model)
        extra = [w for phrase in wake or () for w in phrase.split()]
        return _Loader("vosk", lambda: Recognizer(path, vocabulary() + extra))
    sphinx_model()  # installed?
    grammar = jsgf(wake=wake)
    return _Loader("pocketsphinx", lambda: SphinxRecognizer(grammar, wake=wake, front=front))


class _Loader:
    """A recogniser loader that says which recogniser it loads."""

    def __init__(self, backend: str, load: Callable[[], Any]) -> None:
        self.backend, self.load = backend, load

    def __call__(self) -> Any:
        return self.load()


class Listener:
    """Runs a recogniser on thread `ui-speech`: `feed()` audio from any thread, hearings go to `on_text`.

    `on_text(source, heard)` gets each utterance as a `Heard`: a `str` (the text) whose `unsure`
    says the recogniser doubts it (ask "Say again?", naming what was heard; never act on it) and
    whose `why` names the evidence.

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
        self.answering = False  # a read-back waits for "yes" or "no" (set by the UI; every stream is told)
        self.streams: dict[str, Any] = {}
        self._stopping = threading.Event()
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
        """Stop the thread (joined). Audio not yet heard is dropped, not recognised: nothing said
        before a stop is carried out after it, and a long queue does not hold the stop."""
        if not self._thread.is_alive():
            return
        self._stopping.set()
        while True:
            try:
                self.queue.get_nowait()
            except queue.Empty:
                break
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
        while (item := self.queue.get()) is not None and not self._stopping.is_set():
            source, pcm = item
            try:
                if pcm == self.FLUSH:
                    stream = self.streams.pop(source, None)
                    text = stream.flush() if stream is not None else None
                else:
                    stream = self.streams.get(source) or self.streams.setdefault(source, self.recognizer.stream())
                    if hasattr(stream, "answering"):
                        stream.answering = self.answering
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
