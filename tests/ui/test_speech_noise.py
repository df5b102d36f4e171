"""Speech in steady noise: the endpointer ends utterances against the background's own level, each
hearing carries its SNR, a doubted motion command is read back rather than carried out (a stop never
waits), and a lone stop phrase is heard by a keyphrase search even where the grammar mishears it."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from erni.plugins.ui.dialogue import DID_YOU_SAY, Dialogue, Naming
from erni.plugins.ui.speech import RATE, NoiseFloorEndpointer, SphinxStream

TEAM = ["robot1", "robot2", "robot3"]


def pcm(x: np.ndarray) -> bytes:
    return np.clip(np.round(x), -32768, 32767).astype("<i2").tobytes()


def syllables(seconds: float, rms: float, rng: np.random.Generator) -> np.ndarray:
    """Speech-like sound: 200 ms bursts of a voiced buzz, 4 a second, each rising and falling."""
    t = np.arange(int(seconds * RATE)) / RATE
    buzz = np.sign(np.sin(2 * np.pi * 140 * t)) * np.sin(2 * np.pi * 900 * t) + 0.3 * rng.normal(size=t.size)
    envelope = np.clip(np.sin(2 * np.pi * 4 * t), 0, None) ** 2
    x = buzz * envelope
    return x * rms / np.sqrt(np.mean(x[envelope > 0.3] ** 2))


def run(ep: NoiseFloorEndpointer, audio: np.ndarray) -> list[tuple[str, float]]:
    """Feed `audio` in the endpointer's frames; the starts and ends it reports, with their times."""
    data, events, size = pcm(audio), [], ep.frame_bytes
    for i in range(0, len(data) - size + 1, size):
        was = ep.in_speech
        ep.process(data[i:i + size])
        if ep.in_speech and not was:
            events.append(("start", i / 2 / RATE))
        elif was and not ep.in_speech:
            events.append(("cancel" if ep.cancelled else "end", i / 2 / RATE))
    return events


@pytest.mark.parametrize("snr", [15.0, 5.0])
def test_an_utterance_in_steady_noise_ends_soon_after_the_speech(snr):
    """Steady white noise, 1.5 s of syllables at `snr` dB, then the noise goes on: the utterance
    starts with the speech and ends well under a second after it, with its SNR measured."""
    rng = np.random.default_rng(4)
    noise = 300.0
    speech = syllables(1.5, noise * 10 ** (snr / 20), rng)
    audio = rng.normal(0, noise, int(5.0 * RATE))
    audio[RATE * 2:RATE * 2 + speech.size] += speech
    ep = NoiseFloorEndpointer()
    events = run(ep, audio)
    starts = [t for e, t in events if e == "start"]
    ends = [t for e, t in events if e == "end"]
    assert len(starts) >= 1 and len(ends) == len(starts), events
    assert 1.5 <= starts[-1] <= 2.2 and 3.5 - 0.3 <= ends[-1] <= 3.5 + 0.8, events  # the speech: 2.0-3.5 s
    assert abs(ep.snr - snr) < 4.0, ep.snr
    assert not ep.in_speech


def test_noise_that_comes_on_is_no_utterance_and_the_floor_follows_it():
    """A quiet room, then steady noise 30 dB louder: no utterance is left open; speech after it is cut."""
    rng = np.random.default_rng(5)
    quiet, loud = rng.normal(0, 30, RATE), rng.normal(0, 1000, 4 * RATE)
    ep = NoiseFloorEndpointer()
    events = run(ep, np.concatenate([quiet, loud]))
    assert events and events[-1][0] == "cancel" and events[-1][1] < 2.5, events
    assert not ep.in_speech
    speech = rng.normal(0, 1000, 3 * RATE)
    speech[RATE:RATE + int(1.5 * RATE)] += syllables(1.5, 5000, rng)
    assert [e for e, _ in run(ep, speech)] == ["start", "end"]


def test_the_recognisers_stream_ends_an_utterance_in_steady_noise():
    """Through the stream a page's microphone feeds: in steady noise a hearing comes before the source stops."""
    pytest.importorskip("pocketsphinx")
    from erni.plugins.ui.jsgf import jsgf
    from erni.plugins.ui.speech import SphinxRecognizer

    rng = np.random.default_rng(6)
    stream = SphinxRecognizer(jsgf()).stream()
    audio = rng.normal(0, 300, 6 * RATE)
    audio[2 * RATE:int(3.5 * RATE)] += syllables(1.5, 300 * 10 ** 0.75, rng)
    data = pcm(audio)
    for i in range(0, len(data), 3200):
        stream.feed(data[i:i + 3200])
    assert not stream.in_utterance  # ended in the noise, not left for flush()
    assert stream.evidence and 10 < stream.evidence["snr"] < 20, stream.evidence


