"""The server's offline recognisers, one per study engine and vocabulary, loaded on first use.

A recogniser for a protocol's yes/no phrases (app.speech.engines: Whisper by default, or
pocketsphinx) takes a while to build (it loads a model), so the server keeps one per engine
settings and vocabulary and every station whose study shares them shares it; each answer gets an
utterance of its own. The engine's module is imported only when a room first streams audio
(app.speech.engines imports it when it builds the first recogniser): a server whose rooms never
listen does not pay for the model, and one without the engine installed says so in one line
instead of failing to start.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from app.errors import TrustlabError
from app.speech.engines import EngineSettings, RecognizerLike, make_recognizer
from app.speech.vocabulary import Vocabulary

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
        recognizer = make_recognizer(vocabulary, engine)
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
