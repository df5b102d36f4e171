"""Speech benchmark: the speech test set through the control node's recogniser, per condition.

Every utterance of the test set (tests/ui/speech_set.py: the paper's operator lines and the stop
phrasings) is spoken by espeak-ng in each voice at each speed, clean and in white noise, read
through the control node's audio path, and streamed in 100 ms frames through the recogniser it
uses (PocketSphinx with ERNI's grammar, `SphinxRecognizer.stream()`: the same code as a page's
microphone, decoded as fast as it goes rather than in real time). Each hearing is judged against
the same text typed, through the spoken dialogue (tests/ui/speech_set.py `judge`): exact (what the
typed line does; `confirmed` counts those carried out after a read-back answered "yes", the answer
spoken in the same voice and noise and heard by the same recogniser), asked (nothing sent: asked
again, or the answer to a read-back was not heard as said), refused (the parser refused what was
heard), wrong (a different command carried out), false stop (a stop carried out where something
else was said). Each condition starts with 2 s of its room (noise) before the first clip.

Printed: one row per condition (voice x speed x noise), the totals per noise level, the stop
phrasings heard as a stop and the time from the end of their speech to their hearing (the audio
waited for plus the decodes), and every wrong hearing and false stop; written to --json.

    python bench/bench_speech.py [--voices en-us,en-gb,en-us+f3] [--speeds 130,160,190]
                                 [--noises clean,15,5] [--seed 36] [--every 1] [--part 1/1]
                                 [--json artifacts/ui/speech_set.json]
    python bench/bench_speech.py --denoise webrtc|speex|rnnoise|off --vad silero|webrtc|off  # a front end
    python bench/bench_speech.py --recogniser vosk --vosk-model DIR ...  # an English vosk model instead

The front end's other candidates are not dependencies of ERNI (RNNoise's package pulls in PyAV and requests
for its command line): `pip install speexdsp-ns pyrnnoise` before measuring `--denoise speex|rnnoise`.
    python bench/bench_speech.py --report RUN.json [RUN.json ...]   # the Markdown tables of saved runs
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from erni.plugins.ui.frontend import DENOISERS, VADS, FrontEnd  # noqa: E402
from erni.plugins.ui.speech import RATE, SpeechError, choose_recognizer  # noqa: E402
from tests.ui import speech_set as S  # noqa: E402

COLUMNS = ("exact", "confirmed", "asked", "refused", "wrong", "false stop")  # exact counts the confirmed too
PRIME = 2.0  # seconds of each condition's room before its first clip: the background is there before anyone speaks


def noises(text: str) -> tuple[float | None, ...]:
    out: list[float | None] = []
    for part in text.split(","):
        out.append(None if part.strip() == "clean" else float(part))
    return tuple(out)


class Answers:
    """The operator's answers to read-backs in one condition: spoken, mixed with its noise, heard."""

    def __init__(self, stream: Any, condition: S.Condition, rng: np.random.Generator, answering: bool) -> None:
        self.stream, self.c, self.rng = stream, condition, rng
        self.answering = answering  # heard among the short lines, as while the UI's read-back waits (--no-answers: not)
        self.heard: list[dict[str, Any]] = []
        self.seconds = 0.0

    def __call__(self, word: str) -> tuple[str, bool]:
        said = S.synthesise(word, self.c.voice, self.c.speed)
        self.stream.answering = self.answering  # as the UI tells its listener while a read-back waits
        try:
            a = S.hear(self.stream, S.as_heard(said, self.c.snr, self.rng), S.speech_end(said))
        finally:
            self.stream.answering = False
        self.heard.append({"said": word, "heard": a.text, "unsure": a.unsure, "why": a.why})
        self.seconds += a.seconds
        return a.text, a.unsure


def save(args: argparse.Namespace, rows: list[dict[str, Any]], clips: list[dict[str, Any]]) -> None:
    """The rows and every clip (what was said and heard, the answers to read-backs, the evidence) as JSON."""
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    which = (f"vosk {args.vosk_model or os.environ.get('VOSK_MODEL_PATH', '')}, ERNI grammar, word confidences"
             if args.backend == "vosk" else "pocketsphinx en-us, ERNI grammar as JSGF, two decodes + word scores, "
             "noise-floor endpointer, stop keyphrases")
    front = {"denoise": args.denoise, "vad": args.vad, "suppression": args.suppression, "gain": args.gain, "loud": args.loud,
             "answers": not args.no_answers, "live": not args.no_live, "live_again": not args.no_live and args.live_again}
    which += "; front end: " + front_name({"front_end": front})
    out.write_text(json.dumps({"recogniser": which, "cost": getattr(args, "cost", {}), "front_end": front,
                               "seed": args.seed, "every": args.every, "part": args.part, "rows": rows,
                               "clips": clips}, indent=1) + "\n")


