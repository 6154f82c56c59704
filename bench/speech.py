"""How well an offline recogniser (app/speech/engines.py: ``--engine whisper``, the default, or
``--engine pocketsphinx``) takes yes/no answers in a noisy room.

The labelled set is built here, in a temporary folder, with espeak-ng: every yes and no phrase of
the default vocabulary plus out-of-grammar speech ("maybe", "I don't know", "the second key"…)
and coughs and noise bursts, each said by several synthetic voices (accent, speed, pitch). Each
clip is streamed in 20 ms frames through the engine's ``Utterance``, clean and with
room noise (pink and brown noise plus a babble of overlapping espeak sentences) mixed in at each
SNR, over several noise seeds.

Reported per condition (mean ± standard deviation over the seeds):

* **accuracy**: yes/no items recognised as their answer;
* **wrong**: yes/no items recognised as the other answer (the error that misleads a learner);
* **accepted**: out-of-grammar items and noises accepted as a yes or a no;
* **latency**: from the endpointer calling the end of speech (the frame on which it does, fed)
  to :meth:`finish` returning the answer (median and p95 over all items; for a clip whose end is
  never called, from its last frame). **endpoint wait** is the audio time from the last speech
  frame to that call (≈ 0.6 s of quiet by design): a live participant waits for both.
  By default frames are fed as fast as they are processed, so an early decode (app/speech/
  whisper.py: the stretch is decoded during the endpointer's wait) has no wait to overlap and
  the latency is the whole decode; ``--real-time`` feeds the frames after the clip's silent lead
  at the pace a microphone delivers them (one 20 ms frame per 20 ms), as a room does, which is
  what a participant meets. **CPU** is the process's processor time from the last speech frame
  to the answer (every thread: the decode's cost on one core).

    .venv/bin/python bench/speech.py                      # the full set, Whisper
    .venv/bin/python bench/speech.py --engine pocketsphinx
    .venv/bin/python bench/speech.py --voices 1 --snrs 10 --seeds 1    # a smoke run
    .venv/bin/python bench/speech.py --split held-out    # only the voices not used for tuning
    .venv/bin/python bench/speech.py --real-time          # the latency a participant meets

Figures are per core: Whisper's model is loaded with one CTranslate2 thread and one worker (run
with ``OMP_NUM_THREADS=1``); the first line gives the model's load time, the last the process's
peak resident memory.

The recogniser's settings were chosen on the ``tuning`` half of the voices (even positions in
:data:`VOICES`, and the even noise repeats); ``--split held-out`` reports on the other half alone,
which is the fairer figure for voices and rooms the bench has never heard.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from app.speech.engines import (  # noqa: E402
    ENGINES,
    SAMPLE_RATE,
    EngineSettings,
    RecognitionLike,
    RecognizerLike,
    UtteranceLike,
    make_recognizer,
)
from app.speech.vocabulary import Vocabulary  # noqa: E402
from app.speech.wav import read_wav  # noqa: E402

FRAME = SAMPLE_RATE // 50
"""20 ms of samples: the frame the room streams."""


@dataclass(frozen=True)
class Voice:
    """An espeak-ng voice (language+variant), its speed (words/minute) and pitch (0-99)."""

    name: str
    speed: int
    pitch: int


VOICES = (
    Voice("en-us", 165, 50),
    Voice("en-gb+m3", 150, 40),
    Voice("en-us+f3", 180, 70),
    Voice("en-gb-scotland+f2", 145, 62),
    Voice("en-gb-x-rp+m5", 190, 45),
    Voice("en-us+klatt2", 160, 55),
    Voice("en-gb-x-gbclan+f4", 155, 66),
    Voice("en-us+m7", 200, 35),
)
OUT_OF_GRAMMAR = (
    "maybe",
    "I don't know",
    "the second key",
    "hello",
    "wait a moment",
    "the red box",
    "perhaps",
)
NOISES = ("cough", "double cough", "noise burst")
BABBLE_SENTENCES = (
    "I think we should try the other door first, it looked a bit more promising.",
    "Did you see where the robot put the blue card after the last round?",
    "The weather was lovely this morning, but they say it will rain later on.",
    "Can you pass me the notes from yesterday, I want to check one thing.",
    "We still have about ten minutes left, so there is no need to hurry.",
    "My sister is moving to a new flat near the station next month.",
)
SNRS = (20.0, 10.0, 5.0)
TARGETS = {"accuracy": 97.0, "wrong": 0.5, "accepted": 2.0, "p95_ms": 400.0}
LEAD_SECONDS, TRAIL_SECONDS = 0.5, 1.0
SPEECH_LEVEL_DBFS = -23.0


@dataclass(frozen=True)
class Clip:
    """One labelled item: expected "yes"/"no", or None for anything that is not an answer."""

    label: str
    voice: str
    expected: str | None
    samples: np.ndarray
    """Float samples at 16 kHz, lead and trailing silence included."""
    last_speech_frame: int


@dataclass(frozen=True)
class Outcome:
    condition: str
    seed: int
    label: str
    voice: str
    expected: str | None
    answer: str | None
    transcript: str
    heard: str
    confidence: float
    latency_ms: float
    cpu_ms: float
    """Processor time of the same stretch: the latency on an otherwise idle core."""
    endpoint_wait_ms: float | None
    no_speech: float | None = None
    """Whisper only: its no-speech probability (to re-decide from records)."""
    words_probability: float | None = None
    """Whisper only: the probability of the transcript's words (see app/speech/whisper.py)."""


