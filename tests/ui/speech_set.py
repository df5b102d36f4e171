"""The speech test set: the paper's operator utterances and the stop phrasings, spoken by several
espeak-ng voices at several speeds, clean and in white noise, and how each hearing is judged.

The audio is made at test time (espeak-ng, then the control node's own audio path to 16 kHz
mono PCM); nothing is recorded in the repository. A hearing is judged by meaning against the
same text typed, through the spoken dialogue (`judge`): `exact` when it does what the typed line
does, `confirmed` when it does so after a read-back answered "yes" (that answer spoken and heard
too), `asked` when nothing is sent and the operator is asked again, `refused` when the parser
refuses what was heard, `wrong` when a different command is carried out, `false stop` when a stop
is carried out where something else was said.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from erni.plugins.ui.grammar import Command, Refusal, parse
from erni.plugins.ui.speech import FRAME_SAMPLES, RATE, read_wav

ESPEAK = shutil.which("espeak-ng")
PAPER = Path(__file__).with_name("paper_utterances.txt")
VOICES = ("en-us", "en-gb", "en-us+f3")  # American, British, a female variant
SPEEDS = (130, 160, 190)  # words a minute
NOISES: tuple[float | None, ...] = (None, 15.0, 5.0)  # white noise at this SNR (dB); None: a quiet room
STOPS = ("stop", "everybody stop", "all stop", "halt", "freeze")
ROOM = 50.0  # rms of a quiet room's noise floor (about -56 dBFS): synthetic speech has none


@dataclass(frozen=True)
class Condition:
    voice: str
    speed: int
    snr: float | None

    @property
    def noise(self) -> str:
        return "clean" if self.snr is None else f"{self.snr:g} dB"

    def __str__(self) -> str:
        return f"{self.voice} {self.speed} wpm {self.noise}"


def conditions(voices: tuple[str, ...] = VOICES, speeds: tuple[int, ...] = SPEEDS,
               noises: tuple[float | None, ...] = NOISES) -> list[Condition]:
    return [Condition(v, s, n) for v in voices for s in speeds for n in noises]


def utterances() -> list[str]:
    """The paper's operator lines (tests/ui/paper_utterances.txt) and every stop phrasing, once each."""
    lines = [line.strip() for line in PAPER.read_text(encoding="utf-8").splitlines()
             if line.strip() and not line.startswith("#")]
    return list(dict.fromkeys(lines + list(STOPS)))


def meaning(text: str) -> Command | None:
    """What a text asks for, None when the parser refuses it."""
    try:
        return parse(text)
    except Refusal:
        return None


def synthesise(text: str, voice: str, speed: int) -> np.ndarray:
    """espeak-ng saying `text`, read through the control node's audio path: 16 kHz mono int16 samples."""
    if ESPEAK is None:
        raise RuntimeError("espeak-ng is not installed (apt install espeak-ng)")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "say.wav"
        subprocess.run([ESPEAK, "-v", voice, "-s", str(speed), "-w", str(out), text], check=True, timeout=30,
                       capture_output=True)
        return np.frombuffer(read_wav(out), dtype="<i2").astype(np.float64)


def as_heard(speech: np.ndarray, snr: float | None, rng: np.random.Generator) -> bytes:
    """Speech with half a second of room before and a second after, in a quiet room or in white noise
    at `snr` dB (the speech's power over its loud 10 ms windows against the noise's)."""
    pcm = np.concatenate([np.zeros(int(LEAD * RATE)), speech, np.zeros(RATE)])
    pcm = pcm + rng.normal(0.0, noise_level(speech, snr), len(pcm))
    return np.clip(np.round(pcm), -32768, 32767).astype("<i2").tobytes()


