"""The speech front end before the recogniser: WebRTC's noise suppression, Silero's voice-activity
detector cutting utterances, the answers to a read-back heard against the answers alone, all on
synthetic noise (espeak-ng's voice in seeded white noise) and through PocketSphinx itself."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from erni.plugins.ui import frontend
from erni.plugins.ui.frontend import FrontEnd, SileroVad, VoiceEndpointer, WebRtcSuppressor
from erni.plugins.ui.speech import RATE, SpeechError, SphinxRecognizer
from tests.ui import speech_set as S

needs_espeak = pytest.mark.skipif(S.ESPEAK is None, reason="espeak-ng is not installed (apt install espeak-ng)")


def pcm(x: np.ndarray) -> bytes:
    return np.clip(np.round(x), -32768, 32767).astype("<i2").tobytes()


def db(x: np.ndarray) -> float:
    return 10 * float(np.log10(np.mean(np.asarray(x, dtype=np.float64) ** 2) + 1e-9))


def cleaned(suppressor: WebRtcSuppressor, audio: bytes) -> np.ndarray:
    step = 960  # 30 ms, as the recogniser's stream hands it over
    out = b"".join(suppressor.process(audio[i:i + step]) for i in range(0, len(audio) - step + 1, step))
    return np.frombuffer(out, dtype="<i2").astype(np.float64)


@needs_espeak
def test_webrtc_suppression_takes_the_noise_down_and_keeps_the_voice():
    """White noise at 5 dB under a spoken command: between the words the noise falls by more than 10 dB,
    while the voice keeps its level within 4 dB; the same number of samples comes back."""
    rng = np.random.default_rng(55)
    speech = S.synthesise("robot one go forward two meters", "en-us", 160)
    noise = S.noise_level(speech, 5.0)
    audio = np.concatenate([np.zeros(2 * RATE), speech, np.zeros(RATE)])
    noisy = audio + rng.normal(0, noise, audio.size)
    out = cleaned(WebRtcSuppressor(), pcm(noisy))
    assert out.size == noisy.size // 480 * 480
    room = slice(int(1.0 * RATE), int(1.9 * RATE))  # noise alone, the suppressor has heard a second of it
    voice = slice(2 * RATE, 2 * RATE + speech.size)
    assert db(noisy[room]) - db(out[room]) > 10.0, (db(noisy[room]), db(out[room]))
    assert abs(db(out[voice]) - db(audio[voice])) < 4.0, (db(out[voice]), db(audio[voice]))


@needs_espeak
@pytest.mark.parametrize("snr", [None, 15.0, 5.0])
def test_the_voice_detector_cuts_an_utterance_where_the_voice_is(snr):
    """Silero's probability ends the utterance within half a second of the voice's end, in a quiet room and in
    white noise at 15 and 5 dB, starts it with the voice, and its SNR is measured on the audio as it came in."""
    rng = np.random.default_rng(7)
    speech = S.synthesise("all robots go to three four", "en-us", 160)
    clip = S.room(speech, snr, rng, 2.0) + S.as_heard(speech, snr, rng)
    voice_from, voice_to = 2.0 + S.LEAD, 2.0 + S.speech_end(speech)
    suppressor = WebRtcSuppressor()
    ep = VoiceEndpointer(SileroVad(), suppressor)
    events = []
    for i in range(0, len(clip) - ep.frame_bytes + 1, ep.frame_bytes):
        raw = clip[i:i + ep.frame_bytes]
        was = ep.in_speech
        ep.process(suppressor.process(raw), raw=raw)
        if ep.in_speech != was:
            events.append(("start" if ep.in_speech else "end", i / 2 / RATE))
    assert [e for e, _ in events] == ["start", "end"], events
    assert voice_from - 0.4 <= events[0][1] <= voice_from + 0.3, (events, voice_from)
    assert voice_to <= events[1][1] <= voice_to + 0.5 + VoiceEndpointer.HANGOVER, (events, voice_to)
    if snr is not None:
        assert abs(ep.snr - snr) < 5.0, ep.snr


def heard(stream, audio: bytes) -> list[str]:
    out = [h for i in range(0, len(audio), 3200) if (h := stream.feed(audio[i:i + 3200]))]
    return [str(h) for h in out + [h for h in [stream.flush()] if h]]


@pytest.fixture(scope="module")
def recognisers():
    from erni.plugins.ui.jsgf import jsgf

    grammar = jsgf()
    return {"bare": SphinxRecognizer(grammar), "front": SphinxRecognizer(grammar, front=FrontEnd("webrtc", "silero"))}


# Lines of the speech set the front end hears in white noise at 5 dB where the bare recogniser does not (bench_speech)
AT_5_DB = ("everybody stop", "everyone stop", "everyone freeze", "robot 1 go to 3 4",
           "robot 1 relay between robot 2 and control", "where are you", "all robots go to 0 0",
           "robot 2 turn 180 degrees")


@needs_espeak
def test_lines_in_loud_noise_are_heard_with_the_front_end_and_missed_without(recognisers):
    """Eight lines (stops, moves, a question) in white noise at 5 dB, seeded: with the front end at least two more
    mean what was said than the recogniser hears from the audio as it came (so this fails when the front end does
    nothing), and nothing is heard as another stop-free command that moves robots with certainty."""
    got = {}
    for name, rec in recognisers.items():
        stream, rng = rec.stream(), np.random.default_rng(36)
        got[name] = []
        for text in AT_5_DB:
            speech = S.synthesise(S.in_words(text), "en-us", 160)
            got[name].append(" ".join(heard(stream, S.room(speech, 5.0, rng, 1.5) + S.as_heard(speech, 5.0, rng))))
    right = {name: sum(S.meaning(h) == S.meaning(t) for h, t in zip(said, AT_5_DB)) for name, said in got.items()}
    assert right["front"] >= right["bare"] + 2, (right, got)


@needs_espeak
def test_an_answer_in_noise_is_heard_against_the_short_lines(recognisers):
    """While a read-back waits, "yes" and "no" in three voices at 15 and 5 dB: most are heard as said and none as
    the other answer; short commands said instead keep their own hearing, never an answer."""
    rng = np.random.default_rng(5)
    stream = recognisers["front"].stream()
    stream.answering = True
    got = []
    for snr in (15.0, 5.0):
        for voice in ("en-us", "en-gb", "en-us+f3"):
            for word in ("yes", "no"):
                speech = S.synthesise(word, voice, 160)
                got.append((word, heard(stream, S.room(speech, snr, rng, 1.0) + S.as_heard(speech, snr, rng))))
    assert sum(said == [word] for word, said in got) >= 9, got
    assert not [(w, said) for w, said in got if said == [{"yes": "no", "no": "yes"}[w]]], got
    answers = {"yes", "no", "confirm", "yes confirm", "negative", "affirmative"}
    for text in ("faster", "robot one", "go home", "robot two turn left"):
        speech = S.synthesise(text, "en-us", 160)
        said = heard(stream, S.room(speech, 15.0, rng, 1.0) + S.as_heard(speech, 15.0, rng))
        assert not answers & set(said), (text, said)


@needs_espeak
def test_a_stop_inside_a_longer_line_is_heard_by_the_live_decode_without_a_decode_after_it(recognisers):
    """ "robot two stop" and "everyone stop" are no lone stop phrase for the keyphrase search: the live decoder,
    fed the utterance as it is spoken, hears the stop, and it acts when the utterance ends, with no decode of the
    whole grammar before it (which is what took a stop said this way seconds on a busy machine); the live decoder
    decodes it whole after it, and hearing the same stop adds nothing. A command that is no stop still gets its two
    decodes."""
    stream, rng = recognisers["front"].stream(), np.random.default_rng(3)
    decodes: list[tuple[str, bool]] = []
    decode = stream._decode

    def recorded(audio: bytes, whole: bool) -> None:
        decodes.append((stream.decoder.current_search(), whole))
        decode(audio, whole)

    stream._decode = recorded
    first = S.synthesise("robot one go home", "en-us", 160)  # the first utterance: no live hearing (no mean yet)
    heard(stream, S.room(first, None, rng, 1.0) + S.as_heard(first, None, rng))
    assert "live" not in stream.evidence, stream.evidence
    for text in ("robot two stop", "everyone stop", "where are you"):
        decodes.clear()
        speech = S.synthesise(text, "en-us", 160)
        audio = S.room(speech, None, rng, 1.0) + S.as_heard(speech, None, rng)
        said, before = [], None  # the hearings, and the decodes made until the first
        for i in range(0, len(audio), 3200):
            if h := stream.feed(audio[i:i + 3200]):
                said.append(str(h))
                before = list(decodes) if before is None else before
        said += [str(h) for h in [stream.flush()] if h]
        grammar = [whole for search, whole in decodes if search == stream.COMMANDS]
        if text.endswith("stop"):
            assert said == [text] and stream.evidence.get("live") == text, (text, said, stream.evidence)
            assert before is not None and [s for s, _ in before if s == stream.COMMANDS] == [], (text, before)
            assert grammar == [], (text, decodes)  # the main decoder decodes no grammar for it, before or after
            assert stream.evidence.get("recheck") == text, stream.evidence  # the live decoder's whole decode after it
        else:
            assert said == [text] and stream.evidence["live"] == text, (text, said, stream.evidence)
            assert grammar == [True, False], (text, decodes)  # whole, then in pieces: the doubt rule's two decodes


def test_a_stop_the_live_decode_heard_for_another_robot_is_added_by_the_whole_grammar():
    """The live decode heard "robot twenty stop" where the whole grammar, decoding the same audio after it on the
    live decoder (not the main one), hears "robot one stop": the stop to robot 1 is heard too, at the next audio;
    the same stop adds nothing."""
    from erni.plugins.ui.speech import SphinxStream

    class Decoder:  # the whole grammar's decode of the kept audio, on the live decoder
        def __init__(self, text: str) -> None:
            self.text = text

        def get_cmn(self) -> str:
            return "40,3,-1"

        def set_cmn(self, cmn: str) -> None: ...

        def start_utt(self) -> None: ...
        def process_raw(self, *a: object) -> None: ...
        def end_utt(self) -> None: ...
        def seg(self) -> list[object]:
            return []

        def hyp(self) -> object:
            return type("Hyp", (), {"hypstr": self.text})()

    for whole, extra in (("robot one stop", "robot one stop"), ("robot twenty stop", None), ("robot one turn left", None)):
        stream = SphinxStream(Decoder("robot seven stop"), VoiceEndpointer(lambda f, s: 0.0), live=Decoder(whole))
        stream._stopped = (bytes(960), "robot twenty stop")
        got = stream.feed(bytes(960))
        assert (str(got) if got else None) == extra, (whole, got)
        assert stream._stopped is None and stream.feed(bytes(960)) is None


def test_a_missing_library_is_one_line_naming_its_package(monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    with pytest.raises(SpeechError, match=r"needs the pyrnnoise package: pip install pyrnnoise") as err:
        FrontEnd("rnnoise", "off")
    assert "\n" not in str(err.value)
    with pytest.raises(SpeechError, match=r"denoise 'loud': expected one of off, auto, webrtc, speex, rnnoise"):
        FrontEnd("loud", "off")
    auto = FrontEnd("auto", "off")  # auto without pyrnnoise: WebRTC alone, and a line that says so
    assert "pyrnnoise is not installed" in auto.note and "\n" not in auto.note
    suppressor = auto.suppressor()
    assert isinstance(suppressor, frontend.AutoSuppressor) and suppressor.make is None


def test_the_ui_hears_through_the_front_end_by_default():
    from erni.plugins.ui.plugin import UISettings

    s = UISettings()
    front = FrontEnd(s.denoise, s.vad, s.auto_gain, loud=s.loud_room)
    assert front.active and isinstance(front.suppressor(), frontend.AutoSuppressor)
    assert isinstance(front.endpointer(), VoiceEndpointer)
    assert isinstance(FrontEnd("off", "off").endpointer(), frontend.NoiseFloorEndpointer)


needs_rnnoise = pytest.mark.skipif(importlib.util.find_spec("pyrnnoise") is None,
                                   reason="pyrnnoise is not installed (pip install 'erni[denoise]')")


def room_then_voice(snr: float | None, rng: np.random.Generator) -> tuple[bytes, np.ndarray]:
    speech = S.synthesise("everybody stop", "en-us", 160)
    return S.room(speech, snr, rng, 3.0) + S.as_heard(speech, snr, rng), speech


@needs_espeak
@needs_rnnoise
def test_auto_hears_a_quiet_room_through_webrtc_and_a_loud_one_through_rnnoise():
    """The same auto suppressor on one stream: a quiet room (-56 dBFS) and then 15 and 5 dB of white noise under
    a voice at about -20 dBFS. In the quiet room its output is WebRTC's, sample for sample; once the room is
    loud it is RNNoise's (which leaves less of the noise between words than WebRTC does), and back in the quiet
    room WebRTC's again once the room's window has forgotten the noise; the voice never switches it, and the
    room's level it reads is the noise's within 2 dB."""
    rng = np.random.default_rng(57)
    auto = FrontEnd("auto", "off").suppressor()
    twin = WebRtcSuppressor()  # what WebRTC alone gives the same audio
    for snr, noisy in ((None, False), (15.0, True), (5.0, True), (None, False)):
        audio, speech = room_then_voice(snr, rng)
        out, alone = cleaned(auto, audio), cleaned(twin, audio)
        assert auto.noisy is noisy, (snr, auto.room())
        level = 20 * np.log10(S.noise_level(speech, snr) / 32768)
        assert abs(auto.room() - level) < 2.0, (snr, auto.room(), level)
        tail = slice(len(alone) - int(0.3 * RATE), len(alone))  # the room after the voice
        if noisy:
            assert db(out[tail]) < db(alone[tail]) - 3.0, (snr, db(out[tail]), db(alone[tail]))
        else:  # the voice and after: WebRTC's (in the first quiet room from the start)
            assert np.array_equal(out[3 * RATE:], alone[3 * RATE:])
    assert auto.switches == 2


@needs_rnnoise
def test_the_loud_rooms_level_is_a_setting():
    """`loud_room` moves the point where auto hands over: 5 dB noise at -22 dBFS is heard through WebRTC when
    the setting is -15 dBFS, and a setting outside 0..-90 dBFS is refused by the UI's settings."""
    from pydantic import ValidationError

    from erni.plugins.ui.plugin import UISettings

    rng = np.random.default_rng(58)
    noise = pcm(rng.normal(0.0, 2600.0, 3 * RATE))  # about -22 dBFS
    high = FrontEnd("auto", "off", loud=-15.0).suppressor()
    cleaned(high, noise)
    low = FrontEnd("auto", "off", loud=UISettings().loud_room).suppressor()
    cleaned(low, noise)
    assert (high.noisy, low.noisy) == (False, True)
    with pytest.raises(ValidationError, match="loud_room"):
        UISettings(loud_room=3.0)


