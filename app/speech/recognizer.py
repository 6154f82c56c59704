"""Offline yes/no recognition with pocketsphinx, whose US-English model ships inside its wheel.

Two searches run over the same audio, frame by frame as it streams in:

* the **answer grammar**: a JSGF grammar whose only sentences are the vocabulary's phrases, so
  the best path is always one of them — which is also why it cannot be trusted alone: a pure
  grammar forces every sound ("maybe", a cough) onto its nearest phrase;
* a **free phone loop** (pocketsphinx's allphone search over the model's phone bigram): the best
  sequence of any English phones, a yardstick of how well *anything* could explain the audio.

The confidence is the log-likelihood ratio of the two best paths, per frame of speech: a phrase
that was really said fits nearly as well as (or better than, thanks to its context-dependent
phones) the free loop, while a phrase forced onto other words or noise fits far worse. The ratio
is mapped to 0-1 by a logistic curve (:func:`confidence_of`) calibrated on bench/speech.py so
that the vocabulary's default ``min_confidence`` (0.4) is the operating point; the vocabulary's
``classify`` then makes the final call, so a protocol can be stricter than the default.

Decoders take about half a second to load, so a :class:`Recognizer` keeps a pool of decoder
pairs and lends one to each :class:`Utterance` (several stations may listen at once).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from importlib.metadata import version
from typing import Literal

import numpy as np
from pocketsphinx import Decoder, get_model_path

from app.speech.endpoint import Endpointer
from app.speech.vocabulary import Heard, Vocabulary
from app.speech.wav import read_wav

__all__ = ["SAMPLE_RATE", "Recognition", "Recognizer", "UnknownWords", "Utterance", "read_wav"]

SAMPLE_RATE = 16000
LANGUAGE = "en-us"

ALLPHONE_LANGUAGE_WEIGHT = 3.0
"""How much the phone loop trusts its phone bigram: lower makes it a freer, tougher yardstick."""
LLR_AT_MIN_CONFIDENCE = -4.0
"""The per-frame log-likelihood ratio (pocketsphinx score units) that maps to confidence 0.4."""
LLR_SCALE = 4.0
"""How many score units move the confidence by one logit."""
MIN_SPEECH_FRAMES = 20
"""A floor under the per-frame normalisation, so a 50 ms blip cannot swing the ratio."""
NOISE_FLOOR = 30.0
"""Standard deviation (int16 units, about -60 dBFS) of a fixed noise added to the input: the
model was trained on real microphones, and digitally silent stretches (as in synthetic or
gated audio) otherwise derail its normalisation."""
BLOCK_BYTES = SAMPLE_RATE // 50 * 2
"""20 ms: the unit the decoders are fed in."""
_FILLERS = frozenset({"SIL", "<sil>", "<s>", "</s>", "+NSN+", "+SPN+", "[NOISE]", "[SPEECH]"})
_DEFAULT_MIN_CONFIDENCE_LOGIT = math.log(0.4 / 0.6)


def confidence_of(llr_per_frame: float) -> float:
    """The logistic map of the grammar-vs-phone-loop ratio to 0-1 (0.4 at the calibrated point)."""
    logit = (llr_per_frame - LLR_AT_MIN_CONFIDENCE) / LLR_SCALE + _DEFAULT_MIN_CONFIDENCE_LOGIT
    return 1.0 / (1.0 + math.exp(-max(-50.0, min(50.0, logit))))


class UnknownWords(ValueError):
    """A phrase uses words the recogniser's dictionary cannot pronounce."""


@dataclass(frozen=True)
class Recognition:
    """What was recognised in one utterance."""

    answer: Literal["yes", "no"] | None
    """None: unclear (another phrase, noise, a doubtful match) or silence."""
    transcript: str
    """The phrase the answer grammar matched best ("" for silence): what the recogniser heard
    within its vocabulary, also when the confidence then rejects it."""
    confidence: float
    """0-1, from the grammar-vs-phone-loop likelihood ratio (:func:`confidence_of`)."""
    engine: str
    seconds: float
    """Processing time of the final decode (from :meth:`Utterance.finish` being called)."""


def engine_name() -> str:
    """Engine and model, as stored with every answer."""
    return f"pocketsphinx {version('pocketsphinx')} ({LANGUAGE})"


def _jsgf(vocabulary: Vocabulary) -> str:
    alternatives = " | ".join(" ".join(phrase.split()) for phrase in vocabulary.phrases)
    return f"#JSGF V1.0;\ngrammar answers;\npublic <answer> = {alternatives};\n"


class _Decoders:
    """One answer-grammar decoder and one phone-loop decoder, used by one utterance at a time."""

    def __init__(self, jsgf: str) -> None:
        model = get_model_path(LANGUAGE)
        common = {
            "hmm": f"{model}/{LANGUAGE}",
            "dict": f"{model}/cmudict-en-us.dict",
            "lm": None,
            "loglevel": "FATAL",
            "cmn": "live",
        }
        self.grammar = Decoder(**common)
        unknown = sorted(
            {w for w in jsgf_words(jsgf) if self.grammar.lookup_word(w) is None},
        )
        if unknown:
            raise UnknownWords(f"not in the recogniser's dictionary: {', '.join(unknown)}")
        self.grammar.add_jsgf_string("answers", jsgf)
        self.grammar.activate_search("answers")
        self.phones = Decoder(
            allphone=f"{model}/{LANGUAGE}-phone.lm.bin", lw=ALLPHONE_LANGUAGE_WEIGHT, **common
        )

    def start(self) -> None:
        """Begin an utterance from fresh feature extraction: live normalisation would otherwise
        carry the previous utterance's room over, and the same audio could be heard differently
        depending on who spoke before."""
        for decoder in (self.grammar, self.phones):
            decoder.reinit_feat()
            decoder.start_utt()


