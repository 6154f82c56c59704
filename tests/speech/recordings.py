"""What both recognisers' tests share: the shipped recordings with the answer each must give, and
room-quiet audio to put around words."""

from __future__ import annotations

from pathlib import Path

import numpy as np

DATA = Path(__file__).parent / "data"
SAMPLE_RATE = 16000

SHIPPED_ANSWERS = [
    ("yes", "yes"),
    ("yeah", "yes"),
    ("sure", "yes"),
    ("no", "no"),
    ("nope", "no"),
    ("no_way", "no"),
    ("maybe", None),
    ("i_dont_know", None),
    ("cough", None),
    ("silence", None),
]
"""Each WAV under data/ and the answer it must give (None: not an answer, asked again)."""


def quiet(seconds: float, seed: int = 0) -> bytes:
    """Room-quiet audio (about -60 dBFS), as a microphone sends between words."""
    noise = np.random.default_rng(seed).normal(0, 30, int(seconds * SAMPLE_RATE))
    return noise.astype("<i2").tobytes()
