"""Speech benchmark: the speech test set through the control node's recogniser, per condition.

Every utterance of the test set (tests/ui/speech_set.py: the paper's operator lines and the stop
phrasings) is spoken by espeak-ng in each voice at each speed, clean and in white noise, read
through the control node's audio path, and streamed in 100 ms frames through the recogniser it
uses (PocketSphinx with ERNI's grammar, `SphinxRecognizer.stream()`: the same code as a page's
microphone, decoded as fast as it goes rather than in real time). Each hearing is judged against
the same text typed: exact, asked ("Say again?": the recogniser was unsure), refused (the parser
refused what was heard), wrong (a different command would be carried out).

Printed: one row per condition (voice x speed x noise), the totals, the stop phrasings, the
recogniser's latency after the end of a stop, and every wrong hearing; written to --json.

    python bench/bench_speech.py [--voices en-us,en-gb,en-us+f3] [--speeds 130,160,190]
                                 [--noises clean,15,5] [--seed 36] [--every 1] [--part 1/1]
                                 [--json artifacts/ui/speech_set.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from erni.plugins.ui.jsgf import jsgf  # noqa: E402
from erni.plugins.ui.speech import SphinxRecognizer  # noqa: E402
from tests.ui import speech_set as S  # noqa: E402

OUTCOMES = ("exact", "asked", "refused", "wrong")


def noises(text: str) -> tuple[float | None, ...]:
    out: list[float | None] = []
    for part in text.split(","):
        out.append(None if part.strip() == "clean" else float(part))
    return tuple(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--voices", default=",".join(S.VOICES))
    ap.add_argument("--speeds", default=",".join(map(str, S.SPEEDS)))
    ap.add_argument("--noises", default="clean,15,5", help="clean and/or SNRs in dB")
    ap.add_argument("--seed", type=int, default=36, help="seed of the noise")
    ap.add_argument("--json", default="artifacts/ui/speech_set.json")
    ap.add_argument("--every", type=int, default=1, help="the stop phrasings and every K-th other line of the set")
    ap.add_argument("--part", default="1/1", help="run the I-th of N shares of the conditions (I/N), "
                    "for N processes side by side")
    args = ap.parse_args()
    if S.ESPEAK is None:
        print("espeak-ng is not installed (apt install espeak-ng)", file=sys.stderr)
        return 2
    conditions = S.conditions(tuple(args.voices.split(",")), tuple(int(s) for s in args.speeds.split(",")),
                              noises(args.noises))
    i, n_parts = (int(x) for x in args.part.split("/"))
    conditions = conditions[i - 1::n_parts]
    texts = S.utterances()
    texts = [t for t in texts if t in S.STOPS] + [t for t in texts if t not in S.STOPS][::args.every]
    stream = SphinxRecognizer(jsgf()).stream()  # one decoder, as for one microphone
    rng = np.random.default_rng(args.seed)
    rows, wrong, stop_latency, audio_s, compute_s = [], [], [], 0.0, 0.0
    clips: list[dict[str, object]] = []
    stops = Counter[str]()
    started = time.time()
    print(f"{'voice':10} {'wpm':>4} {'noise':>6} {'n':>4} " + " ".join(f"{o:>8}" for o in OUTCOMES), flush=True)
    for c in conditions:
        count = Counter[str]()
        for text in texts:
            speech = S.synthesise(text, c.voice, c.speed)
            pcm = S.as_heard(speech, c.snr, rng)
            h = S.hear(stream, pcm, S.speech_end(speech))
            outcome = S.judge(text, h.text, h.unsure)
            clips.append({"condition": str(c), "said": text, "outcome": outcome, "evidence": h.evidence})
            count[outcome] += 1
            audio_s += len(pcm) / 2 / S.RATE
            compute_s += h.seconds
            if text in S.STOPS:
                stops[outcome] += 1
                if outcome == "exact":
                    stop_latency.append(h.latency)
            if outcome == "wrong":
                wrong.append({"condition": str(c), "said": text, "heard": h.text, "unsure": h.unsure})
        n = sum(count.values())
        rows.append({"voice": c.voice, "wpm": c.speed, "noise": c.noise, "n": n, **{o: count[o] for o in OUTCOMES}})
        print(f"{c.voice:10} {c.speed:>4} {c.noise:>6} {n:>4} " + " ".join(f"{count[o]:>8}" for o in OUTCOMES),
              flush=True)
    total = {o: sum(r[o] for r in rows) for o in OUTCOMES}
    n = sum(total.values())
    print(f"{'all':10} {'':>4} {'':>6} {n:>4} " + " ".join(f"{total[o]:>8}" for o in OUTCOMES))
    print(f"exact {total['exact'] / n:.1%}, asked {total['asked'] / n:.1%}, refused {total['refused'] / n:.1%}, "
          f"wrong {total['wrong']} ({total['wrong'] / n:.1%})")
    for noise in sorted({r["noise"] for r in rows}):
        part = [r for r in rows if r["noise"] == noise]
        m = sum(r["n"] for r in part)
        print(f"  {noise:>6}: exact {sum(r['exact'] for r in part) / m:.1%}, wrong {sum(r['wrong'] for r in part)}/{m}")
    ns = sum(stops.values())
    print(f"stop phrasings ({', '.join(S.STOPS)}): {stops['exact']}/{ns} = {stops['exact'] / max(ns, 1):.1%} "
          f"exact, {stops['wrong']} wrong, {stops['asked'] + stops['refused']} not heard as a stop")
    if stop_latency:
        print(f"recogniser latency after a stop is said (trailing silence + decodes): median "
              f"{statistics.median(stop_latency):.2f} s, max {max(stop_latency):.2f} s")
    print(f"{audio_s:.0f} s of audio decoded in {compute_s:.0f} s ({compute_s / audio_s:.2f} x real time); "
          f"wall {time.time() - started:.0f} s")
    for w in wrong:
        print(f"  WRONG [{w['condition']}] said {w['said']!r} heard {w['heard']!r}{' (unsure)' if w['unsure'] else ''}")
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"recogniser": "pocketsphinx en-us, ERNI grammar as JSGF, two decodes + word scores",
                                   "seed": args.seed, "rows": rows, "total": total, "stops": dict(stops),
                                   "stop_latency_s": stop_latency, "wrong": wrong,
                                   "real_time_factor": compute_s / audio_s, "clips": clips}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