def jsgf_words(jsgf: str) -> set[str]:
    """The words of the grammar's single rule."""
    rule = jsgf.split("=", 1)[1].rstrip(";\n")
    return set(rule.replace("|", " ").split())


_NOISE_TABLE = np.random.default_rng(20240601).normal(0.0, NOISE_FLOOR, SAMPLE_RATE)


class Recognizer:
    """Recognises yes/no answers among a vocabulary's phrases (thread-safe; reuse it)."""

    def __init__(self, vocabulary: Vocabulary) -> None:
        if not vocabulary.phrases:
            raise ValueError("the vocabulary has no phrases")
        self.vocabulary = vocabulary
        self.engine = engine_name()
        self._jsgf = _jsgf(vocabulary)
        self._lock = threading.Lock()
        self._idle: list[_Decoders] = [_Decoders(self._jsgf)]

    def recognize(self, pcm: bytes) -> Recognition:
        """A whole utterance (16 kHz mono int16 LE) at once."""
        utterance = self.utterance()
        utterance.feed(pcm)
        return utterance.finish()

    def utterance(self) -> Utterance:
        """A streaming recognition: :meth:`Utterance.feed` frames as they come, then finish."""
        with self._lock:
            decoders = self._idle.pop() if self._idle else None
        return Utterance(self, decoders or _Decoders(self._jsgf))

    def _give_back(self, decoders: _Decoders) -> None:
        with self._lock:
            self._idle.append(decoders)


class Utterance:
    """One participant's answer, streamed in (:meth:`feed`) and decoded on :meth:`finish`."""

    def __init__(self, recognizer: Recognizer, decoders: _Decoders) -> None:
        self._recognizer = recognizer
        self._decoders: _Decoders | None = decoders
        self._endpointer = Endpointer(SAMPLE_RATE)
        self._samples = 0
        self._pending = b""
        decoders.start()

    @property
    def speech_ended(self) -> bool:
        """Speech was heard and then at least ~0.6 s of (near) silence: time to answer."""
        return self._endpointer.speech_ended

    @property
    def speech_started(self) -> bool:
        """Something that sounds like speech was heard."""
        return self._endpointer.speech_started

    def feed(self, pcm: bytes) -> None:
        """More audio (16 kHz mono int16 LE, any length).

        The decoders always get whole :data:`BLOCK_BYTES` blocks, whatever the caller's chunks:
        their live normalisation updates per call, so this keeps a streamed utterance and the
        same audio given at once (:meth:`Recognizer.recognize`) recognised identically."""
        self._require()
        self._pending += pcm
        whole = len(self._pending) - len(self._pending) % BLOCK_BYTES
        for start in range(0, whole, BLOCK_BYTES):
            self._block(self._pending[start : start + BLOCK_BYTES])
        self._pending = self._pending[whole:]

    def _block(self, block: bytes) -> None:
        decoders = self._require()
        samples = np.frombuffer(block, "<i2").astype(np.float64)
        index = (self._samples + np.arange(samples.size)) % _NOISE_TABLE.size
        floored = np.clip(np.rint(samples + _NOISE_TABLE[index]), -32768, 32767).astype("<i2")
        self._samples += samples.size
        chunk = floored.tobytes()
        self._endpointer.feed(block)
        decoders.grammar.process_raw(chunk, False, False)
        decoders.phones.process_raw(chunk, False, False)

    def finish(self) -> Recognition:
        """Close the utterance and decide; the decoders go back to the recogniser's pool."""
        started = time.perf_counter()
        tail = self._pending[: len(self._pending) - len(self._pending) % 2]
        if tail:
            self._block(tail)
        self._pending = b""
        decoders = self._require()
        self._decoders = None
        try:
            heard, transcript, confidence = _decide(decoders)
        finally:
            self._recognizer._give_back(decoders)
        answer = self._recognizer.vocabulary.classify(heard) if heard else None
        return Recognition(
            answer=answer,
            transcript=transcript,
            confidence=confidence,
            engine=self._recognizer.engine,
            seconds=time.perf_counter() - started,
        )

    def _require(self) -> _Decoders:
        if self._decoders is None:
            raise RuntimeError("this utterance is finished")
        return self._decoders


def _decide(decoders: _Decoders) -> tuple[Heard | None, str, float]:
    """End both searches and compare them: (what was heard, transcript, confidence)."""
    decoders.grammar.end_utt()
    decoders.phones.end_utt()
    phones = [seg for seg in decoders.phones.seg() or [] if seg.word not in _FILLERS]
    grammar_hyp, phone_hyp = decoders.grammar.hyp(), decoders.phones.hyp()
    transcript = grammar_hyp.hypstr.strip() if grammar_hyp is not None else ""
    if not phones or not transcript or phone_hyp is None:
        return None, "", 0.0
    logmath = decoders.grammar.get_logmath()
    frames = max(MIN_SPEECH_FRAMES, phones[-1].end_frame - phones[0].start_frame + 1)
    llr = (logmath.log(grammar_hyp.best_score) - logmath.log(phone_hyp.best_score)) / frames
    confidence = confidence_of(llr)
    return Heard(transcript, confidence), transcript, confidence