@pytest.mark.parametrize("text,snr,doubted", [
    ("robot one go forward two meters", 8.0, True),
    ("robots one and two", 8.0, True),
    ("robot one go forward two meters", 30.0, False),
    ("stop", 3.0, False),
    ("everybody halt", 3.0, False),
    ("yes", 3.0, False),
    ("no", 3.0, False),
    ("robot one where are you", 3.0, False),
    ("listen", 3.0, False),
])
def test_a_hearing_in_poor_audio_is_doubted_when_it_would_move_robots(text, snr, doubted):
    heard = SphinxStream._judged(text, False, [], text, snr)
    assert heard is not None and heard.unsure == doubted, heard
    if doubted:
        assert heard.why == f"the speech is only {snr:.0f} dB above the background"


def spoken() -> Dialogue:
    d = Dialogue(Naming(), read_back=5.0, echo=True)
    d.select(["robot1"])
    return d


def test_a_doubted_motion_command_is_read_back_and_runs_only_on_yes():
    d = spoken()
    asked = d.hear("robot two go forward two meters", TEAM, unsure=True)
    assert (asked.say, asked.tasks, asked.asked) == (
        f"{DID_YOU_SAY} robot 2, go forward 2 metres? Say yes or no", [], True)
    assert d.targets == ["robot1"]  # a doubted hearing picks no robots
    done = d.hear("yes", TEAM)
    assert done.say == "Roger: robot 2, go forward 2 metres"
    assert [(t.preposition, t.destination, t.params.distance) for t in done.tasks] == [("forward", "robot2", 2.0)]
    assert d.targets == ["robot2"]
    d.hear("robot three turn left", TEAM, unsure=True)
    no = d.hear("no", TEAM)
    assert (no.say, no.tasks) == ("Not sent: robot 3, turn left 90 degrees", [])
    # a read-back left waiting is dropped by the next doubted command, which is read back itself
    d.hear("robot three turn left", TEAM, unsure=True)
    again = d.hear("robot one turn right", TEAM, unsure=True)
    assert again.say == f"Not sent: robot 3, turn left 90 degrees. {DID_YOU_SAY} robot 1, turn right 90 degrees? " \
                        "Say yes or no"


def test_a_spoken_teleport_is_read_back_however_sure_the_hearing():
    """A teleport re-bases a real robot's odometry: spoken, it runs only on "yes"; typed, at once."""
    d = spoken()
    asked = d.hear("robot one teleport to three four", TEAM)
    assert (asked.say, asked.tasks) == ("Robot 1, teleport to x 3, y 4 \u2014 say yes to confirm", [])
    assert [t.preposition for t in d.hear("yes", TEAM).tasks] == ["teleport"]
    assert Dialogue(Naming()).hear("robot one teleport to three four", TEAM).tasks


def test_a_doubted_stop_acts_at_once_and_other_doubted_lines_are_asked_again():
    d = spoken()
    d.hear("robot two go forward two meters", TEAM, unsure=True)
    stop = d.hear("everybody stop", TEAM, unsure=True)
    assert stop.stop and {t.destination for t in stop.tasks} == set(TEAM) and not stop.asked
    assert d.pending is None  # the read-back is dropped: a stop never waits
    for text in ("robot one set speed to zero point two", "cancel that", "robots one and two", "robot one fly"):
        reply = d.hear(text, TEAM, unsure=True)
        assert reply.say is not None and reply.say.startswith("Say again?") and not reply.tasks, (text, reply)
    typed = Dialogue(Naming())  # typed commands run at once, as before
    assert typed.hear("robot two go forward two meters", TEAM).tasks


ESPEAK = shutil.which("espeak-ng")


@pytest.mark.skipif(ESPEAK is None, reason="espeak-ng is not installed")
def test_a_lone_stop_phrase_in_noise_is_spotted_before_any_grammar_decode():
    """'halt' and 'freeze' in white noise at 15 dB: heard as themselves (or, which stop unsure, as a stop
    to everyone) by the stop keyphrase search, with no decode of the whole grammar; 'listen', 'yes' and 'no' are not heard as stops."""
    pytest.importorskip("pocketsphinx")
    from erni.plugins.ui.jsgf import jsgf
    from erni.plugins.ui.speech import SphinxRecognizer
    from tests.ui import speech_set as S

    stream = SphinxRecognizer(jsgf()).stream()
    rng = np.random.default_rng(1)
    first = S.synthesise("robot one go forward two meters", "en-us", 160)
    S.hear(stream, S.as_heard(first, 15.0, rng), 0.0)  # the front end settles on the voice and the room
    for text in ("halt", "freeze"):
        speech = S.synthesise(text, "en-us", 160)
        h = S.hear(stream, S.as_heard(speech, 15.0, rng), S.speech_end(speech))
        assert h.text in (text, "everybody stop") and not h.unsure, (text, h)
        # heard before any decode of the whole grammar (which in noise takes seconds)
        assert stream.evidence["stop"] == text and "text" not in stream.evidence, stream.evidence
    for text in ("listen", "yes", "no"):
        speech = S.synthesise(text, "en-us", 160)
        h = S.hear(stream, S.as_heard(speech, None, rng), S.speech_end(speech))
        assert "stop" not in h.text, (text, h, stream.evidence)  # spotted or not, the short decode overrules it