def espeak(text: str, voice: Voice, folder: Path) -> np.ndarray:
    """``text`` said by ``voice``, as floats at 16 kHz."""
    out = folder / "say.wav"
    command = ["espeak-ng", "-v", voice.name, "-s", str(voice.speed), "-p", str(voice.pitch)]
    subprocess.run([*command, "-w", str(out), text], check=True, capture_output=True, timeout=60)
    return np.frombuffer(read_wav(out), "<i2").astype(np.float64) / 32768.0


def trim(signal: np.ndarray) -> np.ndarray:
    """Without espeak's leading and trailing silence (the clip adds its own)."""
    loud = np.flatnonzero(np.abs(signal) > 1e-3)
    return signal[loud[0] : loud[-1] + 1] if loud.size else signal


def set_level(signal: np.ndarray, dbfs: float) -> np.ndarray:
    rms = float(np.sqrt(np.mean(signal**2))) or 1.0
    return signal * (10 ** (dbfs / 20) / rms)


def colored_noise(samples: int, exponent: float, rng: np.random.Generator) -> np.ndarray:
    """Noise whose power falls as 1/f**exponent (1: pink, 2: brown), unit RMS."""
    spectrum = np.fft.rfft(rng.normal(size=samples))
    frequencies = np.fft.rfftfreq(samples, 1 / SAMPLE_RATE)
    frequencies[0] = frequencies[1]
    shaped = np.fft.irfft(spectrum / frequencies ** (exponent / 2), samples)
    return shaped / np.sqrt(np.mean(shaped**2))


def burst(seconds: float, decay: float, rng: np.random.Generator) -> np.ndarray:
    """Band-limited noise (300-3500 Hz) with a sharp attack and exponential decay."""
    n = int(seconds * SAMPLE_RATE)
    spectrum = np.fft.rfft(rng.normal(size=n))
    frequencies = np.fft.rfftfreq(n, 1 / SAMPLE_RATE)
    spectrum[(frequencies < 300) | (frequencies > 3500)] = 0
    t = np.arange(n) / SAMPLE_RATE
    envelope = np.minimum(1.0, t / 0.01) * np.exp(-t / decay) if decay else np.ones(n)
    return np.fft.irfft(spectrum, n) * envelope


def noise_sound(kind: str, rng: np.random.Generator) -> np.ndarray:
    if kind == "cough":
        return burst(0.3, 0.07, rng)
    if kind == "double cough":
        gap = np.zeros(int(0.15 * SAMPLE_RATE))
        return np.concatenate([burst(0.3, 0.07, rng), gap, burst(0.3, 0.06, rng)])
    return burst(0.45, 0.0, rng)