def report(paths: list[str]) -> str:
    """The Markdown tables of runs saved with --json (one run, or its parts run side by side)."""
    rows: list[dict[str, Any]] = []
    clips: list[dict[str, Any]] = []
    for path in paths:
        try:
            run = json.loads(Path(path).read_text())
            rows += run["rows"]
            clips += run["clips"]
        except (OSError, ValueError, KeyError) as err:
            raise SystemExit(f"{path}: not a speech bench run saved with --json ({err})") from None
    order = {(v, s, n): i for i, (v, s, n) in enumerate((c.voice, c.speed, c.noise) for c in S.conditions())}
    rows.sort(key=lambda r: order.get((r["voice"], r["wpm"], r["noise"]), len(order)))
    out = ["| voice | wpm | noise | clips | exact | of which after a read-back | asked | refused | wrong | false stop |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    out += [f"| {r['voice']} | {r['wpm']} | {r['noise']} | {r['n']} | "
            + " | ".join(str(r[o]) for o in COLUMNS) + " |" for r in rows]
    out += ["", "| noise | conditions | clips | exact | after a read-back | asked | refused | wrong | false stop "
                "| stop phrasings heard as a stop | end of speech → stop heard: median, max, under 1 s |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for noise in [*dict.fromkeys(r["noise"] for r in rows), "all"]:
        part = [r for r in rows if noise in ("all", r["noise"])]
        said = [c for c in clips if noise in ("all", c["condition"].split(" wpm ")[1]) and c["said"] in S.STOPS]
        heard = [c["latency"] for c in said if c["outcome"] == "exact"]
        m = sum(r["n"] for r in part)
        exact = sum(r["exact"] for r in part)
        lat = (f"{statistics.median(heard):.2f} s, {max(heard):.2f} s, {sum(x < 1.0 for x in heard)}/{len(heard)}"
               if heard else "-")
        out.append(f"| {noise} | {len(part)} | {m} | {exact} ({exact / max(m, 1):.1%}) | "
                   + " | ".join(str(sum(r[o] for r in part)) for o in COLUMNS[1:])
                   + f" | {len(heard)}/{len(said)} ({len(heard) / max(len(said), 1):.0%}) | {lat} |")
    bad = [c for c in clips if c["outcome"] in ("wrong", "false stop")]
    out += ["", *(f"- {c['outcome']} [{c['condition']}]: said “{c['said']}”, heard “{c['heard']}”"
                  + (f" (unsure: {c['why']})" if c["unsure"] else "")
                  + "".join(f"; answered “{a['said']}”, heard “{a['heard']}”" for a in c["answers"]) for c in bad)]
    return "\n".join(out)


ABOUT = "the speech test set through the control node's front end and recogniser, per voice, speed and noise"
EXACT_GOAL = {"clean": 0.95, "15 dB": 0.85, "5 dB": 0.60}  # exact (after a read-back and "yes") at least
STOPS_GOAL = {"clean": 0.98, "15 dB": 0.98, "5 dB": 0.90}  # stop phrasings heard as a stop at least


def speech_targets(rows: list[dict[str, Any]], clips: list[dict[str, Any]], cost: dict[str, Any]) -> list[dict[str, Any]]:
    """The benchmark's targets from a run's rows and clips (or the parts of one, side by side)."""
    import results

    wrong = sum(r["wrong"] for r in rows)
    false = sum(r["false stop"] for r in rows)
    others = sum(1 for c in clips if c["said"] not in S.STOPS)
    out = [results.target("commands carried out as something else", "none", "the typed line", f"{wrong} wrong",
                          wrong == 0),
           results.target("false stops, of the commands that are no stop", "at most 1 %", "the typed line",
                          f"{false}/{others} ({false / max(others, 1):.1%})", false <= 0.01 * others)]
    for noise in dict.fromkeys(r["noise"] for r in rows):
        part = [r for r in rows if r["noise"] == noise]
        exact = sum(r["exact"] for r in part) / max(sum(r["n"] for r in part), 1)
        said = [c for c in clips if c["condition"].split(" wpm ")[1] == noise and c["said"] in S.STOPS]
        heard = [c["latency"] for c in said if c["outcome"] == "exact"]
        goal, stops_goal = EXACT_GOAL.get(noise), STOPS_GOAL.get(noise)
        out.append(results.target(f"understood exactly (after a read-back and a yes), noise {noise}",
                                  f"at least {goal:.0%}" if goal else "reported", "the typed line", f"{exact:.1%}",
                                  exact >= goal if goal else None))
        share = len(heard) / max(len(said), 1)
        out.append(results.target(f"stop phrasings heard as a stop, noise {noise}",
                                  f"at least {stops_goal:.0%}" if stops_goal else "reported", "the typed line",
                                  f"{len(heard)}/{len(said)} ({share:.0%})", share >= stops_goal if stops_goal else None))
        if heard:
            under = sum(x < 1.0 for x in heard)
            out.append(results.target(f"stops acted on within 1 s of the voice's end, noise {noise}", "every one",
                                      "the endpointer's 0.4 s of hangover", f"{under}/{len(heard)}, median "
                                      f"{statistics.median(heard):.2f} s", under == len(heard)))
    if cost.get("front_end") is not None:
        delay = cost.get("suppressor_delay")
        out.append(results.target("front end's CPU per second of audio", "reported", "the recogniser's "
                                  f"{1000 * cost['recogniser']:.0f} ms", f"{1000 * cost['front_end']:.0f} ms (suppressor "
                                  f"{1000 * cost['suppressor']:.0f}, voice detector {1000 * cost['endpointer']:.0f})",
                                  None))
        out.append(results.target("suppressor's delay", "reported", "none without it",
                                  f"{1000 * delay:.1f} ms" if delay is not None else "no suppressor", None))
    return out


def combine(argv: list[str]) -> int:
    """`--combine RUN.json ... [--results PATH] [--tables RUN.json ...]`: the parts of one run (`--part I/N`) as its
    results, with the per-condition table and, given `--tables`, the candidates compared (these runs first)."""
    import results

    ap = argparse.ArgumentParser(prog="bench_speech.py --combine")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--candidates", nargs="*", default=[], help="runs of other front ends, for the comparison")
    ap.add_argument("--before", nargs="*", default=[], help="the parts of a run without the front end")
    ap.add_argument("--command", required=True, help="the command the parts were run with (without --part)")
    results.add_argument(ap)
    args = ap.parse_args(argv)
    runs = load_runs(args.runs)
    rows = [r for run in runs for r in run["rows"]]
    clips = [c for run in runs for c in run["clips"]]
    costs = [run.get("cost") or {} for run in runs]
    cost = {k: statistics.mean(c[k] for c in costs if c.get(k) is not None) for k in costs[0]
            if any(c.get(k) is not None for c in costs)}
    tables = [{"title": f"per condition, {front_name(runs[0])}", "markdown": report(args.runs)}]
    if args.before:
        tables.append({"title": f"per condition, {front_name(load_runs(args.before)[0])} (before)",
                       "markdown": report(args.before)})
    if args.candidates:
        tables.append({"title": "front-end candidates (3 voices at 160 words a minute, clean, 15 and 5 dB)",
                       "markdown": compare(args.candidates)})
    results.write("bench_speech", speech_targets(rows, clips, cost), path=args.results, about=ABOUT,
                  argv=args.command.split(), tables=tables)
    return 0


def load_runs(paths: list[str]) -> list[dict[str, Any]]:
    runs = []
    for path in paths:
        try:
            run = json.loads(Path(path).read_text())
            run["rows"], run["clips"]
        except (OSError, ValueError, KeyError) as err:
            raise SystemExit(f"{path}: not a speech bench run saved with --json ({err})") from None
        runs.append(run)
    return runs


def front_name(run: dict[str, Any]) -> str:
    f = run.get("front_end") or {"denoise": "off", "vad": "off", "gain": 0, "answers": False}
    level = f" (level {f['suppression']})" if f["denoise"] == "webrtc" and f.get("suppression", 2) != 2 else ""
    if f["denoise"] == "auto":
        level = f" (RNNoise above {f.get('loud', 0):g} dBFS)"
    parts = [f"denoise {f['denoise']}{level}", f"vad {f['vad']}"] + ([f"gain {f['gain']} dBFS"] if f.get("gain") else [])
    live = ("live decode as the second hearing" if f.get("live_again") else "live decode for stops") if f.get("live") \
        else "no live decode"
    return ", ".join(parts) + (", answers among the short lines" if f.get("answers") else ", answers by the whole grammar") \
        + f", {live}"


def compare(paths: list[str]) -> str:
    """One row per run (a front-end candidate): exact, stops heard and their latency, false stops, wrong, cost."""
    runs = load_runs(paths)
    noises = list(dict.fromkeys(r["noise"] for run in runs for r in run["rows"]))
    head = ["front end", "conditions"] + [f"exact, {n}" for n in noises] + [f"stops heard, {n}" for n in noises] + [
        "stop heard: median after the voice", "false stops", "wrong", "front end CPU per audio second"]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for run in runs:
        rows, clips = run["rows"], run["clips"]
        cells = [front_name(run), str(len(rows))]
        for n in noises:
            part = [r for r in rows if r["noise"] == n]
            m = sum(r["n"] for r in part)
            cells.append(f"{sum(r['exact'] for r in part) / m:.0%}" if m else "-")
        lat = []
        for n in noises:
            said = [c for c in clips if c["condition"].split(" wpm ")[1] == n and c["said"] in S.STOPS]
            heard = [c for c in said if c["outcome"] == "exact"]
            lat += [c["latency"] for c in heard]
            cells.append(f"{len(heard)}/{len(said)}" if said else "-")
        cells.append(f"{statistics.median(lat):.2f} s" if lat else "-")
        cells += [str(sum(r["false stop"] for r in rows)), str(sum(r["wrong"] for r in rows))]
        cost = run.get("cost") or {}
        cells.append(f"{1000 * cost['front_end']:.0f} ms" if "front_end" in cost else "-")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def into(path: str, title: str, markdown: str) -> None:
    """Keep `markdown` in a results file's tables under `title` (replacing a table of that title)."""
    data = json.loads(Path(path).read_text(encoding="utf-8"))
    tables = [t for t in data.get("tables", []) if t["title"] != title]
    data["tables"] = [*tables, {"title": title, "markdown": markdown}]
    Path(path).write_text(json.dumps(data, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")


def tables_main(argv: list[str]) -> int:
    """`--report|--compare RUN.json ... [--into RESULTS.json --title TITLE]`: print a table, or keep it in a results file."""
    ap = argparse.ArgumentParser(prog=f"bench_speech.py {argv[0]}")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--into", default=None, help="a results file (bench/results/bench_speech.json) to keep the table in")
    ap.add_argument("--title", default=None)
    mode, args = argv[0], ap.parse_args(argv[1:])
    text = report(args.runs) if mode == "--report" else compare(args.runs)
    print(text)
    if args.into:
        into(args.into, args.title or ("per condition" if mode == "--report" else "front-end candidates"), text)
    return 0


class Timed:
    """A part of the stream (its suppressor, its endpointer) whose `process` calls are timed."""

    def __init__(self, inner: Any) -> None:
        self.inner, self.seconds = inner, 0.0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def process(self, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return self.inner.process(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - t0


def suppressor_delay(front: FrontEnd) -> float | None:
    """The suppressor's delay (s): where a spoken clip's cleaned copy best matches it."""
    suppressor = front.suppressor()
    if suppressor is None or S.ESPEAK is None:
        return None
    x = S.synthesise("robot one go forward two meters", "en-us", 160)
    pcm = np.clip(np.round(np.concatenate([np.zeros(RATE), x])), -32768, 32767).astype("<i2").tobytes()
    y = np.frombuffer(suppressor.process(pcm[: len(pcm) // 320 * 320]), dtype="<i2").astype(np.float64)
    x = np.frombuffer(pcm[: len(y) * 2], dtype="<i2").astype(np.float64)
    lags = range(0, 800)
    best = max(lags, key=lambda k: float(np.dot(x[: len(x) - k], y[k:])))
    return best / RATE


def main() -> int:
    if sys.argv[1:2] == ["--combine"]:
        return combine(sys.argv[2:])
    if sys.argv[1:2] in (["--report"], ["--compare"]):
        if len(sys.argv) < 3:
            print("usage: bench_speech.py --report|--compare RUN.json [RUN.json ...] [--into RESULTS.json --title T]",
                  file=sys.stderr)
            return 2
        return tables_main(sys.argv[1:])
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--voices", default=",".join(S.VOICES))
    ap.add_argument("--speeds", default=",".join(map(str, S.SPEEDS)))
    ap.add_argument("--noises", default="clean,15,5", help="clean and/or SNRs in dB")
    ap.add_argument("--seed", type=int, default=36, help="seed of the noise")
    ap.add_argument("--recogniser", choices=("auto", "vosk", "pocketsphinx"), default="pocketsphinx",
                    help="as the UI's setting: vosk needs --vosk-model or VOSK_MODEL_PATH")
    ap.add_argument("--vosk-model", default=None, help="a vosk model directory (an English one)")
    from erni.plugins.ui.plugin import UISettings

    ui = UISettings()  # the control node's defaults
    ap.add_argument("--denoise", choices=DENOISERS, default=ui.denoise, help="the front end's noise suppressor "
                    "(default: the control node's)")
    ap.add_argument("--vad", choices=VADS, default=ui.vad, help="the front end's voice-activity detector "
                    "(off: the level-based endpointer; default: the control node's)")
    ap.add_argument("--gain", type=int, default=ui.auto_gain, help="WebRTC's automatic gain target, dBFS (0 = off)")
    ap.add_argument("--loud", type=float, default=ui.loud_room, help="denoise auto: the room's level (dBFS) above "
                    "which RNNoise hears")
    ap.add_argument("--suppression", type=int, choices=range(5), default=2, help="WebRTC's suppression level (0-4)")
    ap.add_argument("--no-answers", action="store_true", help="decode answers to read-backs with the whole grammar")
    ap.add_argument("--no-live", action="store_true", help="no live decode as the voice goes on (a stop then waits "
                    "for the decodes after the utterance)")
    ap.add_argument("--live-again", action="store_true", help="the live decode as the doubt rule's second hearing "
                    "(instead of a decode in pieces after the utterance)")
    ap.add_argument("--json", default="artifacts/ui/speech_set.json")
    ap.add_argument("--every", type=int, default=1, help="the stop phrasings and every K-th other line of the set")
    ap.add_argument("--part", default="1/1", help="run the I-th of N shares of the conditions (I/N), "
                    "for N processes side by side")
    results.add_argument(ap)
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
    try:  # the control node's own choice and loading of its recogniser
        front = FrontEnd(args.denoise, args.vad, args.gain, args.suppression, loud=args.loud)
        loader = choose_recognizer(args.recogniser, args.vosk_model, front=front)
        args.backend = getattr(loader, "backend", args.recogniser)
        recogniser = loader()
    except SpeechError as err:
        print(f"bench_speech: {err}", file=sys.stderr)
        return 2
    stream = recogniser.stream()  # one decoder, as for one microphone
    if args.no_live:
        stream.live = None
    stream.live_again = args.live_again
    parts = {"suppressor": getattr(stream, "suppressor", None), "endpointer": getattr(stream, "ep", None)}
    if parts["suppressor"] is not None:
        stream.suppressor = parts["suppressor"] = Timed(parts["suppressor"])
    if parts["endpointer"] is not None:
        stream.ep = parts["endpointer"] = Timed(parts["endpointer"])
    args.cost = {}
    rng = np.random.default_rng(args.seed)
    rows: list[dict[str, Any]] = []
    wrong: list[dict[str, Any]] = []
    clips: list[dict[str, Any]] = []
    latency: dict[str, list[float]] = {}
    stops: dict[str, Counter[str]] = {}
    audio_s = compute_s = 0.0
    started = time.time()
    head = f"{'voice':10} {'wpm':>4} {'noise':>6} {'n':>4} " + " ".join(f"{o:>10}" for o in COLUMNS)
    print(head, flush=True)
    for c in conditions:
        count = Counter[str]()
        S.hear(stream, S.room(S.synthesise(texts[0], c.voice, c.speed), c.snr, rng, PRIME), 0.0)
        for text in texts:
            speech = S.synthesise(text, c.voice, c.speed)
            pcm = S.as_heard(speech, c.snr, rng)
            h = S.hear(stream, pcm, S.speech_end(speech))
            answer = Answers(stream, c, rng, answering=not args.no_answers)
            outcome = S.judge(text, h.text, h.unsure, answer)
            answers = answer.heard
            clips.append({"condition": str(c), "said": text, "heard": h.text, "unsure": h.unsure, "why": h.why,
                          "outcome": outcome, "answers": answers, "latency": h.latency, "evidence": h.evidence})
            count[outcome] += 1
            audio_s += len(pcm) / 2 / RATE
            compute_s += h.seconds + answer.seconds
            if text in S.STOPS:
                stops.setdefault(c.noise, Counter())[outcome] += 1
                if outcome == "exact":
                    latency.setdefault(c.noise, []).append(h.latency)
            if outcome in ("wrong", "false stop"):
                wrong.append({"condition": str(c), "said": text, "heard": h.text, "unsure": h.unsure,
                              "why": h.why, "answers": answers, "outcome": outcome})
        n = sum(count.values())
        row: dict[str, Any] = {"voice": c.voice, "wpm": c.speed, "noise": c.noise, "n": n,
                               **{o: count[o] for o in COLUMNS}}
        row["exact"] += row["confirmed"]
        rows.append(row)
        print(f"{c.voice:10} {c.speed:>4} {c.noise:>6} {n:>4} " + " ".join(f"{row[o]:>10}" for o in COLUMNS),
              flush=True)
        if args.json:  # after each condition: a run stopped early keeps what it measured
            save(args, rows, clips)
    total = {o: sum(r[o] for r in rows) for o in COLUMNS}
    n = sum(r["n"] for r in rows)
    print(f"{'all':10} {'':>4} {'':>6} {n:>4} " + " ".join(f"{total[o]:>10}" for o in COLUMNS))
    print(f"exact {total['exact'] / n:.1%} (after a read-back and a yes: {total['confirmed']}), "
          f"asked {total['asked'] / n:.1%}, refused {total['refused'] / n:.1%}, wrong {total['wrong']}, "
          f"false stops {total['false stop']}")
    for noise in dict.fromkeys(r["noise"] for r in rows):
        part = [r for r in rows if r["noise"] == noise]
        m = sum(r["n"] for r in part)
        got = stops.get(noise, Counter())
        lat = latency.get(noise, [])
        print(f"  {noise:>6}: {m} clips, exact {sum(r['exact'] for r in part) / m:.1%} ("
              + ", ".join(f"{o} {sum(r[o] for r in part)}" for o in COLUMNS) + f"); stop phrasings "
              f"{got['exact']}/{sum(got.values())} heard as a stop"
              + (f", from the end of speech to the stop's hearing median {statistics.median(lat):.2f} s, "
                 f"max {max(lat):.2f} s, {sum(x < 1.0 for x in lat)}/{len(lat)} under 1 s" if lat else ""))
    print(f"{audio_s:.0f} s of audio decoded in {compute_s:.0f} s ({compute_s / audio_s:.2f} x real time); "
          f"wall {time.time() - started:.0f} s")
    front_s = sum(p.seconds for p in parts.values() if isinstance(p, Timed))
    delay = suppressor_delay(front)
    args.cost = {"front_end": front_s / audio_s, "suppressor": getattr(parts["suppressor"], "seconds", 0.0) / audio_s,
                 "endpointer": getattr(parts["endpointer"], "seconds", 0.0) / audio_s,
                 "recogniser": (compute_s - front_s) / audio_s, "suppressor_delay": delay}
    print(f"front end ({front.name}): {1000 * args.cost['front_end']:.1f} ms of CPU per second of audio (suppressor "
          f"{1000 * args.cost['suppressor']:.1f}, endpointer and VAD {1000 * args.cost['endpointer']:.1f}); "
          f"the recogniser {1000 * args.cost['recogniser']:.0f} ms per second; the suppressor's delay "
          + (f"{1000 * delay:.1f} ms" if delay is not None else "none (no suppressor)"))
    if args.part == "1/1":  # a share of the conditions is not the benchmark's result
        results.write("bench_speech", speech_targets(rows, clips, args.cost), path=args.results, about=ABOUT)
    for w in wrong:
        said_back = "; ".join(f"answered {a['said']!r}, heard {a['heard']!r}" for a in w["answers"])
        print(f"  {w['outcome'].upper()} [{w['condition']}] said {w['said']!r} heard {w['heard']!r}"
              f"{' (unsure: ' + w['why'] + ')' if w['unsure'] else ''}{'; ' + said_back if said_back else ''}")
    if args.json:
        save(args, rows, clips)
    return 0


if __name__ == "__main__":
    sys.exit(main())