def noise_level(speech: np.ndarray, snr: float | None) -> float:
    """The rms of the noise that puts `speech` at `snr` dB (a quiet room's for None)."""
    windows = speech[: len(speech) // 160 * 160].reshape(-1, 160)
    power = np.mean(windows ** 2, axis=1)
    loud = power[power > 0.1 * power.max()] if power.size else np.array([0.0])
    return ROOM if snr is None else float(np.sqrt(loud.mean() / 10 ** (snr / 10)))


def room(speech: np.ndarray, snr: float | None, rng: np.random.Generator, seconds: float) -> bytes:
    """`seconds` of the room `as_heard(speech, snr)` puts the speech in, with nobody speaking."""
    pcm = rng.normal(0.0, noise_level(speech, snr), int(seconds * RATE))
    return np.clip(np.round(pcm), -32768, 32767).astype("<i2").tobytes()


def in_frames(pcm: bytes) -> list[bytes]:
    """100 ms frames, as the page's microphone sends them."""
    return [pcm[i:i + FRAME_SAMPLES * 2] for i in range(0, len(pcm), FRAME_SAMPLES * 2)]


TEAM = [f"robot{n}" for n in range(1, 21)]  # every robot number the spoken grammar has


def _outcome(reply: Any) -> Any:
    """What an answer does: the tasks it sends, or (sending none) what it says."""
    return (reply.say if not reply.tasks else None,
            [(t.verb, t.preposition, t.destination, t.params.model_dump()) for t in reply.tasks])


OUTCOMES = ("exact", "confirmed", "asked", "refused", "wrong", "false stop")


def _targets(reply: Any) -> set[str]:
    return {t.destination for t in reply.tasks}


def judge(said: str, heard: str, unsure: bool, answer: Callable[[str], tuple[str, bool]] | None = None) -> str:
    """What the operator gets for saying `said` when the recogniser hears `heard` (unsure or not),
    answered by the control node's spoken dialogue (a stop acts however it was heard; an unsure
    hearing of a motion command, a command to several robots and a long move are read back and wait
    for "yes"; any other unsure hearing is asked again) against the same text typed, which runs at once.

    A read-back is answered as the operator would: "yes" when it restates what was said, "no"
    otherwise, that answer heard through `answer(word) -> (heard, unsure)` (default: heard right).

    `exact`: the same tasks or answer as typed (a stop said, answered by a stop to at least the robots
    meant, is exact too); `confirmed`: exact after a read-back and a "yes" heard; `asked`: nothing sent,
    the operator asked again (or the answer to a read-back was not heard as it was said); `refused`:
    nothing sent, the line refused; `wrong`: tasks sent that differ from what was said; `false stop`:
    a stop carried out where something else was said (safe, but not what was said)."""
    from erni.plugins.ui.dialogue import Dialogue, Naming

    typed = Dialogue(Naming(), verb="RemoteBotMotion")
    spoken = Dialogue(Naming(), verb="RemoteBotMotion", read_back=5.0, read_back_numbers=True)  # the UI's defaults
    for d in (typed, spoken):
        d.select(["robot1"])
    want = typed.hear(said, TEAM)

    def carried_out(got: Any, confirmed: bool) -> str:
        if _outcome(got) == _outcome(want):
            return "confirmed" if confirmed else "exact"
        if got.stop and want.stop and _targets(got) >= _targets(want):
            return "exact"
        return "false stop" if got.stop else "wrong"

    got = spoken.hear(heard, TEAM, unsure=unsure) if heard else None
    if got is None:
        return "refused"
    if got.tasks:
        return carried_out(got, False)
    if _outcome(got) == _outcome(want):
        return "exact"
    pending = getattr(spoken, "pending", None)
    if got.asked and pending is not None:
        word = "yes" if _outcome(pending.reply) == _outcome(want) else "no"
        reply, doubt = answer(word) if answer is not None else (word, False)
        final = spoken.hear(reply, TEAM, unsure=doubt) if reply else None
        return carried_out(final, True) if final is not None and final.tasks else "asked"
    return "asked" if unsure or got.asked else "refused"


@dataclass
class Hearing:
    """What the recogniser made of one clip: its hearings in order, and when the last one came."""

    texts: list[str]
    evidence: list[dict[str, Any]]  # the recogniser's evidence of each hearing, when it keeps it
    unsure: bool
    why: str
    latency: float  # seconds from the end of the speech to the last hearing, the audio coming in real time
    seconds: float  # compute time of the whole clip

    @property
    def text(self) -> str:
        return " ".join(self.texts)


def hear(stream: Any, pcm: bytes, speech_end: float) -> Hearing:
    """Stream one clip through a recogniser stream in 100 ms frames, as fast as it decodes. The latency is
    that of a live microphone: each frame is handed over when it has been spoken, or when the stream is done
    with the frames before it if it has fallen behind, so a decode slower than the speech delays the hearing.
    Compute is the process's CPU time (the bench does nothing else), so the latency is that of a stream with
    the machine to itself, whatever else is running beside it."""
    texts: list[str] = []
    evidence: list[dict[str, Any]] = []
    unsure, why, latency = False, "", 0.0
    started = time.perf_counter()
    chunks = in_frames(pcm)
    busy = 0.0  # when the stream is done with the frames handed over so far (seconds of the clip)
    for i, frame in enumerate([*chunks, None]):
        at = len(pcm) / 2 / RATE if frame is None else (i + 1) * FRAME_SAMPLES / RATE  # spoken by then
        t0 = time.process_time()
        heard = stream.feed(frame) if frame is not None else stream.flush()
        busy = max(busy, at) + (time.process_time() - t0)
        if heard:
            texts.append(str(heard))
            evidence.append(dict(getattr(stream, "evidence", {}), unsure=bool(getattr(heard, "unsure", False))))
            unsure = unsure or bool(getattr(heard, "unsure", False))
            why = why or str(getattr(heard, "why", ""))
            latency = max(0.0, busy - speech_end)
    return Hearing(texts, evidence, unsure, why, latency, time.perf_counter() - started)


LEAD = 0.5  # seconds of room before the speech in `as_heard`


def speech_end(speech: np.ndarray) -> float:
    """Where the voice of `as_heard(speech, ...)` ends, in seconds from the clip's start (espeak-ng
    ends its audio with about 0.35 s of silence, which is not speech)."""
    loud = np.flatnonzero(np.abs(speech) > 0.01 * max(float(np.abs(speech).max(initial=0.0)), 1.0))
    return LEAD + (int(loud[-1]) + 1 if loud.size else len(speech)) / RATE


_ONES = "zero one two three four five six seven eight nine".split()
_TEENS = "ten eleven twelve thirteen fourteen fifteen sixteen seventeen eighteen nineteen".split()
_TENS = "_ _ twenty thirty forty fifty sixty seventy eighty ninety".split()


def _int_words(n: int) -> list[str]:
    if n >= 100:
        rest = _int_words(n % 100) if n % 100 else []
        return [_ONES[n // 100], "hundred", *rest]
    if n >= 20:
        return [_TENS[n // 10]] + ([_ONES[n % 10]] if n % 10 else [])
    return [(_ONES + _TEENS)[n]] if n < 10 else [_TEENS[n - 10]]


def in_words(text: str) -> str:
    """The text with its numbers in words, as it is spoken ("robot 1 set velocity to 0.3" ->
    "robot one set velocity to zero point three")."""
    out: list[str] = []
    for word in text.split():
        whole, _, frac = word.partition(".")
        if whole.lstrip("-").isdigit():
            out += (["minus"] if whole.startswith("-") else []) + _int_words(int(whole.lstrip("-")))
            out += ["point", *(_ONES[int(d)] for d in frac)] if frac else []
        else:
            out.append(word)
    return " ".join(out)
