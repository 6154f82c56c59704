"""The server's offline recognisers, one per study engine and vocabulary, loaded on first use.

A recogniser for a protocol's yes/no phrases (app.speech.engines: Whisper by default, or
pocketsphinx) takes a while to build (it loads a model), so the server keeps one per engine
settings and vocabulary and every station whose study shares them shares it; each answer gets an
utterance of its own. The engine's module is imported only when a room first streams audio: a
server whose rooms never listen does not pay for the model, and one without the engine installed
says so in one line instead of failing to start.
"""

from __future__ import annotations

import importlib
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from app.errors import TrustlabError
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


RecognizerFactory = Callable[[Vocabulary, EngineSettings], RecognizerLike]
"""Builds the recogniser of (vocabulary, engine settings)."""


class RecognitionUnavailable(TrustlabError):
    """The server has no offline recogniser (its engine is not installed, or failed to load)."""

    status_code = 503


def offline_recognizer(
    vocabulary: Vocabulary, engine: EngineSettings = EngineSettings()
) -> RecognizerLike:
    """The shipped offline recogniser of ``engine`` for ``vocabulary`` (RecognitionUnavailable
    without it)."""
    try:
        engines = importlib.import_module("app.speech.engines")
        recognizer: RecognizerLike = engines.make_recognizer(vocabulary, engine)
    except ImportError as exc:
        raise RecognitionUnavailable(
            f"offline speech recognition is unavailable on this server: {exc}"
        ) from None
    except ValueError as exc:  # e.g. a phrase the recogniser's dictionary cannot pronounce
        raise RecognitionUnavailable(
            f"the offline recogniser cannot take this study: {exc}"
        ) from None
    return recognizer


class RecognizerPool:
    """One recogniser per engine settings and vocabulary, built on first use (thread-safe; build
    in a worker thread)."""

    def __init__(self, make: RecognizerFactory = offline_recognizer) -> None:
        self._make = make
        self._made: dict[tuple[EngineSettings, Vocabulary], RecognizerLike] = {}
        self._lock = threading.Lock()

    def get(
        self, vocabulary: Vocabulary, engine: EngineSettings = EngineSettings()
    ) -> RecognizerLike:
        """The ``engine`` recogniser of ``vocabulary``, built now if it is the first time."""
        with self._lock:
            recognizer = self._made.get((engine, vocabulary))
            if recognizer is None:
                recognizer = self._make(vocabulary, engine)
                self._made[(engine, vocabulary)] = recognizer
            return recognizer
