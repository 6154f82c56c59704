"""Offline yes/no recognition with pocketsphinx, whose US-English model ships inside its wheel.

Two searches listen to the same stretch of speech:

* the **answer grammar**: a JSGF grammar whose only sentences are the vocabulary's phrases, so
  its best path is always one of them — which is why it cannot be trusted alone: a pure grammar
  forces every sound ("maybe", a cough) onto its nearest phrase;
* an **open-vocabulary listener**: the model's own English trigram language model (also in the
  wheel, about 130,000 words), which says what else the speech could have been ("maybe" comes out
  as "maybe", "I don't know" as "i don't know", a cough as nothing or a stray short word).

An answer counts only when the two agree: the listener's words must *sound* like a phrase of the
answer the grammar chose — closer, phone by phone, than to any phrase of the other answer. The
confidence is that phonetic agreement (:func:`agreement`), so the vocabulary's ``min_confidence``
(0.4 by default) is the operating point and a protocol can be stricter. Comparing sounds rather
than spellings keeps near misses of a real answer ("yea" for "yeah", "no wait" for "no way")
while anything that is really other speech sounds different. Both sides are scored by the same
acoustic model on the same frames, so room noise shifts neither the way the old grammar-vs-phone
loop score was shifted (docs/performance.md).

Only the speech is decoded: the endpointer (app.speech.endpoint) marks where speech started and
where its last word ended, and :meth:`Utterance.finish` decodes that stretch plus
:data:`PAD_SECONDS` either side, with the cepstral mean taken over that stretch (batch
normalisation): leading and trailing room noise can neither pull a phrase over itself nor skew
the normalisation. Audio is only held in memory, for the one utterance.

Decoders take a while to load, so a :class:`Recognizer` keeps a pool of decoder pairs and lends
one to each :class:`Utterance` (several stations may listen at once).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from importlib.metadata import version
from typing import Literal

import numpy as np
from pocketsphinx import Decoder, get_model_path

from app.speech.endpoint import SpeechBuffer
from app.speech.vocabulary import Heard, Vocabulary
from app.speech.wav import read_wav

__all__ = [
    "SAMPLE_RATE",
    "Recognition",
    "Recognizer",
    "UnknownWords",
    "Utterance",
    "agreement",
    "read_wav",
]

SAMPLE_RATE = 16000
LANGUAGE = "en-us"

PAD_SECONDS = 0.2
"""Audio kept either side of the endpointer's speech: soft onsets and final consonants (the
"s" of "yes", the "p" of "nope") are quieter than the vowel the endpointer keys on."""
NOISE_FLOOR = 30.0
"""Standard deviation (int16 units, about -60 dBFS) of a fixed noise added to the decoders'
input: the model was trained on real microphones, and digitally silent stretches (as in synthetic
or gated audio) otherwise derail its normalisation."""
LISTENER_SEARCH = {"maxhmmpf": 3000, "maxwpf": 10}
"""Caps on the open-vocabulary search (active HMMs and words started per frame; the defaults are
30,000 and unlimited): on the bench they halve its processor time and changed none of its
decisions on the tuning voices, clean and at 10 dB."""
_NOT_WORDS = ("<", "[", "+")
"""Fillers the listener may put in its transcript (<sil>, [NOISE], +SPN+…): no words."""


def agreement(phrase: list[str], heard: list[str]) -> float:
    """How much the phones ``heard`` sound like the phrase's phones, 0-1.

    One minus the phone edit distance over the longer sequence, with half an edit and one phone
    of smoothing, so that an exact match of a short word (2-3 phones, little evidence) scores
    about 0.85 and only a long exact match approaches 1."""
    if not phrase:
        return 0.0
    previous = list(range(len(heard) + 1))
    for i, mine in enumerate(phrase, 1):
        current = [i]
        for j, theirs in enumerate(heard, 1):
            current.append(
                min(previous[j] + 1, current[j - 1] + 1, previous[j - 1] + (mine != theirs))
            )
        previous = current
    distance = previous[-1]
    return max(0.0, 1.0 - (distance + 0.5) / (max(len(phrase), len(heard)) + 1))


class UnknownWords(ValueError):
    """A phrase uses words the recogniser's dictionary cannot pronounce."""


@dataclass(frozen=True)
class Recognition:
    """What was recognised in one utterance."""

    answer: Literal["yes", "no"] | None
    """None: unclear (another phrase, noise, a doubtful match) or silence."""
    transcript: str
    """The phrase the answer grammar matched best ("" for silence or noise it could not fit):
    what the recogniser heard within its vocabulary, also when the confidence then rejects it."""
    confidence: float
    """0-1: how much the open-vocabulary listener's words sound like the phrase (:func:`agreement`);
    0 when they sound more like the other answer."""
    engine: str
    seconds: float
    """Processing time of the final decode (from :meth:`Utterance.finish` being called)."""
    heard: str = ""
    """What the open-vocabulary listener made of the same speech (for a lab checking its room)."""


def engine_name() -> str:
    """Engine and model, as stored with every answer."""
    return f"pocketsphinx {version('pocketsphinx')} ({LANGUAGE})"


def _jsgf(vocabulary: Vocabulary) -> str:
    alternatives = " | ".join(" ".join(phrase.split()) for phrase in vocabulary.phrases)
    return f"#JSGF V1.0;\ngrammar answers;\npublic <answer> = {alternatives};\n"


def jsgf_words(jsgf: str) -> set[str]:
    """The words of the grammar's single rule."""
    rule = jsgf.split("=", 1)[1].rstrip(";\n")
    return set(rule.replace("|", " ").split())