def last_speech_frame(signal: np.ndarray) -> int:
    """The last 20 ms frame whose level is within 35 dB of the loudest frame."""
    frames = signal[: signal.size - signal.size % FRAME].reshape(-1, FRAME)
    power = np.mean(frames**2, axis=1) + 1e-12
    loud = np.flatnonzero(10 * np.log10(power / power.max()) > -35)
    return int(loud[-1])


def clip(label: str, voice: str, expected: str | None, sound: np.ndarray) -> Clip:
    lead = np.zeros(int(LEAD_SECONDS * SAMPLE_RATE))
    tail = np.zeros(int(TRAIL_SECONDS * SAMPLE_RATE))
    samples = np.concatenate([lead, set_level(sound, SPEECH_LEVEL_DBFS), tail])
    return Clip(label, voice, expected, samples, last_speech_frame(samples))


SPLITS = ("all", "tuning", "held-out")


def in_split(index: int, split: str) -> bool:
    """Whether the voice (or noise repeat) at ``index`` belongs to ``split``."""
    return split == "all" or (index % 2 == 0) == (split == "tuning")


def build_clips(
    voices: tuple[Voice, ...], vocabulary: Vocabulary, folder: Path, split: str = "all"
) -> list[Clip]:
    clips: list[Clip] = []
    for index, voice in enumerate(voices):
        if not in_split(index, split):
            continue
        for answer, phrases in (("yes", vocabulary.yes), ("no", vocabulary.no)):
            for phrase in phrases:
                clips.append(clip(phrase, voice.name, answer, trim(espeak(phrase, voice, folder))))
        for phrase in OUT_OF_GRAMMAR:
            clips.append(clip(phrase, voice.name, None, trim(espeak(phrase, voice, folder))))
    rng = np.random.default_rng(7)
    for repeat in range(max(1, len(voices) // 2)):
        for kind in NOISES:
            sound = noise_sound(kind, rng)
            if in_split(repeat, split):
                clips.append(clip(kind, f"noise{repeat}", None, sound))
    return clips


def build_babble(folder: Path) -> np.ndarray:
    """Several espeak talkers at once, at random offsets: the murmur of a room (unit RMS)."""
    rng = np.random.default_rng(11)
    talkers = []
    for index, sentence in enumerate(BABBLE_SENTENCES):
        voice = VOICES[index % len(VOICES)]
        talkers.append(set_level(trim(espeak(sentence, voice, folder)), -20))
    length = max(t.size for t in talkers) * 2
    babble = np.zeros(length)
    for talker in talkers:
        for _ in range(2):
            start = int(rng.integers(0, length - talker.size))
            babble[start : start + talker.size] += talker
    return babble / np.sqrt(np.mean(babble**2))


def room_noise(samples: int, babble: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Equal parts steady noise (pink + brown) and babble, unit RMS, drawn from ``rng``."""
    steady = colored_noise(samples, 1.0, rng) + 0.5 * colored_noise(samples, 2.0, rng)
    start = int(rng.integers(0, babble.size - samples))
    mixed = steady / np.sqrt(np.mean(steady**2)) + babble[start : start + samples]
    return mixed / np.sqrt(np.mean(mixed**2))


def with_noise(item: Clip, snr_db: float, babble: np.ndarray, seed: int) -> np.ndarray:
    """The clip with room noise at ``snr_db`` below the level of its sound."""
    rng = np.random.default_rng([seed, zlib.crc32(f"{item.label}|{item.voice}".encode())])
    sound_power = 10 ** (SPEECH_LEVEL_DBFS / 10)
    noise = room_noise(item.samples.size, babble, rng) * np.sqrt(sound_power / 10 ** (snr_db / 10))
    return item.samples + noise


LEAD_FRAMES = round(LEAD_SECONDS * 50)
"""The clip's silent lead, in frames: fed at once also in real time (nothing to decode yet)."""


def stream(
    recognizer: RecognizerLike, item: Clip, samples: np.ndarray, real_time: bool = False
) -> tuple[RecognitionLike, float, float, int]:
    """Feed 20 ms frames (after the lead at a microphone's pace when ``real_time``);
    (recognition, ms from the end being called to the answer, processor ms from the last speech
    frame to the answer, frames fed)."""
    pcm = np.clip(np.rint(samples * 32768), -32768, 32767).astype("<i2").tobytes()
    utterance: UtteranceLike = recognizer.utterance()
    frames = len(pcm) // (2 * FRAME)
    cpu = time.process_time()
    fed = frames
    paced_from = time.perf_counter() - LEAD_FRAMES * 0.02
    for index in range(frames):
        if real_time and index >= LEAD_FRAMES:
            delay = paced_from + index * 0.02 - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        if index == item.last_speech_frame:
            cpu = time.process_time()
        utterance.feed(pcm[index * 2 * FRAME : (index + 1) * 2 * FRAME])
        if index > item.last_speech_frame and utterance.speech_ended:
            fed = index + 1
            break
    called = time.perf_counter()
    recognition = utterance.finish()
    elapsed, cpu = time.perf_counter() - called, time.process_time() - cpu
    return recognition, elapsed * 1000, cpu * 1000, fed


def run(
    recognizer: RecognizerLike,
    clips: list[Clip],
    condition: str,
    seed: int,
    noise: tuple[float, np.ndarray] | None,
    real_time: bool = False,
) -> list[Outcome]:
    """Every clip once, clean or with ``noise`` (SNR in dB, babble) drawn from ``seed``."""
    outcomes = []
    for item in clips:
        samples = item.samples if noise is None else with_noise(item, *noise, seed)
        recognition, latency, cpu, fed = stream(recognizer, item, samples, real_time)
        ended = fed < samples.size // FRAME
        wait = (fed - 1 - item.last_speech_frame) * 20.0 if ended else None
        outcomes.append(
            Outcome(
                condition=condition,
                seed=seed,
                label=item.label,
                voice=item.voice,
                expected=item.expected,
                answer=recognition.answer,
                transcript=recognition.transcript,
                heard=getattr(recognition, "heard", ""),
                confidence=recognition.confidence,
                latency_ms=latency,
                cpu_ms=cpu,
                endpoint_wait_ms=wait,
                no_speech=getattr(recognition, "no_speech", None),
                words_probability=getattr(recognition, "words_probability", None),
            )
        )
    return outcomes


@dataclass(frozen=True)
class Rates:
    """One seed's figures for one condition, in percent."""

    accuracy: float
    wrong: float
    accepted: float


def rates(outcomes: list[Outcome]) -> Rates:
    answers = [o for o in outcomes if o.expected is not None]
    others = [o for o in outcomes if o.expected is None]
    right = sum(o.answer == o.expected for o in answers)
    wrong = sum(o.answer is not None and o.answer != o.expected for o in answers)
    accepted = sum(o.answer is not None for o in others)
    return Rates(
        accuracy=100 * right / max(1, len(answers)),
        wrong=100 * wrong / max(1, len(answers)),
        accepted=100 * accepted / max(1, len(others)),
    )


def spread(values: list[float]) -> str:
    mean = statistics.fmean(values)
    if len(values) < 2:
        return f"{mean:5.1f}"
    return f"{mean:5.1f} ± {statistics.stdev(values):3.1f}"


def percentile(values: list[float], fraction: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(fraction * (len(ordered) - 1)))]


def report(condition: str, outcomes: list[Outcome]) -> tuple[str, dict[str, float]]:
    """One table row for ``condition`` and its figures (means over seeds)."""
    by_seed: dict[int, list[Outcome]] = {}
    for outcome in outcomes:
        by_seed.setdefault(outcome.seed, []).append(outcome)
    per_seed = [rates(group) for group in by_seed.values()]
    latencies = [o.latency_ms for o in outcomes]
    waits = [o.endpoint_wait_ms for o in outcomes if o.endpoint_wait_ms is not None]
    figures = {
        "accuracy": statistics.fmean(r.accuracy for r in per_seed),
        "wrong": statistics.fmean(r.wrong for r in per_seed),
        "accepted": statistics.fmean(r.accepted for r in per_seed),
        "median_ms": statistics.median(latencies),
        "p95_ms": percentile(latencies, 0.95),
        "p95_cpu_ms": percentile([o.cpu_ms for o in outcomes], 0.95),
    }
    wait = f"{statistics.median(waits):5.0f}" if waits else "    -"
    unended = len(outcomes) - len(waits)
    row = (
        f"| {condition:9s} | {spread([r.accuracy for r in per_seed]):>10s} "
        f"| {spread([r.wrong for r in per_seed]):>9s} "
        f"| {spread([r.accepted for r in per_seed]):>10s} "
        f"| {figures['median_ms']:5.0f} | {figures['p95_ms']:5.0f} "
        f"| {figures['p95_cpu_ms']:5.0f} | {wait} "
        f"| {unended:5d} |"
    )
    return row, figures


HEADER = (
    "| condition | accuracy % | wrong % | accepted % | median ms | p95 ms | p95 CPU ms "
    "| endpoint wait ms | not ended |\n"
    "|---|---|---|---|---|---|---|---|---|"
)


def verdict(name: str, figures: dict[str, float]) -> str:
    """Which targets the condition meets."""
    checks = [
        ("accuracy", figures["accuracy"] >= TARGETS["accuracy"], "≥", "%"),
        ("wrong", figures["wrong"] <= TARGETS["wrong"], "≤", "%"),
        ("accepted", figures["accepted"] <= TARGETS["accepted"], "≤", "%"),
        ("p95_ms", figures["p95_ms"] <= TARGETS["p95_ms"], "≤", " ms"),
    ]
    parts = [
        f"{key} {figures[key]:.1f}{unit} (target {sign} {TARGETS[key]:g}{unit}) "
        f"{'met' if ok else 'MISSED'}"
        for key, ok, sign, unit in checks
    ]
    return f"{name}: " + "; ".join(parts)


def voice_split(voice: str) -> str:
    """Which half a recorded outcome's voice (or noise repeat) belongs to."""
    names = [v.name for v in VOICES]
    index = names.index(voice) if voice in names else int(voice.removeprefix("noise"))
    return "tuning" if in_split(index, "tuning") else "held-out"


def report_records(files: list[Path], split: str) -> int:
    """The table and verdicts of outcomes recorded by earlier runs, per condition."""
    by_condition: dict[str, list[Outcome]] = {}
    for file in files:
        for line in file.read_text().splitlines():
            outcome = Outcome(**json.loads(line))
            if split == "all" or voice_split(outcome.voice) == split:
                by_condition.setdefault(outcome.condition, []).append(outcome)
    order = sorted(
        by_condition, key=lambda c: (c != "clean", -float(c.split()[1]) if " " in c else 0)
    )
    seeds = ", ".join(f"{c} {len({o.seed for o in by_condition[c]})}" for c in order)
    print(f"{len(files)} record files, {split} voices; noise seeds: {seeds}")
    print(HEADER)
    summary = []
    for condition in order:
        row, figures = report(condition, by_condition[condition])
        print(row)
        if condition == "clean" or float(condition.split()[1]) >= 10:
            summary.append(verdict(condition, figures))
    for line in summary:
        print(line)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--voices", type=int, default=len(VOICES), help="how many voices (1-8)")
    parser.add_argument("--snrs", type=float, nargs="+", default=list(SNRS), help="SNRs in dB")
    parser.add_argument("--seeds", type=int, default=8, help="noise seeds per SNR")
    parser.add_argument("--first-seed", type=int, default=0, help="the first noise seed")
    parser.add_argument("--no-clean", action="store_true", help="skip the clean condition")
    parser.add_argument(
        "--split", choices=SPLITS, default="all", help="all voices, or the tuning or held-out half"
    )
    parser.add_argument(
        "--engine", choices=sorted(ENGINES), default="whisper", help="the recogniser to measure"
    )
    parser.add_argument(
        "--min-confidence", type=float, help="the operating point (default: the vocabulary's)"
    )
    parser.add_argument(
        "--encoder-frames",
        type=int,
        help="whisper: the fewest 10 ms frames the encoder sees (default 3000: Whisper's 30 s)",
    )
    parser.add_argument("--beam", type=int, help="whisper: beam size (default 1: greedy)")
    parser.add_argument(
        "--no-prompt", action="store_true", help="whisper: do not prime the decode with the phrases"
    )
    parser.add_argument(
        "--real-time",
        action="store_true",
        help="feed each clip at a microphone's pace (the latency a participant meets)",
    )
    parser.add_argument(
        "--no-early-decode",
        action="store_true",
        help="whisper: decode only once the end is called, not during the endpointer's wait",
    )
    parser.add_argument("--records", type=Path, help="write every outcome to this JSON-lines file")
    parser.add_argument(
        "--from-records",
        type=Path,
        nargs="+",
        help="only report: the table of these --records files (e.g. seeds run in parallel)",
    )
    args = parser.parse_args(argv)
    if args.from_records:
        return report_records(args.from_records, args.split)
    if shutil.which("espeak-ng") is None:
        print("error: espeak-ng is not installed (Debian: apt-get install espeak-ng)")
        return 2
    vocabulary = Vocabulary()
    if args.min_confidence is not None:
        vocabulary = Vocabulary(min_confidence=args.min_confidence)
    if args.engine == "whisper" and (args.encoder_frames or args.beam or args.no_early_decode):
        import app.speech.whisper as whisper

        whisper.ENCODER_FRAMES = args.encoder_frames or whisper.ENCODER_FRAMES
        whisper.BEAM_SIZE = args.beam or whisper.BEAM_SIZE
        whisper.DECODE_DURING_WAIT = not args.no_early_decode
    load_started = time.perf_counter()
    engine = EngineSettings(args.engine, prompt=not args.no_prompt)
    recognizer = make_recognizer(vocabulary, engine, per_core=True)
    load_seconds = time.perf_counter() - load_started
    voices = VOICES[: max(1, min(len(VOICES), args.voices))]
    with tempfile.TemporaryDirectory(prefix="trustlab-speech-bench-") as folder:
        clips = build_clips(voices, vocabulary, Path(folder), args.split)
        babble = build_babble(Path(folder))
    answers = sum(c.expected is not None for c in clips)
    print(
        f"{len(clips)} clips ({answers} yes/no, {len(clips) - answers} other), "
        f"{len({c.voice for c in clips if c.expected})} voices ({args.split}), "
        f"{getattr(recognizer, 'engine', args.engine)}, {args.seeds} noise seeds; "
        f"loaded in {load_seconds:.2f} s"
    )
    if args.engine == "whisper":
        early = "off" if args.no_early_decode else "on"
        prompt = "off" if args.no_prompt else "on"
        fed = "in real time" if args.real_time else "at once"
        print(f"prompt {prompt}, early decode {early}, fed {fed}")
    print(HEADER)
    conditions: list[tuple[str, float | None]] = [] if args.no_clean else [("clean", None)]
    conditions += [(f"SNR {snr:g} dB", snr) for snr in args.snrs]
    summary = []
    records = args.records.open("w") if args.records else None
    for name, snr in conditions:
        outcomes: list[Outcome] = []
        seeds = [0] if snr is None else range(args.first_seed, args.first_seed + args.seeds)
        for seed in seeds:
            noise = None if snr is None else (snr, babble)
            outcomes += run(recognizer, clips, name, seed, noise, args.real_time)
        row, figures = report(name, outcomes)
        print(row, flush=True)
        if records is not None:
            records.writelines(json.dumps(asdict(outcome)) + "\n" for outcome in outcomes)
            records.flush()
        if snr is None or snr >= 10:
            summary.append(verdict(name, figures))
    for line in summary:
        print(line)
    print(f"peak RSS {peak_rss_mb():.0f} MB")
    if records is not None:
        records.close()
    return 0


def peak_rss_mb() -> float:
    """This process's peak resident memory (Linux: ru_maxrss in KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


if __name__ == "__main__":
    sys.exit(main())