class Scripted:
    """A decoder whose hearing per search (and per whole or piecewise decode) is given: the keyphrase searches
    spot nothing; `texts[search]` is a hearing, or a pair (whole, in pieces)."""

    def __init__(self, texts: dict[str, object]) -> None:
        self.texts, self.search, self.pieces, self.text = texts, "erni", False, ""

    def activate_search(self, name: str) -> None:
        self.search = name

    def current_search(self) -> str:
        return self.search

    def get_cmn(self) -> str:
        return "40,3,-1"

    def set_cmn(self, cmn: str) -> None: ...

    def start_utt(self) -> None:
        self.pieces = False

    def process_raw(self, audio: bytes, no_search: bool, full: bool) -> None:
        self.pieces = not full

    def end_utt(self) -> None:
        got = self.texts.get(self.search, "")
        self.text = got[self.pieces] if isinstance(got, tuple) else got

    def seg(self) -> list[object]:  # the keyphrase search's hit: texts["stops"] over the first half second
        spotted = self.texts.get("stops") if self.search == "stops" else None
        return [type("Seg", (), {"word": spotted, "start_frame": 0, "end_frame": 49, "ascore": 1.0})()] if spotted else []

    def hyp(self) -> object:
        return type("Hyp", (), {"hypstr": self.text})() if self.text and self.search != "stops" else None