class _Decoders:
    """The answer grammar and the open-vocabulary listener, used by one utterance at a time."""

    def __init__(self, jsgf: str) -> None:
        model = get_model_path(LANGUAGE)
        common = {
            "hmm": f"{model}/{LANGUAGE}",
            "dict": f"{model}/cmudict-en-us.dict",
            "loglevel": "FATAL",
            "cmn": "batch",
        }
        self.grammar = Decoder(lm=None, **common)
        unknown = sorted({w for w in jsgf_words(jsgf) if self.grammar.lookup_word(w) is None})
        if unknown:
            raise UnknownWords(f"not in the recogniser's dictionary: {', '.join(unknown)}")
        self.grammar.add_jsgf_string("answers", jsgf)
        self.grammar.activate_search("answers")
        self.listener = Decoder(
            lm=f"{model}/{LANGUAGE}.lm.bin",
            **common,
            **LISTENER_SEARCH,
        )

    def phones(self, words: str) -> list[str]:
        """The words' phones by the shared dictionary (unknown words give none)."""
        phones: list[str] = []
        for word in words.split():
            if not word.startswith(_NOT_WORDS):
                phones += (self.grammar.lookup_word(word) or "").split()
        return phones

    def decode(self, pcm: bytes) -> tuple[str, str]:
        """(grammar's phrase, listener's words) for one stretch of speech, decoded as a whole."""
        said = []
        for decoder in (self.grammar, self.listener):
            decoder.start_utt()
            decoder.process_raw(pcm, False, True)
            decoder.end_utt()
            hypothesis = decoder.hyp()
            words = hypothesis.hypstr if hypothesis is not None else ""
            said.append(" ".join(w for w in words.split() if not w.startswith(_NOT_WORDS)))
        return said[0], said[1]


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
        """A streaming recognition: :meth:`Utterance.feed` frames as they come, then finish.

        Its decoders are lent now (a new pair loaded if all are lent, a few seconds), so that
        the load falls at the start of listening, not between the end of speech and the answer."""
        with self._lock:
            decoders = self._idle.pop() if self._idle else None
        return Utterance(self, decoders or _Decoders(self._jsgf))

    def _give_back(self, decoders: _Decoders) -> None:
        with self._lock:
            self._idle.append(decoders)

    def _decide(self, decoders: _Decoders, phrase: str, words: str) -> tuple[Heard, float]:
        """The grammar's phrase with its confidence: the listener's agreement with it (0 when
        the listener sounds at least as much like a phrase of the other answer)."""
        answer = self.vocabulary.classify(Heard(phrase, 1.0))
        if answer is None:
            return Heard(phrase, 0.0), 0.0
        vocabulary = self.vocabulary
        same, other = (
            (vocabulary.yes, vocabulary.no) if answer == "yes" else (vocabulary.no, vocabulary.yes)
        )
        heard = decoders.phones(words)
        mine = max(agreement(decoders.phones(p), heard) for p in same)
        theirs = max((agreement(decoders.phones(p), heard) for p in other), default=0.0)
        confidence = mine if mine > theirs else 0.0
        return Heard(phrase, confidence), confidence


class Utterance:
    """One participant's answer, streamed in (:meth:`feed`) and decoded on :meth:`finish`."""

    def __init__(self, recognizer: Recognizer, decoders: _Decoders) -> None:
        self._recognizer = recognizer
        self._decoders = decoders
        self._buffer = SpeechBuffer(SAMPLE_RATE)

    @property
    def speech_ended(self) -> bool:
        """Speech was heard and then at least ~0.6 s of (near) silence: time to answer."""
        return self._buffer.speech_ended

    @property
    def speech_started(self) -> bool:
        """Something that sounds like speech was heard."""
        return self._buffer.speech_started

    def feed(self, pcm: bytes) -> None:
        """More audio (16 kHz mono int16 LE, any length), kept in memory until :meth:`finish`."""
        self._buffer.feed(pcm)

    def finish(self) -> Recognition:
        """Close the utterance and decide (silence when the endpointer heard no speech); the
        decoders go back to the recogniser's pool."""
        self._buffer.close()
        started = time.perf_counter()
        recognizer = self._recognizer
        phrase, words, confidence, heard = "", "", 0.0, None
        decoders = self._decoders
        try:
            speech = _with_noise_floor(*self._buffer.padded_speech(PAD_SECONDS))
            if speech:
                phrase, words = decoders.decode(speech)
                if phrase:
                    heard, confidence = recognizer._decide(decoders, phrase, words)
        finally:
            recognizer._give_back(decoders)
        return Recognition(
            answer=recognizer.vocabulary.classify(heard),
            transcript=phrase,
            confidence=confidence,
            engine=recognizer.engine,
            seconds=time.perf_counter() - started,
            heard=words,
        )

    def abandon(self) -> None:
        """Forget the utterance unheard (the question was answered elsewhere, or the client
        cancelled): its audio is dropped and its decoders go back to the pool without the
        decode :meth:`finish` would pay for. Nothing happens if it is already finished."""
        if self._buffer.drop():
            self._recognizer._give_back(self._decoders)


def _with_noise_floor(first: int, stretch: bytes) -> bytes:
    """The speech stretch (starting ``first`` bytes into the utterance) with the noise floor
    added, so that digital silence does not derail the decoders (b"" stays b"")."""
    if not stretch:
        return b""
    samples = np.frombuffer(stretch, "<i2").astype(np.float64)
    index = (first // 2 + np.arange(samples.size)) % _NOISE_TABLE.size
    floored = np.rint(samples + _NOISE_TABLE[index])
    return np.clip(floored, -32768, 32767).astype("<i2").tobytes()