@pytest.mark.parametrize("whole, live, pieces, short, heard, stops, spot", [  # spot: the keyphrase search's hit
    # the garbled line a grammar fits with an "uh" before a stop word, which the decode in pieces hears otherwise:
    # doubted, as the decode in pieces heard it; no stop (the live decode hearing the same garbled stop adds nothing)
    ("robots one and two uh freeze moving", "robot two where are you please", "robot one go to three four", "",
     "robot one go to three four", False, ""),
    ("robots two thirteen one uh freeze", "robots two thirteen one uh freeze", "robot two turn one hundred eighty "
     "degrees", "", "robot two turn one hundred eighty degrees", False, ""),
    # ... and heard so by every decode, where the keyphrase search spots no stop phrase: doubted, without the stop
    ("robots two thirteen one uh freeze", "robots two thirteen one uh freeze", None, "", "robots two thirteen one uh",
     False, ""),
    ("robot two turn left", "robots two thirteen one uh freeze", None, "", "robot two turn left", False, ""),
    # a short line the short lines' decode hears as one a stop is taken for
    ("cancel that", "please all stop", None, "cancel that", "cancel that", False, ""),
    ("please all stop", "please all stop", "cancel that", "cancel that", "cancel that", False, ""),
    # heard as a stop by the decode in pieces too, or not doubtful: the stop acts
    ("please all stop", "please all stop", None, "cancel that", "please all stop", True, ""),
    ("robot two uh freeze", None, "robot two freeze", "", "robot two uh freeze", True, "freeze"),
    # ... unless the live decode heard the line otherwise ("degrees" heard as "uh freeze" by the whole grammar)
    ("robot two uh freeze", "robot two turn one hundred eighty degrees", "robot two freeze", "", "robot two", False, "freeze"),
    # a short line: the keyphrase search spotted "all stop" (not alone), the short lines' decode "cancel that"
    ("please all stop", "please all stop", "cancel that", "cancel that", "cancel that", False, "all stop"),
    ("robot two freeze", "robot two freeze", "robot two where are you", "", "robot two freeze", True, ""),
    ("everybody stop", None, "everybody", "everybody stop", "everybody stop", True, ""),
    # the short lines' decode hears the stop's subject alone ("robot two"; it has no "robot two stop"): no doubt
    ("robot two stop", "robot two stop", "robot two where are you", "robot two", "robot two stop", True, ""),
])
def test_a_stop_heard_once_from_garbled_audio_or_a_short_line_needs_a_second_hearing(
        whole, live, pieces, short, heard, stops, spot):
    """A stop a grammar decode heard in a short line the short lines' decode hears as no stop ("cancel that" as
    "please all stop") acts only when the decode in pieces hears a stop too; one heard with a hesitation ("robot 2
    turn 180 degrees" as "robots two thirteen one uh freeze") only when the live decode did too and the keyphrase
    search spots a stop phrase. Else the utterance is heard as the decode in pieces heard it, without its stop
    words, doubted (nothing moves). A stop that is not doubtful acts at once, whatever a later decode hears."""
    from erni.plugins.ui.speech import SphinxStream, is_stop

    decoder = Scripted({SphinxStream.COMMANDS: (whole, pieces if pieces is not None else whole),
                        SphinxStream.SHORT: short, SphinxStream.STOPS: spot})
    stream = SphinxStream(decoder, VoiceEndpointer(lambda f, s: 0.0), others=("cancel that", "listen"),
                          live=Scripted({SphinxStream.COMMANDS: live or ""}) if live is not None else None)
    stream._heard_one = True  # the main decoder has settled: the live decode is listened to
    stream.settled = True
    if live is not None:
        stream._hear_live(bytes(960))
    got = stream._hearing(bytes(32000))
    assert got is not None and str(got) == heard, (got, stream.evidence)
    assert is_stop(str(got)) is stops
    if not stops:
        assert got.unsure or not is_stop(whole), (got, stream.evidence)
        assert stream._stopped is None
